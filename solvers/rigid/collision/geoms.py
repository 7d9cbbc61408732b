"""Collision, host side (numpy, once per scene): the geoms of the entities (GeomTable), which pairs can
touch (candidate_pairs) and the contact slots of each pair (build_slots, sample_points). See the
package's docstring for the slot kinds.
"""

import itertools
from dataclasses import dataclass, field
from typing import List

import numpy as np

from ..kinematics import JOINT_FIXED

GEOM_PLANE, GEOM_SPHERE, GEOM_BOX, GEOM_CAPSULE, GEOM_CYLINDER, GEOM_MESH = 0, 1, 2, 3, 4, 5
GEOM_CODE = {"plane": GEOM_PLANE, "sphere": GEOM_SPHERE, "box": GEOM_BOX, "capsule": GEOM_CAPSULE,
             "cylinder": GEOM_CYLINDER, "mesh": GEOM_MESH}
# slot kinds: a fixed sample point of the point-side geom; the deepest rim point of a cylinder cap
# towards a plane (aux = cap side +-1); the closest points of two capsule segments; the closest points
# of the two box edges whose cross product separates two boxes best (edge against edge); a point where
# an edge of one box's face crosses the rim of the other box's face lying on it (face on face, aux = the
# slot's code: incident edge code // 2, entry or exit code % 2; see narrow.func_box_face_contact)
SLOT_POINT, SLOT_CYL_RIM, SLOT_SEGSEG, SLOT_BOXEDGE, SLOT_BOXFACE = 0, 1, 2, 3, 4
# the closest points of the two edges whose cross product separates two convex volumes best (a mesh's
# planes, hull_planes, against another mesh's or a box: narrow.func_hull_pair_test), edge against edge
SLOT_HULLEDGE = 5
# face on face: a point where an edge of one volume's face crosses the rim of the other's face lying on it (the
# pair's test finds up to N_HULLFACE such crossings, one per slot: narrow.func_hull_face_crossings)
SLOT_HULLFACE = 6
N_HULLFACE = 8
# an edge-edge axis counts only where it separates two boxes better than every face axis by this
# fraction of the smaller box's smallest half size (ties, as in face-on-face stacks, are the faces');
# a face-face crossing counts only this far from the corners of both faces (where corner slots are)
BOXEDGE_TOL = 0.02
# face-face slots per box pair: the incident face's 4 edges, each entering and leaving the reference
# face's rectangle at most once (it is convex), so at most 8 crossings
N_BOXFACE = 8

# A mesh collides as the intersection of N_KDOP half-spaces around its convex hull (hull_planes): the
# planes of the hull's own faces, chosen to fit it, or, when qhull cannot split the hull into them, the
# k-DOP of these fixed directions: 3 axes, 6 edge diagonals, 4 corner diagonals, each with both signs
_D = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1), (0, 1, 1), (0, 1, -1),
      (1, 1, 1), (1, 1, -1), (1, -1, 1), (-1, 1, 1)]
KDOP_DIRS = np.array([d for d in _D] + [tuple(-x for x in d) for d in _D], dtype=float)
KDOP_DIRS /= np.linalg.norm(KDOP_DIRS, axis=1, keepdims=True)
N_KDOP = len(KDOP_DIRS)

# the largest convex volume of the hull-edge slots (polytope_hull): N_KDOP planes bound one of at most
# 2 N_KDOP - 4 corners and 3 N_KDOP - 6 edges (Euler's formula, every corner on three faces or more)
N_HULL_CORNERS, N_HULL_EDGES = 2 * N_KDOP - 4, 3 * N_KDOP - 6

