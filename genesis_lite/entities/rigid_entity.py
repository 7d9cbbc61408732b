"""RigidEntity: a thin view (index ranges) over the rigid solver's state, with Genesis's API.

Every getter returns a genesis_lite.grad.Tensor on gs.device in the scene precision, with a leading
env axis when the scene was built with n_envs > 0. Every setter takes torch tensors, numpy arrays or
lists; with requires_grad=True scenes, tensors that require grad carry gradients into the rollout.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import List, Optional

import numpy as np
import torch

from solvers.rigid.model import JOINT_NQ, JOINT_NV, EntityModel

from ..errors import GenesisException, GenesisWarning, ZeroGainWarning
from ..grad.indexing import all_finite, index_put
from ..grad.remake import derive, recipe
from ..grad.tensor import wrap
from ..grad.views import routed
from ..utils.geom import _unit_quat_to_R as _quat_to_R
from ..utils.geom import quat_to_xyz, xyz_to_quat
from .contact_api import ContactMixin
from .external_api import GravityCompensationMixin
from .kinematics_api import KinematicsMixin


@dataclass
class RigidLink:
    name: str
    idx_local: int
    idx: int
    parent_idx_local: int
    entity: "RigidEntity"

    @property
    def joint(self):
        return self.entity.joints[self.idx_local]

    def get_mass(self, envs_idx=None):
        """This link's mass (kg), per env in a batched scene (Genesis's RigidLink.get_mass)."""
        return self.entity.get_links_mass([self.idx_local], envs_idx)[..., 0]

    def get_pos(self, envs_idx=None):
        """This link's origin in the world frame (m): (3,), or (n_envs, 3) in a batched scene (Genesis's
        RigidLink.get_pos); differentiable, as entity.get_links_pos."""
        return self.entity.get_links_pos([self.idx_local], envs_idx)[..., 0, :]

    def get_quat(self, envs_idx=None):
        """This link's orientation in the world frame (w, x, y, z), as get_pos."""
        return self.entity.get_links_quat([self.idx_local], envs_idx)[..., 0, :]

    def get_vel(self, envs_idx=None):
        """The linear velocity (m/s, world) of this link's origin, as get_pos."""
        return self.entity.get_links_vel([self.idx_local], envs_idx)[..., 0, :]

    def get_ang(self, envs_idx=None):
        """This link's angular velocity (rad/s, world), as get_pos."""
        return self.entity.get_links_ang([self.idx_local], envs_idx)[..., 0, :]

    @property
    def is_fixed(self) -> bool:
        """Whether this link is fixed to the world (no joint with dofs on its way to the root)."""
        return self.entity._link_is_fixed(self.idx_local)

    def set_mass(self, mass, envs_idx=None):
        """Set this link's mass (kg), as Genesis's RigidLink.set_mass: its rotational inertia is scaled by the
        same ratio (a uniformly denser body, centre of mass kept). A number, or per env (n_envs,) in a
        batched scene; differentiable. On a link fixed to the world it changes nothing and warns, as
        Genesis does (entity.set_links_mass sets the mass alone, on any link)."""
        if self.is_fixed:
            warnings.warn(f"entity '{self.entity.name}', link '{self.name}': the link is fixed to the world, so its "
                          "mass has no effect; set_mass skipped (as in Genesis)", GenesisWarning, stacklevel=2)
            return
        ent = self.entity
        envs, ls = ent._envs(envs_idx), ent._links([self.idx_local])
        old_m = ent._sim.params["mass"].detach()[envs][:, ls]
        old_i = ent._sim.params["inertia"].detach()[envs][:, ls]
        # (a derived value keeps its recipe through the reshape: grad/remake.py)
        m = derive(lambda x: (x if torch.is_tensor(x) else torch.as_tensor(x)).reshape(*np.shape(x), 1), mass)
        new_m = ent._values(m, envs, 1, "mass")
        ent._set_links_mass(new_m, envs, ls, "set_mass")
        ent._set_links_inertia(derive(lambda v: old_i * (v / old_m.clamp_min(1e-300))[..., None, None], new_m),
                               envs, ls, "set_mass")


@dataclass
class RigidJoint:
    name: str
    type: str
    idx_local: int
    link_idx_local: int
    dof_start_local: int
    n_dofs: int
    q_start_local: int
    n_qs: int
    entity: Optional["RigidEntity"] = field(default=None, repr=False, compare=False)

    # Genesis's index names. Without `_local` they number the scene's rigid solver (every rigid entity's
    # links, joints, positions q and dofs, in the order of add_entity); with it, the joint's entity. A
    # `*s_idx*` name is always a list; the older singular `dof_idx*` / `q_idx*` (deprecated in Genesis) are an
    # int for one index, None for none, a list otherwise. Known from add_entity on, before build too.
    @property
    def idx(self) -> int:
        """The joint's index among the scene's joints (one per link: the link's joint to its parent)."""
        return self.entity.joint_start + self.idx_local

    @property
    def link(self) -> "RigidLink":
        """The link this joint moves (Genesis's joint.link)."""
        return self.entity.links[self.link_idx_local]

    @property
    def dof_start(self) -> int:
        """The joint's first dof in the scene's dof numbering."""
        return self.entity.dof_start + self.dof_start_local

    @property
    def dof_end(self) -> int:
        return self.dof_start + self.n_dofs

    @property
    def q_start(self) -> int:
        """The joint's first position coordinate in the scene's q numbering (qpos)."""
        return self.entity.q_start + self.q_start_local

    @property
    def q_end(self) -> int:
        return self.q_start + self.n_qs

    @property
    def dofs_idx(self):
        """The joint's dofs in the scene's dof numbering: `scene.rigid_solver`'s dofs_idx= arguments."""
        return list(range(self.dof_start, self.dof_end))

    @property
    def dofs_idx_local(self):
        """The joint's dofs in its entity: the entity's dofs_idx_local= arguments."""
        return list(range(self.dof_start_local, self.dof_start_local + self.n_dofs))

    @property
    def qs_idx(self):
        return list(range(self.q_start, self.q_end))

    @property
    def qs_idx_local(self):
        """The joint's position coordinates in its entity: the entity's qs_idx_local= arguments."""
        return list(range(self.q_start_local, self.q_start_local + self.n_qs))

    @staticmethod
    def _one_or_list(idx):
        return idx[0] if len(idx) == 1 else (None if not idx else idx)

    @property
    def dof_idx(self):
        return self._one_or_list(self.dofs_idx)

    @property
    def dof_idx_local(self):
        return self._one_or_list(self.dofs_idx_local)

    @property
    def q_idx(self):
        return self._one_or_list(self.qs_idx)

    @property
    def q_idx_local(self):
        return self._one_or_list(self.qs_idx_local)


