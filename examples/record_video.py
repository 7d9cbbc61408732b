"""Record a rollout to MP4 and GIF with no display: a Panda (example-robot-data, drawn from its visual
meshes) swings through a tower of boxes on the ground, seen by a camera placed as in Genesis.

    python examples/record_video.py [--seconds 3] [--out out/record_video] [--quick]

Writes <out>/rollout.mp4 (every step at 1/dt frames per second) and <out>/rollout.gif (every third
step, GIFs play at most 50 frames per second), and <out>/first_frame.png. Only pip packages are
needed (Pillow, imageio-ffmpeg): no OpenGL, no window.
"""
import os
import sys
import time

import numpy as np
import genesis_lite as gs  # before torch: its OpenMP threads then sleep between ops (README)
import torch


sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from example_utils import panda_urdf, parse_args, progress, summary  # noqa: E402


def main():
    t_start = time.time()

    def extra(ap):
        ap.add_argument("--seconds", type=float, default=3.0)
        ap.add_argument("--res", type=int, nargs=2, default=(640, 480), metavar=("W", "H"))

    args = parse_args("record_video", __doc__, extra)  # --quick: 0.3 s at 320x240
    seconds, res = (0.3, (320, 240)) if args.quick else (args.seconds, tuple(args.res))

    gs.init(backend=gs.cpu, precision="64")
    dt = 0.01
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt))
    scene.add_entity(gs.morphs.Plane())
    arm = scene.add_entity(gs.morphs.URDF(file=panda_urdf(), fixed=True))
    colors = [(0.9, 0.45, 0.2), (0.3, 0.6, 0.9), (0.5, 0.8, 0.35), (0.9, 0.75, 0.3)]
    for i, c in enumerate(colors):
        scene.add_entity(gs.morphs.Box(size=(0.08, 0.08, 0.08), pos=(0.45, 0.25, 0.04 + 0.081 * i)),
                         surface=gs.surfaces.Default(color=c))
    # cameras can be placed before build (as in Genesis) or after
    cam = scene.add_camera(res=res, pos=(1.7, -1.2, 1.1), lookat=(0.25, 0.1, 0.35), fov=40)
    side = scene.add_camera(res=res, pos=(0.3, 2.0, 0.6), lookat=(0.3, 0.0, 0.3), fov=45)
    scene.build()

    arm.set_dofs_kp(torch.tensor([600.0] * 7 + [100.0] * 2, dtype=torch.float64))
    arm.set_dofs_kv(torch.tensor([40.0] * 7 + [5.0] * 2, dtype=torch.float64))
    start = torch.tensor([-0.9, 0.3, 0.0, -2.0, 0.0, 2.3, 0.8, 0.04, 0.04], dtype=torch.float64)
    sweep = torch.tensor([1.2, 0.5, 0.0, -1.9, 0.0, 2.4, 0.8, 0.04, 0.04], dtype=torch.float64)
    arm.set_dofs_position(start)
    arm.control_dofs_position(sweep)

    t0 = time.time()
    first = cam.render()[0]  # the first render reads and decimates the robot's meshes
    from PIL import Image

    Image.fromarray(first).save(os.path.join(args.out, "first_frame.png"))
    print(f"first frame in {time.time() - t0:.1f} s (mesh files read on first use)")

    cam.start_recording()
    side.start_recording()
    steps = int(round(seconds / dt))
    render_s = 0.0
    for t in progress(range(steps), desc="record", total=steps):
        scene.step()
        r0 = time.perf_counter()
        cam.render()
        if t % 3 == 0:
            side.render()
        render_s += time.perf_counter() - r0
    mp4 = cam.stop_recording(save_to_filename=os.path.join(args.out, "rollout.mp4"), fps=round(1 / dt))
    gif = side.stop_recording(save_to_filename=os.path.join(args.out, "rollout.gif"), fps=round(1 / (3 * dt)))
    n_side = len(range(0, steps, 3))
    tower = np.array([0.04 + 0.081 * i for i in range(len(colors))])
    heights = np.array([e.get_pos()[2].item() for e in scene.entities[2:]])
    summary("record_video", [f"{steps} steps; rendering {1e3 * render_s / (steps + n_side):.1f} ms per frame "
                             f"({res[0]}x{res[1]}); {steps} MP4 frames, {n_side} GIF frames",
                             f"box heights (m): start {np.round(tower, 3).tolist()}, end {np.round(heights, 3).tolist()}"],
            [os.path.join(args.out, "first_frame.png"), mp4, gif], t_start)


if __name__ == "__main__":
    main()
