"""Collision, Taichi side: the signed distance functions of the geom types (exact for plane, sphere, capsule,
box and cylinder; a mesh's convex hull through planes of its faces, geoms.hull_planes) and the closest
points of two segments.
"""
import taichi as ti

from ..math3d import div_floor
from .geoms import GEOM_BOX, GEOM_CAPSULE, GEOM_CYLINDER, GEOM_PLANE, GEOM_SPHERE, N_KDOP

# ------------------------------------------------------------------------------------------------
# Narrow phase (Taichi), in the single-assignment form of the other differentiated stages (every local
# assigned once, cases blended with ti.select: see kinematics.py). Every blended case must stay finite
# even where it is not selected (its adjoint is multiplied by 0, and 0 * inf is NaN): hence the tiny
# constants under square roots and the clamped divisors.
# ------------------------------------------------------------------------------------------------
TINY = 1e-30


@ti.func
def func_sgn3(q):
    return ti.Vector([ti.select(q[0] >= 0, 1.0, -1.0), ti.select(q[1] >= 0, 1.0, -1.0),
                      ti.select(q[2] >= 0, 1.0, -1.0)])


@ti.func
def func_sdf_round(v, r, chat):
    """Distance of the vector v (from the nearest core point) minus r; the normal falls back to chat
    when v vanishes."""
    L = ti.sqrt(v.dot(v) + TINY)
    return L - r, ti.select(L > 1e-12, v / ti.max(L, 1e-12), chat)


@ti.func
def func_sdf_box(q, b, chat, beta):
    """Exact outside; inside, the face of least penetration with a bias `beta` towards the face that
    looks at chat (unit direction to the other geom)."""
    d = ti.abs(q) - b
    sg = func_sgn3(q)
    od = ti.max(d, 0.0)
    L = ti.sqrt(od.dot(od) + TINY)
    outside = d.max() > 0
    s0 = d[0] + beta * sg[0] * chat[0]
    s1 = d[1] + beta * sg[1] * chat[1]
    s2 = d[2] + beta * sg[2] * chat[2]
    # bitwise & | (not the short-circuit `and`/`or`, which become control flow and adstacks)
    k0 = (s0 >= s1) & (s0 >= s2)
    k1 = (s1 > s0) & (s1 >= s2)
    k2 = (s2 > s0) & (s2 > s1)
    phi_in = ti.select(k0, d[0], ti.select(k1, d[1], d[2]))
    n_in = ti.Vector([ti.select(k0, sg[0], 0.0), ti.select(k1, sg[1], 0.0), ti.select(k2, sg[2], 0.0)])
    return ti.select(outside, L, phi_in), ti.select(outside, sg * od / L, n_in)


@ti.func
def func_sdf_cylinder(q, r, hl, chat, beta):
    rho = ti.sqrt(q[0] * q[0] + q[1] * q[1] + TINY)
    lc = ti.sqrt(chat[0] * chat[0] + chat[1] * chat[1] + TINY)
    u_c = ti.select(lc > 1e-12, ti.Vector([chat[0], chat[1], 0.0]) / ti.max(lc, 1e-12), ti.Vector([1.0, 0.0, 0.0]))
    u = ti.select(rho > 1e-12, ti.Vector([q[0], q[1], 0.0]) / ti.max(rho, 1e-12), u_c)
    sz = ti.select(q[2] >= 0, 1.0, -1.0)
    dr = rho - r
    dz = ti.abs(q[2]) - hl
    a = ti.max(dr, 0.0)
    b = ti.max(dz, 0.0)
    L = ti.sqrt(a * a + b * b + TINY)
    outside = (dr > 0) | (dz > 0)
    side = dr + beta * u.dot(chat) >= dz + beta * sz * chat[2]
    ez = ti.Vector([0.0, 0.0, sz])
    n_in = ti.select(side, u, ez)
    phi_in = ti.select(side, dr, dz)
    return ti.select(outside, L, phi_in), ti.select(outside, (a * u + b * ez) / L, n_in)


@ti.func
def func_kdop_plane(c: ti.template(), g, q, chat, beta, k: ti.template()):
    """Plane k of mesh geom g (geoms.hull_planes): its value n . q - d at q, that value with the face-choice
    bias, and its normal n."""
    dk = c.geom_kdop_dir[g, k]
    v = dk.dot(q) - c.geom_kdop[g, k]
    return v, v + beta * dk.dot(chat), dk


