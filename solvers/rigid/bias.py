"""Stage 3, bias forces: Coriolis, centrifugal and gravity by recursive Newton-Euler (qacc = 0).

With the implicit integrators (implicitfast, approximate_implicitfast) a free body's gyroscopic moment
w x (I_c w) is taken implicitly (func_gyro_implicit), as MuJoCo's implicit integrators do for a free body:
explicit, it feeds the body's tumbling energy step after step once h |w| is a few tenths (a 1.2 m plank
thrown tumbling at 40 rad/s went to NaN within 0.7 s at dt = 10 ms, in flight, as it does in MuJoCo's
Euler; MuJoCo's implicitfast keeps it, but damps the tumbling; tests/test_integrators.py)."""
import taichi as ti

from .kinematics import (JOINT_FREE, func_add_vec3, func_free_twist, func_hinge_rate, func_link_joint_velocity,
                         func_parent_slot)
from .layout import func_take
from .math3d import (func_add, func_cross_force, func_inertia_mul, func_inertia_mul_adjoint, func_mm, func_mtv, func_mv,
                     func_skew)

# a link lighter than this (kg) gets no implicit gyroscopic moment (func_gyro_implicit: its centre of mass
# is mc / m)
GYRO_MIN_MASS = 1e-9


@ti.func
def func_gyro_implicit(s: ti.template(), on, m, mc, J, w, h):
    """The change that takes a free body's gyroscopic moment g = w x (I_c w) implicitly over a step h: one
    Newton step of I_c (w' - w) / h = -w_t x (I_c w_t), w_t = w + theta (w' - w), gives w' = w - h (I_c +
    theta h K)^-1 g, K = [w]x I_c - [I_c w]x the derivative of g, so the moment that gives it explicitly is
    g* = I_c (I_c + theta h K)^-1 g. theta = 1 is Bullet's implicit gyroscopic body and MuJoCo's implicit
    integrators' step for a free body alone: stable, but it damps a tumbling body (a plank at 40 rad/s and
    dt = 10 ms lost 97 % of its tumbling energy in 1 s); theta = 1/2, the implicit midpoint's, keeps it (to
    1 % over 5 s while h |w| <= 1 rad) and is more accurate (tests/test_integrators.py).
    Returns g* - g, a pure moment (m, mc = m c, J about the origin: the link's spatial inertia, world
    frame). It keeps M symmetric (the correction is a force, not a term of the system matrix). on: 1, or 0
    for a link it does not apply to (then exactly 0, computed on the identity: finite for a massless link)."""
    c = mc / ti.max(m, GYRO_MIN_MASS)
    E = ti.Matrix.identity(s.dtype, 3)
    Ic = on * (J - m * (c.dot(c) * E - c.outer_product(c))) + (1.0 - on) * E
    ws = on * w
    # (func_mm / func_mv, not `@`: math3d.func_rotate_inertia on the adjoint's compile time)
    L = func_mv(Ic, ws)
    g = ws.cross(L)
    # theta 1/2 (the implicit midpoint's linearisation: second order, the tumbling's energy kept to 1 %
    # over 5 s up to h |w| = 1) rising smoothly to 1 (implicit Euler: damped, stable at any spin) from
    # h |w| = 1 to 2 (in h^2 |w|^2, so that the adjoint stays finite at w = 0)
    x = ti.min(ti.max((h * h * ws.dot(ws) - 1.0) / 3.0, 0.0), 1.0)
    theta = 0.5 + 0.5 * x * x * (3.0 - 2.0 * x)
    A = Ic + (theta * h) * (func_mm(func_skew(ws), Ic) - func_skew(L))
    return func_mv(Ic, func_mv(A.inverse(), g)) - g


