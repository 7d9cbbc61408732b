"""Stage 6, collision: which geoms can touch (built once, numpy), and the narrow phase (Taichi).

Every candidate pair of geoms gets a fixed set of contact *slots* at build time, so a step has a
fixed amount of work and a fixed computation graph (what Taichi's reverse mode needs): a slot is a
sample point of one geom (the "point side", with a radius) tested against the signed distance
function (SDF) of the other (the "SDF side"):

  pair                        point side                                   SDF side
  plane  x any                sphere centre / capsule ends / box corners /  plane
                              cylinder rims / mesh hull vertices
  sphere x any non-plane      the sphere centre (radius r): exact           the other geom
  capsule x capsule           closest points of the two segments, and each  the other capsule
                              capsule's end points
  box x box                   as other primitive pairs below, plus the      the other box
                              closest points of the edge pair whose axis
                              (cross product) separates the boxes best,
                              where it beats every face axis (edge on edge)
  other primitive pairs,      corners + edge midpoints (box), rim and cap   the other geom
  mesh x primitive            samples (cylinder), axis samples (capsule),
                              hull vertices (mesh), in both directions
  mesh x mesh                 unsupported (an error at build, see below)

SDFs are exact for plane, sphere, capsule, box and cylinder; a mesh is its convex hull, whose SDF is
approximated by a 26-plane discrete-orientation polytope (k-DOP) around it. Inside a box, cylinder or
k-DOP the nearest face is ambiguous where faces meet (two stacked identical boxes touch corner on
corner), so the face is chosen by penetration plus a bias towards the face that looks at the other
geom's centre.

Which pairs are candidates: geoms of different entities; geoms of one entity only with
`enable_self_collision`, and never on the same or adjacent (parent/child) links; never two geoms that
cannot move. A cheap test per pair (the broad phase: the geom's support function against a plane,
bounding spheres otherwise) skips the slots of pairs that are not within the contact margin, so a
robot standing on the ground computes only its feet's slots. A mesh is contacted through at most
RigidOptions.max_mesh_contact_points of its hull vertices (farthest-point sampled, extremes kept).
"""

from dataclasses import dataclass, field
from typing import List

import numpy as np
import taichi as ti
from .. import taichi_compat


GEOM_PLANE, GEOM_SPHERE, GEOM_BOX, GEOM_CAPSULE, GEOM_CYLINDER, GEOM_MESH = 0, 1, 2, 3, 4, 5
GEOM_CODE = {"plane": GEOM_PLANE, "sphere": GEOM_SPHERE, "box": GEOM_BOX, "capsule": GEOM_CAPSULE,
             "cylinder": GEOM_CYLINDER, "mesh": GEOM_MESH}
# slot kinds: a fixed sample point of the point-side geom; the deepest rim point of a cylinder cap
# towards a plane (aux = cap side +-1); the closest points of two capsule segments; the closest points
# of the two box edges whose cross product separates two boxes best (edge against edge)
SLOT_POINT, SLOT_CYL_RIM, SLOT_SEGSEG, SLOT_BOXEDGE = 0, 1, 2, 3
# an edge-edge axis counts only where it separates two boxes better than every face axis by this
# fraction of the smaller box's smallest half size (ties, as in face-on-face stacks, are the faces')
BOXEDGE_TOL = 0.02

# k-DOP directions: 3 axes, 6 edge diagonals, 4 corner diagonals, each with both signs
_D = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1), (0, 1, 1), (0, 1, -1),
      (1, 1, 1), (1, 1, -1), (1, -1, 1), (-1, 1, 1)]
KDOP_DIRS = np.array([d for d in _D] + [tuple(-x for x in d) for d in _D], dtype=float)
KDOP_DIRS /= np.linalg.norm(KDOP_DIRS, axis=1, keepdims=True)
N_KDOP = len(KDOP_DIRS)

CYL_RIM_PLANE = 3  # rim samples per cap against a plane (plus the deepest rim point of each cap)
CYL_RIM_OTHER = 8  # rim samples per cap against other geoms


class ContactBuildError(ValueError):
    """A scene whose collision geometry cannot be simulated (the message says which geoms and why)."""


