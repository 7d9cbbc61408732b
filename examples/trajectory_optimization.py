"""The trajectory-optimisation example of Genesis's differentiable-simulation page (scene.reset()
inside the epoch loop, Adam on a control sequence), on the project's 4-dof arm: the tool link is
driven to a target point.

    python examples/trajectory_optimization.py [--quick] [--epochs 60] [--steps 100] [--out out/trajectory_optimization]

Writes loss.csv (loss per epoch), controls.csv (the optimised torques) and trajectory_optimization.png
(loss curve, optimised torques, tool path before/after).
"""
import os
import sys
import time

import numpy as np
import genesis_lite as gs  # before torch: its OpenMP threads then sleep between ops (README)
import torch


sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from example_utils import parse_args, progress, pyplot, repo_path, save_figure, summary, write_csv  # noqa: E402


def extra(ap):
    ap.add_argument("--epochs", type=int, default=60, help="Adam iterations (--quick: 4)")
    ap.add_argument("--steps", type=int, default=100, help="steps of 10 ms (--quick: 30)")


t_start = time.time()
args = parse_args("trajectory_optimization", __doc__, extra)
epochs, n_steps = (4, 30) if args.quick else (args.epochs, args.steps)

gs.init(backend=gs.cpu, precision="64")
scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True))
robot = scene.add_entity(gs.morphs.URDF(file=repo_path("assets", "urdf", "arm.urdf"), fixed=True))
scene.build()

n_dofs = robot.n_dofs
controls = torch.zeros(n_steps, n_dofs, requires_grad=True, device=gs.device, dtype=gs.tc_float)
optimizer = torch.optim.Adam([controls], lr=0.5)
target = torch.tensor([0.3, 0.3, 0.6], device=gs.device, dtype=gs.tc_float)


def rollout(path=None):
    scene.reset()
    for t in range(n_steps):
        robot.control_dofs_force(controls[t])
        scene.step()
        if path is not None:
            path.append(robot.get_links_pos()[-1].detach().numpy().copy())
    return robot.get_links_pos()[-1]


history = []
path_before, path_after = [], []
bar = progress(range(epochs), desc="Adam", total=epochs)
for epoch in bar:
    scene.reset()
    final_pos = rollout(path_before if epoch == 0 else None)
    loss = torch.nn.functional.mse_loss(final_pos, target) + 1e-5 * (controls ** 2).mean()
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    history.append(loss.item())
    if hasattr(bar, "set_postfix"):
        bar.set_postfix(loss=f"{loss.item():.3e}")
with torch.no_grad():
    final_pos = rollout(path_after)
final_err = (final_pos - target).norm().item()

written = []
write_csv(args.out, "loss.csv", ["epoch", "loss"], [np.arange(epochs), history], written)
u = controls.detach().numpy()
write_csv(args.out, "controls.csv", ["t"] + [f"u{i}" for i in range(n_dofs)],
          [np.arange(n_steps) * 0.01] + [u[:, i] for i in range(n_dofs)], written)
plt = pyplot()
fig = plt.figure(figsize=(14, 4))
ax0 = fig.add_subplot(1, 3, 1)
ax0.semilogy(history)
ax0.set_xlabel("epoch")
ax0.set_ylabel("loss (m^2)")
ax0.set_title("Adam on the torques")
ax1 = fig.add_subplot(1, 3, 2)
ax1.plot(np.arange(n_steps) * 0.01, u)
ax1.set_xlabel("t (s)")
ax1.set_ylabel("torque (N m)")
ax1.set_title("optimised controls")
ax2 = fig.add_subplot(1, 3, 3, projection="3d")
for pth, lab in ((path_before, "before"), (path_after, "after")):
    pth = np.array(pth)
    ax2.plot(pth[:, 0], pth[:, 1], pth[:, 2], label=lab)
ax2.scatter(*target.numpy(), color="r", marker="*", s=120, label="target")
ax2.set_title("tool path")
ax2.legend()
save_figure(fig, args.out, "trajectory_optimization.png", written)
summary("trajectory_optimization", [f"{epochs} epochs of {n_steps} steps; loss {history[0]:.5f} -> {history[-1]:.5f} m^2; "
                                    f"final distance to the target {final_err:.4f} m"], written, t_start)