@ti.func
def func_kdop_best(c: ti.template(), g, q, chat, beta, k: ti.template()):
    """Over planes k..N_KDOP-1: (value, biased score, normal) of the best-scoring plane and (value,
    normal) of the largest plane distance, by static recursion (no local is assigned twice)."""
    v, sc, dk = func_kdop_plane(c, g, q, chat, beta, k)
    if ti.static(k == N_KDOP - 1):
        return v, sc, dk, v, dk
    else:
        bv, bs, bn, ov, on = func_kdop_best(c, g, q, chat, beta, k + 1)
        take = sc > bs
        big = v > ov
        return ti.select(take, v, bv), ti.select(take, sc, bs), ti.select(take, dk, bn), ti.select(big, v, ov), \
            ti.select(big, dk, on)


@ti.func
def func_sdf_kdop(c: ti.template(), g, q, chat, beta):
    """Signed distance to the mesh's planes (geoms.hull_planes): inside, the plane of least penetration with
    the face-choice bias; outside (a plane distance > 0), the largest plane distance (a lower bound of the
    distance)."""
    bv, bs, bn, ov, on = func_kdop_best(c, g, q, chat, beta, 0)
    return ti.select(ov > 0, ov, bv), ti.select(ov > 0, on, bn)


@ti.func
def func_sdf_of(c: ti.template(), T: ti.template(), g, q, chat, beta):
    """Signed distance and outward unit normal (geom frame) of geom g of static type T at q."""
    sz = c.geom_size[g]
    if ti.static(T == GEOM_PLANE):
        return q[2], ti.Vector([0.0, 0.0, 1.0])
    elif ti.static(T == GEOM_SPHERE):
        return func_sdf_round(q, sz[0], chat)
    elif ti.static(T == GEOM_CAPSULE):
        return func_sdf_round(ti.Vector([q[0], q[1], q[2] - ti.min(ti.max(q[2], -sz[1]), sz[1])]), sz[0], chat)
    elif ti.static(T == GEOM_BOX):
        return func_sdf_box(q, sz, chat, beta)
    elif ti.static(T == GEOM_CYLINDER):
        return func_sdf_cylinder(q, sz[0], sz[1], chat, beta)
    else:
        return func_sdf_kdop(c, g, q, chat, beta)


@ti.func
def func_sdf_any(c: ti.template(), k: ti.template(), tb, g, q, chat, beta):
    """The SDF of geom g (runtime type tb) among the types c.sdf_types[k:] that this scene uses (static
    recursion: code exists only for those types)."""
    T = ti.static(c.sdf_types[k])
    phi, n = func_sdf_of(c, T, g, q, chat, beta)
    if ti.static(k == len(c.sdf_types) - 1):
        return phi, n
    else:
        phi_r, n_r = func_sdf_any(c, k + 1, tb, g, q, chat, beta)
        return ti.select(tb == T, phi, phi_r), ti.select(tb == T, n, n_r)


@ti.func
def func_sdf_branched(c: ti.template(), tb, g, q, chat, beta):
    """func_sdf_any with a runtime branch: only the SDF of geom g's own type tb is evaluated (no gradients)."""
    phi = ti.cast(0.0, c.dtype)
    n = ti.Vector.zero(c.dtype, 3)
    for k in ti.static(range(len(c.sdf_types))):
        if tb == ti.static(c.sdf_types[k]):
            phi, n = func_sdf_of(c, ti.static(c.sdf_types[k]), g, q, chat, beta)
    return phi, n


@ti.func
def func_segment_closest(p1, q1, p2, q2):
    """Closest points of segments p1q1 and p2q2 (Ericson, Real-Time Collision Detection 5.1.9)."""
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2
    a = ti.max(d1.dot(d1), 1e-18)
    e = ti.max(d2.dot(d2), 1e-18)
    f = d2.dot(r)
    c = d1.dot(r)
    b = d1.dot(d2)
    den = a * e - b * b
    s0 = ti.select(den > 1e-12 * a * e, ti.min(ti.max((b * f - c * e) / ti.max(den, ti.static(div_floor())), 0.0), 1.0), 0.0)
    t0 = (b * s0 + f) / e
    s = ti.select(t0 < 0.0, ti.min(ti.max(-c / a, 0.0), 1.0), ti.select(t0 > 1.0, ti.min(ti.max((b - c) / a, 0.0), 1.0), s0))
    t = ti.min(ti.max(t0, 0.0), 1.0)
    return p1 + d1 * s, p2 + d2 * t
