"""Co-simulation with optimised controls: a URDF arm (assets/urdf/arm.urdf, 4 joints, PD position
control) presses its tool into a block of plasticine (von Mises elasto-plastic MPM). The target is the
dent that known controls leave; from a wrong guess, gradient descent through the rollout (MPM,
coupling and the arm's dynamics) finds PD targets that leave nearly the same dent.

Controls: offsets of the shoulder-pitch and elbow PD targets from the start pose at 3 knots (at 1/3,
2/3 and all of the horizon), interpolated linearly in time: 6 numbers (rad). Loss: mean over
particles of |final position - target position|^2 (m^2). Adam on the knots with a decaying rate;
the best iterate is kept.

The coupling is two-way (the default CouplerOptions): the tool moves the material, the arm feels the
material's reaction through its joints, and the gradient runs through both directions (the gradient
matrix's arm_press case checks it against central finite differences in float64, on this scene at 32
cells/m and 6 steps). The block rests on the MPM domain's floor, frictionless as Genesis's walls are, so
the press also pushes it along. The arm is position-controlled and much heavier than the forces the
plasticine puts on it, so the reaction shifts its last link by a fraction of a millimetre; its lag
behind the PD targets (~0.04 rad) is its own dynamics.

What is fitted is the dent, not the controls: in the full run the rms distance of the particles to their
target falls from 21.5 mm to 3.7 mm (2026-11-28), but the fitted knots are not the true ones (up to 0.09
rad off): other controls leave nearly the same dent, and on the way from them to the true knots the loss
rises before it falls. The loss is only piecewise smooth: the rigid boundary on the MPM grid makes
discrete choices (the geom a node answers to, the face of a box it is pushed out through), and where one
changes, the loss jumps by up to ~3e-4 of its value. Adam needs no line search, which such jumps can
stall.

    python examples/arm_press_plasticine.py [--quick] [--iters 30] [--out out/arm_press_plasticine]

Writes fitted_press.gif (the rollout of the fitted controls), loss.csv, knots.md (true / initial /
fitted), arm_press_plasticine.png (loss curve and the plasticine's top surface: target, initial
guess, fitted) and before_after.png (camera views of the final dent: target, initial guess, fitted).
"""
import os
import sys
import time

import numpy as np
import genesis_lite as gs  # before torch: its OpenMP threads then sleep between ops (README)
import torch


sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from example_utils import (format_table, parse_args, progress, pyplot, repo_path, save_figure, summary,  # noqa: E402
                           write_csv, write_text)

F64 = dict(dtype=torch.float64)


def heightmap(P, ps):
    """Top of the plasticine per particle column: (x, y, z_max) rows, columns keyed by rounding to the
    particle spacing ps (m)."""
    key = np.round(P[:, :2] / ps).astype(int)
    cols = {}
    for k, z in zip(map(tuple, key), P[:, 2]):
        cols[k] = max(cols.get(k, -np.inf), z)
    return np.array([(a * ps, b * ps, z) for (a, b), z in cols.items()])