@ti.func
def func_link_forces(s: ti.template(), i_b, e, src, h):
    """Link accelerations with qacc = 0 (gravity as an upward world acceleration) and the forces they
    need. A free joint contributes sum_k cdofd_k qd_k = (0, vb x wb). With gradients a branch on the joint:
    a free joint's link is a root (model.py) and reads its six velocities, the others one (blended, the free
    joint's reads and cross product were differentiated at every link: see kinematics.func_free_pose)."""
    zero = ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)
    for i_l in range(s.n_links):
        p = s.link_parent[i_l]
        has_p = p >= 0
        pp = func_parent_slot(s, p)
        if ti.static(s.requires_grad):
            if s.link_jtype[i_l] == JOINT_FREE:
                vb, wb = func_free_twist(s, i_b, src, s.link_dof_start[i_l])
                func_link_force(s, i_b, i_l, zero, vb.cross(wb) - s.gravity[i_b], 1.0, h)
            else:
                d0, qd = func_hinge_rate(s, i_b, src, i_l)
                aw = ti.select(has_p, s.cacc_w[i_b, pp], zero) + s.cdofd_w[i_b, d0] * qd
                av = ti.select(has_p, s.cacc_v[i_b, pp], -s.gravity[i_b]) + s.cdofd_v[i_b, d0] * qd
                func_link_force(s, i_b, i_l, aw, av, 0.0, h)
        else:
            d0, qd, free, vb, wb = func_link_joint_velocity(s, i_b, src, i_l)
            aw = ti.select(has_p, s.cacc_w[i_b, pp], zero) + s.cdofd_w[i_b, d0] * qd
            av = ti.select(has_p, s.cacc_v[i_b, pp], -s.gravity[i_b]) + s.cdofd_v[i_b, d0] * qd + free * vb.cross(wb)
            func_link_force(s, i_b, i_l, aw, av, free, h)


@ti.func
def func_link_force(s: ti.template(), i_b, i_l, aw, av, free, h):
    """Link i_l's acceleration (aw, av) stored and the force it needs with the velocity's (free: 1 for a free
    joint's link)."""
    s.cacc_w[i_b, i_l] = aw
    s.cacc_v[i_b, i_l] = av
    m, mc, J = s.link_mass[i_b, i_l], s.link_h[i_b, i_l], s.link_J[i_b, i_l]
    n, f = func_inertia_mul(m, mc, J, aw, av)
    wv, vv = s.cvel_w[i_b, i_l], s.cvel_v[i_b, i_l]
    hn, hf = func_inertia_mul(m, mc, J, wv, vv)
    cn, cf = func_cross_force(wv, vv, hn, hf)
    if ti.static(s.requires_grad):
        # the free bodies' gyroscopic moments: the next stage (func_free_gyro)
        s.cfrc_n[i_b, i_l] = n + cn
    else:
        # a free body's gyroscopic moment implicit with the implicit integrators (module docstring)
        on = free * s.implicit_on * ti.cast(m > GYRO_MIN_MASS, s.dtype)
        gy = ti.Vector.zero(s.dtype, 3)
        if on > 0.0:
            gy = func_gyro_implicit(s, on, m, mc, J, wv, h)
        s.cfrc_n[i_b, i_l] = n + cn + gy
    s.cfrc_f[i_b, i_l] = f + cf


@ti.func
def func_free_gyro(s: ti.template(), i_b, e, src, h):
    """With gradients, the stage after func_link_forces: each free body's implicit gyroscopic moment (module
    docstring) added to its link force, over the list of free joints (core.free_link); the same sum
    (n + cn) + g as the branch without gradients. Computed in the select form at every link in
    func_link_forces (0 where off, a 3x3 inverse a link), that stage's adjoint took 2.3-4.5 ms against 0.8-1.9
    without it for a 1,024-env Panda, which has no free joint (results/grad.md). Nothing without gradients."""
    if ti.static(s.requires_grad):
        for t in range(s.n_free_links):
            i_l = s.free_link[t]
            m, mc, J = s.link_mass[i_b, i_l], s.link_h[i_b, i_l], s.link_J[i_b, i_l]
            on = s.implicit_on * ti.cast(m > GYRO_MIN_MASS, s.dtype)
            func_add(s, s.cfrc_n, i_b, i_l, func_gyro_implicit(s, on, m, mc, J, s.cvel_w[i_b, i_l], h))


@ti.func
def func_accumulate_forces(s: ti.template(), i_b, e, src, h):
    for k in range(s.n_links):
        i_l = s.n_links - 1 - k
        p = s.link_parent[i_l]
        if p >= 0:
            func_add(s, s.cfrc_n, i_b, p, s.cfrc_n[i_b, i_l])
            func_add(s, s.cfrc_f, i_b, p, s.cfrc_f[i_b, i_l])


@ti.func
def func_project_forces(s: ti.template(), i_b, e, src, h):
    for i_d in range(s.n_dofs):
        i_l = s.dof_link[i_d]
        s.bias[i_b, i_d] = s.cdof_w[i_b, i_d].dot(s.cfrc_n[i_b, i_l]) + s.cdof_v[i_b, i_d].dot(s.cfrc_f[i_b, i_l])


