"""Co-simulation: a rigid blade pushed through a bed of sand (Drucker-Prager MPM, two-way coupling).
The blade moves at a prescribed speed, like a bulldozer's; the sand heaps up in front of it and
flows round its sides, and the drag it puts on the blade (read with get_links_mpm_force) grows with
the heap. A camera records the push to a GIF.

    python examples/push_through_sand.py [--quick] [--seconds 0.8] [--out out/push_through_sand]

Writes push_through_sand.gif, drag.csv (blade position and the force of the sand on it per step) and
push_through_sand.png (drag against distance, the sand's surface before and after).
"""
import os
import sys
import time

import numpy as np
import genesis_lite as gs  # before torch: its OpenMP threads then sleep between ops (README)
import torch


sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from example_utils import parse_args, progress, pyplot, save_figure, summary, write_csv  # noqa: E402

F64 = dict(dtype=torch.float64)
G = 9.81


def surface(P, x_edges):
    """Mean over y of the sand's top (m) in bins of x: the highest particle per (x, y) column."""
    ps = np.diff(x_edges).mean()
    ix = np.digitize(P[:, 0], x_edges) - 1
    iy = np.round(P[:, 1] / ps).astype(int)
    tops = {}
    for a, b, z in zip(ix, iy, P[:, 2]):
        tops[(a, b)] = max(tops.get((a, b), -np.inf), z)
    out = np.full(len(x_edges) - 1, np.nan)
    for a in range(len(x_edges) - 1):
        v = [z for (i, _), z in tops.items() if i == a]
        if v:
            out[a] = np.mean(v)
    return out


def main():
    t_start = time.time()
    args = parse_args("push_through_sand", __doc__, lambda ap: ap.add_argument(
        "--seconds", type=float, default=0.8, help="simulated time (--quick: 0.25 s)"))
    quick = args.quick
    dens = 40 if quick else 64
    seconds = 0.25 if quick else args.seconds
    dt, substeps = 2e-3, 10
    res = (240, 180) if quick else (480, 360)

    gs.init(backend=gs.cpu, precision="64")
    wall = 3.0 / dens
    Lx, Ly, Lz = 0.5, 0.3, 0.25
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, substeps=substeps),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(Lx, Ly, Lz),
                                                       grid_density=dens))
    bed_h = 0.06
    bed_x0, bed_x1 = 0.16, Lx - wall - 0.002
    bed_w = Ly - 2 * wall - 0.004
    sand = scene.add_entity(gs.morphs.Box(pos=((bed_x0 + bed_x1) / 2, Ly / 2, wall + bed_h / 2),
                                          size=(bed_x1 - bed_x0, bed_w, bed_h)),
                            material=gs.materials.MPM.Sand(E=2e5, nu=0.3, rho=1600, friction_angle=35),
                            surface=gs.surfaces.Default(color=(0.85, 0.72, 0.45)))
    blade_size = (0.03, 0.12, 0.08)
    blade = scene.add_entity(gs.morphs.Box(pos=(0.11, Ly / 2, wall + 0.005 + blade_size[2] / 2), size=blade_size),
                             material=gs.materials.Rigid(rho=2000, coup_friction=0.4),
                             surface=gs.surfaces.Default(color=(0.35, 0.35, 0.4)))
    cam = scene.add_camera(res=res, pos=(Lx / 2 + 0.15, -0.45, 0.4), lookat=(Lx / 2, Ly / 2, 0.03), fov=40)
    scene.build()
    print(f"{sand} built in {time.time() - t_start:.1f} s")

    speed = 0.3  # m/s along +x
    weight = blade.get_mass().item() * G
    ps = scene.mpm_options.particle_size
    x_edges = np.arange(wall, Lx - wall + ps, 2 * ps)
    # the bed's free edge slumps towards its angle of repose: let it settle, blade held still, before
    # the surface it is compared against is taken
    settle = int(round((0.04 if quick else 0.15) / dt))
    for _ in progress(range(settle), desc="settle", total=settle):
        blade.set_dofs_velocity(torch.zeros(6, **F64))
        blade.control_dofs_force(torch.tensor([0, 0, weight, 0, 0, 0], **F64))
        scene.step()
    before = surface(sand.get_particles_pos().numpy(), x_edges)
    steps = int(round(seconds / dt))
    every = max(1, int(round(1 / (25 * dt))))
    xs, fx, fz = [], [], []
    cam.start_recording()
    cam.render()
    for t in progress(range(steps), desc="push", total=steps):
        # prescribed motion: the velocity is reset every step and gravity is held by a lifting force,
        # so the sand's push shows up as a force, not as a change of course
        blade.set_dofs_velocity(torch.tensor([speed, 0, 0, 0, 0, 0], **F64))
        blade.control_dofs_force(torch.tensor([0, 0, weight, 0, 0, 0], **F64))
        scene.step()
        xs.append(blade.get_pos()[0].item())
        f = blade.get_links_mpm_force()[0].numpy()
        fx.append(f[0])
        fz.append(f[2])
        if (t + 1) % every == 0:
            cam.render()
    gif = cam.stop_recording(save_to_filename=os.path.join(args.out, "push_through_sand.gif"), fps=25)
    after = surface(sand.get_particles_pos().numpy(), x_edges)
    written = [gif]
    write_csv(args.out, "drag.csv", ["t", "blade_x", "Fx_from_sand", "Fz_from_sand"],
              [np.arange(1, steps + 1) * dt, xs, fx, fz], written)

    front = xs[-1] + blade_size[0] / 2
    xc = 0.5 * (x_edges[1:] + x_edges[:-1])
    ahead = (xc > front) & (xc < front + 0.05)
    heap = np.nanmax(after[ahead]) - np.nanmean(before[ahead]) if ahead.any() else np.nan
    win = max(1, steps // 10)
    drag_end = -np.mean(fx[-win:])
    if not drag_end > 0:
        raise SystemExit(f"the sand did not resist the blade (mean Fx over the last {win} steps {-drag_end:.3f} N)")

    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(12, 4))
    ax[0].plot(np.array(xs) - xs[0], -np.array(fx))
    ax[0].set_xlabel("blade travel (m)")
    ax[0].set_ylabel("drag -Fx (N)")
    ax[0].set_title(f"sand drag at {speed} m/s")
    ax[1].plot(xc, before, label="before (settled)")
    ax[1].plot(xc, after, label="after")
    ax[1].axvline(front, c="gray", ls="--", label="blade front at the end")
    ax[1].set_xlabel("x (m)")
    ax[1].set_ylabel("sand surface z, mean over y (m)")
    ax[1].legend()
    save_figure(fig, args.out, "push_through_sand.png", written)
    summary("push_through_sand", [
        f"{sand.n_particles} sand particles, grid {dens} cells/m, {steps} steps of {dt} s ({substeps} substeps)",
        f"blade pushed {xs[-1] - xs[0] + speed * dt:.3f} m at {speed} m/s; drag at the end {drag_end:.3f} N "
        f"(blade weight {weight:.3f} N); heap ahead of it {1e3 * heap:.1f} mm above the initial surface",
    ], written, t_start)


if __name__ == "__main__":
    main()
