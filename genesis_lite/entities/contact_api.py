"""Contact-related entity API: get_contacts, get_links_net_contact_force, set_friction, get_friction.

Contacts are those of the last evaluation of the last step (for substeps > 1, the last substep; the
state it saw is the one the step started from). They are read-only: no gradient flows through them.
Friction is a differentiable parameter: `set_friction(mu)` with a tensor that requires grad makes
`mu.grad` appear after `loss.backward()`.
"""
from __future__ import annotations

import numpy as np
import torch

from ..errors import GenesisException
from ..grad.remake import derive
from ..grad.tensor import wrap


class ContactMixin:
    # ---------------------------------------------------------------- geoms of this entity
    @property
    def n_geoms(self) -> int:
        """Number of collision geoms of the entity (fixed links merged into their parents)."""
        return sum(len(l.geoms) for l in self.model.links)

    @property
    def _contact(self):
        """The scene's contact solver, or None when the scene has no collision pairs."""
        return self._sim.solver.contact

    def _geom_start(self):
        c = self._contact
        if c is not None:
            return c.entity_geom_start[self._solver_idx]
        return sum(e.n_geoms for e in self._scene.rigid_entities[: self._solver_idx])

    # ---------------------------------------------------------------- friction
    def set_friction(self, friction, envs_idx=None):
        """Coulomb friction coefficient (dimensionless, >= 0) of every collision geom of this entity: a
        number, or a tensor of shape () / (n_geoms,) (batched scenes: also (n_envs, n_geoms)). A contact
        uses the larger coefficient of its two geoms (as MuJoCo). Differentiable: a tensor that requires
        grad receives the gradient of the loss."""
        sim = self._sim
        envs = self._envs(envs_idx)
        n = self.n_geoms
        if isinstance(friction, torch.Tensor) and friction.dim() == 0:
            friction = derive(lambda f: f.reshape(1).expand(n), friction)  # keeps a leaf's recipe (grad/remake.py)
        elif not isinstance(friction, torch.Tensor) and np.ndim(friction) == 0:
            friction = np.full(n, float(friction))
        vals = self._values(friction, envs, n, "friction")
        if not torch.isfinite(vals.detach()).all() or (vals.detach() < 0).any():
            raise GenesisException(f"entity '{self.name}': friction must be finite and >= 0, got "
                                   f"{vals.detach().cpu().numpy().reshape(-1)[:8]}")
        if n == 0:
            return
        if self._contact is None:
            if vals.requires_grad:
                raise GenesisException(
                    f"entity '{self.name}': set_friction with a tensor that requires grad, but the scene has no "
                    "collision pairs (or RigidOptions(enable_collision=False)), so friction has no effect and would "
                    "receive no gradient. Add a ground plane or other colliding entities, or pass friction.detach().")
            full = self._friction_table().clone()
            full[envs.to(full.device)] = vals.detach().to(full.dtype)
            self._friction_no_contact = full
            return
        idx = torch.arange(n, device=vals.device) + self._geom_start()
        sim.set_param("friction", vals, envs, idx)

    def set_friction_ratio(self, friction_ratio, links_idx_local=None, envs_idx=None):
        """Genesis's domain randomisation of friction: the geoms of each link named get the model's friction
        coefficient times that link's ratio (dimensionless, >= 0), one ratio per link, (n,) or (n_envs, n).
        The other geoms keep their current coefficient. Differentiable in the ratio, as set_friction."""
        envs, ls = self._envs(envs_idx), self._links(links_idx_local)
        ratio = self._values(friction_ratio, envs, len(ls), "friction_ratio")
        base = torch.tensor([g.friction if g.friction is not None else self.material.friction
                             for l in self.model.links for g in l.geoms], dtype=ratio.dtype, device=ratio.device)
        cur = self.get_friction(envs_idx)
        cur = (cur if self._scene.n_envs > 0 else cur.reshape(1, -1)).detach().to(ratio.dtype)
        starts = np.cumsum([0] + [len(l.geoms) for l in self.model.links])
        if self.n_geoms == 0:
            return
        links = (ls - self._link_start).tolist()
        batched = self._scene.n_envs > 0

        def frictions(r):
            cols = [cur[:, k:k + 1] for k in range(self.n_geoms)]
            for k, li in enumerate(links):
                for gi in range(starts[li], starts[li + 1]):
                    cols[gi] = base[gi] * r[:, k:k + 1]
            new = torch.cat(cols, -1)
            return new if batched else new[0]

        # made again from the ratio in a new rollout (grad/remake.py)
        self.set_friction(derive(frictions, ratio), envs_idx)

    def get_friction(self, envs_idx=None):
        """Friction coefficients of the entity's collision geoms, (n_geoms,) (batched: (n_envs, n_geoms))."""
        sim = self._sim
        envs = self._envs(envs_idx)
        n = self.n_geoms
        if self._contact is None:
            return self._out(self._friction_table()[envs])
        s = self._geom_start()
        return self._out(sim.params["friction"][envs][:, s:s + n])

    def _friction_table(self):
        """(n_envs, n_geoms) frictions of a scene without contacts (kept for get_friction only)."""
        v = getattr(self, "_friction_no_contact", None)
        if v is None:
            sim = self._sim
            base = torch.tensor([g.friction if g.friction is not None else self.material.friction
                                 for l in self.model.links for g in l.geoms], dtype=sim.dtype, device=sim.device)
            v = base.reshape(1, -1).expand(sim.B, base.numel())
        return v

    # ---------------------------------------------------------------- contacts
    def _contact_slots(self, with_entity=None):
        """(slot indices, flip) of the slots that involve this entity (and with_entity's if given);
        flip marks slots where this entity is on the SDF side (b), to be reported as side a."""
        c = self._contact
        ls, le = self._link_start, self._link_start + self.n_links
        la, lb = c.np_slot_link_a, c.np_slot_link_b
        in_a = (la >= ls) & (la < le)
        in_b = (lb >= ls) & (lb < le)
        if with_entity is not None:
            if with_entity._scene is not self._scene:
                raise GenesisException(f"entity '{self.name}': get_contacts(with_entity=...) needs an entity of the same scene")
            os_, oe = with_entity._link_start, with_entity._link_start + with_entity.n_links
            o_a = (la >= os_) & (la < oe)
            o_b = (lb >= os_) & (lb < oe)
            keep = (in_a & o_b) | (in_b & o_a)
            flip = in_b & o_a & ~(in_a & o_b)
        else:
            keep = in_a | in_b
            flip = in_b & ~in_a
        idx = np.nonzero(keep)[0]
        return idx, flip[idx]

    def get_contacts(self, with_entity=None):
        """Contacts of this entity at the last step, as a dict of tensors (no gradient):
        'link_a', 'link_b', 'geom_a', 'geom_b' (global indices; side a is this entity's), 'position' (m,
        world), 'normal' (unit, pointing from b towards a), 'force_a' (N, the contact force on link a, world
        frame), 'force_b' (= -force_a), 'penetration' (m, > 0 when overlapping; the force starts slightly
        before contact, see RigidOptions.contact_smoothing). Unbatched scenes: one row per contact point
        that applied a force in the step. Batched: rows for every potential contact point, shape (n_envs,
        n, ...), and 'valid_mask' (n_envs, n) marks those. The forces add up to what the bodies felt: a
        contact whose linearised normal law pulled in the step (solvers/rigid/contact, step 5) is listed
        with its pull (force_a . normal < 0). with_entity: only contacts against that entity."""
        sim = self._sim
        dev, dt = sim.device, sim.dtype
        c = self._contact
        B = sim.B
        if c is None:
            idx, flip = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool)
        else:
            idx, flip = self._contact_slots(with_entity)
        n = len(idx)
        if c is not None and n:
            r = c.read()
            pos, nrm, F, depth = (r[k][:, idx] for k in ("position", "normal", "force", "depth"))
            sgn = np.where(flip, -1.0, 1.0)[None, :, None]
            nrm = nrm * sgn
            F = F * sgn
            ga = np.where(flip, c.np_slot_gb[idx], c.np_slot_ga[idx])
            gb = np.where(flip, c.np_slot_ga[idx], c.np_slot_gb[idx])
        else:
            pos = nrm = F = np.zeros((B, n, 3))
            depth = np.zeros((B, n))
            ga = gb = np.zeros(n, dtype=np.int64)
        # every contact that applied a force (read() zeroes the others): one whose linearised normal law
        # pulled in the step too (its normal component is then negative), so that the forces add up to
        # what the bodies felt
        valid = np.abs(F).sum(-1) > 0
        geom_link = c.geoms.link if c is not None else np.zeros(0, dtype=np.int64)
        la = geom_link[ga] if n else ga
        lb = geom_link[gb] if n else gb
        T = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=dt, device=dev)  # noqa: E731
        L = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.int64, device=dev)  # noqa: E731
        pos, nrm, F, depth = (np.where(valid[..., None] if x.ndim == 3 else valid, x, 0.0) for x in (pos, nrm, F, depth))
        if self._scene.n_envs == 0:
            m = valid[0]
            return {"link_a": L(la[m]), "link_b": L(lb[m]), "geom_a": L(ga[m]), "geom_b": L(gb[m]),
                    "position": wrap(T(pos[0][m])), "normal": wrap(T(nrm[0][m])), "force_a": wrap(T(F[0][m])),
                    "force_b": wrap(T(-F[0][m])), "penetration": wrap(T(depth[0][m]))}
        tile = lambda a: np.broadcast_to(a, (B, n))  # noqa: E731
        return {"link_a": L(tile(la)), "link_b": L(tile(lb)), "geom_a": L(tile(ga)), "geom_b": L(tile(gb)),
                "position": wrap(T(pos)), "normal": wrap(T(nrm)), "force_a": wrap(T(F)), "force_b": wrap(T(-F)),
                "penetration": wrap(T(depth)), "valid_mask": torch.as_tensor(valid, device=dev)}

    def get_links_net_contact_force(self, envs_idx=None):
        """Sum of the contact forces on each link of the entity at the last step (N, world frame),
        (n_links, 3) (batched: (n_envs, n_links, 3)); no gradient."""
        sim = self._sim
        envs = self._envs(envs_idx)
        out = np.zeros((sim.B, self.n_links, 3))
        c = self._contact
        if c is not None:
            idx, _ = self._contact_slots()
            if len(idx):
                r = c.read()
                F = r["force"][:, idx]
                ls = self._link_start
                per_link = out.transpose(1, 0, 2)  # a view: (n_links, B, 3)
                for side, sgn in ((c.np_slot_link_a[idx], 1.0), (c.np_slot_link_b[idx], -1.0)):
                    mine = (side >= ls) & (side < ls + self.n_links)
                    np.add.at(per_link, side[mine] - ls, sgn * F[:, mine].transpose(1, 0, 2))
        t = torch.as_tensor(out, dtype=sim.dtype, device=sim.device)
        return self._out(t[envs.cpu()])

    def get_links_mpm_force(self, envs_idx=None):
        """Force the MPM material exerted on each link of the entity (N, world frame), averaged over the
        substeps of the last step, (n_links, 3) (batched: (n_envs, n_links, 3)); zeros when the scene
        couples no MPM material to it; no gradient."""
        sim = self._sim
        envs = self._envs(envs_idx)
        s = sim.solver
        out = np.zeros((sim.B, self.n_links, 3))
        if s.external is not None:
            ls = self._link_start
            out = s.external.ext_f.to_numpy().mean(1)[:, ls:ls + self.n_links]
        t = torch.as_tensor(out, dtype=sim.dtype, device=sim.device)
        return self._out(t[envs.cpu()])