@dataclass
class GeomTable:
    """All collision geoms of a scene, entity after entity, link after link (global geom index)."""

    type: np.ndarray            # (G,) int
    link: np.ndarray            # (G,) global link index
    entity: np.ndarray          # (G,) entity index
    pos: np.ndarray             # (G, 3) in the link frame
    quat: np.ndarray            # (G, 4)
    size: np.ndarray            # (G, 3)
    friction: np.ndarray        # (G,)
    center: np.ndarray          # (G, 3) centre in the geom frame (mesh: hull centroid)
    rbound: np.ndarray          # (G,) bounding radius about `center` (plane: inf)
    beta: np.ndarray            # (G,) face-choice bias length of its SDF
    kdop: np.ndarray            # (G, 26) k-DOP plane offsets (meshes)
    points: List[np.ndarray]    # per geom: hull sample points in the geom frame (meshes)
    names: List[str]            # "entity 'x', link 'y', <type> geom #k" for messages
    entity_start: List[int] = field(default_factory=list)
    entity_count: List[int] = field(default_factory=list)

    @property
    def n(self):
        return len(self.type)


def _farthest_points(V: np.ndarray, k: int) -> np.ndarray:
    """k of the points V, spread out (greedy farthest-point order from the most extreme point):
    contacts of a hull against a plane happen at its extreme points, which this keeps."""
    if len(V) <= k:
        return V
    c = V.mean(0)
    first = int(np.argmax(((V - c) ** 2).sum(1)))
    chosen = [first]
    d = ((V - V[first]) ** 2).sum(1)
    for _ in range(k - 1):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, ((V - V[i]) ** 2).sum(1))
    return V[np.sort(chosen)]


def _mesh_hull_points(g, what: str, max_points: int):
    V = np.asarray(g.vertices, dtype=float).reshape(-1, 3) if g.vertices is not None else np.zeros((0, 3))
    if len(V) < 4 or not np.all(np.isfinite(V)):
        raise ContactBuildError(f"{what}: a collision mesh needs at least 4 finite vertices that enclose a volume "
                                f"(it has {len(V)}); fix the mesh or use a primitive collision shape")
    h = getattr(g, "hull", None)
    if h is not None:
        # the loader computed the same hull (model.GeomDesc.hull): no trimesh import on a warm start
        hv, hc = np.asarray(h["vertices"], dtype=float), np.asarray(h["centroid"], dtype=float)
        ok = bool(h["is_volume"]) and h["volume"] > 1e-12 * max(np.ptp(V, 0).max(), 1e-9) ** 3
    else:
        import trimesh

        try:
            hull = trimesh.Trimesh(vertices=V, process=False).convex_hull
            ok = hull.is_volume and hull.volume > 1e-12 * max(np.ptp(V, 0).max(), 1e-9) ** 3
            hv, hc = np.asarray(hull.vertices, dtype=float), np.asarray(hull.centroid, dtype=float)
        except Exception:  # qhull rejects flat or degenerate point sets
            ok = False
    if not ok:
        raise ContactBuildError(f"{what}: the collision mesh has no volume (its points are flat or degenerate), so "
                                "it has no inside to push out of; use a closed mesh that encloses a volume, a "
                                "primitive shape, or remove the <collision> element")
    P = _farthest_points(hv, max_points)
    return P, hv, hc


def link_is_dynamic(flat) -> np.ndarray:  # flat: the scene's flatten.FlatModel
    """(L,) bool: the link moves with some dof (it or an ancestor has a joint with dofs)."""
    L = flat.n_links
    dyn = np.zeros(L, dtype=bool)
    for i in range(L):
        p = flat.np_link_parent[i]
        dyn[i] = flat.np_link_ndof[i] > 0 or (p >= 0 and dyn[p])
    return dyn


