"""Triangle meshes for drawing: tessellated primitives, visual mesh files with their colours,
decimation by vertex clustering, and per-corner normals with a crease angle.

A drawable mesh is (V (n, 3) float64, F (m, 3) int64, N (m, 3, 3) per-corner unit normals,
C (m, 3) per-face colours in [0, 1] or None) in the frame of its shape. Corner normals let one
array hold both smooth surfaces (spheres, capsule sides) and sharp edges (box faces, machined parts).
"""
from __future__ import annotations

import os
from typing import Dict, Optional, Tuple

import numpy as np

# Budget per visual mesh file: a Panda's ten files then come to ~30k triangles, which the numpy
# rasteriser draws within its frame budget; its raw files hold 134k.
MAX_FACES_PER_MESH = 3000

_FILE_CACHE: Dict[tuple, tuple] = {}


def _face_normals(V, F):
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def flat_normals(V, F):
    n = _face_normals(V, F)
    return np.repeat(n[:, None, :], 3, axis=1)


def corner_normals(V, F, crease_deg: float = 35.0):
    """Per-corner normals (m, 3, 3): each corner averages (area-weighted) the normals of the faces
    around its vertex that bend less than `crease_deg` from its own face, so curved surfaces shade
    smoothly and edges sharper than the crease stay sharp."""
    F = np.asarray(F, dtype=np.int64)
    m = len(F)
    if m == 0:
        return np.zeros((0, 3, 3))
    raw = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # length = 2 x area
    fn = raw / np.maximum(np.linalg.norm(raw, axis=1, keepdims=True), 1e-300)
    cv = F.ravel()
    cf = np.repeat(np.arange(m), 3)
    order = np.argsort(cv, kind="stable")
    deg = np.bincount(cv, minlength=len(V))
    start = np.concatenate([[0], np.cumsum(deg)[:-1]])
    # all (corner, corner) pairs that share a vertex: sum of deg^2 pairs, built without a loop
    d_c = deg[cv[order]]
    s_c = start[cv[order]]
    a = np.repeat(np.arange(len(order)), d_c)
    b = s_c[a] + (np.arange(a.size) - np.repeat(np.cumsum(d_c) - d_c, d_c))
    fa, fb = cf[order[a]], cf[order[b]]
    ok = np.einsum("ij,ij->i", fn[fa], fn[fb]) >= np.cos(np.radians(crease_deg))
    acc = np.zeros((3 * m, 3))
    np.add.at(acc, order[a[ok]], raw[fb[ok]])
    acc /= np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-300)
    return acc.reshape(m, 3, 3)


def _cluster(V, F, lo, h):
    """Faces (indices into the cells) that survive snapping V to cells of size h, and the cell of
    each vertex."""
    cell = np.floor((V - lo) / h).astype(np.int64)
    dims = cell.max(0) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    uniq, inv = np.unique(key, return_inverse=True)
    inv = inv.reshape(-1)
    F2 = inv[F]
    good = (F2[:, 0] != F2[:, 1]) & (F2[:, 1] != F2[:, 2]) & (F2[:, 0] != F2[:, 2])
    idx = np.flatnonzero(good)
    # two faces on the same three cells are one face after merging (keep the first's winding)
    srt = np.sort(F2[idx], axis=1)
    n = np.int64(len(uniq))
    _, first = np.unique((srt[:, 0] * n + srt[:, 1]) * n + srt[:, 2], return_index=True)
    return idx[np.sort(first)], inv, len(uniq), F2


