"""Stages 4-5, passive and actuation forces, assembled with the bias into the generalised force.

Joint limits are Genesis's soft constraint by default (func_limit_constraint: a term on M's diagonal and in
the force, linear in qacc, released by the solve where it would pull: func_limit_release), or, on request,
penalty springs. Diagonal stiffness K and damping D are treated implicitly, (M + h D + h^2 K) qacc = f(q, v) -
h K v: with every integrator, the joint-limit springs (stiff by design); with implicitfast, the joint damping,
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
from .layout import func_take
from .math3d import (func_add2, func_euler_xyz_quat, func_euler_xyz_quat_adjoint, func_quat_log, func_quat_log_adjoint,
                     func_quat_mul, func_quat_mul_adjoint)

CTRL_FORCE, CTRL_POSITION, CTRL_VELOCITY = 0, 1, 2
FRICTIONLOSS_VEL = 1e-2  # m/s or rad/s: velocity scale of the smooth tanh friction loss
# joint-limit models (RigidCore.limits_on): none, the penalty springs (RigidOptions.joint_limit_stiffness /
# joint_limit_damping), Genesis's soft constraint (the default)
LIMITS_OFF, LIMITS_SPRING, LIMITS_CONSTRAINT = 0, 1, 2
LIMIT_MIN_DIAG = 1e-15  # Genesis's floor of the constraint's regulariser invweight (1 - imp) / imp


def limit_gains(timeconst, dampratio, dmax):
    """(k, b) of the limit constraint's reference acceleration aref = -b v - k imp d (MuJoCo's solref as
    Genesis reads it: b = 2 / (dmax timeconst), k = 1 / (dmax^2 timeconst^2 dampratio^2)); numpy arrays."""
    return 1.0 / (dmax * dmax * timeconst * timeconst * dampratio * dampratio), 2.0 / (dmax * timeconst)


@ti.func
def func_limit_constraint(s: ti.template(), i_b, i_d, on, q, v, lo, hi):
    """Genesis's joint limit (v0.4.5 constraint/solver.py add_joint_limit_constraints), a soft constraint
    on the acceleration while the joint is past a limit by d = min(q - lo, hi - q) < 0: with j = +1 at the
    lower limit and -1 at the upper, the constraint force j f with f = D (aref - j qacc), D = imp / ((1 -
    imp) invweight), aref = -b j v - k imp d, imp rising from dmin to dmax over the first `width` of
    penetration (MuJoCo's impedance curve: two power-law pieces meeting at `mid`; the joint's solimp and, from
    its solref, k and b: RigidSolver.limit_constraint_params). Linear in qacc, it joins the solve as D on M's
    diagonal and j D aref in the force (the minimiser of Genesis's constraint cost while the constraint pushes;
    func_limit_release lets go of one that pulls at the solution). Returns (force, diagonal term, j), zero where
    `on` is false."""
    d_lo = q - lo
    d_hi = hi - q
    d = ti.min(d_lo, d_hi)
    active = on and d < 0.0
    j = ti.select(d_lo < d_hi, 1.0, -1.0)
    dmin, dmax, width, mid, power = (s.dof_imp[i_d][0], s.dof_imp[i_d][1], s.dof_imp[i_d][2], s.dof_imp[i_d][3],
                                     s.dof_imp[i_d][4])
    x = ti.min(ti.max(-d, 0.0) / width, 1.0)
    # x^p / mid^(p - 1) below mid, 1 - (1 - x)^p / (1 - mid)^(p - 1) above: one pow, the constant denominators
    # computed at load (four pows and their adjoints were ~40 % of the gradient path's generalised force)
    low = x < mid
    z = ti.pow(ti.select(low, x, 1.0 - x), power)
    y = ti.select(low, z * s.dof_imp[i_d][5], 1.0 - z * s.dof_imp[i_d][6])
    imp = dmin + y * (dmax - dmin)
    aref = -s.dof_lim_b[i_d] * j * v - s.dof_lim_k[i_d] * imp * d
    D = 1.0 / ti.max(s.dof_invweight[i_b, i_d] * (1.0 - imp) / imp, LIMIT_MIN_DIAG)
    return ti.select(active, j * D * aref, 0.0), ti.select(active, D, 0.0), ti.select(active, j, 0.0)


LIMIT_ROUNDS = 8  # solves again after changing the set of limit constraints, at most


@ti.func
def func_limit_release(s: ti.template(), i_b, e):
    """Genesis's limit constraint is one-sided: at the solution qacc[e] of the system with every active limit,
    one whose force j (lim_f - lim_D qacc) pulls (the joint would leave the limit faster than its reference
    acceleration asks) is released: its terms leave M's diagonal and the force (dof_lim_off), as the active
    set of Genesis's (MuJoCo's) Newton solve drops it; and a released one that would push at the solution comes
    back (releasing one limit can drive a coupled joint back into its own). Returns how many it changed; the
    caller solves again (the same final solve) while one is, at most LIMIT_ROUNDS times. Differentiable as the
    system it ends with (func_limit_release_grad)."""
    n = 0
    # with gradients every dof (the active ones have D > 0), without the list of the active ones (the same
    # dofs in the same order)
    for k in range(s.n_dofs if ti.static(s.requires_grad) else s.dof_lim_n[i_b]):
        i_d = k if ti.static(s.requires_grad) else s.dof_lim_list[i_b, k]
        D = s.dof_lim_D[i_b, i_d]
        if D > 0.0:
            off = s.dof_lim_off[i_b, i_d]
            push = s.dof_lim_j[i_b, i_d] * (s.dof_lim_f[i_b, i_d] - D * s.qacc[e, i_b, i_d]) > 0.0
            if (off == 0 and not push) or (off == 1 and push):
                sign = 1.0 - 2.0 * (1 - off)  # -1: released, +1: back
                s.dof_lim_off[i_b, i_d] = 1 - off
                s.mass_mat[i_b, i_d, i_d] = s.mass_mat[i_b, i_d, i_d] + sign * D
                s.force[i_b, i_d] = s.force[i_b, i_d] + sign * s.dof_lim_f[i_b, i_d]
                n += 1
    return n


@ti.func
def func_limit_rounds_next(s: ti.template(), i_b, e, r):
    """After a final solve in the fused step: r + 1 when round r changed the set of limit constraints (solve
    again), else -1 (done; also past LIMIT_ROUNDS, or without limit constraints)."""
    nxt = -1
    if s.limits_on == LIMITS_CONSTRAINT and r < LIMIT_ROUNDS:
        if func_limit_release(s, i_b, e) > 0:
            nxt = r + 1
    return nxt


@ti.func
def func_limit_release_grad(s: ti.template(), i_b, e, y: ti.template()):
    """Adjoint of the releases, right after the final solve's adjoint (y[0, i_b] = A^-1 qacc_bar, which that
    adjoint added to force_bar and, as -y qacc^T, to M_bar): a released limit's terms were subtracted from the
    final system after the dynamics added them, so the final solve's share of their adjoints is taken back
    out (what the earlier solves of a contact scene, made with the limit in, gave them stays)."""
    for i_d in range(s.n_dofs):
        if s.dof_lim_off[i_b, i_d] == 1:
            s.dof_lim_f.grad[i_b, i_d] = s.dof_lim_f.grad[i_b, i_d] - y[0, i_b, i_d]
            s.dof_lim_D.grad[i_b, i_d] = s.dof_lim_D.grad[i_b, i_d] + y[0, i_b, i_d] * s.qacc[e, i_b, i_d]


@ti.func
def func_tanh_where(s: ti.template(), on, x):
    """tanh(x) where `on`, else 0, for the friction loss -fl tanh(v / vel) (`on`: fl != 0): without gradients
    a branch skips the tanh (a libm call per dof and evaluation) where fl is 0, which changes no number. With
    gradients tanh(x) everywhere: at fl = 0 the force's derivative in fl is -tanh(v / vel), not 0 (the select
    form of before gave 0 there, a silent wrong gradient for a friction loss identified from 0)."""
    if ti.static(s.requires_grad):
        return ti.tanh(x)
    else:
        r = ti.cast(0.0, s.dtype)
        if on:
            r = ti.tanh(x)
        return r


@ti.func
def func_free_rot_vec(s: ti.template(), i_b, src, i_l):
    """A free joint's rotational PD error (module docstring): the rotation vector of q_target q^-1, q_target
    from the link's three Euler-angle targets."""
    qs = s.link_q_start[i_l] + 3
    ds = s.link_dof_start[i_l] + 3
    q = ti.Vector([s.qpos[src, i_b, qs + k] for k in ti.static(range(4))])
    qt = func_euler_xyz_quat(s.ctrl_pos[i_b, ds], s.ctrl_pos[i_b, ds + 1], s.ctrl_pos[i_b, ds + 2])
    return func_quat_log(func_quat_mul(qt, ti.Vector([q[0], -q[1], -q[2], -q[3]])))


