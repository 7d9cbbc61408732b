"""A collision mesh collides as its convex hull: the SDF's planes (solvers/rigid/collision/geoms.py,
hull_planes) hold the hull and fit it, and a body resting on a slanted face of a mesh rests on the face.

The fit is measured here independently of the code's choices: qhull (scipy) gives the hull's faces, the
corners of the planes' intersection are computed with scipy's HalfspaceIntersection, and the distance
of a corner outside the hull is its largest distance beyond a face plane."""
import itertools
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull, HalfspaceIntersection

import genesis_lite as gs
from solvers.rigid.collision.geoms import KDOP_DIRS, N_KDOP, hull_planes


def _outside(H, normals, offsets):
    """How far the planes' intersection reaches outside the hull of H (m), and how far a hull vertex lies
    outside the intersection (m; 0 when the intersection holds the hull)."""
    eq = ConvexHull(H).equations
    corners = HalfspaceIntersection(np.c_[normals, -offsets], H.mean(0)).intersections
    return float((corners @ eq[:, :3].T + eq[:, 3]).max()), float((H @ normals.T - offsets).max())


def test_the_planes_hold_every_panda_mesh_and_fit_it(robots_dir):
    """Every collision mesh of example-robot-data's Panda: the 26 planes hold the hull (to rounding) and
    reach at most 5 % of the mesh's size outside it, at most 0.6 of the fixed directions' k-DOP's reach; the
    finger (a polytope of 32 faces) within 1 %. Measured 2026-11-29: 0.2-4.6 % of the size with the planes
    (finger 0.1 mm, the rounded links up to 8.5 mm), 8-18 % with the fixed directions (finger 7.9 mm)."""
    files = sorted((robots_dir / "panda_description" / "meshes" / "collision").glob("*.stl"))
    assert len(files) >= 9
    for f in files:
        H = np.asarray(trimesh.load(f, force="mesh").convex_hull.vertices, dtype=float)
        size = float(np.ptp(H, 0).max())
        normals, offsets = hull_planes(H)
        assert normals.shape == (N_KDOP, 3) and offsets.shape == (N_KDOP,)
        assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)
        out, miss = _outside(H, normals, offsets)
        old, _ = _outside(H, KDOP_DIRS, (H @ KDOP_DIRS.T).max(0))
        assert miss < 1e-9 * size, (f.name, miss)
        assert out < 0.05 * size and out < 0.6 * old, (f.name, out / size, old / size)
        if f.name == "finger.stl":
            assert out < 0.01 * size, out


def test_a_polytope_of_few_faces_is_exact():
    """A wedge (a triangular prism, 5 faces) and a tilted box: their planes are their faces exactly."""
    wedge = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0.4], [0, 1, 0], [1, 1, 0], [0, 1, 0.4]], dtype=float)
    R = trimesh.transformations.euler_matrix(0.3, -0.5, 0.9)[:3, :3]
    box = trimesh.creation.box(extents=(0.3, 0.2, 0.1)).vertices @ R.T
    for H in (wedge, box):
        out, miss = _outside(H, *hull_planes(H))
        assert out < 1e-12 and miss < 1e-12, (out, miss)


