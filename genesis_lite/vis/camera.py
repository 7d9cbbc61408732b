"""Camera: Genesis's camera API on a headless numpy rasteriser.

    cam = scene.add_camera(res=(640, 480), pos=(3.5, 0, 2.5), lookat=(0, 0, 0.5), fov=30)
    scene.build()
    cam.start_recording()
    for _ in range(100):
        scene.step()
        cam.render()
    cam.stop_recording(save_to_filename="out/rollout.mp4", fps=60)

Frames need no display, no OpenGL and nothing outside pip (Pillow, imageio-ffmpeg).
"""
from __future__ import annotations

import logging
import os
import sys
import time

import numpy as np

from ..errors import GenesisException
from .drawables import PLANE_TILE
from .raster import Light, Rasterizer, pack_rgb
from .video import FrameSpool, check_output_path, write_video

logger = logging.getLogger("genesis_lite")

# towards the light, world frame: high and to one side, so that the faces of a box differ in shade
LIGHT_DIR_WORLD = np.array([0.45, -0.3, 1.0]) / np.linalg.norm([0.45, -0.3, 1.0])
SKY_TOP, SKY_HORIZON = np.array([0.62, 0.72, 0.85]), np.array([0.90, 0.92, 0.94])
_IGNORED = {"model", "aperture", "focus_dist", "spp", "denoise", "debug"}


def _vec3(name, v):
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"camera {name}={v!r}: expected 3 finite numbers (m)")
    return a


def _look_rotation(pos, lookat, up):
    """Rows: right, up, forward (world frame) of a camera at pos looking at lookat."""
    fwd = lookat - pos
    d = np.linalg.norm(fwd)
    if d < 1e-9:
        raise ValueError(f"camera pos {pos.tolist()} and lookat {lookat.tolist()} coincide; "
                         "the camera needs a direction to look in")
    fwd = fwd / d
    right = np.cross(fwd, up)
    n = np.linalg.norm(right)
    if n < 1e-6 * max(np.linalg.norm(up), 1e-12):
        raise ValueError(f"camera up {up.tolist()} is parallel to the viewing direction {fwd.tolist()}; "
                         "give an up vector that is not along lookat - pos")
    right = right / n
    return np.stack([right, np.cross(right, fwd), fwd])


