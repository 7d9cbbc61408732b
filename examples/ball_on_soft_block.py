"""Co-simulation: a rigid ball dropped on a soft elastic block (two-way rigid-MPM coupling). The ball
falls, presses into the block, bounces back out and settles on a dent; the block's top surface sags
under it and springs back. A camera records the drop to a GIF.

    python examples/ball_on_soft_block.py [--quick] [--seconds 1.2] [--out out/ball_on_soft_block]

Writes ball_on_soft_block.gif (the drop, side view), ball.csv (ball height, velocity and the vertical
force the block exerts on it per step), ball_on_soft_block.png (height, force against weight, the
block's top surface profile at the deepest press and at the end).
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


def main():
    t_start = time.time()
    args = parse_args("ball_on_soft_block", __doc__, lambda ap: ap.add_argument(
        "--seconds", type=float, default=1.2, help="simulated time (--quick: 0.3 s)"))
    quick = args.quick
    dens = 32 if quick else 64              # grid cells per metre
    seconds = 0.3 if quick else args.seconds
    dt, substeps = 2e-3, 8 if quick else 10
    res = (240, 180) if quick else (480, 360)

    gs.init(backend=gs.cpu, precision="64")
    wall = 3.0 / dens                       # the grid's 3 outer cells are walls: the floor is at z = 3 dx
    L, H = 0.4, 0.4                         # domain width and height (m)
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, substeps=substeps),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(L, L, H), grid_density=dens))
    block_h = 0.1
    block = scene.add_entity(gs.morphs.Box(pos=(L / 2, L / 2, wall + block_h / 2), size=(0.18, 0.18, block_h)),
                             material=gs.materials.MPM.Elastic(E=3e4, nu=0.3, rho=1000),
                             surface=gs.surfaces.Default(color=(0.35, 0.6, 0.9)))
    r = 0.04
    z_drop = wall + block_h + r + 0.1       # dropped from 10 cm above the block
    ball = scene.add_entity(gs.morphs.Sphere(pos=(L / 2, L / 2, z_drop), radius=r),
                            material=gs.materials.Rigid(rho=1500, coup_friction=0.5),
                            surface=gs.surfaces.Default(color=(0.9, 0.35, 0.2)))
    cam = scene.add_camera(res=res, pos=(L / 2 + 0.05, L / 2 - 0.8, 0.3), lookat=(L / 2, L / 2, 0.1), fov=35)
    scene.build()
    print(f"{block} and a {ball.get_mass().item():.3f} kg ball, built in {time.time() - t_start:.1f} s")

    steps = int(round(seconds / dt))
    every = max(1, int(round(1 / (25 * dt))))  # 25 frames per simulated second
    weight = ball.get_mass().item() * G
    z, vz, fz = [], [], []
    top0 = block.get_particles_pos()[:, 2].max().item()
    deepest, profile_deep = np.inf, None
    cam.start_recording()
    cam.render()
    for t in progress(range(steps), desc="simulate", total=steps):
        scene.step()
        z.append(ball.get_pos()[2].item())
        vz.append(ball.get_vel()[2].item())
        fz.append(ball.get_links_mpm_force()[0, 2].item())
        if z[-1] < deepest:
            deepest, profile_deep = z[-1], block.get_particles_pos().numpy().copy()
        if (t + 1) % every == 0:
            cam.render()
    gif = cam.stop_recording(save_to_filename=os.path.join(args.out, "ball_on_soft_block.gif"), fps=25)
    profile_end = block.get_particles_pos().numpy()
    written = [gif]
    t_axis = np.arange(1, steps + 1) * dt
    write_csv(args.out, "ball.csv", ["t", "z", "vz", "Fz_from_block"], [t_axis, z, vz, fz], written)

    z_rest = wall + block_h + r             # where the ball would touch an undeformed block
    sink = z_rest - deepest
    end_sink = z_rest - z[-1]
    if sink <= 0:
        raise SystemExit(f"the ball never pressed into the block (lowest centre {deepest:.4f} m, contact at {z_rest:.4f} m)")

    plt = pyplot()
    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    ax[0].plot(t_axis, z, label="ball centre")
    ax[0].axhline(z_rest, ls="--", c="gray", label="touching the undeformed block")
    ax[0].set_xlabel("t (s)")
    ax[0].set_ylabel("z (m)")
    ax[0].legend()
    ax[1].plot(t_axis, fz, label="force of the block on the ball")
    ax[1].axhline(weight, ls="--", c="gray", label=f"weight {weight:.2f} N")
    ax[1].set_xlabel("t (s)")
    ax[1].set_ylabel("Fz (N)")
    ax[1].legend()
    ps = scene.mpm_options.particle_size
    for P, lab in ((profile_deep, "deepest press"), (profile_end, "end")):
        sel = np.abs(P[:, 1] - L / 2) < ps      # the particle columns through the centre
        col = np.round((P[sel, 0] - P[sel, 0].min()) / ps).astype(int)
        top = np.array([(P[sel, 0][col == c].mean(), P[sel, 2][col == c].max()) for c in np.unique(col)])
        ax[2].plot(top[:, 0], top[:, 1], "o-", ms=3, label=lab)
    ax[2].axhline(top0, ls="--", c="gray", label="top before")
    ax[2].set_xlabel("x (m)")
    ax[2].set_ylabel("top surface z (m)")
    ax[2].legend()
    ax[2].set_title("block surface, slice through the centre")
    save_figure(fig, args.out, "ball_on_soft_block.png", written)
    summary("ball_on_soft_block", [
        f"{block.n_particles} particles, grid {dens} cells/m, {steps} steps of {dt} s ({substeps} substeps)",
        f"deepest press {1e3 * sink:.1f} mm into the block; at the end {1e3 * end_sink:.1f} mm, ball speed {abs(vz[-1]):.3f} m/s",
        f"block force at the end {fz[-1]:.3f} N against a weight of {weight:.3f} N",
    ], written, t_start)


if __name__ == "__main__":
    main()
