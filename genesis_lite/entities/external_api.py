"""External link forces and gravity compensation with Genesis's API.

`scene.sim.rigid_solver` (the scene's rigid solver) gets Genesis's solver-level methods from
RigidSolverAPI: apply_links_external_force / apply_links_external_torque and the link getters a script
uses around them (get_links_pos / quat / vel / ang / root_COM), indexed by the solver's link index
(`entity.links[i].idx`, counted over every rigid entity of the scene). Genesis has no entity-level form.

Genesis's meaning, kept here:
- a force or torque lasts one step: what is applied between two `scene.step()` calls adds up and acts
  during every substep of the next step, then is dropped (scene.reset drops it too);
- ref says where a force acts: "link_origin" (the link frame's origin, the default), "link_com" (the
  link's centre of mass), "root_com" (the centre of mass of the link's whole kinematic tree: the entity's
  for a single-rooted entity); for a torque ref only names the frame of local=True;
- local=False: the vector is in world axes; local=True: in the link's axes ("root_com" refuses it).
  Genesis takes a "link_com" local vector in the link's inertial frame; genesis_lite keeps no inertial
  frame of its own (the inertia tensor is in link axes), so "link_com" local is the link's axes at its
  centre of mass: the same wherever the inertial frame is not rotated (boxes, spheres, URDF links with
  rpy="0 0 0"). Genesis also rotates a "link_origin" local force by that inertial frame (its torque by
  the link frame); here both use the link frame;
- the lever is taken at the pose of the call; within the step it follows the link's origin.
Differentiable: force and torque tensors that require grad get gradients, and so does the pose the
lever was taken at. A force is stored as (f, m) per link: the force in world axes and its moment about
the link origin (solvers/rigid/external.py).

Gravity compensation (gs.materials.Rigid(gravity_compensation=gc), entity.set_gravity_compensation):
the entity's links feel (1 - gc) of gravity, as in Genesis (an upward force gc m g at each link's centre
of mass); a differentiable parameter.
"""
from __future__ import annotations

import weakref

import numpy as np
import torch

from ..errors import GenesisException
from ..grad.remake import derive
from ..grad.tensor import wrap
from ..utils.geom import quat_to_R

REFS = ("link_origin", "link_com", "root_com")


