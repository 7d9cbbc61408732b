"""Small rotation and spatial-algebra helpers shared by the rigid stages (Taichi functions).

Spatial vectors are pairs of 3-vectors expressed in the world frame about a point fixed in space over
an evaluation, each kinematic tree's root link's origin (kinematics.func_link_origin): motion (w, v) and
force (n, f), as in MuJoCo's com-based formulation (MuJoCo takes the tree's centre of mass).
"""
import taichi as ti

from .. import taichi_compat


def div_floor() -> float:
    """Floor of a denominator that may be exactly 0 (parallel edges, a slot without load): 1e-30 in float64; in
    float32 1e-15, whose square (in the adjoint of a division, -num / den^2) is still a normal float32. With 1e-30
    it underflows to 0 and the adjoint becomes 0 / 0 or 0 * inf = NaN, even where a select discards the branch
    (a box sliding onto a plane in float32, gs.init's default: a NaN gradient from its first step). Read at
    compile time: ti.static(div_floor())."""
    return 1e-30 if taichi_compat.config().default_fp == ti.f64 else 1e-15


@ti.func
def func_quat_mul(a, b):
    return ti.Vector([
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ])


@ti.func
def func_quat_to_R(q):
    w, x, y, z = q[0], q[1], q[2], q[3]
    return ti.Matrix([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


@ti.func
def func_quat_rotate(q, v):
    """v rotated by the unit quaternion q (= func_quat_to_R(q) @ v, without forming R)."""
    u = ti.Vector([q[1], q[2], q[3]])
    t = 2.0 * u.cross(v)
    return v + q[0] * t + u.cross(t)


@ti.func
def func_quat_mul_adjoint(a, b, g):
    """The adjoint of func_quat_mul(a, b) for the product's adjoint g: (a's, b's). The product is bilinear, r =
    L(a) b = R(b) a, so a gets R(b)^T g and b gets L(a)^T g."""
    ga = ti.Vector([g[0] * b[0] + g[1] * b[1] + g[2] * b[2] + g[3] * b[3],
                    -g[0] * b[1] + g[1] * b[0] - g[2] * b[3] + g[3] * b[2],
                    -g[0] * b[2] + g[1] * b[3] + g[2] * b[0] - g[3] * b[1],
                    -g[0] * b[3] - g[1] * b[2] + g[2] * b[1] + g[3] * b[0]])
    gb = ti.Vector([g[0] * a[0] + g[1] * a[1] + g[2] * a[2] + g[3] * a[3],
                    -g[0] * a[1] + g[1] * a[0] + g[2] * a[3] - g[3] * a[2],
                    -g[0] * a[2] - g[1] * a[3] + g[2] * a[0] + g[3] * a[1],
                    -g[0] * a[3] + g[1] * a[2] - g[2] * a[1] + g[3] * a[0]])
    return ga, gb


@ti.func
def func_quat_to_R_adjoint(q, G):
    """The adjoint of func_quat_to_R(q) for R's adjoint G: q's (differentiated as written, not on the unit sphere)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return 2.0 * ti.Vector([
        -G[0, 1] * z + G[0, 2] * y + G[1, 0] * z - G[1, 2] * x - G[2, 0] * y + G[2, 1] * x,
        G[0, 1] * y + G[0, 2] * z + G[1, 0] * y - 2.0 * G[1, 1] * x - G[1, 2] * w + G[2, 0] * z + G[2, 1] * w
        - 2.0 * G[2, 2] * x,
        -2.0 * G[0, 0] * y + G[0, 1] * x + G[0, 2] * w + G[1, 0] * x + G[1, 2] * z - G[2, 0] * w + G[2, 1] * z
        - 2.0 * G[2, 2] * y,
        -2.0 * G[0, 0] * z - G[0, 1] * w + G[0, 2] * x + G[1, 0] * w - 2.0 * G[1, 1] * z + G[1, 2] * y + G[2, 0] * x
        + G[2, 1] * y])


@ti.func
def func_quat_rotate_adjoint(q, v, g):
    """The adjoint of func_quat_rotate(q, v) = v + q0 t + u x t (t = 2 u x v, u = q's vector part) for the
    result's adjoint g: (q's, v's), differentiated as written."""
    u = ti.Vector([q[1], q[2], q[3]])
    t = 2.0 * u.cross(v)
    gt = q[0] * g + g.cross(u)
    gu = t.cross(g) + 2.0 * v.cross(gt)
    return ti.Vector([g.dot(t), gu[0], gu[1], gu[2]]), g + 2.0 * gt.cross(u)


@ti.func
def func_axis_angle_quat(axis, angle):
    h = 0.5 * angle
    s = ti.sin(h)
    return ti.Vector([ti.cos(h), axis[0] * s, axis[1] * s, axis[2] * s])


@ti.func
def func_rotvec_quat(w, dt):
    """Quaternion of the rotation by angular velocity w over dt (exp map), smooth at w = 0: below a
    tiny half angle the Taylor series in h^2 is used, so no square root of 0 enters the gradient."""
    h2 = 0.25 * dt * dt * w.dot(w)
    hs = ti.sqrt(ti.max(h2, 1e-12))
    small = h2 < 1e-6
    c = ti.select(small, 1.0 - h2 / 2.0 + h2 * h2 / 24.0, ti.cos(hs))
    sinc = ti.select(small, 1.0 - h2 / 6.0 + h2 * h2 / 120.0, ti.sin(hs) / hs)
    k = 0.5 * dt * sinc
    return ti.Vector([c, k * w[0], k * w[1], k * w[2]])


@ti.func
def func_euler_xyz_quat(a, b, c):
    """Quaternion of intrinsic x-y-z Euler angles (roll a, pitch b, yaw c), R = Rx(a) Ry(b) Rz(c): the
    product qx(a) qy(b) qz(c) written out. Genesis's convention for a free joint's rotational dof
    positions (its gu.qd_xyz_to_quat)."""
    ca, sa = ti.cos(0.5 * a), ti.sin(0.5 * a)
    cb, sb = ti.cos(0.5 * b), ti.sin(0.5 * b)
    cc, sc = ti.cos(0.5 * c), ti.sin(0.5 * c)
    return ti.Vector([ca * cb * cc - sa * sb * sc, sa * cb * cc + ca * sb * sc,
                      ca * sb * cc - sa * cb * sc, ca * cb * sc + sa * sb * cc])


@ti.func
def func_quat_log(q):
    """Rotation vector (axis times angle, |angle| <= pi) of the quaternion q, which need not be unit (the
    result depends on its direction only). Smooth at the identity, where a PD error converges: below a
    tiny sine the series 2 atan(x) / x = 2 (1 - x^2 / 3), x = |v| / |w|, is used, and neither branch
    divides by 0, so an unselected branch puts no NaN into the gradient. Discontinuous at half a turn
    (w = 0), where the short way flips."""
    v, s2, sgn, w, s, small = func_quat_log_parts(q)
    k = ti.select(small, 2.0 / w * (1.0 - s2 / (3.0 * w * w)), 2.0 * ti.atan2(s, w) / s)
    return sgn * k * v


@ti.func
def func_quat_log_parts(q):
    """func_quat_log's (and its adjoint's) intermediates: the vector part v, its squared norm s2, the sign of q0
    sgn, w = max(|q0|, 1e-6), s = sqrt(max(s2, 1e-20)), and whether the series is used."""
    v = ti.Vector([q[1], q[2], q[3]])
    s2 = v.dot(v)
    w = ti.max(ti.abs(q[0]), 1e-6)
    return v, s2, ti.select(q[0] < 0.0, -1.0, 1.0), w, ti.sqrt(ti.max(s2, 1e-20)), s2 < 1e-10 * w * w


@ti.func
def func_euler_xyz_quat_adjoint(a, b, c, g):
    """The adjoint of func_euler_xyz_quat(a, b, c) for the quaternion's adjoint g: (a's, b's, c's)."""
    ca, sa = ti.cos(0.5 * a), ti.sin(0.5 * a)
    cb, sb = ti.cos(0.5 * b), ti.sin(0.5 * b)
    cc, sc = ti.cos(0.5 * c), ti.sin(0.5 * c)
    da = ti.Vector([-sa * cb * cc - ca * sb * sc, ca * cb * cc - sa * sb * sc,
                    -sa * sb * cc - ca * cb * sc, -sa * cb * sc + ca * sb * cc])
    db = ti.Vector([-ca * sb * cc - sa * cb * sc, -sa * sb * cc + ca * cb * sc,
                    ca * cb * cc + sa * sb * sc, -ca * sb * sc + sa * cb * cc])
    dc = ti.Vector([-ca * cb * sc - sa * sb * cc, -sa * cb * sc + ca * sb * cc,
                    -ca * sb * sc - sa * cb * cc, ca * cb * cc - sa * sb * sc])
    return 0.5 * g.dot(da), 0.5 * g.dot(db), 0.5 * g.dot(dc)


@ti.func
def func_quat_log_adjoint(q, g):
    """The adjoint of func_quat_log(q) for the rotation vector's adjoint g: q's, differentiated as written (each
    clamp passes the adjoint where its argument is the one kept, as Taichi's max does)."""
    v, s2, sgn, w, s, small = func_quat_log_parts(q)
    at = ti.atan2(s, w)
    k = ti.select(small, 2.0 / w * (1.0 - s2 / (3.0 * w * w)), 2.0 * at / s)
    gk = sgn * g.dot(v)
    gs2 = 0.0
    gw = 0.0
    if small:
        gs2 = gk * (2.0 / w) * (-1.0 / (3.0 * w * w))
        gw = gk * (-2.0 / (w * w) * (1.0 - s2 / (3.0 * w * w)) + (2.0 / w) * (2.0 * s2 / (3.0 * w * w * w)))
    else:
        r2 = s * s + w * w
        gs = gk * (2.0 * (w / r2) / s - 2.0 * at / (s * s))
        gw = gk * (-2.0 * (s / r2) / s)
        gs2 = ti.select(s2 >= 1e-20, gs * 0.5 / s, 0.0)
    gv = sgn * k * g + 2.0 * gs2 * v
    gq0 = ti.select(ti.abs(q[0]) >= 1e-6, gw * ti.select(q[0] > 0.0, 1.0, ti.select(q[0] < 0.0, -1.0, 0.0)), 0.0)
    return ti.Vector([gq0, gv[0], gv[1], gv[2]])


@ti.func
def func_rotate_inertia(R, I):
    """R I R^T, as (R I) R^T entry by entry, summed in the order of Taichi's `R @ I @ R.transpose()` (the
    same numbers). Taichi's matmul accumulates into a local matrix entry by entry (each entry stored
    three times), and its adjoint compiles about three times slower: seconds for the dynamics' gradient
    kernel."""
    RI = ti.Matrix([[_rowcol(R, a, I, b) for b in ti.static(range(3))] for a in ti.static(range(3))])
    return ti.Matrix([[_rowrow(RI, a, R, b) for b in ti.static(range(3))] for a in ti.static(range(3))])


@ti.func
def func_skew(p):
    """[p]x, the cross-product matrix: [p]x v = p x v."""
    return ti.Matrix([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])


@ti.func
def func_mm(A, B):
    """A @ B for 3x3 matrices, entry by entry in the order of Taichi's `@` (the same numbers; see
    func_rotate_inertia for why: the adjoint of a slot stage with two such products compiled for 4-7 s,
    with these for under 1.5 s)."""
    return ti.Matrix([[_rowcol(A, a, B, b) for b in ti.static(range(3))] for a in ti.static(range(3))])


@ti.func
def func_mv(A, v):
    """A @ v for a 3x3 matrix and a 3-vector, entry by entry in the order of Taichi's `@`."""
    return ti.Vector([A[a, 0] * v[0] + A[a, 1] * v[1] + A[a, 2] * v[2] for a in ti.static(range(3))])


@ti.func
def func_mtv(A, v):
    """A^T @ v (3x3, 3), in the order of Taichi's `A.transpose() @ v`."""
    return ti.Vector([A[0, a] * v[0] + A[1, a] * v[1] + A[2, a] * v[2] for a in ti.static(range(3))])


@ti.func
def _rowcol(A, a: ti.template(), B, b: ti.template()):
    return A[a, 0] * B[0, b] + A[a, 1] * B[1, b] + A[a, 2] * B[2, b]


@ti.func
def _rowrow(A, a: ti.template(), B, b: ti.template()):
    return A[a, 0] * B[b, 0] + A[a, 1] * B[b, 1] + A[a, 2] * B[b, 2]


@ti.func
def func_normalize_quat(q):
    return q / ti.sqrt(q.dot(q))


@ti.func
def func_cross_motion(aw, av, bw, bv):
    """Spatial motion cross product (a x b) for motion vectors (w, v)."""
    return aw.cross(bw), aw.cross(bv) + av.cross(bw)


@ti.func
def func_cross_force(aw, av, n, f):
    """Spatial force cross product (a x* f) for motion a = (w, v) and force (n, f)."""
    return aw.cross(n) + av.cross(f), aw.cross(f)


@ti.func
def func_inertia_mul(m, h, J, w, v):
    """Spatial inertia (mass m, first moment h = m c, rotational inertia J about the origin) times
    motion (w, v): returns the force pair (n, f)."""
    f = m * v + w.cross(h)
    n = func_mv(J, w) + h.cross(v)
    return n, f


@ti.func
def func_inertia_mul_adjoint(m, hh, J, w, v, gn, gf):
    """The adjoint of func_inertia_mul(m, hh, J, w, v) = (J w + hh x v, m v + w x hh) for (gn, gf): (m's, hh's, J's,
    w's, v's)."""
    return (gf.dot(v), gf.cross(w) + v.cross(gn), gn.outer_product(w), func_mtv(J, gn) + hh.cross(gf),
            m * gf + gn.cross(hh))


def plain_updates(s) -> bool:
    """Whether a stage compiling now may update a field of s with a plain read-modify-write (x = x + v)
    rather than `+=`: where nothing differentiates the kernel being compiled (no gradients, or a primal kernel
    of the gradient path: taichi_compat.compiling_adjoint). One thread owns an env's entries, and `+=` on a
    field in the parallel env loop compiles to an atomic (a compare-and-swap loop for floats: the composite
    inertia's loop alone took 387 us against 150 plain, a 1,024-env Panda step in float64; the contact banks'
    accumulations were their stages' main cost). An adjoint's kernel keeps `+=`, the form Taichi's reverse
    mode is written for (its global data access rule: no read of an overwritten value). Both forms add in
    the same order (an env's updates run in program order in one thread either way); the plain one lets LLVM
    fuse a product into the add, a last-bit difference (a 1,024-env Panda's gradients came out the same to the
    bit, a 256-env ANYmal contact rollout's within 2.4e-11 relative)."""
    return not (s.requires_grad and taichi_compat.compiling_adjoint())


@ti.func
def func_add(s: ti.template(), x: ti.template(), i_b, i, v):
    """x[i_b, i] += v inside a stage's env loop, plain where plain_updates(s)."""
    if ti.static(plain_updates(s)):
        x[i_b, i] = x[i_b, i] + v
    else:
        x[i_b, i] += v


@ti.func
def func_add2(s: ti.template(), x: ti.template(), i_b, i, j, v):
    """x[i_b, i, j] += v inside a stage's env loop, plain where plain_updates(s)."""
    if ti.static(plain_updates(s)):
        x[i_b, i, j] = x[i_b, i, j] + v
    else:
        x[i_b, i, j] += v
