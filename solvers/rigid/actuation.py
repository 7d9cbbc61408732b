"""Stages 4-5, passive and actuation forces, assembled with the bias into the generalised force.

Diagonal stiffness K and damping D are treated implicitly, (M + h D + h^2 K) qacc = f(q, v) - h K v:
with implicitfast, the PD gains, joint damping and friction-loss slope; with every integrator, the
joint-limit springs (stiff by design).
"""
import taichi as ti

CTRL_FORCE, CTRL_POSITION, CTRL_VELOCITY = 0, 1, 2
FRICTIONLOSS_VEL = 1e-2  # m/s or rad/s: velocity scale of the smooth tanh friction loss


@ti.func
def func_generalized_force(s: ti.template(), i_b, e, src, h):
    """force = actuation + passive + joint limits - bias; adds the implicit terms to M's diagonal.
    h is the (sub)step length, used by implicitfast only."""
    for i_d in range(s.n_dofs):
        v = s.qvel[src, i_b, i_d]
        i_q = s.dof_q[i_d]
        q = 0.0
        if i_q >= 0:
            q = s.qpos[src, i_b, i_q]
        mode = s.ctrl_mode[i_b, i_d]
        kp = 0.0
        kv = 0.0
        tau = s.ctrl_force[i_b, i_d]
        if mode == CTRL_POSITION:
            kp = s.dof_kp[i_b, i_d]
            kv = s.dof_kv[i_b, i_d]
            tau = kp * (s.ctrl_pos[i_b, i_d] - q) + kv * (s.ctrl_vel[i_b, i_d] - v)
        elif mode == CTRL_VELOCITY:
            kv = s.dof_kv[i_b, i_d]
            tau = kv * (s.ctrl_vel[i_b, i_d] - v)
        lo = s.dof_force_lo[i_b, i_d]
        hi = s.dof_force_hi[i_b, i_d]
        if tau < lo or tau > hi:
            # saturated: the actuator no longer responds to q or v
            tau = ti.min(ti.max(tau, lo), hi)
            kp = 0.0
            kv = 0.0
        s.dof_tau[i_b, i_d] = tau
        fl = s.dof_frictionloss[i_b, i_d]
        th = ti.tanh(v / FRICTIONLOSS_VEL)
        damp = s.dof_damping[i_b, i_d]
        f = tau - damp * v - fl * th - s.bias[i_b, i_d]
        # stiffness/damping treated implicitly: PD and passive terms with implicitfast only,
        # joint-limit springs always (they are constraints, stiff by design)
        K = 0.0
        D = 0.0
        if ti.static(s.implicit):
            K = kp
            D = kv + damp + fl * (1.0 - th * th) / FRICTIONLOSS_VEL
        if ti.static(s.enable_joint_limit):
            if i_q >= 0:
                lim_lo = s.dof_limit_lo[i_d]
                lim_hi = s.dof_limit_hi[i_d]
                if q < lim_lo:
                    f += s.limit_k * (lim_lo - q) - s.limit_d * ti.min(v, 0.0)
                    K += s.limit_k
                    if v < 0:
                        D += s.limit_d
                elif q > lim_hi:
                    f += s.limit_k * (lim_hi - q) - s.limit_d * ti.max(v, 0.0)
                    K += s.limit_k
                    if v > 0:
                        D += s.limit_d
        f -= h * K * v
        s.force[i_b, i_d] = f
        s.mass_mat[i_b, i_d, i_d] += s.dof_armature[i_b, i_d] + h * D + h * h * K