class RigidSolverAPI:
    """Genesis's solver-level link API over every link of a scene's rigid solver (the scene binds these
    methods onto scene.sim.rigid_solver at build). Holds its scene weakly."""

    METHODS = ("apply_links_external_force", "apply_links_external_torque", "get_links_pos", "get_links_quat",
               "get_links_vel", "get_links_ang", "get_links_root_COM", "links_info")

    def __init__(self, scene):
        self._scene_ref = weakref.ref(scene)
        self._root_of = None

    @property
    def links_info(self):
        """Genesis's `rigid_solver.links_info` for reading the links' inertial parameters (read-only here):
        `.inertial_mass`, `.inertial_pos`, `.inertial_i`, each with `.to_numpy()` / `.to_torch()`."""
        return LinksInfoView(self._scene)

    # ---------------------------------------------------------------- indices and values
    @property
    def _scene(self):
        scene = self._scene_ref()
        if scene is None:
            raise GenesisException("rigid_solver: its scene no longer exists")
        return scene

    @property
    def _bridge(self):
        return self._scene._rigid

    def _label(self, method):
        return f"rigid_solver.{method}"

    # Index and value checks in numpy: a script applies forces every step, and each small torch op costs
    # microseconds; values that need no gradient stay numpy arrays up to the solver's upload.
    def _links(self, links_idx, who):
        """links_idx as a numpy int64 array of solver link indices (repeats allowed: they add up)."""
        n = self._bridge.n_links
        if links_idx is None:
            return np.arange(n)
        if isinstance(links_idx, int) and 0 <= links_idx < n:
            return np.array([links_idx])
        if type(links_idx) in (list, tuple) and all(type(i) is int and 0 <= i < n for i in links_idx):
            return np.array(links_idx, dtype=np.int64)  # the common case, checked without numpy's overheads
        if isinstance(links_idx, slice):
            return np.arange(n)[links_idx]
        t = np.asarray(links_idx.detach().cpu().numpy() if torch.is_tensor(links_idx) else links_idx)
        if t.dtype.kind not in "iu":
            raise GenesisException(f"{who}: links_idx must be integer link indices, got {links_idx!r}")
        t = t.reshape(-1).astype(np.int64)
        bad = t[(t < 0) | (t >= n)]
        if len(bad):
            raise GenesisException(f"{who}: links_idx {bad.tolist()} out of range; the scene's rigid solver has {n} "
                                   f"links (indices 0..{n - 1}, entity.links[i].idx)")
        return t

    def _envs(self, envs_idx, who):
        n = self._scene.n_envs
        if envs_idx is None:
            return np.arange(max(n, 1))
        if n == 0:
            raise GenesisException(f"{who}: envs_idx given but the scene was built without n_envs; build with "
                                   "scene.build(n_envs=N) for batched environments")
        t = np.asarray(envs_idx.detach().cpu().numpy() if torch.is_tensor(envs_idx) else envs_idx)
        if t.dtype == np.bool_:
            if t.shape != (n,):
                raise GenesisException(f"{who}: a boolean envs_idx must have shape ({n},), got {tuple(t.shape)}")
            return np.nonzero(t)[0]
        if t.dtype.kind not in "iu":
            raise GenesisException(f"{who}: envs_idx must be integers, got {envs_idx!r}")
        t = t.reshape(-1).astype(np.int64)
        bad = t[(t < 0) | (t >= n)]
        if len(bad):
            raise GenesisException(f"{who}: envs_idx {bad.tolist()} out of range; the scene has {n} envs")
        return t

    def _vectors(self, x, envs, links, who, what):
        """x as (len(envs), len(links), 3), or for a numpy array a shape that broadcasts to it (the caller
        adds it into a full array): a numpy array in the solver's precision, or a torch tensor in the scene
        precision where x is a tensor that requires grad (autograd kept). A batched scene takes (envs,
        links, 3) or anything that broadcasts to it, an unbatched one (links, 3)."""
        import genesis_lite as gs

        scene = self._scene
        grad = torch.is_tensor(x) and x.requires_grad
        if torch.is_tensor(x):
            if x.device.type != gs.device.type:
                raise GenesisException(f"{who}: {what} is on {x.device} but the scene lives on {gs.device}")
            if not (x.is_floating_point() or x.dtype in (torch.int32, torch.int64)):
                raise GenesisException(f"{who}: {what} has dtype {x.dtype}; give floating-point values")
            if grad and not scene.sim_options.requires_grad:
                raise GenesisException(f"{who}: {what} requires grad but the scene was built without gradients, so "
                                       "it would receive none. Create the scene with gs.options.SimOptions("
                                       "requires_grad=True), or pass x.detach().")
            a = x.detach().cpu().numpy()
        else:
            try:
                a = np.asarray(x, dtype=np.float64)
            except (TypeError, ValueError) as e:
                raise GenesisException(f"{who}: {what} must be numbers ({e})") from None
        batched = scene.n_envs > 0
        want = (len(envs), len(links), 3) if batched else (len(links), 3)
        if a.ndim > len(want) or a.shape[-1:] != (3,) or any(n not in (1, w) for n, w in zip(a.shape[::-1], want[::-1])):
            raise GenesisException(
                f"{who}: {what} has shape {tuple(a.shape)}; expected {want} ("
                + ("envs, links, xyz" if batched else "links, xyz")
                + "), or a shape that broadcasts to it such as (3,)")
        if not np.isfinite(a).all():
            bad = ~np.isfinite(a)
            first = [int(i) for i in np.argwhere(bad)[0]]
            raise GenesisException(f"{who}: {what} contains NaN or infinite values ({what}{first} = "
                                   f"{a[tuple(first)]}); pass finite values")
        if grad:
            t = torch.broadcast_to(x.to(gs.tc_float), want)
            return t if batched else t.unsqueeze(0)
        out = a.astype(self._bridge.solver.np_dtype, copy=False)
        return out if batched or out.ndim < len(want) else out[None]

    def _ref(self, ref, local, who):
        if ref not in REFS:
            raise GenesisException(f"{who}: ref={ref!r}; it must be one of {REFS}")
        if ref == "root_com" and local:
            raise ValueError(f"{who}: local=True is not compatible with ref='root_com' (the tree's centre of mass "
                             "has no axes of its own)")

    # ---------------------------------------------------------------- poses
    def _poses(self):
        """(pos (B, L, 3), R (B, L, 3, 3), com (B, L, 3) world centre of mass) at the current state."""
        b = self._bridge
        pos, quat = b.link_outputs()[:2]
        R = quat_to_R(quat)
        com = pos + (R @ b.params["com"].to(pos.dtype).unsqueeze(-1))[..., 0]
        return pos, R, com

    def _root_com(self, com):
        """(B, L, 3): for each link, the centre of mass of its kinematic tree (the links below its root)."""
        b = self._bridge
        if self._root_of is None:
            parent = b.solver.flat.np_link_parent
            root = np.arange(len(parent))
            for i in range(len(parent)):  # parents come before children
                root[i] = root[parent[i]] if parent[i] >= 0 else i
            self._root_of = torch.as_tensor(root, device=com.device)
        r = self._root_of
        m = b.params["mass"].to(com.dtype)
        msum = torch.zeros_like(m).index_add(1, r, m)
        mc = torch.zeros_like(com).index_add(1, r, m.unsqueeze(-1) * com)
        ms = msum[:, r].unsqueeze(-1)
        # a massless tree (a fixed world body): its root's origin
        pos0 = b.link_outputs()[0][:, r]
        return torch.where(ms > 0, mc[:, r] / torch.where(ms > 0, ms, torch.ones_like(ms)), pos0)

    # ---------------------------------------------------------------- getters
    def _out(self, t, envs, links):
        t = t[torch.as_tensor(envs, device=t.device)][:, torch.as_tensor(links, device=t.device)]
        return wrap(t if self._scene.n_envs > 0 else t[0])

    def _check_built(self, who):
        if not self._scene.is_built:
            raise GenesisException(f"{who} before scene.build(): build the scene first")

    def get_links_pos(self, links_idx=None, envs_idx=None, *, ref="link_origin"):
        """World positions (m) of the links' origins, centres of mass ("link_com") or trees' centres of mass
        ("root_com"): (n_envs, len(links_idx), 3), or (len(links_idx), 3) unbatched."""
        who = self._label("get_links_pos")
        self._check_built(who)
        self._ref(ref, False, who)
        links, envs = self._links(links_idx, who), self._envs(envs_idx, who)
        if ref == "link_origin":
            return self._out(self._bridge.link_outputs()[0], envs, links)
        pos, R, com = self._poses()
        return self._out(com if ref == "link_com" else self._root_com(com), envs, links)

    def get_links_quat(self, links_idx=None, envs_idx=None):
        """World orientations (w, x, y, z) of the link frames."""
        who = self._label("get_links_quat")
        self._check_built(who)
        return self._out(self._bridge.link_outputs()[1], self._envs(envs_idx, who), self._links(links_idx, who))

    def get_links_vel(self, links_idx=None, envs_idx=None, *, ref="link_origin"):
        """World linear velocities (m/s) of the point of each link at its origin, centre of mass or tree's
        centre of mass (ref as get_links_pos)."""
        who = self._label("get_links_vel")
        self._check_built(who)
        self._ref(ref, False, who)
        links, envs = self._links(links_idx, who), self._envs(envs_idx, who)
        pos, _, vel, ang = self._bridge.link_outputs()
        if ref != "link_origin":
            _, _, com = self._poses()
            point = com if ref == "link_com" else self._root_com(com)
            vel = vel + torch.cross(ang, point - pos, dim=-1)
        return self._out(vel, envs, links)

    def get_links_ang(self, links_idx=None, envs_idx=None):
        """World angular velocities (rad/s) of the links."""
        who = self._label("get_links_ang")
        self._check_built(who)
        return self._out(self._bridge.link_outputs()[3], self._envs(envs_idx, who), self._links(links_idx, who))

    def get_links_root_COM(self, links_idx=None, envs_idx=None):
        """Centre of mass (m, world) of the kinematic tree each link belongs to (Genesis's name)."""
        return self.get_links_pos(links_idx, envs_idx, ref="root_com")

    # ---------------------------------------------------------------- forces
    def apply_links_external_force(self, force, links_idx=None, envs_idx=None, *, ref="link_origin", local=False):
        """Apply a force (N) to links for the next step: (n_envs, len(links_idx), 3), or (len(links_idx), 3)
        unbatched, or anything that broadcasts to it. It acts at the links' origins (ref="link_origin"),
        centres of mass ("link_com") or their trees' centres of mass ("root_com"); in world axes, or in the
        link's axes with local=True. Calls before one step add up; the step uses them and drops them."""
        who = self._label("apply_links_external_force")
        self._check_built(who)
        self._ref(ref, local, who)
        links, envs = self._links(links_idx, who), self._envs(envs_idx, who)
        f = self._vectors(force, envs, links, who, "force")
        if not local and ref == "link_origin":
            self._bridge.add_applied(envs, links, f, None)
            return
        # the lever (and a local force's axes) at the current pose, differentiable through it
        pos, R, com = self._poses()
        e, l = torch.as_tensor(envs, device=pos.device), torch.as_tensor(links, device=pos.device)
        pos, R_sel = pos[e][:, l], R[e][:, l]
        if not torch.is_tensor(f):
            f = torch.as_tensor(np.array(f), device=pos.device).to(pos.dtype).expand(len(envs), len(links), 3)
        if local:
            f = (R_sel @ f.unsqueeze(-1))[..., 0]
        moment = None
        if ref != "link_origin":
            point = com if ref == "link_com" else self._root_com(com)
            moment = torch.cross(point[e][:, l] - pos, f, dim=-1)
        self._bridge.add_applied(envs, links, f, moment)

    def apply_links_external_torque(self, torque, links_idx=None, envs_idx=None, *, ref="link_origin", local=False):
        """Apply a torque (N m) to links for the next step, shaped as apply_links_external_force's force; in
        world axes, or with local=True in the link's axes (ref "link_origin" or "link_com": both the link's
        axes here, see the module docstring)."""
        who = self._label("apply_links_external_torque")
        self._check_built(who)
        self._ref(ref, local, who)
        links, envs = self._links(links_idx, who), self._envs(envs_idx, who)
        t = self._vectors(torque, envs, links, who, "torque")
        if local:
            _, R, _ = self._poses()
            e, l = torch.as_tensor(envs, device=R.device), torch.as_tensor(links, device=R.device)
            if not torch.is_tensor(t):
                t = torch.as_tensor(np.array(t), device=R.device).to(R.dtype).expand(len(envs), len(links), 3)
            t = (R[e][:, l] @ t.unsqueeze(-1))[..., 0]
        self._bridge.add_applied(envs, links, None, t)