def main():
    t_start = time.time()
    args = parse_args("arm_press_plasticine", __doc__, lambda ap: ap.add_argument(
        "--iters", type=int, default=30, help="Adam iterations (--quick: 2)"))
    quick = args.quick
    dens = 40 if quick else 56
    iters = 2 if quick else args.iters
    T = 60 if quick else 150
    dt, substeps = 2e-3, 10

    gs.init(backend=gs.cpu, precision="64")
    wall = 3.0 / dens
    L, H = 0.3, 0.25
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, substeps=substeps, requires_grad=True),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(L, L, H), grid_density=dens))
    block = scene.add_entity(gs.morphs.Box(pos=(L / 2, L / 2, wall + 0.025), size=(0.1, 0.1, 0.05)),
                             material=gs.materials.MPM.ElastoPlastic(E=5e4, nu=0.3, yield_stress=2e3),
                             surface=gs.surfaces.Default(color=(0.85, 0.5, 0.6)))
    top = wall + 0.05
    # start pose: shoulder pitch a, elbow pi - a, so the last link points straight down; its tool box
    # (merged into link4, 0.115 m below the wrist, 3 cm tall) then hangs 1 cm above the block
    a = 1.2
    q_start = torch.tensor([0.0, a, np.pi - a, 0.0], **F64)
    base = (L / 2 - 0.35 * np.sin(a), L / 2, top + 0.015 + 0.01 - (0.3 + 0.35 * np.cos(a) - 0.415))
    arm = scene.add_entity(gs.morphs.URDF(file=repo_path("assets", "urdf", "arm.urdf"), fixed=True, pos=base))
    cam = scene.add_camera(res=(240, 180) if quick else (400, 300), pos=(L / 2 + 0.25, L / 2 - 0.35, 0.35),
                           lookat=(L / 2, L / 2, wall + 0.03), fov=35)
    scene.build()
    arm.set_dofs_kp(torch.tensor([2000.0, 2000.0, 2000.0, 500.0], **F64))
    arm.set_dofs_kv(torch.tensor([100.0, 100.0, 100.0, 20.0], **F64))
    print(f"{block}, {arm}; built in {time.time() - t_start:.1f} s")

    knot_t = np.array([1 / 3, 2 / 3, 1.0]) * T

    def targets(knots):
        """PD targets per step: q_start + offsets (pitch, elbow) interpolated from 0 at t = 0."""
        k = torch.cat([torch.zeros(1, 2, **F64), knots.reshape(3, 2)])
        tk = np.concatenate([[0.0], knot_t])
        out = []
        for t in range(T):
            i = min(int(np.searchsorted(tk, t, side="right")) - 1, 2)
            w = (t - tk[i]) / (tk[i + 1] - tk[i])
            off = (1 - w) * k[i] + w * k[i + 1]
            out.append(q_start + torch.stack([off.new_zeros(()), off[0], off[1], off.new_zeros(())]))
        return out

    def rollout(knots, every=0):
        """Final particle positions (m); with every > 0 the camera renders every that many steps."""
        scene.reset()
        arm.set_dofs_position(q_start)
        for t, q in enumerate(targets(knots)):
            arm.control_dofs_position(q)
            scene.step()
            if every and t % every == 0:
                cam.render()
        return block.get_particles_pos()

    # (pitch, elbow) offsets at the 3 knots, rad: press 2-3 cm down, then drag the tool sideways
    true_knots = torch.tensor([0.05, 0.0, 0.09, -0.04, 0.09, -0.12], **F64)
    init_knots = torch.tensor([0.03, 0.0, 0.05, 0.0, 0.05, 0.0], **F64)
    with torch.no_grad():
        target = rollout(true_knots).clone()
        img_target = cam.render()[0]
        initial = rollout(init_knots).clone()
        img_initial = cam.render()[0]

    knots = init_knots.clone().requires_grad_(True)
    opt = torch.optim.Adam([knots], lr=0.01)
    # a decaying rate: at a constant one Adam circles the minimum at a few times its loss
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=0.92)
    history, best = [], (np.inf, None)
    bar = progress(range(iters), desc="Adam", total=iters)
    for it in bar:
        opt.zero_grad()
        loss = ((rollout(knots) - target) ** 2).sum(1).mean()
        loss.backward()
        history.append(loss.item())
        if loss.item() < best[0]:
            best = (loss.item(), knots.detach().clone())
        opt.step()
        sched.step()
        if hasattr(bar, "set_postfix"):
            bar.set_postfix(loss=f"{loss.item():.3e}")
    with torch.no_grad():
        knots.copy_(best[1])
        cam.start_recording()
        final_loss = ((rollout(knots, every=3) - target) ** 2).sum(1).mean().item()
        gif = cam.stop_recording(save_to_filename=os.path.join(args.out, "fitted_press.gif"), fps=round(1 / (3 * dt)))
        fitted = block.get_particles_pos().clone()
        img_fit = cam.render()[0]
    history.append(final_loss)
    if not history[-1] < history[0]:
        raise SystemExit(f"the loss did not decrease: {history[0]:.4e} -> {history[-1]:.4e}")

    written = [gif]
    write_csv(args.out, "loss.csv", ["iteration", "loss_m2"], [np.arange(len(history)), history], written)
    names = [f"{j} knot {k + 1}" for k in range(3) for j in ("pitch", "elbow")]
    table = format_table(["offset (rad)", "true", "initial", "fitted"],
                         [[n, t, i, f] for n, t, i, f in zip(names, true_knots.tolist(), init_knots.tolist(),
                                                             knots.detach().tolist())])
    write_text(args.out, "knots.md", table, written)
    plt = pyplot()
    ps = scene.mpm_options.particle_size
    maps = [heightmap(P.numpy(), ps) for P in (target, initial, fitted)]
    zlo, zhi = min(m[:, 2].min() for m in maps), top
    fig, ax = plt.subplots(1, 4, figsize=(18, 4))
    ax[0].semilogy(history)
    ax[0].set_xlabel("Adam iteration")
    ax[0].set_ylabel("mean |x - x_target|^2 (m^2)")
    ax[0].set_title("loss")
    for a_, m, lab in zip(ax[1:], maps, ("target dent", "initial guess", "fitted")):
        sc = a_.scatter(m[:, 0], m[:, 1], c=m[:, 2], vmin=zlo, vmax=zhi, cmap="viridis", s=40, marker="s")
        a_.set_aspect("equal")
        a_.set_title(f"{lab}: top surface z (m)")
        a_.set_xlabel("x (m)")
        fig.colorbar(sc, ax=a_)
    save_figure(fig, args.out, "arm_press_plasticine.png", written)
    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    for a_, img, lab in zip(ax, (img_target, img_initial, img_fit), ("target", "initial guess", "fitted")):
        a_.imshow(img)
        a_.set_title(lab)
        a_.axis("off")
    save_figure(fig, args.out, "before_after.png", written)
    summary("arm_press_plasticine", [
        f"{block.n_particles} plasticine particles, grid {dens} cells/m, {T} steps of {dt} s ({substeps} substeps)",
        f"loss {history[0]:.4e} -> {history[-1]:.4e} m^2 in {iters} Adam iterations "
        f"(rms particle distance {1e3 * np.sqrt(history[0]):.2f} -> {1e3 * np.sqrt(history[-1]):.2f} mm)",
        table,
    ], written, t_start)


if __name__ == "__main__":
    main()