@pytest.mark.parametrize("deg", [20.0, 30.0])
def test_a_box_rests_on_the_slanted_face_of_a_mesh(tmp_path, deg):
    """A fixed wedge mesh whose top face slopes at 20 or 30 degrees (no direction of the fixed k-DOP: its
    diagonals are at 45), a 4 x 4 x 4 cm box set flat on that face (friction 1 > tan(deg): it stays): after
    1 s it rests on the face, its centre half its height from the face's plane within 0.5 mm, and still.
    With the fixed directions the wedge's collision volume reached ~1 cm above the slope's middle: the box,
    set there, was thrown off (measured 2026-11-29 at 20 degrees: 0.19 m up, then through the wedge)."""
    t = np.tan(np.radians(deg))
    L, W = 0.4, 0.3
    V = np.array([[0, 0, 0], [L, 0, 0], [0, 0, L * t], [0, W, 0], [L, W, 0], [0, W, L * t]], dtype=float)
    path = str(tmp_path / "wedge.obj")
    trimesh.convex.convex_hull(V).export(path)
    a = 0.02
    n = np.array([np.sin(np.radians(deg)), 0.0, np.cos(np.radians(deg))])  # the slope's outward normal
    foot = np.array([L / 2, W / 2, (L / 2) * t])  # the middle of the slope, on it
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.005))
    scene.add_entity(gs.morphs.Mesh(file=path, fixed=True, align=False), material=gs.materials.Rigid(friction=1.0))
    box = scene.add_entity(gs.morphs.Box(size=(2 * a,) * 3, pos=tuple(foot + (a + 1e-4) * n), euler=(0.0, deg, 0.0)),
                           material=gs.materials.Rigid(friction=1.0))
    scene.build()
    for _ in range(200):
        scene.step()
    p = box.get_pos().numpy().reshape(-1).astype(float)
    height = float((p - foot) @ n)  # the centre's distance from the slope's plane
    assert abs(height - a) < 5e-4, (height, a)
    assert np.abs(box.get_vel().numpy()).max() < 1e-3 and np.abs(box.get_ang().numpy()).max() < 1e-2


def test_the_volume_s_corners_and_edges_close_it(robots_dir):
    """collision.polytope_hull's corners and edges (what the hull-edge slots test), for every collision mesh of
    example-robot-data's Panda and a tilted box: its corners are the planes' intersection's (scipy's
    HalfspaceIntersection, within 1e-4 of the size: qhull merges corners a fraction of a micrometre apart),
    each edge's two ends lie on the planes of both its faces, and corners, edges and faces close a convex
    polyhedron (Euler: V - E + F = 2)."""
    from solvers.rigid.collision.geoms import polytope_hull

    R = trimesh.transformations.euler_matrix(0.3, -0.5, 0.9)[:3, :3]
    clouds = [trimesh.creation.box(extents=(0.3, 0.2, 0.1)).vertices @ R.T]
    files = sorted((robots_dir / "panda_description" / "meshes" / "collision").glob("*.stl"))
    assert len(files) >= 9
    clouds += [np.asarray(trimesh.load(f, force="mesh").convex_hull.vertices, dtype=float) for f in files]
    for H in clouds:
        kn, kd = hull_planes(H)
        planes, C, E, EF = polytope_hull(kn, kd)
        assert np.allclose(planes[EF[:, 0], :3], E[:, 2]) and np.allclose(planes[EF[:, 1], :3], E[:, 3])
        X = HalfspaceIntersection(np.c_[kn, -kd], H.mean(0)).intersections
        size = float(np.ptp(X, 0).max())
        gap = np.linalg.norm(C[:, None] - X[None], axis=2)
        assert gap.min(1).max() < 1e-4 * size and gap.min(0).max() < 1e-4 * size
        faces = set()
        for p0, p1, n1, n2 in E:
            assert n1 @ n2 < 1.0 - 1e-9
            for n in (n1, n2):
                k = int(np.argmax(kn @ n))
                assert kn[k] @ n > 1.0 - 1e-9
                assert abs(p0 @ kn[k] - kd[k]) < 1e-9 * size and abs(p1 @ kn[k] - kd[k]) < 1e-9 * size
                faces.add(k)  # (argmax: the first of equal planes; hull_planes repeats one in unused entries)
        assert len(C) - len(E) + len(faces) == 2, (len(C), len(E), len(faces))