class Camera:
    """A pinhole camera placed in a scene (Genesis's `scene.add_camera`). res = (width, height) in
    pixels; pos and lookat in metres (world frame); up the world direction that appears up; fov the
    vertical field of view in degrees; near, far the clipping distances (m). It renders environment
    `env_idx` (default 0) of a batched scene. Options of Genesis's ray tracer (model, aperture,
    focus_dist, spp, denoise) are accepted and ignored; GUI=True only logs that there is no window."""

    def __init__(self, scene, idx, res=(320, 320), pos=(0.5, 2.5, 3.5), lookat=(0.5, 0.5, 0.5), up=(0.0, 0.0, 1.0),
                 fov=30.0, GUI=False, near=0.05, far=100.0, env_idx=None, **kwargs):
        unknown = set(kwargs) - _IGNORED
        if unknown:
            raise TypeError(f"scene.add_camera got unexpected arguments {sorted(unknown)}")
        if kwargs.get("model", "pinhole") != "pinhole":
            raise ValueError(f"scene.add_camera(model={kwargs['model']!r}): only the 'pinhole' model is available")
        self._scene = scene
        self._idx = idx
        r = tuple(res) if isinstance(res, (tuple, list, np.ndarray)) else ()
        if len(r) != 2 or not all(isinstance(x, (int, np.integer)) and 1 <= x <= 8192 for x in r):
            raise ValueError(f"scene.add_camera(res={res!r}): expected (width, height), two integers in [1, 8192]")
        self._res = (int(r[0]), int(r[1]))
        if not (isinstance(fov, (int, float, np.floating)) and 0 < fov < 180):
            raise ValueError(f"scene.add_camera(fov={fov!r}): the vertical field of view must be in (0, 180) degrees")
        self._fov = float(fov)
        if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
            raise ValueError(f"scene.add_camera(near={near!r}, far={far!r}): need 0 < near < far (m)")
        self._near, self._far = float(near), float(far)
        if env_idx is not None and not (isinstance(env_idx, (int, np.integer)) and env_idx >= 0):
            raise ValueError(f"scene.add_camera(env_idx={env_idx!r}): expected an environment index >= 0")
        self._env_idx = None if env_idx is None else int(env_idx)
        if GUI:
            logger.warning("camera %d: GUI=True is not supported (the renderer is headless); frames are returned "
                           "by render() and recorded, no window opens", idx)
        self._GUI = bool(GUI)
        self._pos = self._lookat = self._up = None
        self.set_pose(pos=pos, lookat=lookat, up=up)
        self._raster = None
        self._spool = None
        self._recording = False
        self._sky = None
        self._static = None

    # ---------------------------------------------------------------- properties
    @property
    def idx(self):
        return self._idx

    @property
    def res(self):
        """(width, height) in pixels."""
        return self._res

    @property
    def fov(self):
        """Vertical field of view (degrees)."""
        return self._fov

    @property
    def pos(self):
        return self._pos.copy()

    @property
    def lookat(self):
        return self._lookat.copy()

    @property
    def up(self):
        return self._up.copy()

    @property
    def near(self):
        return self._near

    @property
    def far(self):
        return self._far

    @property
    def env_idx(self):
        return 0 if self._env_idx is None else self._env_idx

    @property
    def is_recording(self):
        return self._recording

    @property
    def f(self):
        """Focal length in pixels."""
        return 0.5 * self._res[1] / np.tan(np.radians(self._fov) / 2.0)

    @property
    def intrinsics(self):
        """OpenCV intrinsic matrix K (3, 3): pixel (u, v) = K @ p_cv / z, pixel centres at +0.5."""
        w, h = self._res
        return np.array([[self.f, 0.0, w / 2.0], [0.0, self.f, h / 2.0], [0.0, 0.0, 1.0]])

    @property
    def extrinsics(self):
        """World-to-camera transform (4, 4) in OpenCV axes (x right, y down, z forward)."""
        T = np.eye(4)
        T[:3, :3] = self._R * np.array([1.0, -1.0, 1.0])[:, None]
        T[:3, 3] = -T[:3, :3] @ self._pos
        return T

    @property
    def transform(self):
        """Camera-to-world pose (4, 4) in OpenGL axes (x right, y up, z backward), as in Genesis."""
        T = np.eye(4)
        T[:3, :3] = np.stack([self._R[0], self._R[1], -self._R[2]], 1)
        T[:3, 3] = self._pos
        return T

    # ---------------------------------------------------------------- pose
    def set_pose(self, transform=None, pos=None, lookat=None, up=None):
        """Move the camera: either `transform`, a camera-to-world (4, 4) pose in OpenGL axes (as
        `cam.transform` returns), or any of pos, lookat, up (m, world frame); the others are kept."""
        if transform is not None:
            T = np.asarray(transform, dtype=np.float64)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise ValueError(f"camera.set_pose(transform=...): expected a finite 4x4 matrix, got shape {T.shape}")
            R = T[:3, :3]
            if not np.allclose(R.T @ R, np.eye(3), atol=1e-6):
                raise ValueError("camera.set_pose(transform=...): the upper-left 3x3 block is not a rotation")
            pos = T[:3, 3]
            d = np.linalg.norm(self._lookat - self._pos) if self._pos is not None else 1.0
            lookat, up = pos - R[:, 2] * d, R[:, 1]
        new_pos = _vec3("pos", pos) if pos is not None else self._pos
        new_lookat = _vec3("lookat", lookat) if lookat is not None else self._lookat
        new_up = _vec3("up", up) if up is not None else self._up
        self._R = _look_rotation(new_pos, new_lookat, new_up)
        self._pos, self._lookat, self._up = new_pos, new_lookat, new_up

    # ---------------------------------------------------------------- rendering
    def _env(self):
        n = self._scene.n_envs
        e = self.env_idx
        if (n == 0 and e != 0) or (n > 0 and e >= n):
            raise GenesisException(f"camera {self._idx}: env_idx={e} but the scene has "
                                   f"{'no batched environments (only env 0)' if n == 0 else f'{n} environments'}")
        return e

    def _drawables(self):
        from .drawables import SceneDrawables

        d = getattr(self._scene, "_vis_drawables", None)
        if d is None:
            t0 = time.perf_counter()
            d = SceneDrawables(self._scene)
            self._scene._vis_drawables = d
            logger.info("camera: prepared %d triangles for drawing in %.2f s", d.n_faces, time.perf_counter() - t0)
        return d

    def _background(self, W, H):
        if self._sky is None or self._sky[0] != (W, H):
            # a vertical sky gradient fixed to the image rows: cheap and enough to tell sky from ground
            s = np.linspace(0.0, 1.0, H)[:, None]
            rows = pack_rgb(*((1 - s) * SKY_TOP[c] + s * SKY_HORIZON[c] for c in range(3)))
            self._sky = ((W, H), np.repeat(rows, W, axis=1).reshape(-1))
        return self._sky[1]

    def render(self, rgb=True, depth=False, segmentation=False, colorize_seg=False, normal=False,
               antialiasing=False, force_render=False):
        """Draw the scene's current state. Returns (rgb, depth, segmentation, normal) like Genesis, each
        None unless asked for: rgb (H, W, 3) uint8; depth (H, W) float32, distance along the viewing
        axis in metres, inf where nothing was hit; segmentation (H, W) int32 entity index in
        scene.entities, -1 for background (an (H, W, 3) uint8 colour image with colorize_seg=True);
        normal (H, W, 3) float32 world-frame unit normals facing the camera, zero for background.
        While recording, the rgb frame is also appended to the recording. antialiasing and
        force_render are Genesis options without effect here (every call draws)."""
        if not self._scene.is_built:
            raise GenesisException(f"camera {self._idx}.render() before scene.build(): call scene.build() first "
                                   "(cameras can be added before or after building)")
        env = self._env()
        W, H = self._res
        if self._raster is None or (self._raster.W, self._raster.H, self._raster.f) != (W, H, self.f):
            self._raster = Rasterizer(W, H, self.f, self._near, self._far)
            self._static = None
        rs = self._raster
        dr = self._drawables()
        Rc = self._R  # world -> camera rotation (rows right, up, forward)
        light = Light(Rc @ LIGHT_DIR_WORLD)

        M = b = None
        if dr.rigid:
            Rl, pl = dr.link_poses(env)
            M = np.einsum("ij,ljk->lik", Rc, Rl)  # link -> camera rotations
            b = (pl - self._pos) @ Rc.T  # link origins in the camera frame
        # Planes cover most of a typical frame but rarely move: with a still camera their layer is
        # drawn once and restored from a snapshot afterwards.
        planes = []
        for row, T, ca, cb, seg in dr.planes:
            Rg = M[row] @ T[:3, :3]
            planes.append((M[row] @ T[:3, 3] + b[row], Rg[:, 2], Rg[:, 0], Rg[:, 1], ca, cb, seg))
        key = (np.concatenate([np.concatenate(p[:4]) for p in planes]) if planes else np.zeros(0), bool(normal))
        st = self._static
        same = st is not None and st[0][1] == key[1] and st[0][0].shape == key[0].shape
        if same and np.allclose(st[0][0], key[0], rtol=0, atol=1e-9):
            rs.restore(st[1], normals=normal)
        else:
            rs.clear(self._background(W, H), normals=normal)
            for p0, n, u, v, ca, cb, seg in planes:
                rs.draw_plane(p0, n, u, v, ca, cb, PLANE_TILE, seg, light)
            self._static = (key, rs.snapshot())
        if dr.n_faces:
            V = np.empty_like(dr.V)
            N = np.empty(dr.N.shape, np.float32)
            # vertices and faces are stored link by link: one small matrix product per link
            for row, (v0, v1), (f0, f1) in dr.link_ranges:
                V[v0:v1] = dr.V[v0:v1] @ M[row].T + b[row]
                N[f0:f1] = (dr.N[f0:f1].reshape(-1, 3) @ M[row].T).reshape(-1, 3, 3)  # one GEMM, not m tiny ones
            rs.draw_triangles(V, dr.F, N, dr.C, dr.S, light)
        for P, color, radius, seg in dr.particle_sets(env):
            if len(P):
                rs.draw_spheres((P - self._pos) @ Rc.T, radius, color, np.int32(seg), light)

        img = rs.rgb_uint8()
        if self._recording:
            self._spool.append(img)
        seg_out = None
        if segmentation:
            seg_out = rs.seg()
            if colorize_seg:
                from .drawables import PALETTE

                pal = np.vstack([np.zeros((1, 3)), PALETTE])
                seg_out = (pal[np.where(seg_out < 0, 0, seg_out % len(PALETTE) + 1)] * 255).astype(np.uint8)
        nrm = rs.normal() @ Rc if normal else None  # camera frame -> world frame
        return (img if rgb else None, rs.depth() if depth else None, seg_out, nrm)

    # ---------------------------------------------------------------- recording
    def start_recording(self):
        """Start collecting the frames of every later render() call."""
        if self._recording:
            raise GenesisException(f"camera {self._idx}: start_recording() while already recording; "
                                   "call stop_recording() first")
        if self._spool is not None:
            self._spool.close()
        self._spool = FrameSpool()
        self._recording = True

    def pause_recording(self):
        """Stop appending frames until resume_recording(), without ending the recording."""
        if self._spool is None:
            raise GenesisException(f"camera {self._idx}: pause_recording() without start_recording()")
        self._recording = False

    def resume_recording(self):
        if self._spool is None:
            raise GenesisException(f"camera {self._idx}: resume_recording() without start_recording()")
        self._recording = True

    def stop_recording(self, save_to_filename=None, fps=60):
        """Write the recorded frames to `save_to_filename` (.gif or .mp4, chosen by the extension;
        folders are created; default '<script name>_cam<idx>.mp4' in the working directory) at
        `fps` frames per second, and end the recording. If writing fails the frames are kept, so the
        call can be repeated with another file name. GIF delays are whole hundredths of a second (fps
        above 50 play at 50), and Pillow merges identical consecutive frames into one longer frame."""
        if self._spool is None:
            raise GenesisException(f"camera {self._idx}: stop_recording() without start_recording(); call "
                                   "cam.start_recording() before rendering the frames to record")
        if not (isinstance(fps, (int, float, np.integer, np.floating)) and np.isfinite(fps) and fps > 0):
            raise ValueError(f"camera {self._idx}.stop_recording(fps={fps!r}): fps must be a positive number")
        if save_to_filename is None:
            stem = os.path.splitext(os.path.basename(sys.argv[0] or "genesis_lite"))[0] or "genesis_lite"
            save_to_filename = f"{stem}_cam{self._idx}.mp4"
        path = check_output_path(save_to_filename)
        if self._spool.n == 0:
            raise GenesisException(f"camera {self._idx}: no frames were recorded; call cam.render() after each "
                                   "scene.step() between start_recording() and stop_recording()")
        self._recording = False
        write_video(self._spool, path, fps)
        n = self._spool.n
        self._spool.close()
        self._spool = None
        logger.info("camera %d: wrote %d frames to %s", self._idx, n, path)
        return path

    def __repr__(self):
        return (f"<gs.Camera {self._idx}: res={self._res}, pos={self._pos.tolist()}, lookat={self._lookat.tolist()}, "
                f"fov={self._fov}>")