@ti.func
def func_free_rot_errors(s: ti.template(), i_b, e, src, h):
    """With gradients, the stage before func_generalized_force: each free joint's rotational PD error
    (func_free_rot_vec) into dof_rot_err, once for its three dofs, over the list of free joints
    (core.free_link). The generalised force then reads one number a dof; computing the rotation in its
    select form at every dof, and its adjoint, was half that stage's cost (0.75 of 1.43 ms a step for a
    1,024-env Panda, which has no free joint). Nothing without gradients (a branch there computes it
    only where it is used)."""
    if ti.static(s.requires_grad):
        for t in range(s.n_free_links):
            i_l = s.free_link[t]
            r = func_free_rot_vec(s, i_b, src, i_l)
            for k in ti.static(range(3)):
                s.dof_rot_err[i_b, s.link_dof_start[i_l] + 3 + k] = r[k]


@ti.func
def func_pd_error(s: ti.template(), i_b, src, i_l, i_d, j, free_rot, pos_on, lin_err):
    """The PD position error of dof i_d of link i_l: lin_err (target - coordinate), or for a free joint's
    rotational dof (free_rot, j its index among the three) the rotation error's component. Without gradients a
    branch computes the rotation only for such dofs under position control; with gradients the stage before
    computed it (func_free_rot_errors)."""
    if ti.static(s.requires_grad):
        return ti.select(free_rot, s.dof_rot_err[i_b, i_d], lin_err)
    else:
        err = lin_err
        if free_rot and pos_on:
            r = func_free_rot_vec(s, i_b, src, i_l)
            err = ti.select(j == 0, r[0], ti.select(j == 1, r[1], r[2]))
        return err