class _ParamField:
    """One link parameter of the rigid solver in the layout of Genesis's `links_info` fields: (n_links, ...)
    for the scene's links (every rigid entity's, solver order), with an env axis after the link axis,
    (n_links, n_envs, ...), when the scene has RigidOptions(batch_links_info=True). Read-only."""

    def __init__(self, scene, param, what):
        self._scene_ref, self._param, self._what = weakref.ref(scene), param, what

    def to_torch(self, device=None):
        scene = self._scene_ref()
        if scene is None:
            raise GenesisException(f"rigid_solver.links_info.{self._what}: its scene no longer exists")
        v = scene._rigid.params[self._param].detach()  # (B, n_links, ...)
        if scene.rigid_options.batch_links_info:
            v = v.movedim(0, 1)
        else:
            if v.shape[0] > 1 and not bool((v == v[:1]).all()):
                raise GenesisException(
                    f"rigid_solver.links_info.{self._what}: the envs have different values (set per env), which "
                    "this unbatched layout cannot show; build with gs.options.RigidOptions(batch_links_info=True) "
                    "for the (n_links, n_envs) layout, or read them per entity (entity.get_links_mass / "
                    "get_links_COM / get_links_inertia)")
            v = v[0]
        v = v.clone()
        return v if device is None else v.to(device)

    def to_numpy(self):
        return self.to_torch().cpu().numpy()

    @property
    def shape(self):
        return tuple(self.to_torch().shape)

    def __getitem__(self, key):
        return self.to_numpy()[key]

    def __setitem__(self, key, value):
        raise GenesisException(f"rigid_solver.links_info.{self._what} is read-only in genesis_lite; set link "
                               "parameters with the entity's setters (set_links_inertial_mass, set_links_COM, "
                               "set_links_inertia, link.set_mass), which keep gradients")


