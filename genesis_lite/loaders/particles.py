"""Particle sampling for MPM entities: a morph's volume filled with a regular lattice.

Box, Sphere, Cylinder and Capsule are filled analytically; a Mesh is filled with trimesh's
containment test, which needs a closed (watertight) surface.
"""
from __future__ import annotations

import numpy as np

from .primitives import quat_to_mat, zup_vertices


def _lattice(half_extents, spacing):
    """Cell centres of a lattice of about `spacing` filling the box [-h, h] exactly (the spacing is
    adjusted per axis so the cells tile the box); returns points (n, 3) and the cell volume."""
    counts = np.maximum(np.round(2.0 * np.asarray(half_extents) / spacing).astype(int), 1)
    step = 2.0 * np.asarray(half_extents) / counts
    axes = [-h + (np.arange(n) + 0.5) * d for h, n, d in zip(half_extents, counts, step)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return pts, float(np.prod(step))


def sample_particles(morph, spacing: float, name: str):
    """Particles filling `morph` (gs.morphs.Box / Sphere / Cylinder / Capsule / Mesh) placed at its pos
    and quat: positions (n, 3) in the world frame (m) and the volume each particle stands for (m^3)."""
    from genesis_lite import morphs
    from genesis_lite.errors import GenesisException

    if isinstance(morph, morphs.Box):
        local, vol = _lattice(np.asarray(morph.size) / 2.0, spacing)
    elif isinstance(morph, morphs.Sphere):
        r = morph.radius
        local, vol = _lattice([r, r, r], spacing)
        local = local[np.linalg.norm(local, axis=1) <= r]
    elif isinstance(morph, (morphs.Cylinder, morphs.Capsule)):
        r, h = morph.radius, morph.height / 2.0
        cap = r if isinstance(morph, morphs.Capsule) else 0.0
        local, vol = _lattice([r, r, h + cap], spacing)
        radial = np.linalg.norm(local[:, :2], axis=1)
        if cap:
            # distance to the capsule's axis segment
            zc = np.clip(local[:, 2], -h, h)
            inside = np.linalg.norm(local - np.stack([0 * zc, 0 * zc, zc], -1), axis=1) <= r
        else:
            inside = radial <= r
        local = local[inside]
    elif isinstance(morph, morphs.Mesh):
        import trimesh

        mesh = trimesh.load(morph.file, force="mesh")
        if not morph.file_meshes_are_zup:  # Genesis's turn of a y-up file, before the scale
            mesh.vertices = zup_vertices(np.asarray(mesh.vertices, dtype=np.float64), False)
        mesh.apply_scale(morph.scale)
        if not mesh.is_watertight:
            # an OBJ splits its vertices along texture and normal seams (Genesis's duck.obj): joined at the
            # same positions, the surface is closed; the geometry is unchanged
            mesh.merge_vertices(merge_tex=True, merge_norm=True)
        if not mesh.is_watertight:
            raise GenesisException(
                f"MPM entity '{name}': the mesh {morph.file!r} is not closed (watertight), so the particle sampler "
                "cannot tell its inside from its outside. Close its holes (e.g. trimesh's fill_holes, or a "
                "mesh repair tool) or use a primitive morph.")
        lo, hi = mesh.bounds
        centre = (lo + hi) / 2.0
        pts, vol = _lattice((hi - lo) / 2.0, spacing)
        pts = pts + centre
        local = pts[mesh.contains(pts)]
    else:
        raise GenesisException(
            f"MPM entity '{name}': cannot fill a {type(morph).__name__} with particles; use gs.morphs.Box, Sphere, "
            "Cylinder, Capsule or a closed Mesh")
    if len(local) == 0:
        raise GenesisException(
            f"MPM entity '{name}': the {type(morph).__name__} holds no particle at particle_size {spacing:g} m; make it "
            "larger than a particle or lower MPMOptions.particle_size")
    R = quat_to_mat(np.asarray(morph.quat, dtype=float))
    return local @ R.T + np.asarray(morph.pos, dtype=float), vol
