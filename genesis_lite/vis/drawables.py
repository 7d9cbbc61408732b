"""What a camera draws: the scene's entities turned, once, into link-frame triangle arrays, planes
and particle sets, then posed each frame from the entities' link poses.

Built lazily, on the first render of any camera of a scene, and shared by all its cameras: mesh
files are read then, not at scene.build(). Per link, URDF <visual> shapes (or a gs.morphs.Mesh's
file) are drawn when there are any and the entity's surface does not ask for vis_mode='collision';
otherwise the link's collision geoms. Any entity with `get_particles_pos()` is drawn as points.
"""
from __future__ import annotations

import logging
import warnings
from typing import List

import numpy as np
import torch

from ..loaders.primitives import quat_to_mat
from . import geometry

logger = logging.getLogger("genesis_lite")

# distinct, mid-saturation colours; entity i gets PALETTE[i % len]
PALETTE = np.array([
    [0.90, 0.55, 0.25], [0.35, 0.60, 0.85], [0.55, 0.78, 0.40], [0.85, 0.40, 0.45],
    [0.65, 0.50, 0.80], [0.95, 0.80, 0.35], [0.40, 0.75, 0.75], [0.75, 0.60, 0.50],
])
PLANE_COLORS = (np.array([0.78, 0.80, 0.83]), np.array([0.58, 0.61, 0.66]))
PLANE_TILE = 0.5  # m


def entity_color(ent, idx):
    """The entity's own colour (its `_vis_color`, else its surface's colour) as RGB, or None."""
    c = getattr(ent, "_vis_color", None)
    if c is None:
        c = getattr(getattr(ent, "surface", None), "color", None)
    if c is None:
        return None
    c = np.asarray(c, dtype=np.float64).reshape(-1)[:3]
    return c / 255.0 if c.max() > 1.0 else c  # some callers give 0-255


def _pose(pos, quat):
    T = np.eye(4)
    T[:3, :3] = quat_to_mat(quat)
    T[:3, 3] = pos
    return T


