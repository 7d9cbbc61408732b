"""Stages 4-5, passive and actuation forces, assembled with the bias into the generalised force.

Diagonal stiffness K and damping D are treated implicitly, (M + h D + h^2 K) qacc = f(q, v) - h K v:
with implicitfast, the PD gains, joint damping and friction-loss slope; with every integrator, the
joint-limit springs (stiff by design).
"""
import taichi as ti

from .math3d import func_add

CTRL_FORCE, CTRL_POSITION, CTRL_VELOCITY = 0, 1, 2
FRICTIONLOSS_VEL = 1e-2  # m/s or rad/s: velocity scale of the smooth tanh friction loss


@ti.func
def func_tanh_where(s: ti.template(), on, x):
    """tanh(x) where `on`, else 0. Without gradients a branch skips the tanh (a libm call per dof and
    evaluation) for the dofs without friction loss; with gradients the select form that Taichi's
    reverse mode needs (a local assigned in a branch becomes an adstack)."""
    if ti.static(s.requires_grad):
        return ti.select(on, ti.tanh(x), 0.0)
    else:
        r = ti.cast(0.0, s.dtype)
        if on:
            r = ti.tanh(x)
        return r


@ti.func
def func_generalized_force(s: ti.template(), i_b, e, src, h):
    """force = actuation + passive + joint limits - bias; adds the implicit terms to M's diagonal.
    h is the (sub)step length. Single-assignment form (see kinematics.py)."""
    for i_d in range(s.n_dofs):
        v = s.qvel[src, i_b, i_d]
        i_q = s.dof_q[i_d]
        has_q = ti.cast(i_q >= 0, s.dtype)
        q = s.qpos[src, i_b, ti.max(i_q, 0)] * has_q
        mode = s.ctrl_mode[i_b, i_d]
        pos_mode = ti.cast(mode == CTRL_POSITION, s.dtype)
        vel_mode = ti.cast(mode == CTRL_VELOCITY, s.dtype)
        force_mode = 1.0 - pos_mode - vel_mode
        kp = s.dof_kp[i_b, i_d] * pos_mode
        kv = s.dof_kv[i_b, i_d] * (pos_mode + vel_mode)
        raw = force_mode * s.ctrl_force[i_b, i_d] + kp * (s.ctrl_pos[i_b, i_d] - q) + kv * (s.ctrl_vel[i_b, i_d] - v)
        lo = s.dof_force_lo[i_b, i_d]
        hi = s.dof_force_hi[i_b, i_d]
        # saturated: the actuator no longer responds to q or v
        free_act = ti.cast(raw >= lo and raw <= hi, s.dtype)
        tau = ti.min(ti.max(raw, lo), hi)
        s.dof_tau[i_b, i_d] = tau
        fl = s.dof_frictionloss[i_b, i_d]
        th = func_tanh_where(s, fl != 0.0, v / FRICTIONLOSS_VEL)
        damp = s.dof_damping[i_b, i_d]
        # joint-limit springs, one-sided; their damping acts only while moving further out
        lim_lo = s.dof_limit_lo[i_d]
        lim_hi = s.dof_limit_hi[i_d]
        below = s.limits_on and i_q >= 0 and q < lim_lo
        above = s.limits_on and i_q >= 0 and q > lim_hi
        lim_f = ti.select(below, s.limit_k * (lim_lo - q) - s.limit_d * ti.min(v, 0.0),
                          ti.select(above, s.limit_k * (lim_hi - q) - s.limit_d * ti.max(v, 0.0), 0.0))
        lim_K = ti.select(below or above, s.limit_k, 0.0)
        lim_D = ti.select((below and v < 0) or (above and v > 0), s.limit_d, 0.0)
        # stiffness/damping treated implicitly: PD and passive terms with implicitfast only,
        # joint-limit springs always (they are constraints, stiff by design)
        K = lim_K + s.implicit_on * kp * free_act
        D = lim_D + s.implicit_on * (kv * free_act + damp + fl * (1.0 - th * th) / FRICTIONLOSS_VEL)
        s.force[i_b, i_d] = tau - damp * v - fl * th - s.bias[i_b, i_d] + lim_f - h * K * v
        diag = s.dof_armature[i_b, i_d] + h * D + h * h * K
        if ti.static(s.requires_grad):
            s.mass_mat[i_b, i_d, i_d] += diag
        else:  # see math3d.func_add
            s.mass_mat[i_b, i_d, i_d] = s.mass_mat[i_b, i_d, i_d] + diag