@ti.func
def func_skew_adjoint(G):
    """The adjoint of func_skew(p) for its adjoint G: p's."""
    return ti.Vector([G[2, 1] - G[1, 2], G[0, 2] - G[2, 0], G[1, 0] - G[0, 1]])


@ti.func
def func_gyro_implicit_adjoint(s: ti.template(), on, m, mc, J, w, h, gy):
    """The adjoint of func_gyro_implicit(s, on, m, mc, J, w, h) for its result's adjoint gy: (m's, mc's, J's, w's),
    differentiated as written (theta's smooth step has a zero slope where its clamps switch)."""
    mm = ti.max(m, GYRO_MIN_MASS)
    c = mc / mm
    E = ti.Matrix.identity(s.dtype, 3)
    K = c.dot(c) * E - c.outer_product(c)
    Ic = on * (J - m * K) + (1.0 - on) * E
    ws = on * w
    L = func_mv(Ic, ws)
    g = ws.cross(L)
    raw = (h * h * ws.dot(ws) - 1.0) / 3.0
    x = ti.min(ti.max(raw, 0.0), 1.0)
    theta = 0.5 + 0.5 * x * x * (3.0 - 2.0 * x)
    S = func_skew(ws)
    B = func_mm(S, Ic) - func_skew(L)
    A = Ic + (theta * h) * B
    Ai = A.inverse()
    z = func_mv(Ai, g)
    # y = Ic z - g, z = A^-1 g
    gIc = gy.outer_product(z)
    gz = func_mtv(Ic, gy)
    ag = func_mtv(Ai, gz)
    gg = ag - gy
    gA = -ag.outer_product(z)
    # A = Ic + theta h (S Ic - [L]x)
    th = theta * h
    gIc += gA + th * (S.transpose() @ gA)
    gws = func_skew_adjoint(th * (gA @ Ic.transpose()))
    gL = -th * func_skew_adjoint(gA)
    gtheta = h * (gA * B).sum()
    inside = ti.cast(raw > 0.0 and raw < 1.0, s.dtype)
    gws += (gtheta * 3.0 * x * (1.0 - x) * inside * h * h * 2.0 / 3.0) * ws
    # g = ws x L, L = Ic ws
    gws += L.cross(gg)
    gL += gg.cross(ws)
    gIc += gL.outer_product(ws)
    gws += func_mtv(Ic, gL)
    # Ic = on (J - m K) + (1 - on) E, K = c.c E - c c^T, c = mc / max(m, min)
    gJ = on * gIc
    trI = gIc[0, 0] + gIc[1, 1] + gIc[2, 2]
    gc = -on * m * (2.0 * trI * c - (gIc @ c + gIc.transpose() @ c))
    gm = -on * (gIc * K).sum() - ti.cast(m > GYRO_MIN_MASS, s.dtype) * gc.dot(mc) / (mm * mm)
    return gm, gc / mm, gJ, on * gws


