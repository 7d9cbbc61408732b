"""Genesis's kinematics API on a rigid entity: forward kinematics at any configuration, link Jacobians
and inverse kinematics, in torch (no kernel launches: IK evaluates forward kinematics hundreds of times
at configurations that are not the scene's state).

Forward kinematics follows the solver's joint model (solvers/rigid/model.py, solvers/rigid/kinematics.py):
a link's pose is its parent's times the joint frame (joint_pos, joint_quat) times the joint's motion
(a rotation about / a translation along `joint_axis`, in the joint frame); a free root's pose is its
qpos. tests/test_kinematics_api.py checks it against the solver's link poses and against Pinocchio.

Dof velocities are the solver's: 1-dof joints their rate, a free joint the world-frame linear velocity
of its link's origin then the world-frame angular velocity. So a Jacobian column is the velocity of the
point that a unit dof velocity gives, in the world frame.
"""
from __future__ import annotations

import numpy as np
import torch

from ..errors import GenesisException
from ..grad.tensor import wrap
from ..utils.geom import quat_mul as _qmul
from ..utils.geom import _unit_quat_to_R as _R


def _skew(v):
    z = torch.zeros_like(v[..., 0])
    x, y, w = v.unbind(-1)
    return torch.stack([torch.stack([z, -w, y], -1), torch.stack([w, z, -x], -1), torch.stack([-y, x, z], -1)], -2)


def _rot_error(R):
    """sin(angle) * axis of rotation matrices (..., 3, 3): the rotation error IK drives to zero (equal to
    the rotation vector to first order, smooth everywhere, and a descent direction up to 180 degrees)."""
    return 0.5 * torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)