@ti.func
def func_dof_inputs(s: ti.template(), i_b, src, i_d):
    """What func_generalized_force (and its adjoint) reads of dof i_d: its velocity v, its coordinate's index i_q,
    has_q (0/1) and the coordinate q (0 without one), its link i_l and index k in the link's joint, free_rot (a
    free joint's rotational dof), the index i_lin and value q_lin of what its PD compares with the target, and its
    control mode (and 0/1 masks of it). A free joint's dofs have no coordinate of their own (dof_q -1): the
    translational ones are compared with the base position, the rotational ones with func_free_rot_vec."""
    i_q = s.dof_q[i_d]
    has_q = ti.cast(i_q >= 0, s.dtype)
    q = s.qpos[src, i_b, ti.max(i_q, 0)] * has_q
    i_l = s.dof_link[i_d]
    k = i_d - s.link_dof_start[i_l]
    is_free = s.link_jtype[i_l] == JOINT_FREE
    i_lin = ti.min(s.link_q_start[i_l] + k, s.qpos_len - 1)
    mode = s.ctrl_mode[i_b, i_d]
    pos_mode = ti.cast(mode == CTRL_POSITION, s.dtype)
    vel_mode = ti.cast(mode == CTRL_VELOCITY, s.dtype)
    return (s.qvel[src, i_b, i_d], i_q, has_q, q, i_l, k, is_free and k >= 3, i_lin,
            ti.select(is_free and k < 3, s.qpos[src, i_b, i_lin], q), mode, pos_mode, vel_mode,
            1.0 - pos_mode - vel_mode)


