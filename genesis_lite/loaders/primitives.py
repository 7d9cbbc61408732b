"""Loaders for single-body morphs (Box, Sphere, Capsule, Cylinder, Mesh, Plane), plus the small
geometry toolkit (rotations, mass properties, mesh files) that the URDF loader shares.

Every body here is one link whose frame is the shape's own frame: primitives are centred on it
(capsule and cylinder axes along z), a mesh keeps the origin of its file. Mass is
`material.density(robot=False) * volume` (Genesis's 600 kg/m^3 unless rho is given); inertia is about the
centre of mass in the link axes.
"""
from __future__ import annotations

import os
import warnings
from typing import Dict, Optional, Tuple

import numpy as np

from solvers.rigid.collision.geoms import hull_planes, mesh_box
from solvers.rigid.model import EntityModel, GeomDesc, LinkDesc, VisualDesc

from .cache import coacd_parts, note_file

ROOT_JOINT_NAME = "root_joint"  # what Pinocchio calls the free-flyer it adds; entity-scoped


# --------------------------------------------------------------------------------------------
# Rotations (quaternions are w, x, y, z)
# --------------------------------------------------------------------------------------------
def quat_to_mat(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def mat_to_quat(R) -> np.ndarray:
    """Shepperd's method: branch on the largest diagonal term so the division is well conditioned."""
    R = np.asarray(R, dtype=float)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > max(R[0, 0], R[1, 1], R[2, 2]):
        s = 2.0 * np.sqrt(1.0 + tr)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        s = 2.0 * np.sqrt(max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 0.0))
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] >= R[2, 2]:
        s = 2.0 * np.sqrt(max(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 0.0))
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(max(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 0.0))
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    # q and -q are the same rotation; a canonical sign keeps outputs reproducible
    return -q if q[0] < 0 else q


def quat_mul(a, b) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def quat_from_z_to(n) -> np.ndarray:
    """Shortest rotation taking +z onto the unit vector n."""
    n = np.asarray(n, dtype=float)
    n = n / np.linalg.norm(n)
    c = n[2]
    if c < -1.0 + 1e-12:
        return np.array([0.0, 1.0, 0.0, 0.0])  # any half-turn about a horizontal axis
    axis = np.cross([0.0, 0.0, 1.0], n)
    q = np.array([1.0 + c, axis[0], axis[1], axis[2]])
    return q / np.linalg.norm(q)


def pose_matrix(pos, quat) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_mat(quat)
    T[:3, 3] = pos
    return T


# --------------------------------------------------------------------------------------------
# Mass properties: (mass, com, inertia about com) in the shape's frame
# --------------------------------------------------------------------------------------------
def box_inertia(mass, half_extents) -> np.ndarray:
    a, b, c = np.asarray(half_extents, dtype=float)
    return mass / 3.0 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])


def sphere_inertia(mass, radius) -> np.ndarray:
    return 0.4 * mass * radius**2 * np.eye(3)


def cylinder_inertia(mass, radius, height) -> np.ndarray:
    ixx = mass * (3.0 * radius**2 + height**2) / 12.0
    return np.diag([ixx, ixx, 0.5 * mass * radius**2])


def capsule_mass_inertia(rho, radius, height) -> Tuple[float, np.ndarray]:
    """Cylinder of `height` capped by two hemispheres; each cap's COM sits 3r/8 beyond the cylinder end."""
    r, h = radius, height
    m_cyl = rho * np.pi * r * r * h
    m_caps = rho * 4.0 / 3.0 * np.pi * r**3
    izz = 0.5 * m_cyl * r * r + 0.4 * m_caps * r * r
    ixx = m_cyl * (r * r / 4.0 + h * h / 12.0) + m_caps * (0.4 * r * r + h * h / 4.0 + 3.0 * h * r / 8.0)
    return m_cyl + m_caps, np.diag([ixx, ixx, izz])


def solid_mesh_mass_properties(vertices, faces, rho, what: str):
    """Mass properties of a closed mesh; open or inconsistently wound meshes have no well-defined
    volume, so their convex hull stands in."""
    import trimesh

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    if not mesh.is_volume:
        mesh = convex_hull(vertices, what)
    mesh.density = float(rho)
    return float(mesh.mass), np.array(mesh.center_mass, dtype=float), np.array(mesh.moment_inertia, dtype=float)


