"""Camera rendering speed: milliseconds per 640x480 frame of the numpy rasteriser, and the cost of
writing videos.

    python benchmarks/bench_vis.py [--quick] [--frames 30] [--json out.json]

Scene: example-robot-data's Panda (its <visual> COLLADA meshes, 134k triangles in the files,
decimated to MAX_FACES_PER_MESH per file at first render) at a non-trivial pose on a ground plane,
optionally with 20,000 particles (a stand-in for an MPM entity: an object with get_particles_pos(),
filling a 0.3 x 0.3 x 0.2 m block beside the robot). The camera sits 1.9 m from the robot looking at
its middle (fov 40 deg), so the robot fills about a third of the image height. Each row is the
median over `--frames` renders of `cam.render()` (wall clock, and CPU time of this process, which
is what to compare when other jobs share the cores) (rgb only; depth, segmentation and normal add
little): "still" keeps the camera fixed (the ground layer is drawn once and reused), "orbit" moves
it every frame (the ground is redrawn each time). The robot moves between frames in both. "First
render" includes reading, decimating and shading-normal preparation of the mesh files (not done at
build). Video rows time stop_recording() for the frames rendered, per frame.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parents[1]))  # genesis_lite without an install
from common import panda_urdf, print_table  # noqa: E402


class ParticleBlock:
    """A stand-in for an MPM entity: fixed random particles that sink a little each frame."""

    def __init__(self, n, lo, hi, seed=0):
        rng = np.random.default_rng(seed)
        self._P0 = rng.uniform(lo, hi, size=(n, 3))
        self.n_particles = n
        self._vis_color = (0.85, 0.45, 0.3)
        self._vis_radius = 0.5 * (np.prod(np.subtract(hi, lo)) / n) ** (1 / 3)
        self.t = 0

    def get_particles_pos(self):
        import torch

        # numpy arithmetic: torch's 2-thread elementwise ops spin for milliseconds on a loaded 2-core box
        return torch.from_numpy(self._P0 - np.array([0.0, 0.0, 1e-3 * self.t]))


def run(frames: int, particles: int):
    import torch

    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")
    rows = []
    for with_particles in (False, True):
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
        scene.add_entity(gs.morphs.Plane())
        arm = scene.add_entity(gs.morphs.URDF(file=str(panda_urdf()), fixed=True))
        pos0 = np.array([1.6, 0.9, 1.1])
        cam = scene.add_camera(res=(640, 480), pos=tuple(pos0), lookat=(0.1, 0.0, 0.4), fov=40)
        scene.build()
        block = None
        if with_particles:
            block = ParticleBlock(particles, (0.35, -0.45, 0.0), (0.65, -0.15, 0.2))
            scene.entities.append(block)  # after build: the solver never sees it, the camera does
        arm.set_dofs_kp(torch.tensor([400.0] * 7 + [100.0] * 2, dtype=torch.float64))
        arm.set_dofs_position(torch.tensor([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8, 0.02, 0.02], dtype=torch.float64))
        arm.control_dofs_position(torch.tensor([0.6, 0.2, 0.2, -1.8, 0.2, 1.6, 0.6, 0.03, 0.03], dtype=torch.float64))
        t0 = time.perf_counter()
        cam.render()
        first = time.perf_counter() - t0
        label = "Panda + plane" + (f" + {particles:,} particles" if with_particles else "")
        for mode in ("still", "orbit"):
            times, cpu = [], []
            if mode == "still":
                cam.start_recording()
            for k in range(frames):
                scene.step()
                if block is not None:
                    block.t += 1
                if mode == "orbit":
                    a = 0.05 * (k + 1)
                    c, s = np.cos(a), np.sin(a)
                    cam.set_pose(pos=(c * pos0[0] - s * pos0[1], s * pos0[0] + c * pos0[1], pos0[2]))
                t0, c0 = time.perf_counter(), time.process_time()
                cam.render()
                times.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            row = {"scene": label, "camera": mode, "ms": 1e3 * statistics.median(times),
                   "p90": 1e3 * float(np.percentile(times, 90)), "cpu": 1e3 * statistics.median(cpu), "tris": scene._vis_drawables.n_faces}
            if mode == "still":
                row["first"] = first
                with tempfile.TemporaryDirectory() as d:
                    for ext in ("mp4", "gif"):
                        if ext == "gif":  # record a fresh set of (moving) frames for the GIF
                            cam.start_recording()
                            for _ in range(frames):
                                scene.step()
                                cam.render()
                        t0 = time.perf_counter()
                        cam.stop_recording(save_to_filename=f"{d}/x.{ext}", fps=30)
                        row[f"{ext}_ms"] = 1e3 * (time.perf_counter() - t0) / frames
            rows.append(row)
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="5 frames per row")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--particles", type=int, default=20_000)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    frames = 5 if args.quick else args.frames
    rows = run(frames, args.particles)
    print_table(rows, [("scene", "scene", ""), ("camera", "camera", ""), ("tris", "triangles", "d"),
                       ("ms", "ms/frame (median)", ".1f"), ("p90", "p90", ".1f"), ("cpu", "CPU ms/frame", ".1f"), ("first", "first render (s)", ".2f"),
                       ("mp4_ms", "mp4 write ms/frame", ".1f"), ("gif_ms", "gif write ms/frame", ".1f")],
                title=f"640x480 frames, {frames} per row, numpy rasteriser on this machine's CPU")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