def build_geoms(models, max_mesh_points: int) -> GeomTable:
    types, link, ent, pos, quat, size, fric, center, rb, beta, kdop, pts, names = ([] for _ in range(13))
    starts, counts = [], []
    nl = 0
    for i_e, m in enumerate(models):
        starts.append(len(types))
        for i_l, l in enumerate(m.links):
            for k, g in enumerate(l.geoms):
                what = f"entity '{m.name}', link '{l.name}', {g.type} geom #{k}"
                if g.type not in GEOM_CODE:
                    raise ContactBuildError(f"{what}: unknown collision geometry type '{g.type}'; supported are "
                                            f"{sorted(GEOM_CODE)}")
                sz = np.zeros(3)
                s = np.asarray(g.size, dtype=float).reshape(-1)
                sz[: len(s)] = s
                if g.type != "plane" and g.type != "mesh":
                    need = {"sphere": 1, "box": 3, "capsule": 2, "cylinder": 2}[g.type]
                    if len(s) < need or not np.all(np.isfinite(s[:need])) or np.any(s[:need] <= 0):
                        raise ContactBuildError(f"{what}: size {tuple(s)} must be {need} positive numbers")
                mu = 1.0 if g.friction is None else float(g.friction)
                if not (np.isfinite(mu) and mu >= 0):
                    raise ContactBuildError(f"{what}: friction {mu} must be a finite number >= 0")
                c = np.zeros(3)
                kd = np.zeros(N_KDOP)
                P = np.zeros((0, 3))
                if g.type == "plane":
                    r, b = np.inf, 1.0
                elif g.type == "sphere":
                    r, b = sz[0], sz[0]
                elif g.type == "box":
                    r, b = float(np.linalg.norm(sz)), 0.5 * float(sz.min())
                elif g.type == "capsule":
                    r, b = sz[0] + sz[1], sz[0]
                elif g.type == "cylinder":
                    r, b = float(np.hypot(sz[0], sz[1])), 0.5 * float(min(sz[0], sz[1]))
                else:
                    P, H, c = _mesh_hull_points(g, what, max_mesh_points)
                    # the k-DOP is built from the full hull; contacts use the reduced point set
                    kd = (H @ KDOP_DIRS.T).max(0)
                    r = float(np.sqrt(((H - c) ** 2).sum(1).max()))
                    ext = kd[:3] + kd[N_KDOP // 2: N_KDOP // 2 + 3]
                    b = 0.25 * float(ext.min())
                types.append(GEOM_CODE[g.type]); link.append(nl + i_l); ent.append(i_e)
                pos.append(np.asarray(g.pos, dtype=float)); quat.append(np.asarray(g.quat, dtype=float))
                size.append(sz); fric.append(mu); center.append(c); rb.append(r); beta.append(b)
                kdop.append(kd); pts.append(P); names.append(what)
        counts.append(len(types) - starts[-1])
        nl += m.n_links
    G = len(types)
    arr = lambda x, shape: np.array(x, dtype=float).reshape(shape)  # noqa: E731
    return GeomTable(np.array(types, dtype=np.int32).reshape(G), np.array(link, dtype=np.int32).reshape(G),
                     np.array(ent, dtype=np.int32).reshape(G), arr(pos, (G, 3)), arr(quat, (G, 4)),
                     arr(size, (G, 3)), arr(fric, (G,)), arr(center, (G, 3)), arr(rb, (G,)), arr(beta, (G,)),
                     arr(kdop, (G, N_KDOP)), pts, names, starts, counts)


def candidate_pairs(geoms: GeomTable, flat, self_collision: bool, ignore_unsupported: bool):
    """[(ga, gb)] of geoms that may touch (see the module docstring for the rules)."""
    dyn = link_is_dynamic(flat)
    parent = flat.np_link_parent
    pairs, bad = [], []
    for a in range(geoms.n):
        for b in range(a + 1, geoms.n):
            la, lb = geoms.link[a], geoms.link[b]
            if la == lb or not (dyn[la] or dyn[lb]):
                continue
            if geoms.entity[a] == geoms.entity[b]:
                if not self_collision or parent[la] == lb or parent[lb] == la:
                    continue
            ta, tb = geoms.type[a], geoms.type[b]
            if ta == GEOM_PLANE and tb == GEOM_PLANE:
                continue
            moving_plane = (ta == GEOM_PLANE and dyn[la]) or (tb == GEOM_PLANE and dyn[lb])
            if (ta == GEOM_MESH and tb == GEOM_MESH) or moving_plane:
                bad.append((a, b, "a plane on a moving link" if moving_plane else "mesh against mesh"))
                continue
            # a plane is always the second geom of its pair (the broad phase tests the first against it)
            pairs.append((b, a) if ta == GEOM_PLANE else (a, b))
    if bad and not ignore_unsupported:
        a, b, why = bad[0]
        more = f" (and {len(bad) - 1} more such pairs)" if len(bad) > 1 else ""
        raise ContactBuildError(
            f"unsupported collision pair ({why}): {geoms.names[a]} and {geoms.names[b]}{more}. Supported are plane "
            "(static) against every shape, sphere/box/capsule/cylinder among themselves, and meshes against planes "
            "and primitives. Give one of them primitive collision shapes, turn self-collision off "
            "(RigidOptions(enable_self_collision=False)) if they belong to one entity, or pass "
            "RigidOptions(ignore_unsupported_pairs=True) to let such pairs pass through each other.")
    return pairs


def _box_points(b, edges: bool):
    s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    pts = list(s * b)
    if edges:
        for ax in range(3):
            o = [i for i in range(3) if i != ax]
            for s1 in (-1, 1):
                for s2 in (-1, 1):
                    p = np.zeros(3)
                    p[o[0]], p[o[1]] = s1 * b[o[0]], s2 * b[o[1]]
                    pts.append(p)
    return pts


def _cyl_rim(r, hl, n, side):
    return [np.array([r * np.cos(2 * np.pi * k / n), r * np.sin(2 * np.pi * k / n), side * hl]) for k in range(n)]


def sample_points(geoms: GeomTable, g: int, against_plane: bool):
    """[(kind, point in the geom frame, radius, aux)] of geom g as the point side of a pair."""
    t, sz = geoms.type[g], geoms.size[g]
    P = lambda pts, r=0.0: [(SLOT_POINT, np.asarray(p, float), r, 0.0) for p in pts]  # noqa: E731
    if t == GEOM_SPHERE:
        return P([np.zeros(3)], sz[0])
    if t == GEOM_CAPSULE:
        ts = (-1.0, 1.0) if against_plane else (-1.0, -0.5, 0.0, 0.5, 1.0)
        return P([np.array([0.0, 0.0, u * sz[1]]) for u in ts], sz[0])
    if t == GEOM_BOX:
        return P(_box_points(sz, edges=not against_plane))
    if t == GEOM_CYLINDER:
        r, hl = sz[0], sz[1]
        if against_plane:
            out = [(SLOT_CYL_RIM, np.zeros(3), 0.0, side) for side in (-1.0, 1.0)]
            # rim samples keep a cylinder standing on a cap from rocking on the two deepest points
            return out + P(_cyl_rim(r, hl, CYL_RIM_PLANE, -1) + _cyl_rim(r, hl, CYL_RIM_PLANE, 1))
        return P(_cyl_rim(r, hl, CYL_RIM_OTHER, -1) + _cyl_rim(r, hl, CYL_RIM_OTHER, 1)
                 + [np.array([0.0, 0.0, -hl]), np.array([0.0, 0.0, hl])])
    if t == GEOM_MESH:
        return P(geoms.points[g])
    raise ValueError(f"no sample points for geom type {t}")


def build_slots(geoms: GeomTable, pairs):
    """Contact slots of the candidate pairs: list of (pair, kind, ga, gb, point, radius, aux) with ga the
    point side and gb the SDF side."""
    slots = []
    for i_p, (a, b) in enumerate(pairs):
        ta, tb = geoms.type[a], geoms.type[b]
        if ta == GEOM_PLANE or tb == GEOM_PLANE:
            pa, pb = (b, a) if ta == GEOM_PLANE else (a, b)
            jobs = [(pa, pb, True)]
        elif ta == GEOM_SPHERE or tb == GEOM_SPHERE:
            pa, pb = (a, b) if ta == GEOM_SPHERE else (b, a)
            jobs = [(pa, pb, False)]
        elif ta == GEOM_CAPSULE and tb == GEOM_CAPSULE:
            slots.append((i_p, SLOT_SEGSEG, a, b, np.zeros(3), geoms.size[a][0], 0.0))
            for pa, pb in ((a, b), (b, a)):
                for u in (-1.0, 1.0):
                    slots.append((i_p, SLOT_POINT, pa, pb, np.array([0.0, 0.0, u * geoms.size[pa][1]]),
                                  geoms.size[pa][0], 0.0))
            continue
        else:
            jobs = [(a, b, False), (b, a, False)]
            if ta == GEOM_BOX and tb == GEOM_BOX:
                tol = BOXEDGE_TOL * float(min(geoms.size[a].min(), geoms.size[b].min()))
                slots.append((i_p, SLOT_BOXEDGE, a, b, np.zeros(3), 0.0, tol))
        for pa, pb, plane in jobs:
            for kind, p, r, aux in sample_points(geoms, pa, plane):
                slots.append((i_p, kind, pa, pb, p, r, aux))
    return slots


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
    dk = ti.Vector([KDOP_DIRS[k, 0], KDOP_DIRS[k, 1], KDOP_DIRS[k, 2]])
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
    """Signed distance to the geom's k-DOP: inside, the plane of least penetration with the face-choice
    bias; outside (a plane distance > 0), the largest plane distance (a lower bound of the distance)."""
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


def _div_floor() -> float:
    """Floor of a denominator that may be exactly 0 (parallel edges): 1e-30 in float64; in float32 1e-15,
    whose square (in the adjoint of a division, -num / den^2) is still a normal float32. With 1e-30 it
    underflows to 0 and the discarded branch's adjoint becomes 0 * inf = NaN."""
    return 1e-30 if taichi_compat.config().default_fp == ti.f64 else 1e-15


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
    s0 = ti.select(den > 1e-12 * a * e, ti.min(ti.max((b * f - c * e) / ti.max(den, ti.static(_div_floor())), 0.0), 1.0), 0.0)
    t0 = (b * s0 + f) / e
    s = ti.select(t0 < 0.0, ti.min(ti.max(-c / a, 0.0), 1.0), ti.select(t0 > 1.0, ti.min(ti.max((b - c) / a, 0.0), 1.0), s0))
    t = ti.min(ti.max(t0, 0.0), 1.0)
    return p1 + d1 * s, p2 + d2 * t


@ti.func
def func_geom_pose(s: ti.template(), i_b, e, src, h):
    """World pose of every collision geom (from its link's pose)."""
    c = s.contact
    for g in range(c.n_geoms):
        l = c.geom_link[g]
        R = s.link_R[i_b, l]
        c.geom_xpos[i_b, g] = s.link_pos[i_b, l] + R @ c.geom_pos[g]
        c.geom_xR[i_b, g] = R @ c.geom_R[g]


@ti.func
def func_plane_extent(c: ti.template(), g, R, n, branch: ti.template()):
    """How far geom g (rotation R) reaches from its centre along -n: its support function. Exact for
    sphere, capsule, box and cylinder; the bounding radius for meshes. With `branch` (no gradients)
    only the geom's own type is evaluated; else every type's, selected (single-assignment form)."""
    t = c.geom_type[g]
    sz = c.geom_size[g]
    a = R.transpose() @ n  # n in the geom frame
    r = c.geom_rbound[g]
    if ti.static(branch):
        if t == GEOM_BOX:
            r = sz[0] * ti.abs(a[0]) + sz[1] * ti.abs(a[1]) + sz[2] * ti.abs(a[2])
        elif t == GEOM_CYLINDER:
            r = sz[1] * ti.abs(a[2]) + sz[0] * ti.sqrt(ti.max(1.0 - a[2] * a[2], 0.0))
        elif t == GEOM_CAPSULE:
            r = sz[1] * ti.abs(a[2]) + sz[0]
        elif t == GEOM_SPHERE:
            r = sz[0]
    else:
        box = sz[0] * ti.abs(a[0]) + sz[1] * ti.abs(a[1]) + sz[2] * ti.abs(a[2])
        cyl = sz[1] * ti.abs(a[2]) + sz[0] * ti.sqrt(ti.max(1.0 - a[2] * a[2], 0.0))
        cap = sz[1] * ti.abs(a[2]) + sz[0]
        r = ti.select(t == GEOM_BOX, box, ti.select(t == GEOM_CYLINDER, cyl, ti.select(
            t == GEOM_CAPSULE, cap, ti.select(t == GEOM_SPHERE, sz[0], r))))
    return r


@ti.func
def func_broad_phase(s: ti.template(), i_b, e, src, h):
    """pair_active: the geom reaches within the contact margin of a plane (support function), or two
    bounding spheres do, now or within the step (the margin grows by how far the two can approach each
    other in h at their current velocities: speculative contacts, see contact.py; a turn sweeps a
    geom's extent by at most its diameter, so the spin term is capped at 2 / h). Without gradients
    the plane and sphere tests are branches (each pair evaluates its own: a fifth of the stage on
    ANYmal); with them both are evaluated and selected (single-assignment form)."""
    c = s.contact
    for i_p in range(c.n_pairs):
        ga = c.pair_ga[i_p]
        gb = c.pair_gb[i_p]
        la = c.geom_link[ga]
        lb = c.geom_link[gb]
        Ra = c.geom_xR[i_b, ga]
        Rb = c.geom_xR[i_b, gb]
        ca = c.geom_xpos[i_b, ga] + Ra @ c.geom_center[ga]
        cb = c.geom_xpos[i_b, gb] + Rb @ c.geom_center[gb]
        is_plane = c.geom_type[gb] == GEOM_PLANE
        # closing speed bound: centre velocities, plus rotation of the geoms' extents (a plane does not
        # move: candidate_pairs rejects moving planes); either body may also turn towards the other
        # within the step (stopped by a third one): their speeds bound that (contact.py linearises such
        # candidate contacts again after its first solve)
        va = s.cvel_v[i_b, la] + s.cvel_w[i_b, la].cross(ca)
        vb = s.cvel_v[i_b, lb] + s.cvel_w[i_b, lb].cross(cb)
        wa = s.cvel_w[i_b, la]
        # (a turn sweeps a geom's extent by at most its diameter, whatever the spin: 2 / h caps |w|)
        rot_a = ti.min(ti.sqrt(wa.dot(wa) + TINY), 2.0 / h) * ti.min(c.geom_rbound[ga], 1e6)
        closing = ti.sqrt(va.dot(va) + TINY) + ti.sqrt(vb.dot(vb) + TINY) + rot_a
        gap = ti.cast(0.0, s.dtype)
        if ti.static(s.requires_grad):
            gap_plane = func_gap_plane(c, ga, Ra, Rb, ca, cb, False)
            gap_pair, rot_b = func_gap_spheres(s, ga, gb, lb, i_b, ca, cb, h)
            gap = ti.select(is_plane, gap_plane, gap_pair)
            closing += ti.select(is_plane, 0.0, rot_b)
        else:
            if is_plane:
                gap = func_gap_plane(c, ga, Ra, Rb, ca, cb, True)
            else:
                gap_pair, rot_b = func_gap_spheres(s, ga, gb, lb, i_b, ca, cb, h)
                gap = gap_pair
                closing += rot_b
        c.pair_active[i_b, i_p] = ti.select(gap - h * closing < c.margin, 1, 0)


@ti.func
def func_gap_plane(c: ti.template(), ga, Ra, Rb, ca, cb, branch: ti.template()):
    """Gap of geom ga (rotation Ra, centre ca) above the plane of rotation Rb through cb (its normal the
    plane's z axis)."""
    nb = ti.Vector([Rb[0, 2], Rb[1, 2], Rb[2, 2]])
    return (ca - cb).dot(nb) - func_plane_extent(c, ga, Ra, nb, branch)


@ti.func
def func_gap_spheres(s: ti.template(), ga, gb, lb, i_b, ca, cb, h):
    """Gap of the bounding spheres of geoms ga and gb (centres ca, cb), and how fast gb's rotation can
    sweep its extent."""
    c = s.contact
    dc = ca - cb
    # norms with TINY under the root: no infinite derivative at 0 in the adjoint (0 * inf is NaN)
    ldc = ti.sqrt(dc.dot(dc) + TINY)
    wb = s.cvel_w[i_b, lb]
    return ldc - c.geom_rbound[ga] - c.geom_rbound[gb], ti.min(ti.sqrt(wb.dot(wb) + TINY), 2.0 / h) * ti.min(c.geom_rbound[gb], 1e6)


@ti.func
def func_slot_point(c: ti.template(), i_s, kind, ga, xa, Ra, zb):
    """The point-side point of a slot: a fixed sample point, or the deepest rim point of a cylinder cap
    towards a plane (normal zb)."""
    p_fixed = xa + Ra @ c.slot_p[i_s]
    if ti.static(c.has_rim):
        nl = Ra.transpose() @ zb
        rho = ti.sqrt(nl[0] * nl[0] + nl[1] * nl[1] + 1e-12)
        r_cyl = c.geom_size[ga][0]
        p_rim = xa + Ra @ ti.Vector([-r_cyl * nl[0] / rho, -r_cyl * nl[1] / rho, c.slot_aux[i_s] * c.geom_size[ga][1]])
        return ti.select(kind == SLOT_CYL_RIM, p_rim, p_fixed)
    else:
        return p_fixed


@ti.func
def func_with_segseg(c: ti.template(), kind, ga, gb, xa, za, xb, zb, p, phi, n):
    """(point, signed distance, normal) of the slot: those of the SDF test, or for capsule pairs the
    closest points of the two segments."""
    if ti.static(c.has_segseg):
        hla = c.geom_size[ga][1]
        hlb = c.geom_size[gb][1]
        pa, pb = func_segment_closest(xa - hla * za, xa + hla * za, xb - hlb * zb, xb + hlb * zb)
        phi_ss, n_ss = func_sdf_round(pa - pb, c.geom_size[gb][0], zb)
        ss = kind == SLOT_SEGSEG
        return ti.select(ss, pa, p), ti.select(ss, phi_ss, phi), ti.select(ss, n_ss, n)
    else:
        return p, phi, n


@ti.func
def func_box_axis_sep(T, L, Ra, ha, Rb, hb):
    """Separation of two boxes (centre offset T = xb - xa, rotations, half sizes) along the unit axis L:
    |T . L| minus the two boxes' half extents along L (negative: the projections overlap)."""
    ra = ha[0] * ti.abs(Ra[0, 0] * L[0] + Ra[1, 0] * L[1] + Ra[2, 0] * L[2]) \
        + ha[1] * ti.abs(Ra[0, 1] * L[0] + Ra[1, 1] * L[1] + Ra[2, 1] * L[2]) \
        + ha[2] * ti.abs(Ra[0, 2] * L[0] + Ra[1, 2] * L[1] + Ra[2, 2] * L[2])
    rb = hb[0] * ti.abs(Rb[0, 0] * L[0] + Rb[1, 0] * L[1] + Rb[2, 0] * L[2]) \
        + hb[1] * ti.abs(Rb[0, 1] * L[0] + Rb[1, 1] * L[1] + Rb[2, 1] * L[2]) \
        + hb[2] * ti.abs(Rb[0, 2] * L[0] + Rb[1, 2] * L[1] + Rb[2, 2] * L[2])
    return ti.abs(T.dot(L)) - ra - rb


@ti.func
def func_col(R, i: ti.template()):
    return ti.Vector([R[0, i], R[1, i], R[2, i]])


@ti.func
def func_face_sep(T, Ra, ha, Rb, hb):
    """Largest separation of two boxes over their 6 face axes."""
    return ti.max(ti.max(ti.max(func_box_axis_sep(T, func_col(Ra, 0), Ra, ha, Rb, hb),
                                func_box_axis_sep(T, func_col(Ra, 1), Ra, ha, Rb, hb)),
                         ti.max(func_box_axis_sep(T, func_col(Ra, 2), Ra, ha, Rb, hb),
                                func_box_axis_sep(T, func_col(Rb, 0), Ra, ha, Rb, hb))),
                  ti.max(func_box_axis_sep(T, func_col(Rb, 1), Ra, ha, Rb, hb),
                         func_box_axis_sep(T, func_col(Rb, 2), Ra, ha, Rb, hb)))


@ti.func
def func_edge_best(T, Ra, ha, Rb, hb, k: ti.template()):
    """Over the edge axes k..8 (a_i x b_j, i = k // 3, j = k % 3): (separation, unit axis oriented from
    box a to box b, i, j) of the best-separating one; near-parallel edge pairs never win."""
    i = ti.static(k // 3)
    j = ti.static(k % 3)
    C = func_col(Ra, i).cross(func_col(Rb, j))
    ln = ti.sqrt(C.dot(C) + TINY)
    ok = ln > 1e-6
    Lu = C / ti.max(ln, 1e-6)
    L = ti.select(T.dot(Lu) >= 0, Lu, -Lu)
    v = ti.select(ok, func_box_axis_sep(T, L, Ra, ha, Rb, hb), -1e30)
    if ti.static(k == 8):
        return v, L, i, j
    else:
        bv, bL, bi, bj = func_edge_best(T, Ra, ha, Rb, hb, k + 1)
        take = v > bv
        return ti.select(take, v, bv), ti.select(take, L, bL), ti.select(take, i, bi), ti.select(take, j, bj)


@ti.func
def func_box_edge_contact(c: ti.template(), ga, gb, xa, Ra, xb, Rb, tol):
    """(point midway between the two edges, normal from box b towards box a, depth) of the edge pair
    whose axis separates boxes a and b best; depth -1 (no contact) unless that axis beats every face
    axis by tol and the closest points lie inside both edges (else corners and faces carry the contact)."""
    ha = c.geom_size[ga]
    hb = c.geom_size[gb]
    T = xb - xa
    sep_f = func_face_sep(T, Ra, ha, Rb, hb)
    sep_e, L, i, j = func_edge_best(T, Ra, ha, Rb, hb, 0)
    # the supporting edge of a (towards b) runs along a_i; that of b (towards a) along b_j
    sa = func_sgn3(Ra.transpose() @ L)
    sb = func_sgn3(Rb.transpose() @ L)
    ea = ti.Vector([ti.select(i == 0, 0.0, sa[0] * ha[0]), ti.select(i == 1, 0.0, sa[1] * ha[1]),
                    ti.select(i == 2, 0.0, sa[2] * ha[2])])
    eb = ti.Vector([ti.select(j == 0, 0.0, sb[0] * hb[0]), ti.select(j == 1, 0.0, sb[1] * hb[1]),
                    ti.select(j == 2, 0.0, sb[2] * hb[2])])
    ua = ti.Vector([ti.select(i == 0, ha[0], 0.0), ti.select(i == 1, ha[1], 0.0), ti.select(i == 2, ha[2], 0.0)])
    ub = ti.Vector([ti.select(j == 0, hb[0], 0.0), ti.select(j == 1, hb[1], 0.0), ti.select(j == 2, hb[2], 0.0)])
    ca = xa + Ra @ ea
    cb = xb - Rb @ eb
    da = Ra @ ua
    db = Rb @ ub
    pa, pb = func_segment_closest(ca - da, ca + da, cb - db, cb + db)
    # inside both edges: the closest points are not end points (parameters strictly inside (0, 1))
    ta = (pa - (ca - da)).dot(da) / ti.max(2.0 * da.dot(da), ti.static(_div_floor()))
    tb = (pb - (cb - db)).dot(db) / ti.max(2.0 * db.dot(db), ti.static(_div_floor()))
    inner = (ta > 1e-9) & (ta < 1.0 - 1e-9) & (tb > 1e-9) & (tb < 1.0 - 1e-9)
    on = (sep_e > sep_f + tol) & inner
    return 0.5 * (pa + pb), -L, ti.select(on, -sep_e, -1.0)


@ti.func
def func_with_boxedge(c: ti.template(), i_s, kind, ga, gb, xa, Ra, xb, Rb, pos, n, depth):
    """(point, normal, depth) of the slot: those given, or for box edge slots the edge-edge contact."""
    if ti.static(c.has_boxedge):
        pe, ne, de = func_box_edge_contact(c, ga, gb, xa, Ra, xb, Rb, c.slot_aux[i_s])
        be = kind == SLOT_BOXEDGE
        return ti.select(be, pe, pos), ti.select(be, ne, n), ti.select(be, de, depth)
    else:
        return pos, n, depth


@ti.func
def func_slot_geometry(s: ti.template(), i_b, i_s):
    """(contact point, normal from the SDF side to the point side, depth) of slot i_s; depth > 0 is
    penetration."""
    c = s.contact
    kind = c.slot_kind[i_s]
    ga = c.slot_ga[i_s]
    gb = c.slot_gb[i_s]
    xa = c.geom_xpos[i_b, ga]
    Ra = c.geom_xR[i_b, ga]
    xb = c.geom_xpos[i_b, gb]
    Rb = c.geom_xR[i_b, gb]
    ra = c.slot_r[i_s]
    za = ti.Vector([Ra[0, 2], Ra[1, 2], Ra[2, 2]])
    zb = ti.Vector([Rb[0, 2], Rb[1, 2], Rb[2, 2]])
    p = func_slot_point(c, i_s, kind, ga, xa, Ra, zb)
    q = Rb.transpose() @ (p - xb)
    # unit direction from the SDF geom's centre to the point geom's centre, in the SDF frame
    cl = Rb.transpose() @ (xa + Ra @ c.geom_center[ga] - xb) - c.geom_center[gb]
    chat = cl / ti.sqrt(cl.dot(cl) + 1e-24)
    phi_sdf, n_loc = func_sdf_any(c, 0, c.geom_type[gb], gb, q, chat, c.geom_beta[gb])
    pt, phi, n = func_with_segseg(c, kind, ga, gb, xa, za, xb, zb, p, phi_sdf, Rb @ n_loc)
    depth = ra - phi
    # the contact point: on the point side's surface against a static geom (where that side's velocity
    # and Jacobian belong: a speculative contact's gap can be centimetres, and a fast-turning link's
    # velocity changes across it), else midway between the two surfaces
    mid = pt - n * (0.5 * (ra + phi))
    cp = ti.select(c.link_dyn[c.geom_link[gb]] == 1, mid, pt - n * ra)
    return func_with_boxedge(c, i_s, kind, ga, gb, xa, Ra, xb, Rb, cp, n, depth)


def geom_rotations(quat: np.ndarray) -> np.ndarray:
    w, x, y, z = quat.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


__all__ = ["build_geoms", "candidate_pairs", "build_slots", "func_geom_pose", "func_broad_phase",
           "func_slot_geometry", "ContactBuildError"]