CYL_RIM_PLANE = 3  # rim samples per cap against a plane (plus the deepest rim point of each cap)
# the deepest rim point's slot moves to the cap's centre below this many contact widths of rim height
# difference (narrow.func_slot_point): 1 left a cylinder standing on its cap rocking at dt = 10 ms, 10 holds it
# still at 10 and 2 ms
CYL_RIM_FADE = 10.0
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
    kdop: np.ndarray            # (G, N_KDOP) plane offsets d (meshes: n . x <= d inside; hull_planes)
    kdop_dirs: np.ndarray       # (G, N_KDOP, 3) the planes' unit normals n in the geom frame (meshes)
    half_thick: np.ndarray      # (G,) half the thinnest extent (see contact/report.geom_half_thickness)
    points: List[np.ndarray]    # per geom: hull sample points in the geom frame (meshes)
    names: List[str]            # "entity 'x', link 'y', <type> geom #k" for messages
    entity_start: List[int] = field(default_factory=list)
    entity_count: List[int] = field(default_factory=list)
    # a box around the collision volume, in the geom frame (mesh_box, primitive_box): centres (G, 3), axes
    # (G, 3, 3; columns), half sizes (G, 3); zeros for planes
    box_center: np.ndarray = None
    box_axes: np.ndarray = None
    box_half: np.ndarray = None

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
    if h is not None and "planes" in h:
        kn, kd = np.asarray(h["planes"][0], dtype=float), np.asarray(h["planes"][1], dtype=float)
    else:
        kn, kd = hull_planes(hv)
    box = h["box"] if h is not None and "box" in h else mesh_box(hv, kn, kd)
    return P, hv, hc, kn, kd, box


def hull_planes(H: np.ndarray, k: int = N_KDOP):
    """(normals (k, 3), offsets (k,)): k half-spaces n . x <= d whose intersection holds the convex hull of
    the points H and fits it: the hull's bounding box (6 planes), then, one at a time, the plane of the
    hull's face that the intersection's corner farthest outside the hull lies farthest beyond (a cutting
    plane), until k planes or the intersection is the hull (to 1e-9 of its size); unused entries repeat
    the first plane. With the fixed k-DOP directions (KDOP_DIRS) before 2026-11-29, a Panda finger's mesh
    (Genesis's MJCF) reached ~5 mm past its hull at the pads, and the soft cube of Genesis's
    grasp_soft_cube met the finger's volume where Genesis's met the pads. Falls back to the fixed k-DOP
    where qhull cannot build the hull or the intersection."""
    H = np.asarray(H, dtype=float).reshape(-1, 3)
    lo, hi = H.min(0), H.max(0)
    size = float((hi - lo).max())
    eye = np.eye(3)
    N = [*eye, *(-eye)]
    D = [*hi, *(-lo)]
    try:
        from scipy.spatial import ConvexHull, HalfspaceIntersection

        eq = ConvexHull(H).equations  # n . x + b <= 0 inside, n unit
        fn, fd = eq[:, :3], -eq[:, 3]
        # one plane per face (qhull splits a face into triangles): merge equal planes
        _, first = np.unique(np.round(np.c_[fn, fd / max(size, 1e-12)] * 1e7), axis=0, return_index=True)
        fn, fd = fn[np.sort(first)], fd[np.sort(first)]
        inner = H.mean(0)
        while len(N) < k:
            corners = HalfspaceIntersection(np.c_[np.array(N), -np.array(D)], inner).intersections
            beyond = corners @ fn.T - fd  # (corners, faces): how far each corner is beyond each face plane
            worst = beyond.max(1)
            i = int(np.argmax(worst))
            if worst[i] <= 1e-9 * size:
                break
            j = int(np.argmax(beyond[i]))
            N.append(fn[j])
            D.append(fd[j])
    except Exception:  # qhull: a degenerate hull or intersection; the fixed directions always bound it
        N, D = list(KDOP_DIRS), list((H @ KDOP_DIRS.T).max(0))
    N, D = np.array(N[:k], dtype=float), np.array(D[:k], dtype=float)
    pad = k - len(N)
    return np.r_[N, np.repeat(N[:1], pad, 0)], np.r_[D, np.repeat(D[:1], pad)]


def _polytope_corners(kn: np.ndarray, kd: np.ndarray) -> np.ndarray:
    """The corners of the bounded intersection of the half-spaces n . x <= d (a mesh's collision volume,
    hull_planes): the points where three planes meet that no plane cuts off (every triple solved at once;
    numpy alone: scipy's import is 0.3 s of a build that needs none of it)."""
    planes = np.unique(np.c_[kn, kd], axis=0)  # (hull_planes repeats its first plane in unused entries)
    N, D = planes[:, :3], planes[:, 3]
    i, j, k = np.array(list(itertools.combinations(range(len(N)), 3))).T
    A = np.stack([N[i], N[j], N[k]], 1)
    ok = np.abs(np.linalg.det(A)) > 1e-9
    X = np.linalg.solve(A[ok], np.stack([D[i], D[j], D[k]], 1)[ok][..., None])[..., 0]
    tol = 1e-9 * max(float(np.abs(X).max()), 1e-9)
    return X[(X @ N.T - D <= tol).all(1)]


