"""Main example: a Panda arm (example-robot-data) under PD control reaches a target pose, then the
gradient of its final hand position with respect to the initial joint angles and the PD targets.

    python examples/quickstart.py [--steps 200] [--out out/quickstart]

Writes out/quickstart/trajectory.csv (joint angles over time) and prints progress.
"""
import argparse
import os
import site
import sys
import time
from pathlib import Path

import torch

import genesis_lite as gs


def panda_urdf() -> str:
    for base in site.getsitepackages() + [site.getusersitepackages()]:
        p = Path(base) / "cmeel.prefix/share/example-robot-data/robots/panda_description/urdf/panda.urdf"
        if p.is_file():
            return str(p)
    sys.exit("example-robot-data is not installed: pip install example-robot-data")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--out", default="out/quickstart")
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)

    t0 = time.time()
    gs.init(backend=gs.cpu, precision="64")
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True),
                     rigid_options=gs.options.RigidOptions(integrator=gs.integrator.implicitfast))
    scene.add_entity(gs.morphs.Plane())
    arm = scene.add_entity(gs.morphs.URDF(file=panda_urdf(), fixed=True))
    scene.build()
    print(f"built {arm} in {time.time() - t0:.1f} s")

    n = arm.n_dofs
    arm.set_dofs_kp(torch.tensor([1000.0] * 7 + [100.0] * 2, dtype=torch.float64))
    arm.set_dofs_kv(torch.tensor([60.0] * 7 + [5.0] * 2, dtype=torch.float64))
    q0 = torch.tensor([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8, 0.02, 0.02], dtype=torch.float64, requires_grad=True)
    target = torch.tensor([0.5, 0.4, 0.3, -1.8, 0.2, 1.6, 0.6, 0.03, 0.03], dtype=torch.float64, requires_grad=True)

    scene.reset()
    arm.set_dofs_position(q0)
    arm.control_dofs_position(target)
    rows = []
    t1 = time.time()
    for t in range(args.steps):
        scene.step()
        rows.append(arm.get_dofs_position().detach().tolist())
        if (t + 1) % 50 == 0:
            err = (arm.get_dofs_position() - target).abs().max().item()
            print(f"step {t + 1:4d}/{args.steps}: max joint error {err:.4f} rad")
    hand = arm.get_links_pos()[-1]
    print(f"forward: {args.steps} steps in {time.time() - t1:.2f} s; hand at {hand.detach().numpy().round(4)}")

    t2 = time.time()
    loss = (hand ** 2).sum()
    loss.backward()
    print(f"backward in {time.time() - t2:.2f} s")
    print("d|hand|^2 / d q0     =", q0.grad.numpy().round(5))
    print("d|hand|^2 / d target =", target.grad.numpy().round(5))

    with open(os.path.join(args.out, "trajectory.csv"), "w") as f:
        f.write(",".join(f"q{i}" for i in range(n)) + "\n")
        for r in rows:
            f.write(",".join(f"{x:.6f}" for x in r) + "\n")
    print(f"wrote {args.out}/trajectory.csv")


if __name__ == "__main__":
    main()
