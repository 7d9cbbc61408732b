"""The scene's side of the rigid solver: torch mirrors of state, controls and parameters, their
upload to the solver's fields, and the rigid part of the scene's step node (simulator.py) and of the
link getters' nodes (grad/functions.py).

Invariant: slot 0 of the solver's state fields holds the current state. With gradients, the
current state is also a pair of torch tensors (qpos, qvel) in the autograd graph; controls and
parameters are torch tensors whose values are uploaded to the fields before the next launch.

Applied wrenches (the user's link forces, gravity compensation; solvers/rigid/external.py): the
wrench the user applies between two steps accumulates (in numpy where nothing needs a gradient, else
in torch) into a (B, n_links, 6) tensor that the next step takes as an input and then drops (a force
lasts one step, as in Genesis); gravity compensation is a parameter (B, n_links). Both exist once the solver has applied wrenches (at build when an entity's
material has gravity_compensation, else from the first apply call); a step recorded before that has
neither among its inputs.
"""
from __future__ import annotations

import numpy as np
import taichi as ti
import torch

from solvers.rigid.actuation import LIMITS_CONSTRAINT
from solvers.rigid.model import JOINT_NV
from solvers.rigid.solver import RigidSolver

from ..errors import GenesisException
from ..grad.functions import OutputFunction
from ..grad.indexing import all_finite, as_slices, as_span, incoming_grads, index_put, raise_if_nan_grad
from ..grad.remake import recomposed
from ..utils.geom import quat_to_R as _quat_to_R

# name -> (solver field, trailing shape, axis it is indexed by). The core's parameters travel packed in one
# tensor (RigidSolver.param_layout); contact friction lives in the contact solver's own field.
PARAMS = {
    "mass": ("link_mass", (), "link"),
    "com": ("link_com", (3,), "link"),
    "inertia": ("link_inertia", (3, 3), "link"),
    "damping": ("dof_damping", (), "dof"),
    "armature": ("dof_armature", (), "dof"),
    "frictionloss": ("dof_frictionloss", (), "dof"),
    "kp": ("dof_kp", (), "dof"),
    "kv": ("dof_kv", (), "dof"),
    "stiffness": ("dof_stiffness", (), "dof"),
    "gravity": ("gravity", (3,), "env"),
    # not set by the user: the joint-limit constraint's (M^-1)_jj at qpos0, a function of the armature (_invweight)
    "invweight": ("dof_invweight", (), "dof"),
    "friction": ("contact.geom_friction", (), "geom"),  # only when the scene has contacts
    "gravity_compensation": ("applied_gcomp", (), "link"),  # only when the solver has applied wrenches
}
# the parameters outside the core, and the solver object each needs
OPTIONAL_PARAMS = {"friction": "contact", "gravity_compensation": "applied"}
DEFAULT_KP, DEFAULT_KV = 100.0, 10.0  # Genesis's gains of a joint whose file sets none (N m/rad, N m s/rad)
CTRL = ("force", "pos", "vel")  # rows of the packed control tensor (B, 3, n_dofs)


SPRING_DEFAULTS = (1e4, 1e2)  # N m/rad (N/m), N m s/rad (N s/m): the limit springs' gains when one is given


def _limit_springs(rigid_options):
    """(stiffness, damping) of the joint-limit springs when either option is given (the other at
    SPRING_DEFAULTS), else (None, None): Genesis's limit constraint."""
    k, d = rigid_options.joint_limit_stiffness, rigid_options.joint_limit_damping
    if k is None and d is None:
        return None, None
    return (SPRING_DEFAULTS[0] if k is None else k), (SPRING_DEFAULTS[1] if d is None else d)