def polytope_hull(kn: np.ndarray, kd: np.ndarray):
    """(planes (P, 4): n, d; corners (V, 3); edges (E, 4, 3): the two ends and the unit normals of the two
    faces that meet there; the indices of those two faces' planes (E, 2)) of the bounded intersection of the half-spaces n . x <= d: a mesh's collision
    volume (hull_planes) or a box's. An edge is where the line of two planes runs inside every other plane
    for a length (clipped in one pass over the plane pairs: no hull of the corners, which qhull would
    simplify where planes meet at small angles, up to 0.3 mm on example-robot-data's Panda finger); where
    more than two planes share a line, one of them is kept. The corners are the edges' ends."""
    planes = np.unique(np.c_[kn, kd], axis=0)
    N, D = planes[:, :3], planes[:, 3]
    size = max(float(np.abs(D).max()), 1e-9)
    tol = 1e-9 * size
    edges, faces = [], []
    for i, j in itertools.combinations(range(len(N)), 2):
        u = np.cross(N[i], N[j])
        if np.linalg.norm(u) < 1e-9:
            continue
        u /= np.linalg.norm(u)
        x0 = np.linalg.solve(np.stack([N[i], N[j], u]), np.array([D[i], D[j], 0.0]))
        a, b = N @ u, D - N @ x0  # the line x0 + t u inside plane k: a_k t <= b_k
        a[[i, j]], b[[i, j]] = 0.0, 0.0
        if (b[np.abs(a) <= 1e-12] < -tol).any():
            continue
        up, dn = a > 1e-12, a < -1e-12
        t1 = (b[up] / a[up]).min() if up.any() else np.inf
        t0 = (b[dn] / a[dn]).max() if dn.any() else -np.inf
        if not (np.isfinite(t0) and np.isfinite(t1)) or t1 - t0 <= tol:
            continue
        e = np.stack([x0 + t0 * u, x0 + t1 * u, N[i], N[j]])
        if not any(max(np.abs(f[:2] - e[:2]).max(), np.abs(f[:2] - e[1::-1]).max()) <= tol * 10 for f in edges):
            edges.append(e)
            faces.append((i, j))
    E = np.array(edges).reshape(-1, 4, 3)
    C = []
    for x in E[:, :2].reshape(-1, 3):
        if not any(np.linalg.norm(x - c) <= 10 * tol for c in C):
            C.append(x)
    return planes, np.array(C).reshape(-1, 3), E, np.array(faces, dtype=np.int32).reshape(-1, 2)


def sdf_distance_ratio(planes: np.ndarray, corners: np.ndarray, edges: np.ndarray) -> float:
    """kappa of a convex volume (polytope_hull's planes, corners and edges): its SDF outside, the largest plane
    distance (sdf.func_sdf_kdop), is at least kappa times a point's distance to the volume. A point p whose
    nearest point of the volume is q lies along u = (p - q) / |p - q| in q's normal cone, and its largest
    plane distance is at least |p - q| times the largest n . u over the planes through q: 1 on a face, at
    least cos(half the turn) across an edge, and at a corner the least over the corner's cone of the largest
    n . u of its planes (_cone_least_max). A box's is 1 / sqrt(3). Lets the broad phase part two meshes whose
    distance one side's face plane bounds while no plane of the other side parts the first's corners
    (narrow.func_gap_mesh_planes): their points lie at least kappa times that distance outside."""
    N, D = planes[:, :3], planes[:, 3]
    tol = 1e-6 * max(float(np.abs(D).max()), 1e-9)  # planes within this of a corner count as through it
    kappa = _half_turn_cos(edges[:, 2], edges[:, 3]) if len(edges) else 1.0
    through = np.abs(corners @ N.T - D) <= tol  # (corners, planes)
    for m in np.unique(through.sum(1)):  # the corners with m planes, at once
        A = np.stack([N[row] for row in through[through.sum(1) == m]])
        kappa = min(kappa, _cone_least_max(A))
    return min(kappa, 1.0)


def _half_turn_cos(n1: np.ndarray, n2: np.ndarray) -> float:
    """The least over rows of cos(half the angle between n1 and n2) (unit normals (k, 3)): the least of max(n1 u,
    n2 u) over unit u between them."""
    return float(np.sqrt(np.clip(0.5 * (1.0 + np.einsum("ek,ek->e", n1, n2)), 0.0, 1.0)).min())