class LinksInfoView:
    """Genesis's `rigid_solver.links_info`, the fields scripts read: inertial_mass (kg), inertial_pos (the
    centre of mass in the link frame, m), inertial_i (the inertia about it in link axes, kg m^2)."""

    FIELDS = {"inertial_mass": "mass", "inertial_pos": "com", "inertial_i": "inertia"}

    def __init__(self, scene):
        self._scene_ref = weakref.ref(scene)

    def __getattr__(self, name):
        if name.startswith("_"):
            raise AttributeError(name)
        param = LinksInfoView.FIELDS.get(name)
        if param is None:
            raise GenesisException(f"rigid_solver.links_info.{name} is not available in genesis_lite; readable "
                                   f"are {sorted(LinksInfoView.FIELDS)} (and the entities' getters)")
        return _ParamField(self._scene_ref(), param, name)


class GravityCompensationMixin:
    """Gravity compensation of a rigid entity: Genesis's `gravity_compensation` (its material's) and a
    differentiable setter."""

    @property
    def gravity_compensation(self):
        """The material's gravity compensation (Genesis's entity.gravity_compensation)."""
        return self.material.gravity_compensation

    def _gcomp_values(self, gc, envs):
        import genesis_lite as gs

        t = gc if torch.is_tensor(gc) else torch.as_tensor(np.asarray(gc, dtype=np.float64), dtype=gs.tc_float)
        if t.dim() == 0 or (self._scene.n_envs == 0 and t.numel() == 1):
            t = t.reshape(1)
        elif t.dim() == 1 and self._scene.n_envs > 0:
            t = t.reshape(-1, 1)
        vals = self._values(t, envs, 1, "gravity_compensation")
        return vals.expand(len(envs), self.n_links)

    def set_gravity_compensation(self, gc, envs_idx=None):
        """The fraction of gravity cancelled on every link of this entity (0..1; Genesis sets it with
        gs.materials.Rigid(gravity_compensation=...)): a number, or per env (n_envs,). Differentiable."""
        sim = self._sim
        envs = self._envs(envs_idx)
        vals = derive(lambda g: self._gcomp_values(g, envs), gc)  # made again in a new rollout (grad/remake.py)
        v = vals.detach()
        bad = (v < 0) | (v > 1)
        if bool(bad.any()):
            e = int(torch.nonzero(bad)[0][0])
            env = f" in env {int(envs[e])}" if self._scene.n_envs > 0 else ""
            raise GenesisException(f"entity '{self.name}': gravity_compensation must lie in [0, 1] (the fraction of "
                                   f"gravity cancelled), got {v[e, 0].item()}{env}")
        links = torch.arange(self._link_start, self._link_start + self.n_links, device=vals.device)
        sim.enable_applied()
        sim.set_param("gravity_compensation", vals, envs, links)

    def get_gravity_compensation(self, envs_idx=None):
        """The entity's gravity compensation per env (n_envs,), or a 0-d tensor unbatched."""
        sim = self._sim
        envs = self._envs(envs_idx)
        if not sim.has_applied:
            g = torch.full((len(envs),), float(self.material.gravity_compensation.detach()
                                               if torch.is_tensor(self.material.gravity_compensation)
                                               else self.material.gravity_compensation),
                           dtype=sim.dtype, device=sim.device)
        else:
            g = sim.params["gravity_compensation"][envs][:, self._link_start]
        return wrap(g if self._scene.n_envs > 0 else g[0])


__all__ = ["RigidSolverAPI", "GravityCompensationMixin"]
