"""Stages 4-5, passive and actuation forces, assembled with the bias into the generalised force.

Diagonal stiffness K and damping D are treated implicitly, (M + h D + h^2 K) qacc = f(q, v) - h K v:
with every integrator, the joint-limit springs (stiff by design); with implicitfast, the joint damping,
the friction-loss slope and the PD's kp and kv while the actuator is not saturated (a saturated one no
longer responds to q or v); with approximate_implicitfast (Genesis's default integrator, v0.4.5
rigid/abd/forward_dynamics.py, func_compute_mass_matrix's first-order correction), the joint damping,
the friction-loss slope and the PD's kv, saturated or not, and never kp: Genesis's answers step by step
(tests/test_integrators.py). The joint springs (set_dofs_stiffness, MJCF `stiffness`) are explicit, as in
Genesis and MuJoCo (whose implicit integrators are implicit in velocity only).

Position control of a free joint's dofs follows Genesis (v0.4.5, rigid/abd/forward_dynamics.py,
func_torque_and_passive_force): a translational dof's error is target - world coordinate of the base
origin; the three rotational dofs' targets are intrinsic x-y-z Euler angles (what get_dofs_position
returns), and their error is a rotation vector, a geodesic error without gimbal lock, not a difference
of Euler angles. Genesis's free-joint angular dofs are body-frame, and its error is rotvec(q^-1 q_target)
in body axes; ours are world-frame (model.py), so the error is the same rotation in world axes,
rotvec(q_target q^-1) = R rotvec(q^-1 q_target): the same torque, and the same motion, when the three
rotational kp (and kv) are equal; with unequal gains Genesis's act about the body's axes, ours about the
world's (and a velocity target is body-frame there, world-frame here, as the dof velocities are). The
rotational error uses all three targets whichever of the three dofs are under position control (the
others' last targets, 0 after a reset), as Genesis does; unlike Genesis, a rotational dof in force or
velocity mode keeps its own control instead of being given the PD torque too.
"""
import taichi as ti

from .kinematics import JOINT_FREE
from .math3d import func_add, func_euler_xyz_quat, func_quat_log, func_quat_mul

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
def func_free_rot_error(s: ti.template(), i_b, src, i_l, j, on):
    """Component j (0-2) of a free joint's rotational PD error (module docstring): the rotation vector of
    q_target q^-1, q_target from the link's three Euler-angle targets. `on` False (a dof that is not a
    free joint's, where the reads are clamped into range) computes it at the identity, finite and with
    finite derivatives, for the select of the gradient path."""
    qs = s.link_q_start[i_l] + 3
    ds = s.link_dof_start[i_l] + 3
    q = ti.Vector([ti.select(on, s.qpos[src, i_b, ti.min(qs + k, s.qpos_len - 1)],
                             ti.static(1.0 if k == 0 else 0.0)) for k in ti.static(range(4))])
    a = ti.Vector([ti.select(on, s.ctrl_pos[i_b, ti.min(ds + k, s.qvel_len - 1)], 0.0)
                   for k in ti.static(range(3))])
    qt = func_euler_xyz_quat(a[0], a[1], a[2])
    r = func_quat_log(func_quat_mul(qt, ti.Vector([q[0], -q[1], -q[2], -q[3]])))
    return ti.select(j == 0, r[0], ti.select(j == 1, r[1], r[2]))


@ti.func
def func_pd_error(s: ti.template(), i_b, src, i_l, j, free_rot, pos_on, lin_err):
    """The PD position error of a dof of link i_l: lin_err (target - coordinate), or for a free joint's rotational
    dof (free_rot, j its index among the three) the rotation error's component. Without gradients a
    branch computes the rotation only for such dofs under position control; with gradients the select
    form (see func_tanh_where)."""
    if ti.static(s.requires_grad):
        return ti.select(free_rot, func_free_rot_error(s, i_b, src, i_l, j, free_rot), lin_err)
    else:
        err = lin_err
        if free_rot and pos_on:
            err = func_free_rot_error(s, i_b, src, i_l, j, True)
        return err