class KinematicsMixin:
    """forward_kinematics, get_jacobian, inverse_kinematics (Genesis's names and arguments)."""

    def _joint_tensors(self, dtype, device):
        key = (dtype, device)
        cache = getattr(self, "_fk_consts", None)
        if cache is None or cache[0] != key:
            m = self.model
            t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64), dtype=dtype, device=device)  # noqa: E731
            consts = [(l.parent, l.joint_type, t(l.joint_pos), t(l.joint_quat), t(l.joint_axis)) for l in m.links]
            self._fk_consts = cache = (key, consts)
        return cache[1]

    def forward_kinematics(self, qpos, links_idx_local=None):
        """World poses of the links at configuration `qpos` (m, rad; (n_qs,) or (B, n_qs)): (pos, quat)
        of shape (..., n_links, 3) and (..., n_links, 4), quat (w, x, y, z). Differentiable in qpos."""
        q = torch.as_tensor(qpos)
        if not q.is_floating_point():
            q = q.double()
        single = q.dim() == 1
        q = q.reshape(-1, self.n_qs)
        pos, quat = [], []
        for i, (parent, jt, jp, jq, ax) in enumerate(self._joint_tensors(q.dtype, q.device)):
            qs = self.joints[i].q_start_local
            B = q.shape[0]
            if jt == "free":
                lp, lq = q[:, qs:qs + 3], q[:, qs + 3:qs + 7]
                lq = lq / lq.norm(dim=-1, keepdim=True)
            else:
                lp, lq = jp.expand(B, 3), jq.expand(B, 4)
                if jt == "revolute":
                    half = 0.5 * q[:, qs:qs + 1]
                    lq = _qmul(lq, torch.cat([torch.cos(half), torch.sin(half) * ax], -1))
                elif jt == "prismatic":
                    lp = lp + (_R(jq) @ ax) * q[:, qs:qs + 1]
            if parent >= 0:
                lp = pos[parent] + (_R(quat[parent]) @ lp.unsqueeze(-1)).squeeze(-1)
                lq = _qmul(quat[parent], lq)
            pos.append(lp)
            quat.append(lq)
        pos, quat = torch.stack(pos, -2), torch.stack(quat, -2)
        if links_idx_local is not None:
            idx = torch.as_tensor(links_idx_local).reshape(-1)
            pos, quat = pos[:, idx], quat[:, idx]
        return (pos[0], quat[0]) if single else (pos, quat)

    def _jacobian_at(self, q, link_local, point_local=None, fk=None):
        """(B, 6, n_dofs) world Jacobian [linear; angular] of a point of link `link_local` (its origin, or
        point_local in its frame) at configurations q (B, n_qs); `fk`: forward_kinematics(q) when the
        caller has it already."""
        pos, quat = self.forward_kinematics(q) if fk is None else fk
        B = q.shape[0]
        p = pos[:, link_local]
        if point_local is not None:
            p = p + (_R(quat[:, link_local]) @ torch.as_tensor(point_local, dtype=q.dtype, device=q.device))
        J = q.new_zeros(B, 6, self.n_dofs)
        chain = []
        i = link_local
        while i >= 0:
            chain.append(i)
            i = self.model.links[i].parent
        for i in chain:
            j = self.joints[i]
            d = j.dof_start_local
            if j.type == "free":
                J[:, 0:3, d:d + 3] = torch.eye(3, dtype=q.dtype, device=q.device)
                J[:, 0:3, d + 3:d + 6] = -_skew(p - pos[:, i])
                J[:, 3:6, d + 3:d + 6] = torch.eye(3, dtype=q.dtype, device=q.device)
            elif j.type in ("revolute", "prismatic"):
                axis_w = (_R(quat[:, i]) @ self._joint_tensors(q.dtype, q.device)[i][4])
                if j.type == "revolute":
                    J[:, 0:3, d] = torch.cross(axis_w, p - pos[:, i], dim=-1)
                    J[:, 3:6, d] = axis_w
                else:
                    J[:, 0:3, d] = axis_w
        return J

    def _link_local(self, link):
        if hasattr(link, "idx_local") and getattr(link, "entity", None) is self:
            return link.idx_local
        if isinstance(link, str):
            return self.get_link(link).idx_local
        raise GenesisException(f"entity '{self.name}': expected one of its links (entity.get_link(name)), got "
                               f"{link!r}")

    def get_jacobian(self, link, local_point=None, envs_idx=None):
        """World-frame Jacobian of `link`'s origin (or of `local_point`, m, in the link frame) at the current
        state: (6, n_dofs) rows linear then angular velocity per unit dof velocity; batched
        (n_envs, 6, n_dofs). Differentiable in the state."""
        li = self._link_local(link)
        q = self.get_qpos(envs_idx=envs_idx).reshape(-1, self.n_qs)
        return self._out(self._jacobian_at(q, li, local_point))

    def inverse_kinematics(self, link, pos=None, quat=None, init_qpos=None, respect_joint_limit=True,
                           max_samples=50, max_solver_iters=20, damping=0.01, pos_tol=5e-4, rot_tol=5e-3,
                           pos_mask=(True, True, True), rot_mask=(True, True, True), max_step_size=0.5,
                           dofs_idx_local=None, return_error=False, envs_idx=None):
        """Genesis's inverse kinematics: a qpos that puts `link` at `pos` (m) and/or `quat` (w, x, y, z),
        by damped least squares from init_qpos (default: the current state), restarted from random
        configurations within the joint limits (up to max_samples tries) until the position error is below
        pos_tol (m) and the rotation error below rot_tol (rad). Only 1-dof joints move (those of
        dofs_idx_local when given); the scene's state is not changed.

        Differentiable in pos and quat: the answer is the converged solution plus one damped Gauss-Newton
        step taken in torch, whose derivative with respect to the target is the implicit-function one.
        Returns qpos ((n_qs,) or (n_envs, n_qs)) and, with return_error, the (..., 6) error."""
        if pos is None and quat is None:
            raise GenesisException(f"entity '{self.name}': inverse_kinematics needs a target pos and/or quat")
        import genesis_lite as gs

        li = self._link_local(link)
        batched = self._scene.n_envs > 0
        q0 = self.get_qpos(envs_idx=envs_idx) if init_qpos is None else torch.as_tensor(init_qpos)
        q0 = q0.detach().to(gs.tc_float).reshape(-1, self.n_qs).clone()
        B = q0.shape[0]
        dt, dev = q0.dtype, q0.device

        def target(x, n):
            if x is None:
                return None
            t = x if torch.is_tensor(x) else torch.as_tensor(np.asarray(x, dtype=np.float64))
            t = t.to(dtype=dt, device=dev)
            if t.shape == (n,):
                t = t.expand(B, n)
            if t.shape != (B, n):
                raise GenesisException(f"entity '{self.name}': inverse_kinematics target of shape {tuple(t.shape)}; "
                                       f"expected ({n},)" + (f" or ({B}, {n})" if batched else ""))
            return t

        p_t, q_t = target(pos, 3), target(quat, 4)
        if q_t is not None:
            q_t = q_t / q_t.norm(dim=-1, keepdim=True)
        wmask = torch.cat([torch.as_tensor(pos_mask, dtype=dt) * (p_t is not None),
                           torch.as_tensor(rot_mask, dtype=dt) * (q_t is not None)]).to(dev)

        # the dofs IK may move: 1-dof joints (those of dofs_idx_local when given), with their q index
        allowed = set(range(self.n_dofs)) if dofs_idx_local is None else \
            set(int(i) for i in torch.as_tensor(dofs_idx_local).reshape(-1).tolist())
        movable = [(j.dof_start_local, j.q_start_local) for j in self.joints
                   if j.n_dofs == 1 and j.dof_start_local in allowed]
        if not movable:
            raise GenesisException(f"entity '{self.name}': inverse_kinematics has no revolute or prismatic dof to move")
        dofs = torch.tensor([d for d, _ in movable], device=dev)
        qidx = torch.tensor([k for _, k in movable], device=dev)
        lim = torch.as_tensor(np.array([self.model.links[i].limit for i, j in enumerate(self.joints)
                                        if j.n_dofs == 1 and j.dof_start_local in allowed]), dtype=dt, device=dev)
        lo, hi = lim[:, 0], lim[:, 1]

        def error(q, fk=None):
            ps, qs = self.forward_kinematics(q) if fk is None else fk
            e = []
            e.append(p_t - ps[:, li] if p_t is not None else q.new_zeros(q.shape[0], 3))
            if q_t is not None:
                Rt, Rc = _R(q_t), _R(qs[:, li])
                e.append(_rot_error(Rt @ Rc.transpose(-1, -2)))
            else:
                e.append(q.new_zeros(q.shape[0], 3))
            return torch.cat(e, -1) * wmask

        def dls(q):
            fk = self.forward_kinematics(q)  # one evaluation serves the Jacobian and the error
            J = self._jacobian_at(q, li, fk=fk)[:, :, dofs] * wmask[:, None]
            e = error(q, fk)
            A = J @ J.transpose(-1, -2) + (damping ** 2) * torch.eye(6, dtype=dt, device=dev)
            return (J.transpose(-1, -2) @ torch.linalg.solve(A, e.unsqueeze(-1))).squeeze(-1), e

        def converged(e):
            return (e[:, :3].norm(dim=-1) <= pos_tol) & (e[:, 3:].norm(dim=-1) <= rot_tol)

        gen = torch.Generator(device="cpu").manual_seed(0)
        best_q, best_e = q0.clone(), error(q0)
        done = converged(best_e)
        for sample in range(max(int(max_samples), 1)):
            if bool(done.all()):
                break
            q = best_q.clone()
            if sample > 0:  # restart the unconverged envs from a random configuration within the limits
                u = torch.rand(B, len(movable), generator=gen, dtype=dt).to(dev)
                span_lo = torch.where(torch.isfinite(lo), lo, torch.full_like(lo, -np.pi))
                span_hi = torch.where(torch.isfinite(hi), hi, torch.full_like(hi, np.pi))
                q[:, qidx] = span_lo + u * (span_hi - span_lo)
            with torch.no_grad():
                for _ in range(int(max_solver_iters)):
                    step, e = dls(q)
                    n = step.norm(dim=-1, keepdim=True)
                    step = step * torch.clamp(max_step_size / n.clamp_min(1e-30), max=1.0)
                    q[:, qidx] = q[:, qidx] + step
                    if respect_joint_limit:
                        q[:, qidx] = torch.maximum(torch.minimum(q[:, qidx], hi), lo)
                e = error(q)
            better = (~done) & (e.norm(dim=-1) < best_e.norm(dim=-1))
            best_q = torch.where(better[:, None], q, best_q)
            best_e = torch.where(better[:, None], e, best_e)
            done = converged(best_e)
        # one damped Gauss-Newton step in torch from the (detached) solution: at convergence its value is
        # the solution's to within the tolerance, and its derivative in the target is the implicit one
        step, e = dls(best_q)
        out = best_q.clone()
        out[:, qidx] = best_q[:, qidx] + step
        if respect_joint_limit:
            out[:, qidx] = torch.maximum(torch.minimum(out[:, qidx], hi), lo)
        res = (wrap(out), wrap(e)) if batched else (wrap(out[0]), wrap(e[0]))
        return res if return_error else res[0]