def _raise_if_not_finite(t, who, what, batched):
    """Refuse NaN / inf in a setter's values, whether or not they require grad (the check reads a
    detached view, so a finite value keeps its autograd history). `t` is (envs, n, ...)."""
    if all_finite(t):
        return
    bad = ~torch.isfinite(t.detach())
    if not bool(bad.any()):
        return
    first = [int(i) for i in torch.nonzero(bad)[0]]
    where = first if batched else first[1:]
    value = t.detach()[tuple(first)].item()
    hint = (" It requires grad: if an optimiser step produced it, the previous gradient or step size diverged (look "
            "for a GradientGrowthWarning, shorten the horizon, lower the learning rate or clip the gradient)."
            if t.requires_grad else "")
    raise GenesisException(
        f"{who}: {what} contains NaN or infinite values "
        f"({int(bad.sum())} of {bad.numel()}; {what}{where} = {value}). Pass finite values.{hint}")


class RigidEntity(ContactMixin, KinematicsMixin, GravityCompensationMixin):
    """An articulated rigid body (URDF robot) or a single rigid shape in a scene."""

    @property
    def uid(self):
        """Genesis's entity id (gs.UID: `str(uid)`, `uid.short()`), given by scene.add_entity; unique in
        the scene by its short form. The entity's index in the scene, in the order of add_entity, is `idx`."""
        return self._uid

    def __init__(self, scene, idx: int, model: EntityModel, morph, material):
        self._scene = scene
        self.idx = idx
        self.model = model
        self.morph = morph
        self.material = material
        self.name = model.name
        self.links: List[RigidLink] = []
        self.joints: List[RigidJoint] = []
        q = d = 0
        for i, l in enumerate(model.links):
            self.links.append(RigidLink(l.name, i, -1, l.parent, self))
            nq, nv = JOINT_NQ[l.joint_type], JOINT_NV[l.joint_type]
            self.joints.append(RigidJoint(l.joint_name, l.joint_type, i, i, d, nv, q, nq, self))
            q += nq
            d += nv
        self.n_links, self.n_qs, self.n_dofs = len(self.links), q, d
        self._link_start = self._q_start = self._dof_start = -1
        self._zero_gain = {}  # gain -> (the scene's gain tensor, this entity's (envs, dofs) mask of zeros)
        self._zero_gain_warned = set()  # (gain, dofs) already warned about

    # ---------------------------------------------------------------- structure
    def _on_build(self, link_start, q_start, dof_start):
        self._link_start, self._q_start, self._dof_start = link_start, q_start, dof_start
        for l in self.links:
            l.idx = link_start + l.idx_local
        # per-dof q index (for 1-dof joints) used by get/set_dofs_position
        self._dof_q_local = np.full(self.n_dofs, -1, dtype=np.int64)
        for j in self.joints:
            if j.n_dofs == 1:
                self._dof_q_local[j.dof_start_local] = j.q_start_local

    @property
    def n_joints(self):
        return len(self.joints)

    def _solver_starts(self):
        """(links, qs, dofs) of the rigid entities added before this one: where its own begin in the scene's
        rigid solver (the same before build as after)."""
        if self._dof_start >= 0:
            return self._link_start, self._q_start, self._dof_start
        before = self._scene.rigid_entities[:self._solver_idx]
        return (sum(e.n_links for e in before), sum(e.n_qs for e in before), sum(e.n_dofs for e in before))

    # Genesis's ranges of this entity in the scene's rigid solver (its joints are one per link)
    @property
    def link_start(self) -> int:
        return self._solver_starts()[0]

    @property
    def link_end(self) -> int:
        return self.link_start + self.n_links

    @property
    def joint_start(self) -> int:
        return self._solver_starts()[0]

    @property
    def joint_end(self) -> int:
        return self.joint_start + self.n_joints

    @property
    def q_start(self) -> int:
        return self._solver_starts()[1]

    @property
    def q_end(self) -> int:
        return self.q_start + self.n_qs

    @property
    def dof_start(self) -> int:
        return self._solver_starts()[2]

    @property
    def dof_end(self) -> int:
        return self.dof_start + self.n_dofs

    @property
    def base_link(self):
        return self.links[0]

    @property
    def base_joint(self):
        return self.joints[0]

    @property
    def is_built(self):
        return self._scene.is_built

    def get_joint(self, name: str) -> RigidJoint:
        for j in self.joints:
            if j.name == name:
                return j
        raise GenesisException(f"entity '{self.name}' has no joint '{name}'; its joints are {[j.name for j in self.joints]}"
                               " (fixed joints are merged into their parent link)")

    def get_link(self, name: str) -> RigidLink:
        for l in self.links:
            if l.name == name:
                return l
        raise GenesisException(f"entity '{self.name}' has no link '{name}'; its links are {[l.name for l in self.links]}"
                               " (links attached by fixed joints are merged into their parent)")

    # ---------------------------------------------------------------- index and value handling
    @property
    def _sim(self):
        if not self._scene.is_built:
            raise GenesisException(f"entity '{self.name}': call scene.build() before reading or setting its state")
        return self._scene._rigid

    def _idx(self, idx, n, what, start):
        if isinstance(idx, slice):  # Genesis scripts pass slices (dofs_idx_local=slice(6, 18))
            idx = list(range(n))[idx]
        if idx is None:
            out = torch.arange(n, device=self._device)
        else:
            t = torch.as_tensor(idx.detach().cpu() if isinstance(idx, torch.Tensor) else idx)
            if t.dtype == torch.bool and what == "envs_idx":
                # Genesis's boolean env mask (e.g. scene.get_error_envs_mask())
                if t.shape != (n,):
                    raise GenesisException(f"entity '{self.name}': a boolean envs_idx must have shape ({n},) (one flag "
                                           f"per env), got {tuple(t.shape)}")
                t = torch.nonzero(t).reshape(-1)
            if t.dtype == torch.bool or t.is_floating_point():
                raise GenesisException(f"entity '{self.name}': {what} must be integers, got dtype {t.dtype}")
            t = t.reshape(-1).long()
            if len(t) and (t.min() < 0 or t.max() >= n):
                raise GenesisException(f"entity '{self.name}': {what} {t.tolist()} out of range; it has {n} "
                                       f"({what.split('_')[0]} indices 0..{n - 1})")
            u, counts = torch.unique(t, return_counts=True)
            if bool((counts > 1).any()):
                raise GenesisException(
                    f"entity '{self.name}': {what} {t.tolist()} repeats {u[counts > 1].tolist()}; give each index "
                    "once (a setter would keep only the last of the repeated values).")
            out = t.to(self._device)
        return out + start

    @property
    def _device(self):
        import genesis_lite as gs

        return gs.device

    def _dofs(self, dofs_idx_local):
        return self._idx(dofs_idx_local, self.n_dofs, "dofs_idx_local", self._dof_start)

    def _links(self, links_idx_local):
        return self._idx(links_idx_local, self.n_links, "links_idx_local", self._link_start)

    def _qs(self, qs_idx_local):
        return self._idx(qs_idx_local, self.n_qs, "qs_idx_local", self._q_start)

    def _envs(self, envs_idx):
        n = self._scene.n_envs
        if envs_idx is None:
            return torch.arange(max(n, 1), device=self._device)
        if n == 0:
            raise GenesisException(f"entity '{self.name}': envs_idx given but the scene was built without n_envs; "
                                   "build with scene.build(n_envs=N) for batched environments")
        return self._idx(envs_idx, n, "envs_idx", 0)

    def _values(self, x, envs, n, what, trailing=()):
        """x as a (len(envs), n, *trailing) tensor in the scene precision, keeping autograd history."""
        import genesis_lite as gs

        who = getattr(self, "_label", f"entity '{self.name}'")
        if isinstance(x, torch.Tensor):
            if x.device.type != gs.device.type:
                raise GenesisException(f"{who}: {what} is on {x.device} but the scene lives on "
                                       f"{gs.device}; move it with .to(gs.device)")
            if not (x.is_floating_point() or x.dtype in (torch.int32, torch.int64)):
                raise GenesisException(f"{who}: {what} has dtype {x.dtype}; give floating-point values")
            if x.requires_grad and not self._scene.sim_options.requires_grad:
                raise GenesisException(
                    f"{who}: {what} requires grad but the scene was built without gradients, so it "
                    "would receive none. Create the scene with gs.options.SimOptions(requires_grad=True), or pass "
                    "x.detach().")
            sim = getattr(self._scene, "_simulator", None)
            t = (routed(x, sim.view_nodes) if sim is not None else x).to(gs.tc_float)
        else:
            try:
                t = torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=gs.tc_float, device=gs.device)
            except (TypeError, ValueError) as e:
                raise GenesisException(f"{who}: {what} must be numbers ({e})") from None
        want = (len(envs), n) + tuple(trailing)
        batched = self._scene.n_envs > 0
        shape = tuple(t.shape)
        if shape == want[1:]:
            t = t.unsqueeze(0).expand(want)
        elif shape != want or not batched:
            exp = f"{want[1:]}" + (f" or {want} (envs, ...)" if batched else "")
            raise GenesisException(f"{who}: {what} has shape {shape}; expected {exp}")
        _raise_if_not_finite(t, who, what, batched)
        again = recipe(x)
        if again is not None:
            # a new rollout makes this value again from the leaf (or the leaf's derived value), so the leaf keeps
            # getting gradients (grad/remake.py)
            t._gs_remake = lambda: self._values(again(), envs, n, what, trailing)
        return t

    def _out(self, t):
        return wrap(t if self._scene.n_envs > 0 else t[0])

    # ---------------------------------------------------------------- physical validity of parameters
    def _dof_label(self, d_local):
        for j in self.joints:
            if j.dof_start_local <= d_local < j.dof_start_local + j.n_dofs:
                return f"dof {d_local} (joint '{j.name}')"
        return f"dof {d_local}"

    def _where(self, what, envs, k_env, label):
        env = f" in env {int(envs[k_env])}" if self._scene.n_envs > 0 else ""
        return f"entity '{self.name}': {what} of {label}{env}"

    def _check_sign(self, what, vals, envs, labels, positive, hint, need=None):
        """Raise if an entry of vals (E, n) is < 0 (or <= 0 where positive[k]), naming the entity, the
        link or dof (labels[k]), the env and the value. Reads a detached copy."""
        v = vals.detach().cpu()
        pos = torch.as_tensor(positive, dtype=torch.bool).reshape(1, -1)
        bad = torch.where(pos, v <= 0, v < 0)
        if not bool(bad.any()):
            return
        e, k = [int(i) for i in torch.nonzero(bad)[0]]
        need = need or ("> 0" if bool(pos[0, k]) else ">= 0")
        env = f" in env {int(envs[e])}" if self._scene.n_envs > 0 else ""
        raise GenesisException(f"entity '{self.name}': {what} must be {need}, got {v[e, k].item()} for {labels[k]}{env}. "
                               f"{hint}")

    def _check_inertia(self, vals, envs, ls):
        from ..validation import INERTIA_HINT, inertia_problems

        local = (ls - self._link_start).cpu().tolist()
        strict = [self.joints[i].type == "free" for i in local]  # validation.py: a free body's must be definite
        v = vals.detach().cpu().double().numpy()
        for k in range(v.shape[1]):
            bad = inertia_problems(v[:, k], strict=strict[k])
            if bad:
                (e,), why = bad[0]
                label = f"link '{self.links[local[k]].name}'"
                raise GenesisException(f"{self._where('inertia', envs, e, label)}: {v[e, k].tolist()} {why}. "
                                       f"{INERTIA_HINT}")

    # ---------------------------------------------------------------- state getters
    def get_qpos(self, qs_idx_local=None, envs_idx=None):
        """Generalised positions (m, rad; free bases: xyz then quaternion wxyz)."""
        q, _ = self._sim.get_state()
        return self._out(q[self._envs(envs_idx)][:, self._qs(qs_idx_local)])

    def get_dofs_velocity(self, dofs_idx_local=None, envs_idx=None):
        """Dof velocities (m/s, rad/s; free bases: world-frame linear then angular velocity)."""
        _, v = self._sim.get_state()
        return self._out(v[self._envs(envs_idx)][:, self._dofs(dofs_idx_local)])

    def _dof_positions(self, q):
        """Per-dof positions: joint coordinates; for a free joint, as Genesis, its xyz and its intrinsic x-y-z
        Euler angles (gs.utils.geom.quat_to_xyz: R = Rx Ry Rz, pitch in [-pi/2, pi/2]; differentiable away
        from gimbal lock)."""
        cols = []
        for j in self.joints:
            qs = self._q_start + j.q_start_local
            if j.n_dofs == 1:
                cols.append(q[:, qs:qs + 1])
            elif j.n_dofs == 6:
                cols.append(q[:, qs:qs + 3])
                cols.append(quat_to_xyz(q[:, qs + 3:qs + 7]))
        return torch.cat(cols, -1) if cols else q[:, :0]

    def get_dofs_position(self, dofs_idx_local=None, envs_idx=None):
        """Dof positions (m, rad); a free joint's six are its xyz and its intrinsic x-y-z Euler angles (roll,
        pitch, yaw; R = Rx Ry Rz), Genesis's."""
        q, _ = self._sim.get_state()
        local = self._dofs(dofs_idx_local) - self._dof_start
        return self._out(self._dof_positions(q[self._envs(envs_idx)])[:, local])

    def _dof_result(self, read, dofs_idx_local, envs_idx):
        """A per-dof result of the last step (read: the scene's (n_envs, n_dofs) reader), indexed as asked."""
        self._sim  # noqa: B018 - raises a clear error before build
        return self._out(read()[self._envs(envs_idx)][:, self._dofs(dofs_idx_local)])

    def get_dofs_acc(self, dofs_idx_local=None, envs_idx=None):
        """Dof accelerations of the last step (rad/s^2, m/s^2); no gradient."""
        return self._dof_result(self._scene._dofs_acc, dofs_idx_local, envs_idx)

    def get_dofs_force(self, dofs_idx_local=None, envs_idx=None):
        """Genesis's meaning (its dofs_state.force): the generalised force (N, N m) of the last step's
        state without the constraints, actuator (after force-range clipping) + joint damping + joint
        spring - bias (Coriolis, centrifugal, gravity and applied link wrenches); joint limits, friction loss
        and contacts are not in it. With the Euler integrator and no constraint acting, M qacc equals it
        (the implicit integrators solve (M + h D) qacc = it). No gradient."""
        return self._dof_result(self._scene._dofs_force, dofs_idx_local, envs_idx)

    def get_dofs_control_force(self, dofs_idx_local=None, envs_idx=None):
        """The actuator forces (N, N m): the PD or force controls applied at the last step, after
        force-range clipping; no gradient."""
        return self._dof_result(self._scene._dofs_control_force, dofs_idx_local, envs_idx)

    def _link_out(self, k, links_idx_local, envs_idx):
        out = self._sim.link_outputs()[k]
        return self._out(out[self._envs(envs_idx)][:, self._links(links_idx_local)])

    def get_links_pos(self, links_idx_local=None, envs_idx=None):
        """World positions of link frames (m)."""
        return self._link_out(0, links_idx_local, envs_idx)

    def get_links_quat(self, links_idx_local=None, envs_idx=None):
        """World orientations of link frames (w, x, y, z)."""
        return self._link_out(1, links_idx_local, envs_idx)

    def get_links_vel(self, links_idx_local=None, envs_idx=None):
        """World linear velocities of link frame origins (m/s)."""
        return self._link_out(2, links_idx_local, envs_idx)

    def get_links_ang(self, links_idx_local=None, envs_idx=None):
        """World angular velocities of links (rad/s)."""
        return self._link_out(3, links_idx_local, envs_idx)

    def get_pos(self, envs_idx=None):
        """Base link position (m)."""
        return self._link_out(0, [0], envs_idx)[..., 0, :]

    def get_quat(self, envs_idx=None):
        """Base link orientation (w, x, y, z)."""
        return self._link_out(1, [0], envs_idx)[..., 0, :]

    def get_vel(self, envs_idx=None):
        """Base link linear velocity (m/s)."""
        return self._link_out(2, [0], envs_idx)[..., 0, :]

    def get_ang(self, envs_idx=None):
        """Base link angular velocity (rad/s)."""
        return self._link_out(3, [0], envs_idx)[..., 0, :]

    def get_AABB(self, envs_idx=None):
        """World-frame axis-aligned bounding box of the entity's collision geometry at the current state:
        (2, 3) rows min and max (m), batched (n_envs, 2, 3). Exact for spheres, boxes, capsules and
        cylinders, the convex hull's vertices for meshes; planes (unbounded) are left out. Differentiable
        in the state."""
        import genesis_lite as gs

        envs = self._envs(envs_idx)
        pos, quat = self._sim.link_outputs()[:2]
        pos, quat = pos[envs], quat[envs]
        lows, highs = [], []
        for li, link in enumerate(self.model.links):
            l = self._link_start + li
            R = _quat_to_R(quat[:, l])
            for g in link.geoms:
                if g.type == "plane":
                    continue
                Rl = _quat_to_R(torch.as_tensor(g.quat, dtype=R.dtype, device=R.device))
                Rg = R @ Rl
                c = pos[:, l] + R @ torch.as_tensor(g.pos, dtype=R.dtype, device=R.device)
                if g.type == "mesh":
                    v = torch.as_tensor(np.asarray(g.hull["vertices"] if g.hull is not None else g.vertices),
                                        dtype=R.dtype, device=R.device)
                    w = c[:, None, :] + torch.einsum("eij,kj->eki", Rg, v)
                    lows.append(w.amin(1))
                    highs.append(w.amax(1))
                    continue
                size = torch.as_tensor(g.size, dtype=R.dtype, device=R.device)
                if g.type == "sphere":
                    e = size[0].expand(c.shape)
                elif g.type == "box":
                    e = Rg.abs() @ size
                else:  # capsule, cylinder: radius, half length along the geom's z
                    a = Rg[..., :, 2]
                    radial = size[0] if g.type == "capsule" else size[0] * torch.sqrt((1 - a * a).clamp_min(0))
                    e = a.abs() * size[1] + radial
                lows.append(c - e)
                highs.append(c + e)
        if not lows:
            raise GenesisException(f"entity '{self.name}': get_AABB needs bounded collision geometry; it has "
                                   "only planes or none")
        out = torch.stack([torch.stack(lows, 0).amin(0), torch.stack(highs, 0).amax(0)], -2).to(gs.tc_float)
        return self._out(out)

    def _mass_mat(self):
        """This entity's joint-space mass matrix with the armature on its diagonal, (n_envs, n_dofs, n_dofs)."""
        d = self._dofs(None)
        return self._scene._mass_matrix()[:, d][:, :, d] + torch.diag_embed(self._sim.params["armature"][:, d])

    def get_mass_mat(self, envs_idx=None):
        """Joint-space mass matrix (armature included) of this entity, (n_dofs, n_dofs); no gradient."""
        self._sim  # noqa: B018 - raises a clear error before build
        return self._out(self._mass_mat().detach()[self._envs(envs_idx)])

    def get_links_mass(self, links_idx_local=None, envs_idx=None):
        return self._out(self._sim.params["mass"][self._envs(envs_idx)][:, self._links(links_idx_local)])

    def get_mass(self, envs_idx=None):
        return self.get_links_mass(envs_idx=envs_idx).sum(-1)

    def _energies(self):
        sim = self._sim
        pos, quat = sim.link_outputs()[:2]
        ls = self._links(None)
        m = sim.params["mass"][:, ls]
        com = sim.params["com"][:, ls]
        c = pos[:, ls] + (_quat_to_R(quat[:, ls]) @ com.unsqueeze(-1)).squeeze(-1)
        pe = -(m * (c * sim.params["gravity"][:, None, :]).sum(-1)).sum(-1)
        _, v = sim.get_state()
        d = self._dofs(None)
        vd = v[:, d]
        M = self._mass_mat().to(vd.dtype)
        ke = 0.5 * (vd.unsqueeze(1) @ M @ vd.unsqueeze(-1)).reshape(-1)
        return ke, pe

    def get_kinetic_energy(self, envs_idx=None):
        """0.5 v^T M v (J), the rotors' armature included on M's diagonal (as Genesis's)."""
        return self._out(self._energies()[0][self._envs(envs_idx)])

    def get_potential_energy(self, envs_idx=None):
        """Gravitational potential energy -sum m g.c (J), zero at the world origin."""
        return self._out(self._energies()[1][self._envs(envs_idx)])

    def get_total_energy(self, envs_idx=None):
        ke, pe = self._energies()
        return self._out((ke + pe)[self._envs(envs_idx)])

    # ---------------------------------------------------------------- state setters
    def _set_state(self, q=None, v=None):
        sim = self._sim
        q0, v0 = sim.get_state()
        sim.set_state(q if q is not None else q0, v if v is not None else v0)

    def set_qpos(self, qpos, qs_idx_local=None, envs_idx=None, zero_velocity=True, skip_forward=False):
        """Set generalised positions (free bases: xyz then quaternion wxyz); zeroes the velocity like Genesis.
        skip_forward (Genesis's) changes nothing: link poses are computed when they are read."""
        self._set_qpos(qpos, qs_idx_local, envs_idx, zero_velocity, "qpos")

    def _set_qpos(self, qpos, qs_idx_local, envs_idx, zero_velocity, what):
        envs, qs = self._envs(envs_idx), self._qs(qs_idx_local)
        vals = self._values(qpos, envs, len(qs), what)

        q0, v0 = self._sim.get_state()
        q = index_put(q0, envs, qs, vals)
        v = None
        if zero_velocity:
            d = self._dofs(None)
            v = index_put(v0, envs, d, torch.zeros(len(envs), len(d), dtype=v0.dtype, device=v0.device))
        self._set_state(q, v)

    def set_dofs_position(self, position, dofs_idx_local=None, envs_idx=None, zero_velocity=True):
        """Set dof positions (m, rad; a free joint's six are xyz and intrinsic x-y-z Euler angles, as
        get_dofs_position returns them). Setting some of a free joint's three angles keeps the others' values
        in the current pose's Euler decomposition, as Genesis does."""
        envs, d = self._envs(envs_idx), self._dofs(dofs_idx_local)
        vals = self._values(position, envs, len(d), "position")

        q0, v0 = self._sim.get_state()
        full = self._dof_positions(q0[envs])
        full = index_put(full, torch.arange(len(envs), device=full.device), d - self._dof_start, vals)
        qe = q0[envs].clone()
        cols = []
        for j in self.joints:
            qs = self._q_start + j.q_start_local
            ds = j.dof_start_local
            if j.n_dofs == 1:
                cols.append((qs, full[:, ds:ds + 1]))
            elif j.n_dofs == 6:
                touched = bool(((d - self._dof_start >= ds + 3) & (d - self._dof_start < ds + 6)).any())
                quat = xyz_to_quat(full[:, ds + 3:ds + 6]) if touched else q0[envs][:, qs + 3:qs + 7]
                cols.append((qs, torch.cat([full[:, ds:ds + 3], quat], -1)))
        parts, idx = [], []
        for qs, val in cols:
            parts.append(val)
            idx.extend(range(qs, qs + val.shape[1]))
        if parts:
            qe = torch.cat(parts, -1)
            q = index_put(q0, envs, torch.tensor(idx, device=q0.device), qe)
        else:
            q = q0
        v = None
        if zero_velocity:
            dd = self._dofs(None)
            v = index_put(v0, envs, dd, torch.zeros(len(envs), len(dd), dtype=v0.dtype, device=v0.device))
        self._set_state(q, v)

    def set_dofs_velocity(self, velocity, dofs_idx_local=None, envs_idx=None):
        """Set dof velocities (m/s, rad/s; free bases: world-frame linear then angular)."""
        envs, d = self._envs(envs_idx), self._dofs(dofs_idx_local)
        vals = self._values(velocity, envs, len(d), "velocity")

        _, v0 = self._sim.get_state()
        self._set_state(v=index_put(v0, envs, d, vals))

    def _free_base(self, what):
        j = self.joints[0]
        if j.type != "free":
            raise GenesisException(f"entity '{self.name}': {what} needs a free base, but it is fixed to the world; "
                                   "load it with fixed=False")
        return self._q_start + j.q_start_local

    def set_pos(self, pos, envs_idx=None, zero_velocity=True):
        """Set the base position (m) of a free-base entity."""
        qs = self._free_base("set_pos")
        self._set_qpos(pos, list(range(qs - self._q_start, qs - self._q_start + 3)), envs_idx, zero_velocity, "pos")

    def set_quat(self, quat, envs_idx=None, zero_velocity=True):
        """Set the base orientation (w, x, y, z) of a free-base entity."""
        qs = self._free_base("set_quat")
        self._set_qpos(quat, list(range(qs - self._q_start + 3, qs - self._q_start + 7)), envs_idx, zero_velocity,
                       "quat")

    # ---------------------------------------------------------------- control
    def control_dofs_force(self, force, dofs_idx_local=None, envs_idx=None):
        """Apply generalised forces (N, N m) from the next step on, until changed."""
        envs, d = self._envs(envs_idx), self._dofs(dofs_idx_local)
        self._sim.set_ctrl("force", self._values(force, envs, len(d), "force"), envs, d, 0)

    def control_dofs_position(self, position, dofs_idx_local=None, envs_idx=None):
        """PD position targets (m, rad): force = kp (target - q) - kv v, clipped to the force range.
        A free joint's dofs take targets in get_dofs_position's coordinates, as in Genesis: world xyz, and
        Euler angles whose error is the rotation vector of q_target q^-1 (world axes, the angular dofs'
        frame), not a difference of angles: Genesis's torque when the three rotational gains are equal
        (solvers/rigid/actuation.py says where they differ). Its gains default to 0, as in Genesis: set
        them with set_dofs_kp / set_dofs_kv."""
        envs, d = self._envs(envs_idx), self._dofs(dofs_idx_local)
        self._sim.set_ctrl("pos", self._values(position, envs, len(d), "position target"), envs, d, 1)
        self._sim.set_ctrl("vel", torch.zeros(len(envs), len(d), device=self._device), envs, d, None)
        self._warn_if_zero_gain("kp", envs, d)

    def control_dofs_position_velocity(self, position, velocity, dofs_idx_local=None, envs_idx=None):
        """PD targets of position and velocity together (Genesis's): force = kp (q* - q) + kv (v* - v),
        clipped to the force range."""
        self.control_dofs_position(position, dofs_idx_local, envs_idx)
        envs, d = self._envs(envs_idx), self._dofs(dofs_idx_local)
        self._sim.set_ctrl("vel", self._values(velocity, envs, len(d), "velocity target"), envs, d, None)

    def control_dofs_velocity(self, velocity, dofs_idx_local=None, envs_idx=None):
        """Velocity targets (m/s, rad/s): force = kv (target - v), clipped to the force range."""
        envs, d = self._envs(envs_idx), self._dofs(dofs_idx_local)
        self._sim.set_ctrl("vel", self._values(velocity, envs, len(d), "velocity target"), envs, d, 2)
        self._warn_if_zero_gain("kv", envs, d)

    def _warn_if_zero_gain(self, gain, envs, d):
        """Warn (once per entity, gain and set of dofs) when a PD target lands on dofs whose gain is 0 in
        some of the envs addressed: the target then does nothing. The gains default to Genesis's (kp 100,
        kv 10 on revolute and prismatic joints, the file's where it gives them, 0 on free joints). The zero mask is recomputed only when the gain tensor changes (a setter call or a
        reset), so a control call in a loop pays one identity test."""
        params = self._sim.params[gain]
        tensor, zero = self._zero_gain.get(gain, (None, None))
        if tensor is not params:
            own = params.detach()[:, self._dof_start:self._dof_start + self.n_dofs]
            zero = (own == 0).cpu().numpy()
            self._zero_gain[gain] = (params, zero)
        if not zero.any():
            return
        local = (d - self._dof_start).cpu().numpy()
        hit = zero[envs.cpu().numpy()][:, local].any(0)
        if not hit.any():
            return
        dofs = tuple(int(i) for i in local[hit])
        if (gain, dofs) in self._zero_gain_warned:
            return
        self._zero_gain_warned.add((gain, dofs))
        joints = list(dict.fromkeys(j.name for i in dofs for j in self.joints
                                    if j.dof_start_local <= i < j.dof_start_local + j.n_dofs))
        call, law = (("control_dofs_position", "kp (target - q) - kv v") if gain == "kp" else
                     ("control_dofs_velocity", "kv (target - v)"))
        warnings.warn(
            f"entity '{self.name}': {call} on dofs {list(dofs)} (joints {joints}) whose {gain} is 0"
            f"{' in some of the envs' if self._scene.n_envs else ''}, so their targets have no effect (the "
            f"actuator force is {law}). Set the gains first with set_dofs_{gain}(...), or drive "
            "these dofs with control_dofs_force.", ZeroGainWarning, stacklevel=3)

    # ---------------------------------------------------------------- parameters
    def _set_dof_param(self, name, values, dofs_idx_local, envs_idx, nonneg=True, hint=None):
        envs, d = self._envs(envs_idx), self._dofs(dofs_idx_local)
        vals = self._values(values, envs, len(d), name)
        if nonneg:
            labels = [self._dof_label(int(i)) for i in (d - self._dof_start).cpu()]
            self._check_sign(name, vals, envs, labels, [False] * len(d),
                             hint or f"A negative {name} feeds energy into the system; pass values >= 0.")
        if name == "armature":
            self._check_mass_matrix(envs, "set_dofs_armature", name, vals, d)
        self._sim.set_param(name, vals, envs, d)

    def set_dofs_kp(self, kp, dofs_idx_local=None, envs_idx=None):
        """Position gains (N/m, N m/rad) for control_dofs_position."""
        self._set_dof_param("kp", kp, dofs_idx_local, envs_idx)

    def set_dofs_kv(self, kv, dofs_idx_local=None, envs_idx=None):
        """Velocity gains (N s/m, N m s/rad) for position and velocity control."""
        self._set_dof_param("kv", kv, dofs_idx_local, envs_idx)

    def set_dofs_damping(self, damping, dofs_idx_local=None, envs_idx=None):
        """Viscous joint damping (N s/m, N m s/rad)."""
        self._set_dof_param("damping", damping, dofs_idx_local, envs_idx)

    def set_dofs_armature(self, armature, dofs_idx_local=None, envs_idx=None):
        """Rotor inertia added to the mass matrix diagonal (kg, kg m^2)."""
        self._set_dof_param("armature", armature, dofs_idx_local, envs_idx)

    def set_dofs_stiffness(self, stiffness, dofs_idx_local=None, envs_idx=None):
        """Joint spring stiffness (N/m, N m/rad): the passive force -stiffness (q - q_rest) on hinge and slide
        joints, Genesis's law (its -stiffness (qpos - qpos0)), q_rest being the joint's zero (the file's pose)
        or an MJCF joint's springref, as MuJoCo. Explicit, as in Genesis and MuJoCo. Differentiable. A free
        joint's dofs take none: Genesis keeps their value and ignores it, and so does this, with a warning."""
        self._set_dof_param("stiffness", stiffness, dofs_idx_local, envs_idx,
                            hint="A negative stiffness pushes the joint away from its rest position; pass values >= 0.")
        envs, d = self._envs(envs_idx), self._dofs(dofs_idx_local)
        local = (d - self._dof_start).cpu().numpy()
        free = torch.as_tensor(np.array([self._dof_q_local[i] < 0 for i in local], dtype=bool), device=d.device)
        if bool(free.any()) and bool((self._sim.params["stiffness"].detach()[envs][:, d[free]] != 0).any()):
            dofs = [int(i) for i in local[free.cpu().numpy()]]
            if ("stiffness", tuple(dofs)) not in self._zero_gain_warned:
                self._zero_gain_warned.add(("stiffness", tuple(dofs)))
                warnings.warn(f"entity '{self.name}': set_dofs_stiffness on the free joint's dofs {dofs}: a free "
                              "joint has no spring (Genesis ignores its stiffness too), so these values have no "
                              "effect.", GenesisWarning, stacklevel=2)

    def set_dofs_frictionloss(self, frictionloss, dofs_idx_local=None, envs_idx=None):
        """Dry joint friction (N, N m), smoothed over 0.01 rad/s."""
        self._set_dof_param("frictionloss", frictionloss, dofs_idx_local, envs_idx)

    def set_dofs_force_range(self, lower, upper, dofs_idx_local=None, envs_idx=None):
        """Actuator force limits (N, N m) applied to every control mode."""
        envs, d = self._envs(envs_idx), self._dofs(dofs_idx_local)
        lo = self._values(lower, envs, len(d), "lower")
        hi = self._values(upper, envs, len(d), "upper")
        bad = (lo.detach() > hi.detach()) | torch.isnan(lo.detach()) | torch.isnan(hi.detach())
        if bool(bad.any()):
            e, k = [int(i) for i in torch.nonzero(bad)[0]]
            label = self._dof_label(int(d[k]) - self._dof_start)
            raise GenesisException(f"{self._where('force range', envs, e, label)}: lower > upper ({lo[e, k].item()} > "
                                   f"{hi[e, k].item()}, N or N m); give lower <= upper.")
        self._sim.set_force_range(lo, hi, envs, d)

    def _get_param(self, name, idx, envs_idx):
        return self._out(self._sim.params[name][self._envs(envs_idx)][:, idx])

    def get_dofs_kp(self, dofs_idx_local=None, envs_idx=None):
        return self._get_param("kp", self._dofs(dofs_idx_local), envs_idx)

    def get_dofs_kv(self, dofs_idx_local=None, envs_idx=None):
        return self._get_param("kv", self._dofs(dofs_idx_local), envs_idx)

    def get_dofs_damping(self, dofs_idx_local=None, envs_idx=None):
        return self._get_param("damping", self._dofs(dofs_idx_local), envs_idx)

    def get_dofs_armature(self, dofs_idx_local=None, envs_idx=None):
        return self._get_param("armature", self._dofs(dofs_idx_local), envs_idx)

    def get_dofs_stiffness(self, dofs_idx_local=None, envs_idx=None):
        return self._get_param("stiffness", self._dofs(dofs_idx_local), envs_idx)

    def get_dofs_force_range(self, dofs_idx_local=None, envs_idx=None):
        sim, d, e = self._sim, self._dofs(dofs_idx_local), self._envs(envs_idx)
        return self._out(sim.force_lo[e][:, d]), self._out(sim.force_hi[e][:, d])

    def get_dofs_limit(self, dofs_idx_local=None):
        lim = torch.as_tensor(self._sim.solver.flat.np_dof_limit, dtype=torch.float64)[self._dofs(dofs_idx_local).cpu()]
        return wrap(lim[:, 0]), wrap(lim[:, 1])

    def set_links_mass(self, mass, links_idx_local=None, envs_idx=None):
        """Link masses (kg)."""
        envs, ls = self._envs(envs_idx), self._links(links_idx_local)
        self._set_links_mass(self._values(mass, envs, len(ls), "mass"), envs, ls, "set_links_mass")

    def _set_links_mass(self, vals, envs, ls, call):
        """Masses `vals` (len(envs), len(ls)) of links `ls`: >= 0, and > 0 where a link moves without massive links
        below it; set_mass_shift's may be negative (Genesis's meaning), then checked and warned about by
        _check_mass_matrix, which also checks any mass set while the entity has negative ones."""
        negative = call == "set_mass_shift" and bool((vals.detach() < 0).any())
        if not negative:
            self._check_link_masses(vals, envs, ls)
        self._check_mass_matrix(envs, call, "mass", vals, ls, warn=negative)
        self._sim.set_param("mass", vals, envs, ls)

    def _check_link_masses(self, vals, envs, ls):
        local = (ls - self._link_start).cpu().tolist()
        labels = [f"link '{self.links[i].name}'" for i in local]
        self._check_sign("link masses", vals, envs, labels, [False] * len(local), "Masses are in kg.")
        # a link that moves needs a positive mass (a hinge link may instead carry massive links below it)
        m = self._sim.params["mass"].detach()[envs][:, self._link_start:self._link_start + self.n_links].clone()
        m[:, local] = vals.detach().to(m.dtype)
        below = m.clone()
        for i in range(self.n_links - 1, 0, -1):  # parents come before children
            p = self.links[i].parent_idx_local
            if p >= 0:
                below[:, p] += below[:, i]
        free = torch.tensor([j.type == "free" for j in self.joints], device=m.device)
        hinge = torch.tensor([j.type in ("revolute", "prismatic") for j in self.joints], device=m.device)
        bad = (m <= 0) & (free | (hinge & (below <= 0)))
        if bool(bad.any()):
            e, i = [int(k) for k in torch.nonzero(bad)[0]]
            env = f" in env {int(envs[e])}" if self._scene.n_envs > 0 else ""
            raise GenesisException(
                f"entity '{self.name}': link masses must be > 0 for a link that moves, got {m[e, i].item()} for link "
                f"'{self.links[i].name}' ({self.joints[i].type} joint){env}"
                f"{'' if self.joints[i].type == 'free' else ', which has no massive link below it'}: its equations "
                "of motion would be singular. Give it a positive mass (kg).")

    def set_links_inertia(self, inertia, links_idx_local=None, envs_idx=None):
        """Link rotational inertia about the COM in link axes, (n, 3, 3) in kg m^2."""
        envs, ls = self._envs(envs_idx), self._links(links_idx_local)
        self._set_links_inertia(self._values(inertia, envs, len(ls), "inertia", (3, 3)), envs, ls, "set_links_inertia")

    def _set_links_inertia(self, vals, envs, ls, call):
        self._check_inertia(vals, envs, ls)
        self._check_mass_matrix(envs, call, "inertia", vals, ls)
        self._sim.set_param("inertia", vals, envs, ls)

    def set_links_COM(self, com, links_idx_local=None, envs_idx=None):
        """Link centre of mass in the link frame (m), (n, 3)."""
        envs, ls = self._envs(envs_idx), self._links(links_idx_local)
        self._set_links_COM(self._values(com, envs, len(ls), "com", (3,)), envs, ls, "set_links_COM")

    def _set_links_COM(self, vals, envs, ls, call):
        self._check_mass_matrix(envs, call, "com", vals, ls)
        self._sim.set_param("com", vals, envs, ls)

    def _link_is_fixed(self, i_local: int) -> bool:
        """Whether local link i is fixed to the world: it and its ancestors have joints without dofs."""
        while i_local >= 0:
            if self.joints[i_local].n_dofs > 0:
                return False
            i_local = self.links[i_local].parent_idx_local
        return True

    def set_mass(self, mass, envs_idx=None):
        """Set the entity's mass (kg) as Genesis's RigidEntity.set_mass does: every link that is not fixed to
        the world gets its mass (and inertia) scaled by mass / get_mass(), through RigidLink.set_mass;
        links fixed to the world keep theirs (they do not move), so get_mass() afterwards differs from
        `mass` by what those links lost or would have gained. A number, or per env (n_envs,). Differentiable in
        `mass`; the link masses it scales are taken as the numbers they have at the call."""
        m = torch.as_tensor(mass, dtype=torch.float64) if not torch.is_tensor(mass) else mass
        if not bool(torch.isfinite(m.detach()).all()) or bool((m.detach() <= 0).any()):
            raise GenesisException(f"entity '{self.name}': set_mass({mass!r}): the mass must be a positive number (kg)")
        total = self.get_mass(envs_idx).detach()
        moving = [l for l in self.links if not self._link_is_fixed(l.idx_local)]
        for l in moving:
            share = l.get_mass(envs_idx).detach() / total
            l.set_mass(derive(lambda x, share=share: share * x.to(share.dtype), m), envs_idx)

    def set_links_inertial_mass(self, mass, links_idx_local=None, envs_idx=None):
        """Genesis's name of set_links_mass (kg): the mass alone, the inertia tensor is kept."""
        self.set_links_mass(mass, links_idx_local, envs_idx)

    def get_links_inertial_mass(self, links_idx_local=None, envs_idx=None):
        return self.get_links_mass(links_idx_local, envs_idx)

    def _base_param(self, name, envs, idx):
        """The model's value of a parameter (before any setter), (len(envs), len(idx), ...)."""
        base = self._sim.param_base[name]
        return base[envs][:, idx]

    def set_mass_shift(self, mass_shift, links_idx_local=None, envs_idx=None):
        """Genesis's domain randomisation: each link's mass becomes its model mass plus `mass_shift` (kg).
        Differentiable in the shift. A shift below minus the model mass gives the link a negative mass, as
        Genesis's does (its domain_randomization example draws -0.5 .. 0.5 kg for a Go2's 0.265 kg calves):
        taken with a warning while the entity's joint-space mass matrix at its initial configuration,
        armature included, stays positive definite; refused where it would not."""
        envs, ls = self._envs(envs_idx), self._links(links_idx_local)
        self._set_links_mass(self._shifted("mass", mass_shift, envs, ls), envs, ls, "set_mass_shift")

    def _shifted(self, name, shift, envs, ls, trailing=()):
        """The model's `name` of links `ls` plus `shift`, (len(envs), len(ls), *trailing); made again from the
        shift in a new rollout (scene.reset) when the shift carries a recipe (a leaf that requires grad, or a
        value derived from one: grad/remake.py), so that the leaf keeps receiving gradients."""
        base = self._base_param(name, envs, ls)
        return derive(lambda v: base + v, self._values(shift, envs, len(ls), f"{name}_shift", trailing))

    def _check_mass_matrix(self, envs, call, name, vals, idx, warn=False):
        """Where links of this entity have a negative mass (Genesis's set_mass_shift takes any shift) once
        parameter `name` (mass, com, inertia or armature) of links or dofs `idx` takes `vals` in envs `envs`:
        raise unless the joint-space mass matrix at the initial configuration, armature included, stays
        positive definite in every env (it is then what Genesis integrates; a step's factorisation does not
        check it), and with `warn` say that such links are not physical bodies."""
        links = slice(self._link_start, self._link_start + self.n_links)
        dofs = slice(self._dof_start, self._dof_start + self.n_dofs)
        p = {k: self._sim.params[k].detach()[envs][:, dofs if k == "armature" else links].double().clone()
             for k in ("mass", "com", "inertia", "armature")}
        p[name][:, idx - (self._dof_start if name == "armature" else self._link_start)] = vals.detach().double()
        if not bool((p["mass"] < 0).any()):
            return
        M = self._sim.mass_matrix_at_qpos0(self, p["mass"], p["com"], p["inertia"])
        _, info = torch.linalg.cholesky_ex(M + torch.diag_embed(p["armature"]))
        indefinite = bool((info != 0).any())
        e = int(torch.nonzero(info != 0)[0, 0]) if indefinite else int(p["mass"].min(1).values.argmin())
        k = int(p["mass"][e].argmin())
        env = f" in env {int(envs[e])}" if self._scene.n_envs > 0 else ""
        what = f"entity '{self.name}': link '{self.links[k].name}' has a mass of {p['mass'][e, k].item():.4g} kg{env}"
        if indefinite:
            raise GenesisException(
                f"{what} after {call}, and the entity's joint-space mass matrix at its initial configuration "
                "(armature included) is then not positive definite: its equations of motion mean nothing. Genesis "
                "takes such masses without a word. Draw mass shifts above minus each link's model mass (e.g. a "
                "relative shift times entity.get_links_mass()), or give the joints armature (set_dofs_armature).")
        if warn:
            warnings.warn(
                f"{what} after {call} (the least of the entity's {int((p['mass'] < 0).sum())} negative link masses "
                "over the envs). Genesis takes such "
                "masses, and so does genesis_lite while the joint-space mass matrix, armature included, stays "
                "positive definite (it is, at the initial configuration): gravity then lifts such a link, and a "
                "push accelerates it towards the pusher. For physical bodies draw shifts above minus each link's "
                "model mass (e.g. a relative shift times entity.get_links_mass()).", GenesisWarning, stacklevel=3)

    def set_COM_shift(self, com_shift, links_idx_local=None, envs_idx=None):
        """Genesis's domain randomisation: each link's centre of mass becomes the model's plus `com_shift`
        (m, in the link frame), (n, 3)."""
        envs, ls = self._envs(envs_idx), self._links(links_idx_local)
        self._set_links_COM(self._shifted("com", com_shift, envs, ls, (3,)), envs, ls, "set_COM_shift")

    def get_dofs_invweight(self, dofs_idx_local=None, envs_idx=None):
        """Genesis's dofs_invweight (1/kg, 1/(kg m^2)): the diagonal of the inverse joint-space mass matrix at
        the entity's initial configuration with the model's masses and the current armature (Genesis computes
        it at build and again when set_dofs_armature changes the armature; masses set later leave it as it
        is), a free joint's three translational and three rotational entries each their mean, as Genesis's.
        The joint-limit constraint's impedance uses the same numbers. No gradient."""
        envs, d = self._envs(envs_idx), self._dofs(None)
        w = self._sim.entity_invweight(self, self._sim.params["armature"].detach()[envs][:, d].double())
        return self._out(w[:, self._dofs(dofs_idx_local) - self._dof_start].to(self._sim.dtype))

    def get_links_inertia(self, links_idx_local=None, envs_idx=None):
        return self._get_param("inertia", self._links(links_idx_local), envs_idx)

    def get_links_COM(self, links_idx_local=None, envs_idx=None):
        return self._get_param("com", self._links(links_idx_local), envs_idx)

    def __repr__(self):
        return f"<RigidEntity '{self.name}': {self.n_links} links, {self.n_dofs} dofs>"