def convex_hull(vertices, what: str):
    import trimesh

    try:
        hull = trimesh.Trimesh(vertices=vertices, process=False).convex_hull
    except Exception as e:  # qhull rejects flat or degenerate point sets
        raise ValueError(f"{what}: cannot build a convex hull ({type(e).__name__}: {e}); the mesh must enclose a volume") from e
    if not (hull.is_volume and hull.volume > 0):
        raise ValueError(f"{what}: its convex hull has no volume (flat or degenerate mesh); use a mesh that encloses a volume")
    return hull


def mesh_hull(vertices) -> Optional[dict]:
    """GeomDesc.hull of a collision mesh: its convex hull computed exactly as the contact builder
    (solvers/rigid/collision.py) computes it, so that the builder can take it from the model. None when
    qhull rejects the points; the builder then reports the degenerate mesh itself."""
    import trimesh

    V = np.asarray(vertices, dtype=float).reshape(-1, 3)
    if len(V) < 4 or not np.all(np.isfinite(V)):
        return None
    try:
        hull = trimesh.Trimesh(vertices=V, process=False).convex_hull
        hv = np.asarray(hull.vertices, dtype=float)
        planes = hull_planes(hv)
        return {"vertices": hv, "centroid": np.asarray(hull.centroid, dtype=float),
                "volume": float(hull.volume), "is_volume": bool(hull.is_volume), "planes": planes,
                "box": mesh_box(hv, *planes)}
    except Exception:
        return None


def geom_mass_properties(g: GeomDesc, rho: float, what: str):
    """(mass, com, inertia about com) of a geom at density rho, expressed in the geom's parent link frame."""
    if g.type == "box":
        m = rho * 8.0 * float(np.prod(g.size))
        c, I = np.zeros(3), box_inertia(m, g.size)
    elif g.type == "sphere":
        m = rho * 4.0 / 3.0 * np.pi * g.size[0] ** 3
        c, I = np.zeros(3), sphere_inertia(m, g.size[0])
    elif g.type == "cylinder":
        r, hl = g.size
        m = rho * np.pi * r * r * 2.0 * hl
        c, I = np.zeros(3), cylinder_inertia(m, r, 2.0 * hl)
    elif g.type == "capsule":
        m, I = capsule_mass_inertia(rho, g.size[0], 2.0 * g.size[1])
        c = np.zeros(3)
    elif g.type == "mesh":
        m, c, I = solid_mesh_mass_properties(g.vertices, g.faces, rho, what)
    else:  # planes are static and massless
        return 0.0, np.zeros(3), np.zeros((3, 3))
    R = quat_to_mat(g.quat)
    return m, R @ c + np.asarray(g.pos, dtype=float), R @ I @ R.T


def combine_inertias(parts):
    """Sum rigidly attached bodies [(mass, com, inertia about com)] given in one frame (parallel axis theorem)."""
    if not parts:
        return 0.0, np.zeros(3), np.zeros((3, 3))
    m = float(sum(p[0] for p in parts))
    if m > 0:
        com = sum(p[0] * np.asarray(p[1]) for p in parts) / m
    else:
        com = np.zeros(3)
    I = np.zeros((3, 3))
    for mi, ci, Ii in parts:
        d = np.asarray(ci) - com
        I += Ii + mi * (d @ d * np.eye(3) - np.outer(d, d))
    return m, com, 0.5 * (I + I.T)


# --------------------------------------------------------------------------------------------
# Mesh files
# --------------------------------------------------------------------------------------------
# Robots reuse the same meshes across links and scenes are often rebuilt in one process; the key
# includes mtime and size so an edited file is re-read.
_MESH_CACHE: Dict[tuple, Tuple[np.ndarray, np.ndarray]] = {}