def test_a_volume_s_sdf_outside_is_at_least_kappa_times_the_distance(robots_dir):
    """collision.sdf_distance_ratio (kappa; the broad phase parts two meshes by it where one side's planes
    bound their distance and the other's do not): outside a convex volume its SDF, the largest plane
    distance, is at least kappa times the distance to the volume, and no larger bound holds. Checked without
    the code's own corners or candidates: at every corner of the planes' intersection (scipy) and the middle
    of every edge, points along 9,000 random directions of the normal cone there (positive combinations of
    the normals of the planes through it, Dirichlet weights) and 501 along the arc of each pair of them (the
    cone's sides), whose nearest point of the volume is that corner or middle (so their distance is known);
    and 300 random points around the volume, their distance by a QP (SLSQP). The least ratio over them is >=
    kappa and within 2 % of it (sampling approaches the least from above). A box's is 1 / sqrt(3) (its
    corner's diagonal). Measured 2026-12-04: example-robot-data's Panda's volumes 0.57-0.68 (Genesis's MJCF
    Panda's 0.50-0.69)."""
    from scipy.optimize import minimize
    from solvers.rigid.collision.geoms import polytope_hull, sdf_distance_ratio

    rng = np.random.default_rng(3)
    R = trimesh.transformations.euler_matrix(0.3, -0.5, 0.9)[:3, :3]
    clouds = [trimesh.creation.box(extents=(0.3, 0.2, 0.1)).vertices @ R.T]
    files = sorted((robots_dir / "panda_description" / "meshes" / "collision").glob("*.stl"))
    assert len(files) >= 9
    clouds += [np.asarray(trimesh.load(f, force="mesh").convex_hull.vertices, dtype=float) for f in files]
    kappas = []
    for i, H in enumerate(clouds):
        kn, kd = hull_planes(H)
        planes, C, E, _ = polytope_hull(kn, kd)
        kappa = sdf_distance_ratio(planes, C, E)
        U = np.unique(np.c_[kn, kd], axis=0)  # hull_planes' planes, each once
        N, D = U[:, :3], U[:, 3]
        X = HalfspaceIntersection(np.c_[N, -D], H.mean(0)).intersections
        size = float(np.ptp(X, 0).max())
        least = np.inf
        # the corners, and the middles of the edges (two corners on two common planes, their middle on no other)
        r, c = np.triu_indices(len(X), 1)
        M = (X[r] + X[c]) / 2
        on = ((np.abs(M @ N.T - D) < 1e-7 * size).sum(1) == 2) & ((M @ N.T - D).max(1) < 1e-7 * size)
        for v in np.r_[X, M[on]]:
            A = N[np.abs(N @ v - D) < 1e-7 * size]
            w = [rng.dirichlet(np.full(len(A), a), 3_000) for a in (0.3, 1.0, 3.0)]
            for a, b in itertools.combinations(range(len(A)), 2):  # and along each pair's arc (the sides)
                t = np.linspace(0.0, 1.0, 501)[:, None]
                w.append(t * np.eye(len(A))[a] + (1 - t) * np.eye(len(A))[b])
            u = np.concatenate(w) @ A
            u /= np.linalg.norm(u, axis=1, keepdims=True)
            p = v + 1e-3 * size * u
            least = min(least, float(((p @ N.T - D).max(1) / (1e-3 * size)).min()))
        for _ in range(300):
            p = X.mean(0) + rng.normal(size=3) * size
            sdf = float((N @ p - D).max())
            if sdf <= 1e-3 * size:
                continue
            res = minimize(lambda x: ((x - p) ** 2).sum(), X.mean(0), jac=lambda x: 2 * (x - p), method="SLSQP",
                           constraints=[{"type": "ineq", "fun": lambda x: D - N @ x, "jac": lambda x: -N}],
                           options={"ftol": 1e-14, "maxiter": 500})
            assert res.success and (N @ res.x - D).max() < 1e-9 * size
            least = min(least, sdf / float(np.linalg.norm(res.x - p)))
        assert kappa <= least + 1e-9 and least < 1.02 * kappa, (i, kappa, least)
        if i == 0:
            assert abs(kappa - 1 / np.sqrt(3)) < 1e-12
        kappas.append(kappa)
    assert 0.5 < min(kappas[1:]) and max(kappas[1:]) < 0.75, kappas


