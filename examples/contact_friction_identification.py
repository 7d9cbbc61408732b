"""Parameter identification (b): the friction coefficient of a box from its sliding. A box is launched
along the ground and slides to rest; its x position, observed with 0.5 mm of Gaussian noise, comes
from the simulator with the true coefficient. From a guess a third of it, L-BFGS-B on log(mu) (bounded to 0.02-1.5; through
`box.set_friction(mu)` and the contact model) fits the simulated slide to the observed one; the
closed form v0^2 / (2 g d) from the observed stopping distance is printed beside it.

    python examples/contact_friction_identification.py [--quick] [--iters 10] [--out out/contact_friction_identification]

Writes fit.md (true / initial / fitted / error %), loss.csv, trajectories.csv and
friction_identification.png (loss curve, mu per iteration, observed against fitted slide).
"""
import os
import sys
import time

import numpy as np
import genesis_lite as gs  # before torch: its OpenMP threads then sleep between ops (README)
import torch


sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from example_utils import (fit_log_lbfgsb, identification_table, parse_args, pyplot, save_figure, summary,  # noqa: E402
                           write_csv, write_text)

F64 = dict(dtype=torch.float64)


def main():
    t_start = time.time()
    args = parse_args("contact_friction_identification", __doc__, lambda ap: ap.add_argument(
        "--iters", type=int, default=10, help="L-BFGS-B iterations (--quick: 1)"))
    quick = args.quick
    iters = 1 if quick else args.iters
    T = 40 if quick else 100
    dt = 0.01

    gs.init(backend=gs.cpu, precision="64")
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, requires_grad=True))
    scene.add_entity(gs.morphs.Plane(), material=gs.materials.Rigid(friction=0.0))
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0.0, 0.0, 0.1)))
    scene.build()
    with torch.no_grad():  # settle onto the ground first
        for _ in range(20):
            scene.step()
    start = scene.get_state()
    x0 = box.get_pos()[0].item()
    V0 = 2.5  # m/s

    def rollout(mu):
        """x (m) of the box over T steps after launching it at V0 with friction mu (the ground's is 0:
        a contact uses the larger coefficient of its two geoms)."""
        scene.reset(start)
        box.set_friction(mu)
        box.set_dofs_velocity(torch.tensor([V0, 0, 0, 0, 0, 0], **F64))
        xs = []
        for _ in range(T):
            scene.step()
            xs.append(box.get_pos()[0])
        return torch.stack(xs)

    true = torch.tensor(0.45, **F64)
    init = torch.tensor(0.15, **F64)
    noise = 5e-4  # m
    rng = np.random.default_rng(0)
    with torch.no_grad():
        observed = rollout(true) + torch.tensor(rng.normal(0.0, noise, T), **F64)
        guess = rollout(init)
    # in units of the noise's variance: ~1 at the optimum
    losses, trace = fit_log_lbfgsb(lambda p: ((rollout(p[0]) - observed) ** 2).mean() / noise ** 2, [init.item()],
                                   0.02, 1.5, iters, postfix=lambda p: dict(mu=f"{p[0]:.4f}"))
    trace = [float(p[0]) for p in trace]
    fitted = torch.tensor(trace[-1], **F64)
    with torch.no_grad():
        fit = rollout(fitted)
    loss0 = ((guess - observed) ** 2).mean().item() / noise ** 2
    final_loss = ((fit - observed) ** 2).mean().item() / noise ** 2
    if not final_loss < loss0:
        raise SystemExit(f"the loss did not decrease: {loss0:.4e} -> {final_loss:.4e}")
    # the slide's distance from launch to rest; a short --quick horizon ends before the box stops
    d = observed[-1].item() - x0
    closed = V0 ** 2 / (2 * 9.81 * d)

    table, worst = identification_table(["friction coefficient mu"], [true.item()], [init.item()], [fitted.item()])
    written = []
    write_text(args.out, "fit.md", table, written)
    write_csv(args.out, "loss.csv", ["iteration", "loss_over_noise_var", "mu"],
              [np.arange(len(losses)), losses, trace], written)
    tt = (np.arange(T) + 1) * dt
    write_csv(args.out, "trajectories.csv", ["t", "x_observed", "x_guess", "x_fit"],
              [tt, observed.numpy(), guess.numpy(), fit.numpy()], written)
    plt = pyplot()
    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    ax[0].semilogy(losses, "o-")
    ax[0].set_xlabel("L-BFGS-B iteration")
    ax[0].set_ylabel("mean (x - x_obs)^2 / (0.5 mm)^2")
    ax[0].set_title("loss")
    ax[1].plot(trace, "o-")
    ax[1].axhline(true.item(), c="gray", ls="--", label="true")
    ax[1].set_xlabel("L-BFGS-B iteration")
    ax[1].set_ylabel("mu")
    ax[1].legend()
    ax[2].plot(tt, observed.numpy(), "k.", ms=3, label=f"observed (mu = {true.item()}, noisy)")
    ax[2].plot(tt, guess.numpy(), "--", label=f"initial guess (mu = {init.item()})")
    ax[2].plot(tt, fit.numpy(), "-", label=f"fitted (mu = {fitted.item():.4f})")
    ax[2].set_xlabel("t (s)")
    ax[2].set_ylabel("box x (m)")
    ax[2].legend()
    save_figure(fig, args.out, "friction_identification.png", written)
    summary("contact_friction_identification", [
        f"box launched at {V0} m/s, {T} steps of {dt} s, x observed with {noise * 1e3:.1f} mm noise",
        f"loss (mean (x - x_obs)^2 / noise^2) {loss0:.4e} -> {final_loss:.4e} in {len(losses) - 1} L-BFGS-B iterations; "
        f"error {worst:.3f} %",
        f"closed form v0^2 / (2 g d) from the observed slide: {closed:.4f}" + (" (the quick horizon ends before the box "
                                                                               "stops)" if quick else ""),
        table], written, t_start)
    if not quick and worst > 2.0:  # the full run's promise: every parameter within 2 %
        raise SystemExit(f"an identified value is {worst:.2f} % off (more than 2 %)")


if __name__ == "__main__":
    main()
