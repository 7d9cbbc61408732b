"""The trajectory-optimisation example of Genesis's differentiable-simulation page (scene.reset()
inside the epoch loop, Adam on a control sequence), on the project's 4-dof arm: the tool link is
driven to a target point.

    python examples/trajectory_optimization.py [--epochs 60] [--out out/trajopt]
"""
import argparse
import os
import time

import torch

import genesis_lite as gs

ap = argparse.ArgumentParser()
ap.add_argument("--epochs", type=int, default=60)
ap.add_argument("--steps", type=int, default=100)
ap.add_argument("--out", default="out/trajopt")
args = ap.parse_args()
os.makedirs(args.out, exist_ok=True)

gs.init(backend=gs.cpu, precision="64")
scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True))
robot = scene.add_entity(gs.morphs.URDF(file="assets/urdf/arm.urdf", fixed=True))
scene.build()

n_steps, n_dofs = args.steps, robot.n_dofs
controls = torch.zeros(n_steps, n_dofs, requires_grad=True, device=gs.device, dtype=gs.tc_float)
optimizer = torch.optim.Adam([controls], lr=0.5)
target = torch.tensor([0.3, 0.3, 0.6], device=gs.device, dtype=gs.tc_float)

history = []
t0 = time.time()
for epoch in range(args.epochs):
    scene.reset()
    for t in range(n_steps):
        robot.control_dofs_force(controls[t])
        scene.step()
    final_pos = robot.get_links_pos()[-1]
    loss = torch.nn.functional.mse_loss(final_pos, target) + 1e-5 * (controls ** 2).mean()
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    history.append(loss.item())
    if epoch % 10 == 0 or epoch == args.epochs - 1:
        print(f"Epoch {epoch}: loss = {loss.item():.6f}  tool at {final_pos.detach().numpy().round(3)}  "
              f"({time.time() - t0:.1f} s)")

with open(os.path.join(args.out, "loss.csv"), "w") as f:
    f.write("epoch,loss\n" + "".join(f"{i},{l:.8g}\n" for i, l in enumerate(history)))
print(f"loss {history[0]:.5f} -> {history[-1]:.5f}; wrote {args.out}/loss.csv")