def _cone_least_max(A: np.ndarray) -> float:
    """The least over cones c and unit u in the cone of the rows of A[c] (a corner's m plane normals; A is (C, m,
    3)) of max(A[c] u). The least of a largest of linear functions over a spherical polygon lies where three of
    them are equal, or on a side of the polygon where two are, or at a generator (a linear function has no
    minimum inside a region of the sphere, nor along a circle where two are equal: its stationary point there
    is a maximum): those candidates, kept where inside the cone (every side's plane, by a small tolerance that
    errs towards keeping; a pair of generators that is no side constrains nothing), and the least of max(A u)
    over them."""
    C, m, _ = A.shape
    if m < 3:  # (a corner has three planes or more; an edge's two: its half turn)
        return 1.0 if m < 2 else _half_turn_cos(A[:, 0], A[:, 1])
    unit = lambda x: x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-300)
    cands, sides = [A], []
    pairs = list(itertools.combinations(range(m), 2))
    for a, b in pairs:
        w = np.cross(A[:, a], A[:, b])
        ok = np.linalg.norm(w, axis=1) > 1e-12
        w = unit(w)
        s = np.einsum("cmk,ck->cm", A, w)
        pos, neg = (s >= -1e-9).all(1), (s <= 1e-9).all(1)
        sides.append(np.where((ok & (pos | neg))[:, None], np.where(pos[:, None], w, -w), 0.0))
        for i, j in pairs:  # where A[i] u = A[j] u along that side's circle
            d = unit(np.cross(w, A[:, i] - A[:, j]))
            cands += [d[:, None], -d[:, None]]
    for tri in itertools.combinations(range(m), 3):
        M = A[:, list(tri)]
        ok = np.abs(np.linalg.det(M)) > 1e-12
        u = np.linalg.solve(np.where(ok[:, None, None], M, np.eye(3)), np.ones((C, 3, 1)))[..., 0]
        cands.append(np.where(ok[:, None], unit(u), A[:, :1][:, 0])[:, None])
    U = np.concatenate(cands, 1)  # (C, candidates, 3)
    S = np.stack(sides, 1)  # (C, sides, 3)
    inside = (np.einsum("cuk,csk->cus", U, S) >= -1e-7).all(2)
    f = np.einsum("cuk,cmk->cum", U, A).max(2)
    return float(np.where(inside, f, np.inf).min())


def geom_hull(geoms: "GeomTable", g: int):
    """polytope_hull of geom g, a mesh (its planes) or a box (its six faces), in the geom frame."""
    if geoms.type[g] == GEOM_BOX:
        h = geoms.size[g]
        return polytope_hull(np.r_[np.eye(3), -np.eye(3)], np.r_[h, h])
    return polytope_hull(geoms.kdop_dirs[g], geoms.kdop[g])


def hull_edge_pair(ta: int, tb: int) -> bool:
    """Whether a pair of these geom types gets a hull-edge slot: two meshes, or a mesh and a box (two boxes
    have the box pair's own edge and face slots)."""
    return GEOM_MESH in (ta, tb) and ta in (GEOM_MESH, GEOM_BOX) and tb in (GEOM_MESH, GEOM_BOX)


def mesh_box(H: np.ndarray, kn: np.ndarray, kd: np.ndarray):
    """(centre, axes (columns), half sizes) of a box around a mesh's collision volume, the intersection of
    its planes (hull_planes), in the mesh's frame: along the principal axes of its hull points H or the
    frame's own, whichever box is smaller. The volume reaches up to centimetres past the hull at its corners,
    which the box holds (the SDF the other side's points meet is the planes')."""
    V = _polytope_corners(kn, kd)
    _, _, Vt = np.linalg.svd(H - H.mean(0), full_matrices=False)
    best = None
    for axes in (Vt.T, np.eye(3)):
        loc = V @ axes
        lo, hi = loc.min(0), loc.max(0)
        vol = float(np.prod(hi - lo))
        if best is None or vol < best[0]:
            best = (vol, axes, lo, hi)
    _, axes, lo, hi = best
    pad = 1e-6 * float((hi - lo).max())  # rounding: the corners lie inside in any precision
    return axes @ ((lo + hi) / 2), axes, (hi - lo) / 2 + pad