@ti.func
def func_generalized_force(s: ti.template(), i_b, e, src, h):
    """force = actuation + passive + joint limits - bias; adds the implicit terms to M's diagonal.
    h is the (sub)step length. Single-assignment form (see kinematics.py)."""
    if ti.static(not s.requires_grad):
        s.dof_lim_n[i_b] = 0
    for i_d in range(s.n_dofs):
        v, i_q, has_q, q, i_l, k, free_rot, i_lin, q_lin, mode, pos_mode, vel_mode, force_mode = func_dof_inputs(
            s, i_b, src, i_d)
        kp = s.dof_kp[i_b, i_d] * pos_mode
        kv = s.dof_kv[i_b, i_d] * (pos_mode + vel_mode)
        err = func_pd_error(s, i_b, src, i_l, i_d, k - 3, free_rot, mode == CTRL_POSITION, s.ctrl_pos[i_b, i_d] - q_lin)
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
        springs = s.limits_on == LIMITS_SPRING
        below = springs and i_q >= 0 and q < lim_lo
        above = springs and i_q >= 0 and q > lim_hi
        lim_f = ti.select(below, s.limit_k * (lim_lo - q) - s.limit_d * ti.min(v, 0.0),
                          ti.select(above, s.limit_k * (lim_hi - q) - s.limit_d * ti.max(v, 0.0), 0.0))
        lim_K = ti.select(below or above, s.limit_k, 0.0)
        lim_D = ti.select((below and v < 0) or (above and v > 0), s.limit_d, 0.0)
        con_on = s.limits_on == LIMITS_CONSTRAINT and i_q >= 0
        con_f = 0.0
        con_D = 0.0
        if ti.static(s.requires_grad):
            con_f, con_D, con_j = func_limit_constraint(s, i_b, i_d, con_on, q, v, lim_lo, lim_hi)
            s.dof_lim_D[i_b, i_d] = con_D
            s.dof_lim_f[i_b, i_d] = con_f
            s.dof_lim_j[i_b, i_d] = con_j
            s.dof_lim_off[i_b, i_d] = 0
        elif con_on and (q < lim_lo or q > lim_hi):
            # without gradients only a joint past a limit computes its constraint, and is listed for the
            # release (func_limit_release); nothing is stored for the others
            con_f, con_D, con_j = func_limit_constraint(s, i_b, i_d, con_on, q, v, lim_lo, lim_hi)
            k = s.dof_lim_n[i_b]
            s.dof_lim_list[i_b, k] = i_d
            s.dof_lim_n[i_b] = k + 1
            s.dof_lim_D[i_b, i_d] = con_D
            s.dof_lim_f[i_b, i_d] = con_f
            s.dof_lim_j[i_b, i_d] = con_j
            s.dof_lim_off[i_b, i_d] = 0
        # stiffness/damping treated implicitly: PD and passive terms with the implicit integrators only,
        # joint-limit springs always (they are constraints, stiff by design). approximate_implicitfast
        # (Genesis's): kv whether or not the actuator is saturated, kp never
        kv_only = s.implicit_kv_only
        K = lim_K + s.implicit_on * (1.0 - kv_only) * kp * free_act
        D = lim_D + s.implicit_on * (kv * (free_act + kv_only * (1.0 - free_act)) + damp
                                     + fl * (1.0 - th * th) / FRICTIONLOSS_VEL)
        s.force[i_b, i_d] = tau - damp * v - spring - fl * th - s.bias[i_b, i_d] + lim_f + con_f - h * K * v
        # Genesis's dofs_state.force (get_dofs_force): actuator, damping and spring less the bias; its joint
        # limits and friction loss are constraints, not part of it
        s.dof_qf[i_b, i_d] = tau - damp * v - spring - s.bias[i_b, i_d]
        diag = s.dof_armature[i_b, i_d] + h * D + h * h * K + con_D
        func_add2(s, s.mass_mat, i_b, i_d, i_d, diag)



@ti.func
def func_limit_constraint_adjoint(s: ti.template(), i_b, i_d, q, v, lo, hi, gf, gD):
    """The adjoint of func_limit_constraint for an active constraint (its results' adjoints gf, gD; j has none):
    (q's, v's), the inverse weight's added to its field; differentiated as written (a clamp passes the adjoint
    where its argument is the one kept, as Taichi's max and min do)."""
    d_lo = q - lo
    d_hi = hi - q
    d = ti.min(d_lo, d_hi)
    j = ti.select(d_lo < d_hi, 1.0, -1.0)
    dmin, dmax, width, mid, power = (s.dof_imp[i_d][0], s.dof_imp[i_d][1], s.dof_imp[i_d][2], s.dof_imp[i_d][3],
                                     s.dof_imp[i_d][4])
    xr = ti.max(-d, 0.0) / width
    x = ti.min(xr, 1.0)
    low = x < mid
    wz = ti.select(low, x, 1.0 - x)
    z = ti.pow(wz, power)
    y = ti.select(low, z * s.dof_imp[i_d][5], 1.0 - z * s.dof_imp[i_d][6])
    imp = dmin + y * (dmax - dmin)
    b, k = s.dof_lim_b[i_d], s.dof_lim_k[i_d]
    aref = -b * j * v - k * imp * d
    invw = s.dof_invweight[i_b, i_d]
    u = invw * (1.0 - imp) / imp
    um = ti.max(u, LIMIT_MIN_DIAG)
    D = 1.0 / um
    # f = j D aref
    garef = gf * j * D
    gDt = gf * j * aref + gD
    gu = ti.select(u >= LIMIT_MIN_DIAG, -gDt / (um * um), 0.0)
    s.dof_invweight.grad[i_b, i_d] = s.dof_invweight.grad[i_b, i_d] + gu * (1.0 - imp) / imp
    gimp = gu * (-invw / (imp * imp)) - garef * k * d
    gv = -garef * b * j
    gd = -garef * k * imp
    gy = gimp * (dmax - dmin)
    gz = ti.select(low, gy * s.dof_imp[i_d][5], -gy * s.dof_imp[i_d][6])
    gwz = gz * power * ti.pow(wz, power - 1.0)
    gx = ti.select(low, gwz, -gwz)
    gd -= ti.select(xr <= 1.0 and -d >= 0.0, gx / width, 0.0)
    gq = ti.select(d_lo <= d_hi, gd, -gd)
    return gq, gv