def load_mesh_file(path: str, what: str) -> Tuple[np.ndarray, np.ndarray]:
    """(vertices float64 (n,3), faces int64 (m,3)) of a mesh file in its own units, all parts
    concatenated. Returns fresh copies so callers may scale in place."""
    import trimesh

    path = os.path.realpath(path)
    note_file(path)  # a dependency of the cached model being loaded, if any (loaders/cache.py)
    try:
        st = os.stat(path)
    except OSError as e:
        raise FileNotFoundError(f"{what}: mesh file '{path}' cannot be read ({e})") from e
    key = (path, st.st_mtime_ns, st.st_size)
    hit = _MESH_CACHE.get(key)
    if hit is None:
        try:
            mesh = trimesh.load(path, force="mesh", process=True)
        except Exception as e:
            raise ValueError(f"{what}: failed to load mesh file '{path}' ({type(e).__name__}: {e}); "
                             "use an STL, OBJ, PLY or DAE file trimesh can read") from e
        V = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
        F = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
        if len(V) == 0 or len(F) == 0:
            raise ValueError(f"{what}: failed to load mesh file '{path}': no triangles could be read from it; "
                             "use a valid STL, OBJ, PLY or DAE file with a surface mesh")
        if not np.all(np.isfinite(V)):
            raise ValueError(f"{what}: mesh file '{path}' has non-finite vertex coordinates")
        hit = (V, F)
        _MESH_CACHE[key] = hit
    return hit[0].copy(), hit[1].copy()


# Genesis's FileMorph(file_meshes_are_zup=False): the file's meshes are drawn y-up and are turned +90 degrees about
# x, (x, y, z) -> (x, -z, y), before the morph's (per-axis) scale, as Genesis turns them
_YUP_QUAT = np.array([np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0])


def zup_vertices(V, zup: bool):
    """A mesh file's vertices (n, 3) in the z-up frame: as read where the file is z-up, else turned from y-up."""
    return V if zup else np.stack([V[:, 0], -V[:, 2], V[:, 1]], axis=1)


def zup_visual(quat, scale, zup: bool):
    """(quat, per-axis scale) of a visual mesh drawn from its file as read (vis.geometry.load_visual_file scales
    it, then turns it by quat): a y-up file's turn follows quat, and since Genesis scales after that turn, the
    file's y and z take the scale's z and y."""
    scale = np.broadcast_to(np.asarray(scale, dtype=float), (3,)).copy()
    if zup:
        return np.asarray(quat, dtype=float), scale
    return quat_mul(quat, _YUP_QUAT), scale[[0, 2, 1]]


def scale_mesh(V, F, scale):
    """Apply a per-axis scale; a mirroring scale flips the triangles so normals still point out."""
    s = np.broadcast_to(np.asarray(scale, dtype=float), (3,))
    V = V * s
    if np.prod(s) < 0:
        F = F[:, ::-1].copy()
    return V, F


# --------------------------------------------------------------------------------------------
# Morph loaders
# --------------------------------------------------------------------------------------------
def _root_link(morph, name, mass, com, inertia, geoms) -> EntityModel:
    link = LinkDesc(
        name=name,
        parent=-1,
        joint_name=ROOT_JOINT_NAME,
        joint_type="fixed" if morph.fixed else "free",
        joint_pos=np.array(morph.pos, dtype=float),
        joint_quat=np.array(morph.quat, dtype=float),
        mass=float(mass),
        com=np.asarray(com, dtype=float),
        inertia=np.asarray(inertia, dtype=float),
        geoms=geoms,
    )
    return EntityModel(name=name, links=[link], source=f"gs.morphs.{type(morph).__name__}")