def primitive_box(t: int, sz: np.ndarray):
    """(centre, axes, half sizes) of the box around a sphere, box, capsule or cylinder (zeros for a plane)."""
    half = {GEOM_SPHERE: (sz[0],) * 3, GEOM_BOX: tuple(sz), GEOM_CAPSULE: (sz[0], sz[0], sz[1] + sz[0]),
            GEOM_CYLINDER: (sz[0], sz[0], sz[1])}.get(t, (0.0, 0.0, 0.0))
    return np.zeros(3), np.eye(3), np.asarray(half, dtype=float)


def geom_box_columns(geoms: GeomTable):
    """The geoms' boxes (narrow.func_gap_obbs) as columns of the contact solver's per-geom table: centres
    (G, 3), axes (G, 9, row-major), half sizes (G, 3)."""
    return geoms.box_center, geoms.box_axes.reshape(geoms.n, 9), geoms.box_half


def link_is_dynamic(flat) -> np.ndarray:  # flat: the scene's flatten.FlatModel
    """(L,) bool: the link moves with some dof (it or an ancestor has a joint with dofs)."""
    L = flat.n_links
    dyn = np.zeros(L, dtype=bool)
    for i in range(L):
        p = flat.np_link_parent[i]
        dyn[i] = flat.np_link_ndof[i] > 0 or (p >= 0 and dyn[p])
    return dyn


def build_geoms(models, max_mesh_points: int) -> GeomTable:
    types, link, ent, pos, quat, size, fric, center, rb, beta, kdop, kdirs, thick, pts, names, boxes = (
        [] for _ in range(16))
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
                kd, kn, t = np.zeros(N_KDOP), np.zeros((N_KDOP, 3)), np.nan  # planes, half thickness: meshes
                box = primitive_box(GEOM_CODE[g.type], sz)
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
                    P, H, c, kn, kd, box = _mesh_hull_points(g, what, max_mesh_points)
                    # the planes fit the full hull; contacts use the reduced point set
                    # the bounding radius of the collision volume (the planes' intersection reaches past the
                    # hull at its corners: the hull-edge and hull-face slots lie on it)
                    r = float(np.sqrt(((np.r_[H, _polytope_corners(kn, kd)] - c) ** 2).sum(1).max()))
                    b = 0.25 * float(np.ptp(H, 0).min())
                    # half the thinnest width across the planes' normals
                    t = 0.5 * float((kd + (-(H @ kn.T)).max(0)).min())
                types.append(GEOM_CODE[g.type]); link.append(nl + i_l); ent.append(i_e)
                pos.append(np.asarray(g.pos, dtype=float)); quat.append(np.asarray(g.quat, dtype=float))
                size.append(sz); fric.append(mu); center.append(c); rb.append(r); beta.append(b)
                kdop.append(kd); kdirs.append(kn); pts.append(P); names.append(what)
                thick.append(t); boxes.append(box)
        counts.append(len(types) - starts[-1])
        nl += m.n_links
    G = len(types)
    arr = lambda x, shape: np.array(x, dtype=float).reshape(shape)  # noqa: E731
    return GeomTable(np.array(types, dtype=np.int32).reshape(G), np.array(link, dtype=np.int32).reshape(G),
                     np.array(ent, dtype=np.int32).reshape(G), arr(pos, (G, 3)), arr(quat, (G, 4)),
                     arr(size, (G, 3)), arr(fric, (G,)), arr(center, (G, 3)), arr(rb, (G,)), arr(beta, (G,)),
                     arr(kdop, (G, N_KDOP)), arr(kdirs, (G, N_KDOP, 3)), arr(thick, (G,)), pts, names, starts,
                     counts, arr([b[0] for b in boxes], (G, 3)), arr([b[1] for b in boxes], (G, 3, 3)),
                     arr([b[2] for b in boxes], (G, 3)))


def link_roots(flat) -> np.ndarray:
    """(L,) each link's root: the first link of its kinematic tree, the one its chain of parents ends at
    (attached to the world by a free or a fixed joint). Links of one root are one body's parts (Genesis's
    self-collision); an entity can hold several trees (an MJCF's free bodies, its worldbody's floor)."""
    parent = flat.np_link_parent
    root = np.arange(flat.n_links)
    for i in range(flat.n_links):  # parents come before their children
        if parent[i] >= 0:
            root[i] = root[parent[i]]
    return root