@ti.func
def func_generalized_force(s: ti.template(), i_b, e, src, h):
    """force = actuation + passive + joint limits - bias; adds the implicit terms to M's diagonal.
    h is the (sub)step length. Single-assignment form (see kinematics.py)."""
    for i_d in range(s.n_dofs):
        v = s.qvel[src, i_b, i_d]
        i_q = s.dof_q[i_d]
        has_q = ti.cast(i_q >= 0, s.dtype)
        q = s.qpos[src, i_b, ti.max(i_q, 0)] * has_q
        # a free joint's dofs have no coordinate of their own (dof_q -1): the translational ones are
        # compared with the base position, the rotational ones with func_free_rot_error
        i_l = s.dof_link[i_d]
        k = i_d - s.link_dof_start[i_l]
        is_free = s.link_jtype[i_l] == JOINT_FREE
        free_lin = is_free and k < 3
        free_rot = is_free and k >= 3
        q_lin = ti.select(free_lin, s.qpos[src, i_b, ti.min(s.link_q_start[i_l] + k, s.qpos_len - 1)], q)
        mode = s.ctrl_mode[i_b, i_d]
        pos_mode = ti.cast(mode == CTRL_POSITION, s.dtype)
        vel_mode = ti.cast(mode == CTRL_VELOCITY, s.dtype)
        force_mode = 1.0 - pos_mode - vel_mode
        kp = s.dof_kp[i_b, i_d] * pos_mode
        kv = s.dof_kv[i_b, i_d] * (pos_mode + vel_mode)
        err = func_pd_error(s, i_b, src, i_l, k - 3, free_rot, mode == CTRL_POSITION, s.ctrl_pos[i_b, i_d] - q_lin)
        raw = force_mode * s.ctrl_force[i_b, i_d] + kp * err + kv * (s.ctrl_vel[i_b, i_d] - v)
        lo = s.dof_force_lo[i_b, i_d]
        hi = s.dof_force_hi[i_b, i_d]
        # saturated: the actuator no longer responds to q or v
        free_act = ti.cast(raw >= lo and raw <= hi, s.dtype)
        tau = ti.min(ti.max(raw, lo), hi)
        s.dof_tau[i_b, i_d] = tau
        fl = s.dof_frictionloss[i_b, i_d]
        th = func_tanh_where(s, fl != 0.0, v / FRICTIONLOSS_VEL)
        damp = s.dof_damping[i_b, i_d]
        # joint spring towards the rest position (hinge and slide joints; a free joint's is ignored, as
        # in Genesis)
        spring = has_q * s.dof_stiffness[i_b, i_d] * (q - s.dof_springref[i_d])
        # joint-limit springs, one-sided; their damping acts only while moving further out
        lim_lo = s.dof_limit_lo[i_d]
        lim_hi = s.dof_limit_hi[i_d]
        below = s.limits_on and i_q >= 0 and q < lim_lo
        above = s.limits_on and i_q >= 0 and q > lim_hi
        lim_f = ti.select(below, s.limit_k * (lim_lo - q) - s.limit_d * ti.min(v, 0.0),
                          ti.select(above, s.limit_k * (lim_hi - q) - s.limit_d * ti.max(v, 0.0), 0.0))
        lim_K = ti.select(below or above, s.limit_k, 0.0)
        lim_D = ti.select((below and v < 0) or (above and v > 0), s.limit_d, 0.0)
        # stiffness/damping treated implicitly: PD and passive terms with the implicit integrators only,
        # joint-limit springs always (they are constraints, stiff by design). approximate_implicitfast
        # (Genesis's): kv whether or not the actuator is saturated, kp never
        kv_only = s.implicit_kv_only
        K = lim_K + s.implicit_on * (1.0 - kv_only) * kp * free_act
        D = lim_D + s.implicit_on * (kv * (free_act + kv_only * (1.0 - free_act)) + damp
                                     + fl * (1.0 - th * th) / FRICTIONLOSS_VEL)
        s.force[i_b, i_d] = tau - damp * v - spring - fl * th - s.bias[i_b, i_d] + lim_f - h * K * v
        # Genesis's dofs_state.force (get_dofs_force): actuator, damping and spring less the bias; its joint
        # limits and friction loss are constraints, not part of it
        s.dof_qf[i_b, i_d] = tau - damp * v - spring - s.bias[i_b, i_d]
        diag = s.dof_armature[i_b, i_d] + h * D + h * h * K
        if ti.static(s.requires_grad):
            s.mass_mat[i_b, i_d, i_d] += diag
        else:  # see math3d.func_add
            s.mass_mat[i_b, i_d, i_d] = s.mass_mat[i_b, i_d, i_d] + diag