class SceneDrawables:
    """Link-frame geometry of every drawable entity of a scene, concatenated so that posing them is
    one gather and one batched matrix product per frame."""

    def __init__(self, scene):
        self.scene = scene
        self.rigid = []  # (entity, first row in the link pose arrays)
        self.planes = []  # (global link row, T_link_geom, color_a, color_b, seg)
        self.particles = []  # (entity, color, radius or None, seg)
        Vs, Fs, Ns, Cs, Ss, VL = [], [], [], [], [], []
        n_v = 0
        n_links = 0
        for i_e, ent in enumerate(scene.entities):
            if hasattr(ent, "get_particles_pos"):
                col = entity_color(ent, i_e)
                self.particles.append((ent, PALETTE[i_e % len(PALETTE)] if col is None else col,
                                       getattr(ent, "_vis_radius", None), i_e))
                continue
            model = getattr(ent, "model", None)
            if model is None:
                continue
            self.rigid.append((ent, n_links))
            own = entity_color(ent, i_e)
            fallback = PALETTE[i_e % len(PALETTE)] if own is None else own
            mode = getattr(ent, "vis_mode", None) or getattr(getattr(ent, "surface", None), "vis_mode", None) or "visual"
            for i_l, link in enumerate(model.links):
                row = n_links + i_l
                parts = None
                if mode != "collision" and getattr(link, "visuals", None):
                    parts = self._visual_parts(ent, link, fallback, own)
                if parts is None:
                    parts = self._collision_parts(link, fallback, i_e, row, own)
                for V, F, N, C in parts:
                    Vs.append(V)
                    Fs.append(F + n_v)
                    Ns.append(N)
                    Cs.append(C)
                    Ss.append(np.full(len(F), i_e, np.int32))
                    VL.append(np.full(len(V), row, np.int64))
                    n_v += len(V)
            n_links += model.n_links
        self.n_links = n_links
        if Fs:
            self.V = np.concatenate(Vs)
            self.F = np.concatenate(Fs)
            self.N = np.concatenate(Ns)
            self.C = np.concatenate(Cs).astype(np.float32)
            self.S = np.concatenate(Ss)
            self.v_link = np.concatenate(VL)
            self.f_link = self.v_link[self.F[:, 0]]
            rows = np.unique(self.v_link)
            vb = np.searchsorted(self.v_link, np.append(rows, rows[-1] + 1))
            fb = np.searchsorted(self.f_link, np.append(rows, rows[-1] + 1))
            self.link_ranges = [(int(r), (int(vb[k]), int(vb[k + 1])), (int(fb[k]), int(fb[k + 1])))
                                for k, r in enumerate(rows)]
            self.N = self.N.astype(np.float64)
        else:
            self.V = np.zeros((0, 3))
            self.F = np.zeros((0, 3), np.int64)
            self.link_ranges = []
        self.n_faces = len(self.F)

    # ---------------------------------------------------------------- building
    @staticmethod
    def _place(V, F, N, T):
        R = T[:3, :3]
        return V @ R.T + T[:3, 3], F, N @ R.T

    def _visual_parts(self, ent, link, fallback, own):
        """Drawable parts of a link's visuals, or None to fall back to its collision geoms (when none
        of its visuals could be loaded)."""
        parts = []
        for v in link.visuals:
            T = _pose(v.pos, v.quat)
            if v.type == "mesh":
                if v.file is None:
                    warnings.warn(f"entity '{ent.name}', link '{link.name}': visual mesh '{v.filename}' was not found; "
                                  "drawing its collision shapes instead", stacklevel=4)
                    continue
                try:
                    V, F, N, C = geometry.load_visual_file(v.file, v.scale)
                except Exception as e:  # a broken visual file must not stop a rollout from being recorded
                    warnings.warn(f"entity '{ent.name}', link '{link.name}': visual mesh '{v.file}' could not be "
                                  f"read ({type(e).__name__}: {e}); drawing its collision shapes instead", stacklevel=4)
                    continue
            else:
                V, F, N = geometry.primitive(v.type, v.size)
                C = None
            V, F, N = self._place(V, F, N, T)
            if own is not None:
                C = np.broadcast_to(own, (len(F), 3))
            elif v.rgba is not None:
                C = np.broadcast_to(np.asarray(v.rgba[:3], dtype=np.float64), (len(F), 3))
            elif C is None:
                C = np.broadcast_to(fallback, (len(F), 3))
            else:  # parts of the file without a material take the entity's colour
                C = np.where(np.isnan(C), fallback, C)
            parts.append((V, F, N, C))
        return parts or None

    def _collision_parts(self, link, color, i_e, row, own):
        parts = []
        for g in link.geoms:
            T = _pose(g.pos, g.quat)
            if g.type == "plane":
                if own is None:
                    ca, cb = PLANE_COLORS
                else:
                    ca, cb = np.asarray(own), 0.75 * np.asarray(own)
                self.planes.append((row, T, ca, cb, i_e))
                continue
            if g.type == "mesh":
                V, F, N, _ = geometry.mesh_for_drawing(g.vertices, g.faces)
            else:
                V, F, N = geometry.primitive(g.type, g.size)
            V, F, N = self._place(V, F, N, T)
            parts.append((V, F, N, np.broadcast_to(color, (len(F), 3))))
        return parts

    # ---------------------------------------------------------------- per frame
    def link_poses(self, env_idx: int):
        """World rotations (L, 3, 3) and positions (L, 3) of every rigid link, environment env_idx."""
        R = np.zeros((self.n_links, 3, 3))
        p = np.zeros((self.n_links, 3))
        batched = self.scene.n_envs > 0
        with torch.no_grad():
            for ent, row in self.rigid:
                if batched:
                    pos = ent.get_links_pos(envs_idx=[env_idx])[0]
                    quat = ent.get_links_quat(envs_idx=[env_idx])[0]
                else:
                    pos, quat = ent.get_links_pos(), ent.get_links_quat()
                pos = pos.detach().cpu().numpy().astype(np.float64)
                q = quat.detach().cpu().numpy().astype(np.float64)
                q = q / np.linalg.norm(q, axis=1, keepdims=True)
                w, x, y, z = q.T
                n = len(q)
                R[row:row + n] = np.stack([
                    np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                    np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                    np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)
                p[row:row + n] = pos
        return R, p

    def particle_sets(self, env_idx: int) -> List[tuple]:
        """[(positions (n, 3) world, colour, radius (m), seg)] of the particle entities."""
        out = []
        with torch.no_grad():
            for k, (ent, color, radius, seg) in enumerate(self.particles):
                P = ent.get_particles_pos()
                P = P.detach().cpu().numpy() if isinstance(P, torch.Tensor) else np.asarray(P)
                if P.ndim == 3:
                    P = P[env_idx]
                if getattr(ent, "is_emitter", False):  # only what has been emitted (the rest is 'nowhere')
                    P = P[:ent._emitter.high_water]
                P = P.reshape(-1, 3)
                if radius is None and len(P):
                    radius = _spacing_radius(P)
                    self.particles[k] = (ent, color, radius, seg)
                out.append((P, color, radius, seg))
        return out


def _spacing_radius(P):
    """Half the mean particle spacing of a set that fills its bounding box: a guess at the particle
    size when the entity does not say (`_vis_radius`); fixed at first use so that it does not change
    while a body deforms."""
    ext = np.maximum(P.max(0) - P.min(0), 1e-6)
    # a flat or thin set fills fewer dimensions; use only the axes it really spans
    span = ext[ext > 0.05 * ext.max()]
    vol = float(np.prod(span))
    return max(0.5 * (vol / len(P)) ** (1.0 / len(span)), 1e-4)