def links_adjacent(flat, la: int, lb: int) -> bool:
    """Genesis's adjacency (collider.py, v0.4.5): one link is the other's parent, directly or through links
    attached by fixed joints (a kept link such as a Panda's hand counts as part of its parent here)."""
    parent, jtype = flat.np_link_parent, flat.np_link_jtype
    a, b = min(la, lb), max(la, lb)
    while parent[b] >= 0:
        if parent[b] == a:
            return True
        if jtype[b] != JOINT_FIXED:
            return False
        b = parent[b]
    return False


NEUTRAL_CELLS = 24  # grid cells along a geom's longest side in the zero-configuration overlap test


def neutral_link_poses(flat):
    """(R (L, 3, 3), p (L, 3)): every link's pose with all joints at zero (a free joint at the model's pose),
    each tree in the frame of its root: what the zero-configuration overlap test compares."""
    L = flat.n_links
    Rj = geom_rotations(flat.np_link_jquat.reshape(L, 4))
    R, p = np.zeros((L, 3, 3)), np.zeros((L, 3))
    for i in range(L):  # parents come before their children
        q = flat.np_link_parent[i]
        if q >= 0:
            R[i], p[i] = R[q] @ Rj[i], p[q] + R[q] @ flat.np_link_jpos[i]
        else:
            R[i], p[i] = Rj[i], flat.np_link_jpos[i]
    return R, p


def geom_sdf(geoms: GeomTable, g: int, x: np.ndarray) -> np.ndarray:
    """(N,) the signed distance of geom g's solid at points x (N, 3) of its own frame (meshes: its hull's
    planes, as the contacts see it; negative inside). Planes: +inf (they take no part in the overlap test)."""
    t, sz = geoms.type[g], geoms.size[g]
    if t == GEOM_SPHERE:
        return np.linalg.norm(x, axis=1) - sz[0]
    if t == GEOM_CAPSULE:
        c = np.zeros_like(x)
        c[:, 2] = np.clip(x[:, 2], -sz[1], sz[1])
        return np.linalg.norm(x - c, axis=1) - sz[0]
    if t == GEOM_BOX or t == GEOM_CYLINDER:
        d = (np.abs(x) - sz if t == GEOM_BOX else
             np.stack([np.linalg.norm(x[:, :2], axis=1) - sz[0], np.abs(x[:, 2]) - sz[1]], 1))
        return np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(1), 0.0)
    if t == GEOM_MESH:
        return (x @ geoms.kdop_dirs[g].T - geoms.kdop[g]).max(1)
    return np.full(len(x), np.inf)


def _geom_cells(geoms: GeomTable, g: int):
    """(centres (N, 3) in the geom frame, cell size): the cells of a grid over geom g's bounding box (about
    NEUTRAL_CELLS along its longest side) that its solid reaches, as a voxelisation marks them."""
    t, sz = geoms.type[g], geoms.size[g]
    if t == GEOM_PLANE:
        return np.zeros((0, 3)), 0.0
    if t == GEOM_MESH:
        lo, hi = geoms.points[g].min(0), geoms.points[g].max(0)
    else:
        half = {GEOM_SPHERE: [sz[0]] * 3, GEOM_BOX: sz, GEOM_CAPSULE: [sz[0], sz[0], sz[0] + sz[1]],
                GEOM_CYLINDER: [sz[0], sz[0], sz[1]]}[t]
        lo, hi = -np.asarray(half, dtype=float), np.asarray(half, dtype=float)
    h = float((hi - lo).max()) / NEUTRAL_CELLS
    axes = [np.arange(a + 0.5 * h, b, h) if b - a > h else np.array([0.5 * (a + b)]) for a, b in zip(lo, hi)]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return x[geom_sdf(geoms, g, x) <= 0.5 * np.sqrt(3.0) * h], h