def load_primitive(morph, material, name) -> EntityModel:
    """Box, Sphere, Capsule, Cylinder or Plane -> a one-link EntityModel."""
    from genesis_lite import morphs

    rho = material.density(robot=False)
    if isinstance(morph, morphs.Plane):
        # the plane geom's normal is its +z, so the link is turned to carry +z onto the normal;
        # the normal is read in the frame given by morph.quat (the world for the default quat)
        link = LinkDesc(
            name=name,
            parent=-1,
            joint_name=ROOT_JOINT_NAME,
            joint_type="fixed",
            joint_pos=np.array(morph.pos, dtype=float),
            joint_quat=quat_mul(morph.quat, quat_from_z_to(morph.normal)),
            geoms=[GeomDesc(type="plane")],
        )
        model = EntityModel(name=name, links=[link], source="gs.morphs.Plane")
        model.validate()
        return model

    if isinstance(morph, morphs.Box):
        g = GeomDesc(type="box", size=tuple(float(s) / 2.0 for s in morph.size))
    elif isinstance(morph, morphs.Sphere):
        g = GeomDesc(type="sphere", size=(float(morph.radius),))
    elif isinstance(morph, morphs.Capsule):
        g = GeomDesc(type="capsule", size=(float(morph.radius), float(morph.height) / 2.0))
    elif isinstance(morph, morphs.Cylinder):
        g = GeomDesc(type="cylinder", size=(float(morph.radius), float(morph.height) / 2.0))
    else:
        raise TypeError(f"load_primitive: {type(morph).__name__} is not a primitive morph")
    m, c, I = geom_mass_properties(g, rho, f"entity '{name}'")
    model = _root_link(morph, name, m, c, I, [g])
    model.validate()
    return model


def load_mesh(morph, material, name) -> EntityModel:
    """gs.morphs.Mesh -> one link in the file's frame (scaled); its convex hull is both the
    collision shape and the body whose uniform density gives mass and inertia. A file loaded before,
    with the same morph and density, comes from the on-disk cache (loaders/cache.py)."""
    from .cache import cached

    path = os.path.abspath(morph.file)
    model = cached(path, morph, material, name, lambda: _load_mesh(morph, material, name))
    for msg in getattr(model, "load_warnings", ()):  # kept with the model, so a cached load says it too
        warnings.warn(msg, stacklevel=3)
    return model


def _split_rule(morph, robot):
    """(threshold, forced, settled) of a mesh of this morph: its decomposition threshold (the robot's or the
    object's), the morph's decompose_nonconvex, and whether the rule keeps the hull without looking at the mesh
    (a robot's mesh with the defaults)."""
    threshold = morph.decompose_robot_error_threshold if robot else morph.decompose_object_error_threshold
    forced = morph.decompose_nonconvex
    return threshold, forced, forced is None and morph.convexify and threshold == float("inf")


def convex_parts(morph, mesh, hull, what, notes, robot=False):
    """None (collide as the hull: the mesh is convex, or decomposition is off) or the convex hulls of
    CoACD's parts of `mesh` (a processed trimesh), by Genesis's rules: with convexify=False always (Genesis
    collides the raw mesh; parts are how genesis_lite collides a non-convex surface), else when the hull is
    off the mesh by more than the morph's decompose_robot_error_threshold (robot=True: a link of a robot
    with hinge or slide joints; infinite by default) or decompose_object_error_threshold (an object: 0.15);
    the morph's decompose_nonconvex=True / False forces it either way. CoACD runs with the morph's
    coacd_options (gs.options.CoacdOptions, Genesis's defaults)."""
    import trimesh

    threshold, forced, settled = _split_rule(morph, robot)
    if settled:
        return None  # (a robot's meshes by default: no error to measure, nothing to say)
    solid = mesh
    if not solid.is_winding_consistent:
        solid = mesh.copy()
        solid.process(validate=True)  # (as Genesis tries before measuring)
    if not solid.is_winding_consistent:
        error = float("inf")  # Genesis's: no volume to trust, split it
    elif abs(float(solid.volume)) > 1e-3 * float(hull.volume):
        # Genesis's measure: how much larger the hull's volume is than the mesh's (an open but consistently wound
        # surface too, whose volume trimesh closes; overlapping closed parts count their overlap twice: the error
        # is then underestimated)
        error = max(0.0, float(hull.volume) / abs(float(solid.volume)) - 1.0)
    else:
        # a sheet has no volume to compare (Genesis leaves it whole): how deep its surface lies inside the hull
        # (sampled: a notch's inner corner need not be a vertex), relative to the hull's thinnest extent (the most
        # a point can lie inside it)
        pts = np.vstack([mesh.vertices, trimesh.sample.sample_surface(mesh, 2000, seed=0)[0]])
        d = np.abs(trimesh.proximity.signed_distance(hull, pts)).max()
        error = float(d) / max(0.5 * float(np.ptp(hull.vertices, axis=0).min()), 1e-12)
    how = ("its faces' winding is inconsistent" if error == float("inf")
           else f"its convex hull is {100 * error:.0f} % off it")
    decompose = ((not morph.convexify) or error > threshold) if forced is None else forced
    if not decompose or error <= 1e-9:
        if forced is False and error > threshold:
            notes.append(f"{what}: the mesh is not convex ({how}) and "
                         "collides as its convex hull because decompose_nonconvex=False; leave it None or True to "
                         "split it into convex parts")
        return None
    off = "decompose_nonconvex=False"
    try:
        import coacd
    except ImportError as e:
        raise ImportError(f"{what}: the mesh is not convex ({how}) and splitting it into "
                          f"convex parts needs CoACD: pip install coacd (or pass {off} to collide "
                          "as the convex hull)") from e
    coacd.set_log_level("error")
    V, F = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    opts = morph.coacd_options.kwargs()
    parts = coacd_parts(V, F, opts, lambda: coacd.run_coacd(coacd.Mesh(V, F), **opts))
    out = [convex_hull(np.asarray(pv, dtype=np.float64), what) for pv, _ in parts if len(pv) >= 4]
    if not out:
        raise ValueError(f"{what}: CoACD returned no convex parts; pass {off} to collide as the "
                         "convex hull")
    return out