@ti.func
def func_generalized_force_adjoint(s: ti.template(), i_b, src, h):
    """The adjoint of func_generalized_force then of func_free_rot_errors (grad path), written out
    (solver.HAND_ADJOINTS), plain adds: per dof, the force's and the limit constraint's stored adjoints read and
    zeroed (as Taichi's store adjoints do), M's diagonal adjoint read (its term is added, not stored: the mass
    matrix's store adjoint zeroes it later), differentiated as written; then each free joint's rotation error."""
    for i_d in range(s.n_dofs):
        gF = func_take(s.force, i_b, i_d)
        gLf = func_take(s.dof_lim_f, i_b, i_d)
        gLD = func_take(s.dof_lim_D, i_b, i_d)
        gM = s.mass_mat.grad[i_b, i_d, i_d]
        v, i_q, has_q, q, i_l, k, free_rot, i_lin, q_lin, mode, pos_mode, vel_mode, force_mode = func_dof_inputs(
            s, i_b, src, i_d)
        free_lin = s.link_jtype[i_l] == JOINT_FREE and k < 3
        kp = s.dof_kp[i_b, i_d] * pos_mode
        kv = s.dof_kv[i_b, i_d] * (pos_mode + vel_mode)
        err = ti.select(free_rot, s.dof_rot_err[i_b, i_d], s.ctrl_pos[i_b, i_d] - q_lin)
        raw = force_mode * s.ctrl_force[i_b, i_d] + kp * err + kv * (s.ctrl_vel[i_b, i_d] - v)
        lo = s.dof_force_lo[i_b, i_d]
        hi = s.dof_force_hi[i_b, i_d]
        free_act = ti.cast(raw >= lo and raw <= hi, s.dtype)
        fl = s.dof_frictionloss[i_b, i_d]
        th = ti.tanh(v / FRICTIONLOSS_VEL)
        damp = s.dof_damping[i_b, i_d]
        stiff = s.dof_stiffness[i_b, i_d]
        lim_lo = s.dof_limit_lo[i_d]
        lim_hi = s.dof_limit_hi[i_d]
        springs = s.limits_on == LIMITS_SPRING
        below = springs and i_q >= 0 and q < lim_lo
        above = springs and i_q >= 0 and q > lim_hi
        lim_K = ti.select(below or above, s.limit_k, 0.0)
        ion = s.implicit_on
        kvo = s.implicit_kv_only
        K = lim_K + ion * (1.0 - kvo) * kp * free_act
        # force = tau - damp v - spring - fl th - bias + lim_f + con_f - h K v; M_ii += arm + h D + h^2 K + con_D
        gK = -gF * h * v + gM * h * h
        gD = gM * h
        gv = gF * (-damp - h * K)
        gq = -gF * has_q * stiff
        g_damp = -gF * v + gD * ion
        g_fl = -gF * th + gD * ion * (1.0 - th * th) / FRICTIONLOSS_VEL
        gth = -gF * fl + gD * ion * fl * (-2.0 * th) / FRICTIONLOSS_VEL
        gv += gth * (1.0 - th * th) / FRICTIONLOSS_VEL
        s.dof_stiffness.grad[i_b, i_d] = s.dof_stiffness.grad[i_b, i_d] - gF * has_q * (q - s.dof_springref[i_d])
        s.dof_armature.grad[i_b, i_d] = s.dof_armature.grad[i_b, i_d] + gM
        s.bias.grad[i_b, i_d] = s.bias.grad[i_b, i_d] - gF
        if below:
            gq -= gF * s.limit_k
            gv -= ti.select(v <= 0.0, gF * s.limit_d, 0.0)
        if above:
            gq -= gF * s.limit_k
            gv -= ti.select(v >= 0.0, gF * s.limit_d, 0.0)
        # the PD: K's kp (implicit) and D's kv
        g_kp = gK * ion * (1.0 - kvo) * free_act
        g_kv = gD * ion * (free_act + kvo * (1.0 - free_act))
        # tau = clamp(raw, lo, hi)
        graw = gF * free_act
        s.ctrl_force.grad[i_b, i_d] = s.ctrl_force.grad[i_b, i_d] + graw * force_mode
        s.ctrl_vel.grad[i_b, i_d] = s.ctrl_vel.grad[i_b, i_d] + graw * kv
        gerr = graw * kp
        g_kp += graw * err
        g_kv += graw * (s.ctrl_vel[i_b, i_d] - v)
        gv -= graw * kv
        s.dof_kp.grad[i_b, i_d] = s.dof_kp.grad[i_b, i_d] + g_kp * pos_mode
        s.dof_kv.grad[i_b, i_d] = s.dof_kv.grad[i_b, i_d] + g_kv * (pos_mode + vel_mode)
        s.dof_damping.grad[i_b, i_d] = s.dof_damping.grad[i_b, i_d] + g_damp
        s.dof_frictionloss.grad[i_b, i_d] = s.dof_frictionloss.grad[i_b, i_d] + g_fl
        if free_rot:
            s.dof_rot_err.grad[i_b, i_d] = s.dof_rot_err.grad[i_b, i_d] + gerr
        else:
            s.ctrl_pos.grad[i_b, i_d] = s.ctrl_pos.grad[i_b, i_d] + gerr
            if free_lin:
                s.qpos.grad[src, i_b, i_lin] = s.qpos.grad[src, i_b, i_lin] - gerr
            else:
                gq -= gerr
        # the limit constraint, where active
        con_on = s.limits_on == LIMITS_CONSTRAINT and i_q >= 0
        if con_on and ti.min(q - lim_lo, lim_hi - q) < 0.0:
            cq, cv = func_limit_constraint_adjoint(s, i_b, i_d, q, v, lim_lo, lim_hi, gF + gLf, gM + gLD)
            gq += cq
            gv += cv
        s.qvel.grad[src, i_b, i_d] = s.qvel.grad[src, i_b, i_d] + gv
        if i_q >= 0:
            s.qpos.grad[src, i_b, i_q] = s.qpos.grad[src, i_b, i_q] + gq
    for t in range(s.n_free_links):
        i_l = s.free_link[t]
        qs = s.link_q_start[i_l] + 3
        ds = s.link_dof_start[i_l] + 3
        gr = ti.Vector([func_take(s.dof_rot_err, i_b, ds + k) for k in ti.static(range(3))])
        q = ti.Vector([s.qpos[src, i_b, qs + k] for k in ti.static(range(4))])
        a, b, c = s.ctrl_pos[i_b, ds], s.ctrl_pos[i_b, ds + 1], s.ctrl_pos[i_b, ds + 2]
        qt = func_euler_xyz_quat(a, b, c)
        qc = ti.Vector([q[0], -q[1], -q[2], -q[3]])
        gqt, gqc = func_quat_mul_adjoint(qt, qc, func_quat_log_adjoint(func_quat_mul(qt, qc), gr))
        ga, gb, gc = func_euler_xyz_quat_adjoint(a, b, c, gqt)
        s.ctrl_pos.grad[i_b, ds] = s.ctrl_pos.grad[i_b, ds] + ga
        s.ctrl_pos.grad[i_b, ds + 1] = s.ctrl_pos.grad[i_b, ds + 1] + gb
        s.ctrl_pos.grad[i_b, ds + 2] = s.ctrl_pos.grad[i_b, ds + 2] + gc
        s.qpos.grad[src, i_b, qs] = s.qpos.grad[src, i_b, qs] + gqc[0]
        for k in ti.static(range(1, 4)):
            s.qpos.grad[src, i_b, qs + k] = s.qpos.grad[src, i_b, qs + k] - gqc[k]