PLANK = str(Path(__file__).resolve().parents[1] / "assets" / "meshes" / "plank.obj")  # 0.6 x 0.08 x 0.08 m
RIDGE = 0.04 * np.sqrt(2.0)  # a plank turned 45 degrees about its length: its ridge's height over its centre


def _quat(yaw_deg, roll_deg):
    """A plank's turn: roll_deg about its length (x; 45: a ridge up and one down), then yaw_deg about z."""
    half, r = np.radians(yaw_deg) / 2, np.radians(roll_deg) / 2
    w1, x1, y1, z1 = np.cos(half), 0.0, 0.0, np.sin(half)
    w2, x2, y2, z2 = np.cos(r), np.sin(r), 0.0, 0.0
    return (w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2)


def _raft(tmp_path, mesh, z, yaw_deg, roll_deg):
    """One free body of two such planks side by side (MJCF), their lengths at yaw_deg, 0.3 m apart."""
    geom = ('type="mesh" mesh="plank"' if mesh else 'type="box" size="0.3 0.04 0.04"') + ' quat="{} {} {} {}"'
    q = _quat(yaw_deg, roll_deg)
    side = 0.15 * np.array([np.sin(np.radians(yaw_deg)), -np.cos(np.radians(yaw_deg))])
    geoms = "".join(f'<geom {geom.format(*q)} pos="{sx * side[0]} {sx * side[1]} 0"/>' for sx in (-1, 1))
    xml = (f'<mujoco><asset><mesh name="plank" file="{PLANK}"/></asset><worldbody>'
           f'<body name="raft" pos="0 0 {z}"><freejoint/>{geoms}</body></worldbody></mujoco>')
    path = tmp_path / f"raft_{int(mesh)}.xml"
    path.write_text(xml)
    return gs.morphs.MJCF(file=str(path))


@pytest.mark.parametrize("lay", ["ridge", "flat"])
@pytest.mark.parametrize("lower, upper", [("mesh", "mesh"), ("box", "mesh"), ("mesh", "box")])
def test_crossed_planks_rest_on_each_other(tmp_path, lower, upper, lay):
    """Planks (0.6 x 0.08 x 0.08 m), two fixed side by side, and across them at 70 degrees a free body of two
    more (MJCF), dropped 2 mm onto them: turned 45 degrees about their lengths (ridge up and ridge down) they
    touch only where ridges (edges) cross, four points; lying flat, only where the edges of one's bottom face
    cross the rim of the other's top face, sixteen points. No corner of either lies inside the other. The free
    body comes to rest two ridge heights (0.0566 m each) or two half thicknesses over the fixed planks'
    centres, within 0.5 mm, and still. Before the hull-edge and hull-face slots (collision.narrow.
    func_hull_pair_test) a mesh met a mesh or a box only at its hull points and the other's planes: the free
    body fell through (-4.6 m after 1 s, measured 2026-12-03)."""
    z0, roll = 0.2, (45.0 if lay == "ridge" else 0.0)
    rise = 2 * RIDGE if lay == "ridge" else 0.08
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.005))
    for y in (-0.15, 0.15):
        morph = gs.morphs.Mesh if lower == "mesh" else (lambda **k: gs.morphs.Box(size=(0.6, 0.08, 0.08), **k))
        kw = dict(file=PLANK) if lower == "mesh" else {}
        scene.add_entity(morph(pos=(0.0, y, z0), quat=_quat(0.0, roll), fixed=True, **kw))
    top = scene.add_entity(_raft(tmp_path, upper == "mesh", z0 + rise + 2e-3, 70.0, roll))
    scene.build()
    for _ in range(200):
        scene.step()
    z = float(top.get_pos()[2])
    assert abs(z - (z0 + rise)) < 5e-4, z - (z0 + rise)
    assert float(top.get_vel().abs().max()) < 1e-3 and float(top.get_ang().abs().max()) < 1e-2