def decimate(V, F, max_faces: int, face_data=None):
    """Vertex clustering: snap vertices to a grid, merge each cell into the mean of its vertices and
    drop the faces that collapse, with the cell size chosen so that no more than `max_faces` remain.
    Crude next to quadric simplification, but at camera resolution the difference is a pixel or two
    and it is a handful of vectorised passes. `face_data` (m, k) rides along with the surviving faces."""
    F = np.asarray(F, dtype=np.int64)
    if len(F) <= max_faces:
        return V, F, face_data
    lo = V.min(0)
    ext = float(np.max(V.max(0) - lo))
    if not ext > 0:
        return V, F, face_data
    # a surface keeps ~ (cells per side)^2 faces: aim from a first trial, then shrink until it fits
    idx = _cluster(V, F, lo, ext / 64.0)[0]
    n_cells = 64.0 * 0.95 * np.sqrt(max_faces / max(len(idx), 1))
    for _ in range(12):
        idx, inv, n_uniq, F2 = _cluster(V, F, lo, ext / n_cells)
        if len(idx) <= max_faces or n_cells < 2:
            break
        n_cells *= min(0.97 * np.sqrt(max_faces / len(idx)), 0.97)
    cnt = np.bincount(inv, minlength=n_uniq).astype(np.float64)
    V2 = np.stack([np.bincount(inv, weights=V[:, k], minlength=n_uniq) for k in range(3)], 1) / cnt[:, None]
    F2 = F2[idx]
    # moving corners to cell means can turn a face over; give it back the side of the face it came from
    before = np.cross(V[F[idx, 1]] - V[F[idx, 0]], V[F[idx, 2]] - V[F[idx, 0]])
    after = np.cross(V2[F2[:, 1]] - V2[F2[:, 0]], V2[F2[:, 2]] - V2[F2[:, 0]])
    flip = np.einsum("ij,ij->i", before, after) < 0
    F2[flip] = F2[flip][:, ::-1]
    used = np.unique(F2)
    remap = np.full(len(V2), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return V2[used], remap[F2], None if face_data is None else np.asarray(face_data)[idx]


# --------------------------------------------------------------------------------------------
# Primitives (in the shape's own frame; capsules and cylinders along z)
# --------------------------------------------------------------------------------------------
def _grid_faces(rows, cols, wrap=True):
    """Quads of a (rows x cols) vertex grid, as triangles; columns wrap around when `wrap`."""
    r = np.arange(rows - 1)[:, None]
    c = np.arange(cols if wrap else cols - 1)[None, :]
    c1 = (c + 1) % cols
    a, b = r * cols + c, r * cols + c1
    d, e = (r + 1) * cols + c, (r + 1) * cols + c1
    return np.concatenate([np.stack([a, b, e], -1).reshape(-1, 3), np.stack([a, e, d], -1).reshape(-1, 3)])


def _revolve(profile_r, profile_z, nrm_r, nrm_z, seg):
    """Surface of revolution about z: profile points (r, z) with profile normals (nr, nz)."""
    phi = np.linspace(0, 2 * np.pi, seg, endpoint=False)
    cp, sp = np.cos(phi)[None], np.sin(phi)[None]
    shape = (len(profile_r), seg)
    V = np.stack([profile_r[:, None] * cp, profile_r[:, None] * sp, np.broadcast_to(profile_z[:, None], shape)], -1)
    Nv = np.stack([nrm_r[:, None] * cp, nrm_r[:, None] * sp, np.broadcast_to(nrm_z[:, None], shape)], -1)
    V, Nv = V.reshape(-1, 3), Nv.reshape(-1, 3)
    F = _grid_faces(len(profile_r), seg)
    return V, F, Nv[F]


def sphere(radius, seg=32):
    th = np.linspace(np.pi, 0, seg // 2 + 1)  # from the south pole up
    V, F, N = _revolve(radius * np.sin(th), radius * np.cos(th), np.sin(th), np.cos(th), seg)
    return V, F, N


def capsule(radius, half_length, seg=32):
    k = seg // 4 + 1
    th_lo = np.linspace(np.pi, np.pi / 2, k)
    th_hi = np.linspace(np.pi / 2, 0, k)
    r = np.concatenate([radius * np.sin(th_lo), radius * np.sin(th_hi)])
    z = np.concatenate([-half_length + radius * np.cos(th_lo), half_length + radius * np.cos(th_hi)])
    nr = np.concatenate([np.sin(th_lo), np.sin(th_hi)])
    nz = np.concatenate([np.cos(th_lo), np.cos(th_hi)])
    return _revolve(r, z, nr, nz, seg)


def cylinder(radius, half_length, seg=32):
    Vs, Fs, Ns = _revolve(np.array([radius, radius]), np.array([-half_length, half_length]),
                          np.ones(2), np.zeros(2), seg)
    phi = np.linspace(0, 2 * np.pi, seg, endpoint=False)
    ring = np.stack([radius * np.cos(phi), radius * np.sin(phi)], -1)
    parts = [(Vs, Fs, Ns)]
    for zc, sgn in ((-half_length, -1.0), (half_length, 1.0)):
        Vc = np.concatenate([[[0.0, 0.0, zc]], np.column_stack([ring, np.full(seg, zc)])])
        i = np.arange(seg)
        Fc = np.stack([np.zeros(seg, np.int64), 1 + i, 1 + (i + 1) % seg], -1)
        if sgn < 0:
            Fc = Fc[:, ::-1]
        parts.append((Vc, Fc, np.broadcast_to([0.0, 0.0, sgn], (seg, 3, 3)).copy()))
    return merge(parts)


def box(half):
    hx, hy, hz = half
    corners = np.array([[sx * hx, sy * hy, sz * hz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    # each face listed counter-clockwise seen from outside
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    F = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=np.int64)
    return corners, F, flat_normals(corners, F)


def merge(parts):
    """Concatenate meshes [(V, F, N), ...] into one."""
    Vs, Fs, Ns, off = [], [], [], 0
    for V, F, N in parts:
        Vs.append(V)
        Fs.append(np.asarray(F, dtype=np.int64) + off)
        Ns.append(N)
        off += len(V)
    return np.concatenate(Vs), np.concatenate(Fs), np.concatenate(Ns)


def primitive(kind: str, size) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(V, F, N) of a box (half extents), sphere (radius,), capsule or cylinder (radius, half length)."""
    if kind == "box":
        return box(size)
    if kind == "sphere":
        return sphere(size[0])
    if kind == "capsule":
        return capsule(size[0], size[1])
    if kind == "cylinder":
        return cylinder(size[0], size[1])
    raise ValueError(f"no tessellation for shape type '{kind}'")


def mesh_for_drawing(V, F, colors=None, max_faces: int = MAX_FACES_PER_MESH):
    """(V, F, N, C) of an arbitrary triangle mesh: decimated to `max_faces`, corner normals with a crease."""
    V, F, colors = decimate(np.asarray(V, dtype=np.float64), F, max_faces, colors)
    return V, F, corner_normals(V, F), colors


# --------------------------------------------------------------------------------------------
# Mesh files
# --------------------------------------------------------------------------------------------
def _part_color(geom) -> Optional[np.ndarray]:
    """One RGB colour in [0, 1] for a trimesh part: its material's main colour, else its mean face colour."""
    vis = getattr(geom, "visual", None)
    if vis is None:
        return None
    mat = getattr(vis, "material", None)
    main = getattr(mat, "main_color", None) if mat is not None else None
    if main is not None:
        return np.asarray(main[:3], dtype=np.float64) / 255.0
    if getattr(vis, "kind", None) in ("face", "vertex"):
        try:
            return np.asarray(vis.face_colors, dtype=np.float64)[:, :3].mean(0) / 255.0
        except Exception:
            return None
    return None


def load_visual_file(path: str, scale=1.0, max_faces: int = MAX_FACES_PER_MESH):
    """(V, F, N, C) of a mesh file for drawing: all parts of the file in the file's frame times
    `scale` (per-axis), decimated, with per-face colours from the file's materials (None where the
    file has none). Cached per (path, mtime, size, scale, budget): robots reuse files and scenes are
    rebuilt."""
    import trimesh

    real = os.path.realpath(path)
    st = os.stat(real)
    s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
    key = (real, st.st_mtime_ns, st.st_size, tuple(s), max_faces)
    hit = _FILE_CACHE.get(key)
    if hit is not None:
        return hit
    loaded = trimesh.load(real, force="scene")
    Vs, Fs, Cs, off, any_color = [], [], [], 0, False
    for node in loaded.graph.nodes_geometry:
        T, gname = loaded.graph[node]
        g = loaded.geometry[gname]
        if not hasattr(g, "faces") or len(g.faces) == 0:
            continue
        V = np.asarray(g.vertices, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
        F = np.asarray(g.faces, dtype=np.int64)
        c = _part_color(g)
        any_color |= c is not None
        Vs.append(V)
        Fs.append(F + off)
        Cs.append(np.broadcast_to(c if c is not None else np.full(3, np.nan), (len(F), 3)))
        off += len(V)
    if not Fs:
        raise ValueError(f"mesh file '{path}' holds no triangles")
    V = np.concatenate(Vs) * s
    F = np.concatenate(Fs)
    if np.prod(s) < 0:  # a mirroring scale turns the winding inside out
        F = F[:, ::-1]
    C = np.concatenate(Cs) if any_color else None
    out = mesh_for_drawing(V, F, C, max_faces)
    _FILE_CACHE[key] = out
    return out