def mesh_shapes(morph, V, F, what, robot):
    """The convex shapes a URDF's or MJCF's collision mesh (V, F) collides as, by convex_parts's rules: [(V, F)]
    (its hull) or CoACD's parts as (vertices, faces) each. A robot's mesh with the defaults is not looked at."""
    _, forced, settled = _split_rule(morph, robot)
    if settled or forced is False:  # (forced off: the hull, and a URDF's or MJCF's note would go nowhere)
        return [(V, F)]
    import trimesh

    # (convex_parts splits the mesh or finds it convex enough; a URDF or MJCF leaves no note)
    parts = convex_parts(morph, trimesh.Trimesh(vertices=V, faces=F, process=True), convex_hull(V, what), what, [],
                         robot=robot)
    if parts is None:
        return [(V, F)]
    return [(np.array(p.vertices, dtype=np.float64), np.array(p.faces, dtype=np.int64)) for p in parts]


def _load_mesh(morph, material, name) -> EntityModel:
    path = os.path.abspath(morph.file)
    what = f"gs.morphs.Mesh(file='{path}') for entity '{name}'"
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{what}: no such file; give a path to an existing mesh file")
    V, F = load_mesh_file(path, what)
    V, F = scale_mesh(zup_vertices(V, morph.file_meshes_are_zup), F, morph.scale)
    hull = convex_hull(V, what)
    hull.density = material.density(robot=False)
    import trimesh

    mesh = trimesh.Trimesh(vertices=V, faces=F, process=True)
    notes = []
    parts = convex_parts(morph, mesh, hull, what, notes)
    geoms = []
    for ph in [hull] if parts is None else parts:
        g = GeomDesc(type="mesh", vertices=np.array(ph.vertices, dtype=np.float64),
                     faces=np.array(ph.faces, dtype=np.int64))
        g.hull = mesh_hull(g.vertices)
        geoms.append(g)
    body = hull
    if parts is not None:
        # the solid is the mesh itself when it is closed (a tank's walls, not its hull's volume), else the parts
        body = mesh if mesh.is_volume else trimesh.util.concatenate(parts)
        body.density = material.density(robot=False)
    model = _root_link(morph, name, body.mass, body.center_mass, body.moment_inertia, geoms)
    model.load_warnings = notes
    # cameras draw the file's own surface, not the hull that stands in for it in the physics
    quat, scale = zup_visual((1.0, 0.0, 0.0, 0.0), morph.scale, morph.file_meshes_are_zup)
    model.links[0].visuals.append(VisualDesc("mesh", quat=quat, file=path, filename=morph.file, scale=scale))
    model.source = path
    model.validate()
    return model