@ti.func
def func_bias_adjoint(s: ti.template(), i_b, src, h, forces, accumulate, project):
    """The adjoint of the BIAS stages, written out (solver.HAND_ADJOINTS), last first: of func_project_forces
    (`project`), of func_accumulate_forces (`accumulate`; each link's force adjoint gets its parent's, parents
    first) and of func_link_forces and func_free_gyro (`forces`; the links children first), each store's adjoint
    reading and zeroing the stored field's (as Taichi's do), grad-path branches, differentiated as written, plain
    adds."""
    if project:
        for i_d in range(s.n_dofs):
            i_l = s.dof_link[i_d]
            g = func_take(s.bias, i_b, i_d)
            s.cdof_w.grad[i_b, i_d] = s.cdof_w.grad[i_b, i_d] + g * s.cfrc_n[i_b, i_l]
            s.cdof_v.grad[i_b, i_d] = s.cdof_v.grad[i_b, i_d] + g * s.cfrc_f[i_b, i_l]
            s.cfrc_n.grad[i_b, i_l] = s.cfrc_n.grad[i_b, i_l] + g * s.cdof_w[i_b, i_d]
            s.cfrc_f.grad[i_b, i_l] = s.cfrc_f.grad[i_b, i_l] + g * s.cdof_v[i_b, i_d]
    if accumulate:
        for i_l in range(s.n_links):
            p = s.link_parent[i_l]
            if p >= 0:
                s.cfrc_n.grad[i_b, i_l] = s.cfrc_n.grad[i_b, i_l] + s.cfrc_n.grad[i_b, p]
                s.cfrc_f.grad[i_b, i_l] = s.cfrc_f.grad[i_b, i_l] + s.cfrc_f.grad[i_b, p]
    if forces:
        for t in range(s.n_free_links):
            i_l = s.free_link[t]
            m, mc, J = s.link_mass[i_b, i_l], s.link_h[i_b, i_l], s.link_J[i_b, i_l]
            on = s.implicit_on * ti.cast(m > GYRO_MIN_MASS, s.dtype)
            gm, gmc, gJ, gw = func_gyro_implicit_adjoint(s, on, m, mc, J, s.cvel_w[i_b, i_l], h, s.cfrc_n.grad[i_b, i_l])
            s.link_mass.grad[i_b, i_l] = s.link_mass.grad[i_b, i_l] + gm
            s.link_h.grad[i_b, i_l] = s.link_h.grad[i_b, i_l] + gmc
            s.link_J.grad[i_b, i_l] = s.link_J.grad[i_b, i_l] + gJ
            s.cvel_w.grad[i_b, i_l] = s.cvel_w.grad[i_b, i_l] + gw
        for k in range(s.n_links):
            i_l = s.n_links - 1 - k
            gN = func_take(s.cfrc_n, i_b, i_l)
            gF = func_take(s.cfrc_f, i_b, i_l)
            m, hh, J = s.link_mass[i_b, i_l], s.link_h[i_b, i_l], s.link_J[i_b, i_l]
            aw, av = s.cacc_w[i_b, i_l], s.cacc_v[i_b, i_l]
            wv, vv = s.cvel_w[i_b, i_l], s.cvel_v[i_b, i_l]
            hn, hf = func_inertia_mul(m, hh, J, wv, vv)
            # cfrc = I a + v x* (I v)
            gm, gh, gJ, gaw, gav = func_inertia_mul_adjoint(m, hh, J, aw, av, gN, gF)
            gwv = hn.cross(gN) + hf.cross(gF)
            gvv = hf.cross(gN)
            ghn = gN.cross(wv)
            ghf = gN.cross(vv) + gF.cross(wv)
            gm2, gh2, gJ2, gwv2, gvv2 = func_inertia_mul_adjoint(m, hh, J, wv, vv, ghn, ghf)
            s.link_mass.grad[i_b, i_l] = s.link_mass.grad[i_b, i_l] + gm + gm2
            s.link_h.grad[i_b, i_l] = s.link_h.grad[i_b, i_l] + gh + gh2
            s.link_J.grad[i_b, i_l] = s.link_J.grad[i_b, i_l] + gJ + gJ2
            s.cvel_w.grad[i_b, i_l] = s.cvel_w.grad[i_b, i_l] + gwv + gwv2
            s.cvel_v.grad[i_b, i_l] = s.cvel_v.grad[i_b, i_l] + gvv + gvv2
            gaw += func_take(s.cacc_w, i_b, i_l)
            gav += func_take(s.cacc_v, i_b, i_l)
            d0 = s.link_dof_start[i_l]
            if s.link_jtype[i_l] == JOINT_FREE:
                # av = vb x wb - gravity
                vb, wb = func_free_twist(s, i_b, src, d0)
                func_add_vec3(s.qvel.grad, src, i_b, d0, wb.cross(gav))
                func_add_vec3(s.qvel.grad, src, i_b, d0 + 3, gav.cross(vb))
                s.gravity.grad[i_b] = s.gravity.grad[i_b] - gav
            else:
                p = s.link_parent[i_l]
                if p >= 0:
                    s.cacc_w.grad[i_b, p] = s.cacc_w.grad[i_b, p] + gaw
                    s.cacc_v.grad[i_b, p] = s.cacc_v.grad[i_b, p] + gav
                else:
                    s.gravity.grad[i_b] = s.gravity.grad[i_b] - gav
                if s.link_ndof[i_l] == 1:
                    qd = s.qvel[src, i_b, d0]
                    s.cdofd_w.grad[i_b, d0] = s.cdofd_w.grad[i_b, d0] + gaw * qd
                    s.cdofd_v.grad[i_b, d0] = s.cdofd_v.grad[i_b, d0] + gav * qd
                    s.qvel.grad[src, i_b, d0] = (s.qvel.grad[src, i_b, d0] + gaw.dot(s.cdofd_w[i_b, d0])
                                                 + gav.dot(s.cdofd_v[i_b, d0]))


BIAS = (func_link_forces, func_free_gyro, func_accumulate_forces, func_project_forces)