class RigidSim:
    """Bridge of the rigid solver (the protocol is in bridges/__init__.py). Step inputs: qpos, qvel (its
    state), the packed controls and the parameters; step output: the packed state [qpos | qvel]."""

    n_state = 2
    n_outputs = 1

    def __init__(self, scene, models, n_envs, sim_options, rigid_options, external_wrench=False):
        import genesis_lite as gs

        self.scene = scene
        self.B = max(n_envs, 1)
        self.dtype = gs.tc_float
        self.device = gs.device
        self.requires_grad = sim_options.requires_grad
        # a collision geom without its own friction (GeomDesc.friction None) takes its entity's material's
        for ent in scene.rigid_entities:
            for link in ent.model.links:
                for g in link.geoms:
                    if g.friction is None:
                        g.friction = float(ent.material.friction)
        self.solver = RigidSolver(models, self.B, sim_options.dt, sim_options.substeps, int(rigid_options.integrator),
                                  sim_options.gravity, gs.ti_float, self.requires_grad,
                                  rigid_options.enable_joint_limit, *_limit_springs(rigid_options),
                                  contact_options=rigid_options if rigid_options.enable_collision else None,
                                  mimic=rigid_options.enable_mimic, external_wrench=external_wrench,
                                  specialize=rigid_options.specialize_kernels,
                                  applied_wrench=any(_has_gravity_compensation(e) for e in scene.rigid_entities),
                                  limit_timeconst=rigid_options.constraint_timeconst)
        s = self.solver
        self.n_qs, self.n_dofs, self.n_links = s.n_qs, s.n_dofs, s.n_links
        self.sim = None  # the scene's Simulator, set when it takes this bridge
        # parameters: base values from the model, then the user's setter calls replayed on top
        self.param_names = [k for k in PARAMS if k not in OPTIONAL_PARAMS or getattr(s, OPTIONAL_PARAMS[k]) is not None]
        self.core_params = [k for k in self.param_names if k not in OPTIONAL_PARAMS]
        base = s.initial_params(sim_options.gravity)
        self.param_base = {k: torch.as_tensor(v, device=self.device).to(self.dtype) for k, v in base.items()
                           if k in self.core_params}
        self._default_gains(scene.rigid_entities)
        self._limit_entities = self._limited_entities(scene.rigid_entities, rigid_options)
        self.param_base["invweight"] = self._invweight(self.param_base["armature"])
        if s.contact is not None:
            self.param_base["friction"] = self._field_to_torch(s.contact.geom_friction)
            if s.contact.zeta > 0.0:  # the mass-relative damper weighs each link through its articulation
                W, own = self.contact_link_weights(scene.rigid_entities)
                s.contact.set_link_weights(W.astype(s.np_dtype), own)
        # the applied wrench accumulated for the next step: a numpy (B, n_links, 6) array of what needs no
        # gradient and a torch tensor of what may, each None when nothing
        self._pending_np = self._pending_t = None
        self._step_applied = None  # the one the running step takes as its input
        self._loaded_applied = None  # the tensor whose values are in the solver's fields
        self._zero_applied = None
        if s.applied is not None:
            self.param_base["gravity_compensation"] = self._material_gcomp(scene.rigid_entities)
        self.param_ops = {k: [] for k in self.param_names}
        self.params = dict(self.param_base)
        self.force_lo = torch.as_tensor(base["force_lo"], device=self.device).to(self.dtype)
        self.force_hi = torch.as_tensor(base["force_hi"], device=self.device).to(self.dtype)
        self._upload_core_params()  # the fields hold the model's values, not the default gains: one launch
        self._loaded_params = dict(self.params)  # the tensors whose values are in the fields now
        self._params_dirty = set()
        self.reset_controls()
        q0 = torch.as_tensor(s.flat.np_qpos0, dtype=self.dtype, device=self.device).reshape(1, -1).repeat(self.B, 1)
        self.init_state = (q0, torch.zeros(self.B, self.n_dofs, dtype=self.dtype, device=self.device))
        self.set_state(*self.init_state)
        self._outputs = None
        self._nan_count = 0  # envs with a NaN record, as the last fused launch returned it
        if s.applied is not None:
            self._applied_on()

    def _limited_entities(self, entities, rigid_options):
        """The entities with a finite joint limit under the limit constraint (the default): their limits'
        impedance needs the dofs' inverse weights (_invweight)."""
        if not (rigid_options.enable_joint_limit and self.solver.limit_model == LIMITS_CONSTRAINT):
            return []
        lim = self.solver.flat.np_dof_limit
        return [ent for ent in entities
                if ent.n_dofs and np.isfinite(lim[ent._dof_start:ent._dof_start + ent.n_dofs]).any()]

    def _origin_jacobians_at_qpos0(self, ent):
        """([(1, 6, n) per link], link quaternions (1, n_links, 4)), float64, kept: the Jacobians of `ent`'s links'
        origins (the origin's velocity, the link's rate) and the links' orientations at its initial
        configuration."""
        cache = self.__dict__.setdefault("_origin_jac0", {})
        if ent.name not in cache:
            q0 = torch.as_tensor(self.solver.flat.np_qpos0, dtype=torch.float64)
            q = q0[ent._q_start:ent._q_start + ent.n_qs].reshape(1, -1)
            fk = ent.forward_kinematics(q)
            cache[ent.name] = ([ent._jacobian_at(q, i, fk=fk) for i in range(ent.n_links)], fk[1])
        return cache[ent.name]

    def _com_jacobians_at_qpos0(self, ent, com):
        """[(B, 6, n) per link]: the Jacobians of `ent`'s links' centres of mass `com` (B, n_links, 3, in the link
        frames) at its initial configuration: the COM's velocity v + w x r (r the COM from the origin, world
        axes), the link's rate."""
        jacs, quat = self._origin_jacobians_at_qpos0(ent)
        out = []
        for i, J in enumerate(jacs):
            J = J.expand(com.shape[0], -1, -1)
            r = (_quat_to_R(quat[:, i]) @ com[:, i, :, None]).expand(-1, -1, ent.n_dofs)
            out.append(torch.cat([J[:, :3] + torch.cross(J[:, 3:], r, dim=1), J[:, 3:]], dim=1))
        return out

    def mass_at_qpos0(self, ent):
        """(1, n, n) float64: `ent`'s joint-space mass matrix without armature at its initial configuration,
        from the model's masses and inertias (what Genesis computes its dofs_invweight from), kept."""
        cache = self.__dict__.setdefault("_mass0", {})
        if ent.name not in cache:
            ls = slice(ent._link_start, ent._link_start + ent.n_links)
            cache[ent.name] = self.mass_matrix_at_qpos0(ent, *(self.param_base[k][:1, ls].double()
                                                               for k in ("mass", "com", "inertia")))
        return cache[ent.name]

    def mass_matrix_at_qpos0(self, ent, mass, com, inertia):
        """(B, n, n) float64: `ent`'s joint-space mass matrix without armature at its initial configuration,
        from its links' masses (B, n_links), centres of mass in the link frames (B, n_links, 3) and inertias
        about them in link axes (B, n_links, 3, 3), float64."""
        _, quat = self._origin_jacobians_at_qpos0(ent)
        M = mass.new_zeros(mass.shape[0], ent.n_dofs, ent.n_dofs)
        for i, J in enumerate(self._com_jacobians_at_qpos0(ent, com)):
            R = _quat_to_R(quat[:, i])
            M = M + mass[:, i, None, None] * J[:, :3].transpose(-1, -2) @ J[:, :3]
            M = M + J[:, 3:].transpose(-1, -2) @ (R @ inertia[:, i] @ R.transpose(-1, -2)) @ J[:, 3:]
        return M

    def _inverse_mass_at_qpos0(self, ent, armature):
        """(M0 + diag(armature))^-1 (armature (B, ent.n_dofs), differentiable in it; M0 mass_at_qpos0), or None
        where that matrix is singular (a joint that moves no mass and has no armature)."""
        M = self.mass_at_qpos0(ent).to(armature.dtype) + torch.diag_embed(armature)
        inv, info = torch.linalg.inv_ex(M)
        if bool((info != 0).any()) or not bool(torch.isfinite(inv).all()):
            return None
        return inv

    def entity_invweight(self, ent, armature):
        """(B, ent.n_dofs) Genesis's dofs_invweight: diag((M0 + diag(armature))^-1), M0 `ent`'s joint-space
        mass matrix at its initial configuration with the model's masses (mass_at_qpos0) and `armature` its
        dofs' (B, ent.n_dofs), a free joint's three translational and three rotational entries each their
        mean as Genesis's. Genesis computes it at build and again when set_dofs_armature changes the armature
        (v0.4.5 rigid_solver.py _init_invweight_and_meaninertia; masses set later leave it as it is), and so
        do we; differentiable in the armature. Raises when the matrix is singular."""
        inv = self._inverse_mass_at_qpos0(ent, armature)
        w = None if inv is None else torch.diagonal(inv, dim1=-2, dim2=-1)
        if w is None or not bool((w > 0).all()):
            raise GenesisException(
                f"entity '{ent.name}': its joint-space mass matrix at the initial configuration, armature included, "
                "is singular (a joint moves no mass and has no armature), and the joint-limit constraint needs "
                "its inverse (Genesis's dofs_invweight). Give the links a mass and inertia or the joints an "
                "armature (gs.morphs.URDF / MJCF(default_armature=0.1), set_dofs_armature), or use penalty "
                "springs for the limits (gs.options.RigidOptions(joint_limit_stiffness=1e4)).")
        avg = torch.eye(ent.n_dofs, dtype=w.dtype, device=w.device)  # a free joint's blocks averaged
        for j in ent.joints:
            if j.type == "free":
                for k in (j.dof_start_local, j.dof_start_local + 3):
                    avg[k:k + 3, k:k + 3] = 1.0 / 3.0
        return w @ avg

    def contact_link_weights(self, entities):
        """(W, own_mass): the links' weights for the mass-relative contact damper (contact.law.func_link_invmass),
        numpy (n_links, 3, 3) and (n_links,). W: J (M0 + diag(armature))^-1 J^T, J the Jacobian of the link's
        centre of mass, M0 the entity's mass matrix at its initial configuration (mass_at_qpos0), the model's
        masses and armature: the inverse mass the link's centre of mass has through the articulation, as
        MuJoCo's body_invweight0 (whose mean of the diagonal MuJoCo takes; here the normal's direction picks
        the entry). own_mass 1 for a link that moves alone (an entity of one link on a free joint without
        armature: W is then 1 / mass, and the link's own mass follows the mass setters and their
        gradients) and for an entity whose matrix is singular (massless links without armature), whose
        links take their own masses as under the fixed damper."""
        W = np.zeros((max(self.n_links, 1), 3, 3))
        own = np.ones(max(self.n_links, 1), dtype=np.int32)
        arm = self.param_base["armature"][:1].double()
        for ent in entities:
            if ent.n_dofs == 0:
                continue
            d = slice(ent._dof_start, ent._dof_start + ent.n_dofs)
            if ent.n_links == 1 and ent.joints[0].type == "free" and not bool((arm[:, d] != 0).any()):
                continue
            inv = self._inverse_mass_at_qpos0(ent, arm[:, d])
            if inv is None:
                continue
            com = self.param_base["com"][:1, ent._link_start:ent._link_start + ent.n_links].double()
            for i, J in enumerate(self._com_jacobians_at_qpos0(ent, com)):
                W[ent._link_start + i] = (J[:, :3] @ inv @ J[:, :3].transpose(-1, -2))[0].numpy()
                own[ent._link_start + i] = 0
        return W, own

    def _invweight(self, armature):
        """(B, n_dofs) the limit constraint's inverse weights: entity_invweight for each entity with limits (1
        elsewhere: unused), differentiable in the armature."""
        out = torch.ones_like(armature)
        for ent in self._limit_entities:
            d = torch.arange(ent._dof_start, ent._dof_start + ent.n_dofs, device=self.device)
            out = index_put(out, torch.arange(self.B, device=self.device), d,
                            self.entity_invweight(ent, armature[:, d]))
        return out

    def _default_gains(self, entities):
        """Genesis's PD gains for what the model leaves unset: kp 100, kv 10 on revolute and prismatic
        joints (a URDF's <safety_controller> or an MJCF actuator sets its own), 0 on free joints.
        They act only on dofs given a position or velocity target."""
        kp, kv = self.param_base["kp"].clone(), self.param_base["kv"].clone()
        d = 0
        for ent in entities:
            for link in ent.model.links:
                n = JOINT_NV[link.joint_type]
                if link.joint_type in ("revolute", "prismatic"):
                    kp[:, d] = DEFAULT_KP if link.kp is None else link.kp
                    kv[:, d] = DEFAULT_KV if link.kv is None else link.kv
                d += n
        assert d == self.n_dofs, (d, self.n_dofs)
        self.param_base["kp"], self.param_base["kv"] = kp, kv

    # ---------------------------------------------------------------- applied wrenches
    def _material_gcomp(self, entities):
        """(B, n_links): every link's gravity compensation, its entity's material's (values only)."""
        g = torch.zeros(self.B, self.n_links, dtype=self.dtype, device=self.device)
        for ent in entities:
            gc = ent.material.gravity_compensation
            g[:, ent._link_start: ent._link_start + ent.n_links] = float(gc.detach()) if torch.is_tensor(gc) else float(gc)
        return g

    def after_build(self, entities):
        """Once the scene is built: a material's gravity compensation given as a tensor that requires grad
        becomes the entity's parameter through its setter, so that it receives gradients (rollout after
        rollout)."""
        for ent in entities:
            gc = ent.material.gravity_compensation
            if torch.is_tensor(gc) and gc.requires_grad:
                ent.set_gravity_compensation(gc)

    def enable_applied(self):
        """Give the solver applied wrenches (if it has none yet): the user's first force, or a gravity
        compensation set after build. The parameter list grows by gravity_compensation (zero)."""
        if self.solver.applied is not None:
            return
        self.solver.enable_applied()
        self.param_names.append("gravity_compensation")
        self.param_base["gravity_compensation"] = torch.zeros(self.B, self.n_links, dtype=self.dtype,
                                                              device=self.device)
        self.param_ops["gravity_compensation"] = []
        self.params["gravity_compensation"] = self.param_base["gravity_compensation"]
        self._applied_on()

    def _applied_on(self):
        self._zero_applied = torch.zeros(self.B, self.n_links, 6, dtype=self.dtype, device=self.device)
        self._loaded_applied = self._zero_applied  # AppliedWrench.clear() zeroed the fields
        self._params_dirty.add("gravity_compensation")
        self._loaded_params.pop("gravity_compensation", None)

    @property
    def has_applied(self):
        return self.solver.applied is not None

    def add_applied(self, envs, links, force, moment):
        """Add to the wrench of the next step, on links (numpy int array) of envs (numpy int array), the force
        and the moment about the link origin (world axes), each (len(envs), len(links), 3) or None (zero):
        numpy arrays in the solver's precision (kept in numpy: no autograd to carry), or torch tensors.
        Repeated links add up."""
        self.enable_applied()
        if torch.is_tensor(force) or torch.is_tensor(moment):
            ref = force if torch.is_tensor(force) else moment
            parts = [torch.zeros_like(ref) if x is None else x.to(ref.dtype) if torch.is_tensor(x)
                     else torch.as_tensor(np.array(x), device=ref.device).to(ref.dtype) for x in (force, moment)]
            w = torch.cat(parts, -1).to(self.dtype)
            e = torch.as_tensor(envs, device=self.device)
            l = torch.as_tensor(links, device=self.device)  # noqa: E741
            base = self._pending_t if self._pending_t is not None else self._zero_applied
            self._pending_t = base.index_put((e[:, None], l[None, :]), w, accumulate=True)
            return
        if self._pending_np is None:
            self._pending_np = np.zeros((self.B, self.n_links, 6), dtype=self.solver.np_dtype)
        idx = (envs[:, None], links[None, :])
        # np.add.at sums repeated indices; plain += (faster) keeps one of them
        repeats = ((len(links) > 1 and len(set(links.tolist())) < len(links))
                   or (len(envs) > 1 and len(set(envs.tolist())) < len(envs)))
        for k, x in ((0, force), (3, moment)):
            if x is None:
                continue
            if repeats:
                np.add.at(self._pending_np[..., k:k + 3], idx, x)
            else:
                self._pending_np[envs[:, None], links[None, :], k:k + 3] += x

    def clear_applied(self, envs=None):
        """Drop the wrench applied for the next step (of the envs flagged in the numpy bool array `envs`)."""
        if envs is None:
            self._pending_np = self._pending_t = None
            return
        if self._pending_np is not None:
            self._pending_np[envs] = 0
        if self._pending_t is not None:
            keep = torch.as_tensor(~envs, device=self.device).to(self.dtype).reshape(-1, 1, 1)
            self._pending_t = self._pending_t * keep

    def _take_applied(self):
        """The wrench of the step about to run, as a tensor (its input) and, where it came from numpy
        alone, that array (a cheaper upload); the pending wrench is consumed."""
        a, t = self._pending_np, self._pending_t
        self._pending_np = self._pending_t = None
        if a is None and t is None:
            return self._zero_applied, None
        if t is None:
            return torch.from_numpy(a).to(self.device).to(self.dtype), a
        return (t + torch.from_numpy(a).to(t.device).to(t.dtype) if a is not None else t), None

    def _load_applied(self, w, raw=None):
        if w is not self._loaded_applied:
            self.solver.write_applied(raw if raw is not None else self._c(w))
            self._loaded_applied = w

    # ---------------------------------------------------------------- helpers
    def param_field(self, name):
        """The solver field behind a parameter (a dotted path, e.g. 'contact.geom_friction')."""
        obj = self.solver
        for part in PARAMS[name][0].split("."):
            obj = getattr(obj, part)
        return obj

    def _field_to_torch(self, field):
        return torch.as_tensor(np.ascontiguousarray(field.to_numpy())).to(self.device).to(self.dtype)

    def _c(self, t):
        return t.detach().to(self.dtype).contiguous()

    # ---------------------------------------------------------------- state
    def set_state(self, qpos, qvel):
        self.qpos, self.qvel = qpos, qvel
        self._state_on_device = False
        self._outputs = None

    def get_state(self):
        if self.qpos is None:
            self.qpos, self.qvel = self._split(self._read_state(0))
        return self.qpos, self.qvel

    state = get_state

    def inputs(self):
        x = list(self.get_state()) + [self.ctrl] + [self.params[k] for k in self.param_names]
        if self.has_applied:
            x.append(self._step_applied if self._step_applied is not None else self._zero_applied)
        return x

    def context(self):
        """The control modes of the step (which of the packed controls act)."""
        return self.ctrl_mode

    def state_from_outputs(self, outs):
        return self._split(outs[0])

    def _read_state(self, slot):
        x = torch.empty(self.B, self.n_qs + self.n_dofs, dtype=self.dtype, device=self.device)
        if self.n_qs + self.n_dofs:
            self.solver.read_state(slot, x)
        return x

    def _split(self, x):
        return x[:, : self.n_qs], x[:, self.n_qs:]

    def _write_state(self, q, v):
        if self.n_qs + self.n_dofs:
            self.solver.write_state(0, self._c(torch.cat([q, v], -1)))

    def _upload(self):
        if not self._state_on_device:
            self._write_state(*self.get_state())
            self._state_on_device = True
        if self._ctrl_dirty:
            self._load_ctrl(self.ctrl, self.ctrl_mode)
            self._ctrl_dirty = False
        if self._params_dirty:
            self._load_params(self._params_dirty)
            self._params_dirty = set()

    def _load_params(self, names):
        """Upload the parameters among `names` whose tensors are not the ones in the fields (the core's
        all together, packed: one launch)."""
        stale = [k for k in names if self._loaded_params.get(k) is not self.params[k]]
        if not stale:
            return
        if any(k in self.core_params for k in stale):
            self._upload_core_params()
        for k in stale:
            if k in OPTIONAL_PARAMS:
                self.param_field(k).load(self._c(self.params[k]))
        for k in stale:
            self._loaded_params[k] = self.params[k]

    def _upload_core_params(self):
        parts = [self.params[k] if k in self.params else getattr(self, k) for k, _ in self.solver.param_layout()]
        self.solver.set_params(self._c(torch.cat([p.detach().reshape(self.B, -1).to(self.dtype) for p in parts], -1)))

    # ---------------------------------------------------------------- solver-wide results (scene.py)
    def _result(self, name, shape):
        """A torch copy of one of the solver's per-env dof results (RigidSolver.read_result)."""
        dt = torch.float64 if self.solver.np_dtype == np.float64 else torch.float32
        out = torch.empty(*shape, dtype=dt)
        self.solver.read_result(name, out)
        return out.to(self.device).to(self.dtype)

    def read_mass_matrix(self):
        """(B, n_dofs, n_dofs): the mass matrix the last RigidSolver.mass_matrix computed (lower triangle)."""
        return self._result("mass_mat", (self.B, self.n_dofs, self.n_dofs))

    def read_qacc(self):
        """(n_evals, B, n_dofs): the accelerations of the last step's evaluations."""
        return self._result("qacc", (self.B, self.solver.n_evals, self.n_dofs)).transpose(0, 1).contiguous()

    def read_dof_tau(self):
        """(B, n_dofs): the actuator forces of the last evaluation."""
        return self._result("dof_tau", (self.B, 1, self.n_dofs))[:, 0]

    def read_dof_qf(self):
        """(B, n_dofs): the actuator, damping and spring forces less the bias, of the last evaluation."""
        return self._result("dof_qf", (self.B, 1, self.n_dofs))[:, 0]

    # ---------------------------------------------------------------- controls and parameters
    def reset_controls(self):
        self.ctrl = torch.zeros(self.B, 3, self.n_dofs, dtype=self.dtype, device=self.device)
        self.ctrl_mode = torch.zeros(self.B, self.n_dofs, dtype=torch.int32, device=self.device)
        self._loaded_mode = None
        self._ctrl_dirty = True

    def _load_ctrl(self, ctrl, mode):
        if not self.n_dofs:
            return
        self.solver.write_ctrl(self._c(ctrl))
        if self._loaded_mode is not mode:
            self.solver.write_ctrl_mode(mode)
            self._loaded_mode = mode

    def set_ctrl(self, kind, values, envs, idx, mode):
        row = CTRL.index(kind)
        values = values.to(self.dtype).reshape(len(envs), len(idx))
        out = self.ctrl.clone()
        full_envs, span = as_slices(envs, self.B), as_span(idx)
        if full_envs and span is not None:
            # basic slicing: autograd keeps no index tensors per step
            out[:, row, span] = values
        else:
            out[envs[:, None], row, idx[None, :]] = values
        self.ctrl = out
        if mode is not None:
            # a new tensor when a mode changes (a recorded step keeps the one it ran with: context()); with
            # every env and a run of dofs, basic slicing: the advanced index took 132 us of a 1,024-env step
            if full_envs and span is not None:
                if not bool((self.ctrl_mode[:, span] == mode).all()):
                    m = self.ctrl_mode.clone()
                    m[:, span] = mode
                    self.ctrl_mode = m
            else:
                m = self.ctrl_mode.clone()
                m[envs[:, None], idx[None, :]] = mode
                if not torch.equal(m, self.ctrl_mode):
                    self.ctrl_mode = m
        self._ctrl_dirty = True

    def set_param(self, name, values, envs, idx):
        # a later call on the same entries supersedes an earlier one (keeps the replay list short)
        self.param_ops[name] = [op for op in self.param_ops[name]
                                if not (torch.equal(op[1], envs) and torch.equal(op[2], idx))]
        self.param_ops[name].append((values, envs, idx))
        self.params[name] = index_put(self.params[name], envs, idx, values)
        self._params_dirty.add(name)
        if name == "armature" and self._limit_entities:
            self.params["invweight"] = self._invweight(self.params["armature"])
            self._params_dirty.add("invweight")

    def rebuild_params(self):
        """A new rollout: parameter tensors are recomposed from the user's setter calls so a leaf
        parameter keeps receiving gradients epoch after epoch."""
        for name, ops in self.param_ops.items():
            if not ops:
                continue
            # a value made from a leaf is made again, so the leaf keeps receiving gradients; any other keeps its
            # number only (its graph belongs to the rollout it came from: grad/remake.py)
            self.params[name] = recomposed(self.param_base[name], ops, name)
            self._params_dirty.add(name)
        if self.param_ops["armature"] and self._limit_entities:
            self.params["invweight"] = self._invweight(self.params["armature"])
            self._params_dirty.add("invweight")

    def set_force_range(self, lo, hi, envs, idx):
        self.force_lo = index_put(self.force_lo, envs, idx, lo.detach())
        self.force_hi = index_put(self.force_hi, envs, idx, hi.detach())
        self._upload_core_params()

    # ---------------------------------------------------------------- stepping
    def upload(self):
        """Before a step: the current values into the fields, and the step takes the wrench applied since
        the last one (or none)."""
        self._upload()
        if self.has_applied:
            self._step_applied, raw = self._take_applied()
            self._load_applied(self._step_applied, raw)

    def step_fused(self, step):
        self._nan_count = self.solver.step(step)

    def substep(self, i, grad, step):
        if grad:
            self.solver.substep(i)
        else:
            n = self.solver.substep_fused(step, i)
            if i == self.solver.substeps - 1:
                self._nan_count = n

    def untracked_step_done(self):
        self.qpos = self.qvel = None
        self._state_on_device = True
        self._outputs = None

    def read_outputs(self):
        """The step's result (packed state of the last slot), which also becomes slot 0."""
        self._outputs = None
        return [self._read_state(self.solver.last_slot)]

    def count_nonfinite(self, step, clear=None):
        """How many envs have a record of a non-finite state: the fused step records them (per env, at
        the step it found them) and returns the count with its launch, so this read is free; None when
        the state is a torch tensor (gradient path: check_finite looks at it). clear (numpy bool (B,)):
        forget those envs' records instead (scene.reset)."""
        if clear is not None:
            self._nan_count = self.solver.reset_nan(clear)
            return self._nan_count
        if self.qpos is not None:
            return None
        return self._nan_count

    def check_finite(self):
        """{env: description} of the envs whose state is not finite now, naming the entity and the
        first non-finite entry (the scene's NaN watch, nan_watch.py, names the step and acts)."""
        q, v = (x.detach() for x in self.get_state())
        if all_finite(q, v):
            return {}
        bad_q, bad_v = ~torch.isfinite(q), ~torch.isfinite(v)
        bad = bad_q.any(-1) | bad_v.any(-1)
        out = {}
        if not bool(bad.any()):
            return out
        for i_b in torch.nonzero(bad).reshape(-1).tolist():
            name, x, b = ("qpos", q, bad_q) if bool(bad_q[i_b].any()) else ("qvel", v, bad_v)
            i = int(torch.nonzero(b[i_b])[0])
            ent, local = _entity_of(self.scene.rigid_entities, i, name)
            out[i_b] = f"entity '{ent.name}': {name}[{local}] = {x[i_b, i].item()}"
        return out

    # ---------------------------------------------------------------- the rigid part of the step node
    def _split_inputs(self, values):
        """A recorded step's inputs (qpos, qvel, ctrl, *params[, applied]) as (head, {param: x}, applied):
        a step recorded before the solver had applied wrenches has neither gravity_compensation nor
        applied (None: zero)."""
        names = self.param_names
        if self.has_applied and len(values) == 3 + len(names) - 1:
            names = [k for k in names if k != "gravity_compensation"]
            return values[:3], dict(zip(names, values[3:])), None
        applied = values[3 + len(names)] if self.has_applied else None
        return values[:3], dict(zip(names, values[3:3 + len(names)])), applied

    def load(self, values, mode):
        """Write a step's inputs (qpos, qvel, ctrl, *params[, applied]) into the fields, for its backward or
        replay."""
        (qpos, qvel, ctrl), given, applied = self._split_inputs(values)
        if self.has_applied:
            if "gravity_compensation" not in given:  # (zero before applied wrenches came: param_base's)
                given["gravity_compensation"] = self.param_base["gravity_compensation"]
            self._load_applied(applied if applied is not None else self._zero_applied)
        params = [given[k] for k in self.param_names]
        self._write_state(qpos, qvel)
        self._load_ctrl(ctrl, mode)
        self._ctrl_dirty = True
        changed = [k for k, p in zip(self.param_names, params) if self._loaded_params.get(k) is not p]
        if changed:
            current = dict(self.params)
            self.params.update(zip(self.param_names, params))
            self._load_params(changed)
            self.params = current
            self._params_dirty.update(changed)
        self._state_on_device = False
        self._outputs = None

    def clear_grads(self):
        self.solver.clear_grads()

    def vjp(self, grads, loss):
        (gx,) = grads
        if gx is None:
            return
        # the solver accumulates into its own scalar, whose adjoint its clear_grads seeds to 1 (kernel_vjp)
        self.solver.accumulate_vjp(self.solver.last_slot, self._c(gx))

    def input_grads(self, needs, step):
        """Gradients of one step's inputs (qpos, qvel, ctrl, *params[, applied]) from the adjoint fields."""
        s = self.solver
        (n0, n1, n2), wanted, applied = self._split_inputs(list(needs))
        out = self._input_grads([n0, n1, n2] + [wanted[k] for k in wanted], list(wanted), step)
        if applied is not None:
            g = None
            if applied:
                g = torch.empty(self.B, self.n_links, 6, dtype=self.dtype, device=self.device)
                s.read_applied_grad(g)
                raise_if_nan_grad([g], step)
            out.append(g)
        return out

    def _input_grads(self, needs, param_names, step):
        s = self.solver
        nx = self.n_qs + self.n_dofs
        g = torch.empty(self.B, nx + 3 * self.n_dofs, dtype=self.dtype, device=self.device)
        s.read_grads(g)
        out = [g[:, : self.n_qs] if needs[0] else None, g[:, self.n_qs: nx] if needs[1] else None,
               g[:, nx:].reshape(self.B, 3, self.n_dofs) if needs[2] else None]
        wanted = dict(zip(param_names, needs[3:]))
        packed = {}
        if any(wanted[k] for k in self.core_params):
            layout = [(k, w) for k, w in s.param_layout() if k in self.core_params]
            pg = torch.empty(self.B, sum(w for _, w in layout), dtype=self.dtype, device=self.device)
            s.read_param_grads(pg)
            packed = dict(zip([k for k, _ in layout], torch.split(pg, [w for _, w in layout], -1)))
        for k in param_names:
            if not wanted[k]:
                out.append(None)
            elif k in packed:
                out.append(packed[k].reshape(self.params[k].shape))
            else:
                pg = torch.empty_like(self.params[k], dtype=self.dtype)
                s.read_param_grad(self.param_field(k), pg)
                out.append(pg)
        raise_if_nan_grad(out, step)
        return out

    def outputs(self):
        """(links pos, quat, vel, ang) at the current state, each (B, n_links, 3 or 4)."""
        if self._outputs is None:
            self._upload()
            s = self.solver
            s.scratch_overwritten()
            s.kinematics(0)
            L = self.n_links
            o = [torch.empty(self.B, L, k, dtype=self.dtype, device=self.device) for k in (3, 4, 3, 3)]
            s.read_link_outputs(*o)
            self._outputs = tuple(o)
        return self._outputs

    def link_outputs(self):
        q, v = self.get_state()
        if self.requires_grad and torch.is_grad_enabled() and (q.requires_grad or v.requires_grad):
            out = OutputFunction.apply(self, q, v)
            self._outputs = tuple(o.detach() for o in out)
            return out
        return self.outputs()

    def backward_outputs(self, state, grads, step):
        """Gradients of (qpos, qvel) given those of the link outputs: kinematics replayed on a Tape."""
        s = self.solver
        self._write_state(*state)
        self._state_on_device = False
        self._outputs = None
        s.clear_grads()
        L = self.n_links
        g = [self._c(x) if x is not None else torch.zeros(self.B, L, k, dtype=self.dtype, device=self.device)
             for x, k in zip(grads, (3, 4, 3, 3))]
        s.scratch_overwritten()
        with ti.ad.Tape(loss=self.sim.loss, clear_gradients=False):
            s.kinematics(0)
            s.accumulate_link_vjp(*g)
        g = torch.empty(self.B, self.n_qs + 4 * self.n_dofs, dtype=self.dtype, device=self.device)
        s.read_grads(g)
        gq, gv = g[:, : self.n_qs], g[:, self.n_qs: self.n_qs + self.n_dofs]
        with incoming_grads(grads, self.sim.nan_watch):
            raise_if_nan_grad([gq, gv], step)
        return gq, gv

    # ---------------------------------------------------------------- rollouts
    def new_rollout(self, state):
        qpos, qvel = state
        self._pending_np = self._pending_t = self._step_applied = None
        self._nan_count = self.solver.reset_nan()
        self.reset_controls()
        self.rebuild_params()
        self.set_state(qpos, qvel)


def _has_gravity_compensation(ent):
    gc = ent.material.gravity_compensation
    return bool(torch.is_tensor(gc)) or float(gc) != 0.0


def _entity_of(entities, i, name):
    for ent in entities:
        start, n = (ent._q_start, ent.n_qs) if name == "qpos" else (ent._dof_start, ent.n_dofs)
        if start <= i < start + n:
            return ent, i - start
    return entities[0], i