def neutral_overlaps(geoms: GeomTable, flat, pairs):
    """The pairs among `pairs` (geoms of one tree) whose solids overlap or touch with every joint at zero:
    Genesis leaves such pairs out of self-collision (collider.py, v0.4.5: its geoms voxelised at qpos0), since
    a robot's collision shapes often interpenetrate where its parts meet. Two geoms overlap here when a cell
    that one's solid reaches lies within half a cell's diagonal of the other's (the voxels of both meet)."""
    if not pairs:
        return set()
    R, p = neutral_link_poses(flat)
    Rg = geom_rotations(geoms.quat)
    # each geom's pose in its tree's zero configuration
    gR = np.einsum("gij,gjk->gik", R[geoms.link], Rg)
    gp = p[geoms.link] + np.einsum("gij,gj->gi", R[geoms.link], geoms.pos)
    cells = {}
    out = set()
    for a, b in pairs:
        for u, v in ((a, b), (b, a)):
            if u not in cells:
                cells[u] = _geom_cells(geoms, u)
            x, h = cells[u]
            if len(x) == 0:
                continue
            # u's cells in v's frame
            xv = ((x @ gR[u].T + gp[u]) - gp[v]) @ gR[v]
            if (geom_sdf(geoms, v, xv) <= 0.5 * np.sqrt(3.0) * h).any():
                out.add((a, b))
                break
    return out


def candidate_pairs(geoms: GeomTable, flat, self_collision: bool, ignore_unsupported: bool, no_contact=(),
                    adjacent_collision: bool = False, neutral_collision: bool = False):
    """[(ga, gb)] of geoms that may touch (see the module docstring for the rules); none of the entities
    whose indices are in `no_contact` (gs.materials.Tool's: they act on MPM material only). Geoms of one tree
    (self-collision) only with `self_collision`, and then not on adjacent links unless `adjacent_collision`,
    nor those that overlap with every joint at zero unless `neutral_collision` (Genesis's three options)."""
    dyn = link_is_dynamic(flat)
    root = link_roots(flat)
    pairs, bad, own = [], [], []
    for a in range(geoms.n):
        for b in range(a + 1, geoms.n):
            la, lb = geoms.link[a], geoms.link[b]
            if la == lb or not (dyn[la] or dyn[lb]) or geoms.entity[a] in no_contact or geoms.entity[b] in no_contact:
                continue
            same_tree = root[la] == root[lb]
            if same_tree and (not self_collision or (not adjacent_collision and links_adjacent(flat, la, lb))):
                continue
            ta, tb = geoms.type[a], geoms.type[b]
            if ta == GEOM_PLANE and tb == GEOM_PLANE:
                continue
            moving_plane = (ta == GEOM_PLANE and dyn[la]) or (tb == GEOM_PLANE and dyn[lb])
            if moving_plane:
                bad.append((a, b, "a plane on a moving link"))
                continue
            # a plane is always the second geom of its pair (the broad phase tests the first against it)
            pairs.append((b, a) if ta == GEOM_PLANE else (a, b))
            if same_tree:
                own.append(pairs[-1])
    if own and not neutral_collision:
        drop = neutral_overlaps(geoms, flat, own)
        pairs = [x for x in pairs if x not in drop]
    if bad and not ignore_unsupported:
        a, b, why = bad[0]
        more = f" (and {len(bad) - 1} more such pairs)" if len(bad) > 1 else ""
        raise ContactBuildError(
            f"unsupported collision pair ({why}): {geoms.names[a]} and {geoms.names[b]}{more}. A plane must be "
            "static (the ground, or a body fixed to the world); use a thin box on a moving link, or pass "
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
            if hull_edge_pair(ta, tb):
                # (the broad phase's separating-axis test of the two volumes chooses the edge pair and whether
                # it holds the contact: narrow.func_hull_pair_test)
                slots.append((i_p, SLOT_HULLEDGE, a, b, np.zeros(3), 0.0, 0.0))
                for m in range(N_HULLFACE):
                    slots.append((i_p, SLOT_HULLFACE, a, b, np.zeros(3), 0.0, float(m)))
            if ta == GEOM_BOX and tb == GEOM_BOX:
                # (the pair's separating-axis test decides which of its edge and face slots hold the contact:
                # narrow.func_box_pair_test)
                slots.append((i_p, SLOT_BOXEDGE, a, b, np.zeros(3), 0.0, 0.0))
                # face on face: which box holds the reference face is decided at run time; (a, b) only
                # fixes the convention of the slot's normal (from b towards a) and force (on a)
                for code in range(N_BOXFACE):
                    slots.append((i_p, SLOT_BOXFACE, a, b, np.zeros(3), 0.0, float(code)))
        for pa, pb, plane in jobs:
            for kind, p, r, aux in sample_points(geoms, pa, plane):
                slots.append((i_p, kind, pa, pb, p, r, aux))
    return slots


def geom_rotations(quat: np.ndarray) -> np.ndarray:
    w, x, y, z = quat.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)
