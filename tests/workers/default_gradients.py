"""Worker for tests/test_adstack.py: the cases of issue #20 that were wrong with Taichi's adaptive
autodiff-stack sizing, run as a user runs them (default options, a fresh process; the test chooses
Taichi's own runtime). Prints one JSON line with the autograd and reference gradients."""
import json
from pathlib import Path

import numpy as np
import torch

import genesis_lite as gs

F64 = dict(dtype=torch.float64)
ASSETS = Path(__file__).resolve().parents[2] / "assets"


def free_box():
    """A box in free flight, 5 steps: the final position is the initial one plus terms that do not
    depend on it, so d(w . pos) / d(initial pos) = w exactly."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=5e-3, requires_grad=True))
    box = scene.add_entity(gs.morphs.Box(pos=(0, 0, 1), size=(0.2, 0.3, 0.4)))
    scene.build()
    p = torch.tensor([0.1, 0.2, 1.0], **F64, requires_grad=True)
    w = torch.tensor([1.0, 2.0, 3.0], **F64)
    box.set_pos(p)
    box.set_dofs_velocity(torch.tensor([0.3, -0.2, 0.5, 1.0, -2.0, 0.5], **F64))
    for _ in range(5):
        scene.step()
    (box.get_pos() * w).sum().backward()
    return p.grad.tolist(), w.tolist()


def double_pendulum():
    """The fixed-base double pendulum, 3 steps: d sum(q) / d q0 against central differences."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=1e-2, requires_grad=True))
    robot = scene.add_entity(gs.morphs.URDF(file=str(ASSETS / "urdf" / "double_pendulum.urdf"), fixed=True))
    scene.build()
    q0 = torch.tensor([0.7, -0.4], **F64)

    def loss(q):
        scene.reset()
        robot.set_dofs_position(q)
        for _ in range(3):
            scene.step()
        return (robot.get_dofs_position() * torch.tensor([1.0, 0.5], **F64)).sum()

    q = q0.clone().requires_grad_(True)
    loss(q).backward()
    h, fd = 1e-6, []
    with torch.no_grad():
        for i in range(2):
            e = torch.zeros(2, **F64)
            e[i] = h
            fd.append(((loss(q0 + e) - loss(q0 - e)) / (2 * h)).item())
    return q.grad.tolist(), fd


if __name__ == "__main__":
    gs.init(backend=gs.cpu, precision="64")
    print(json.dumps({"free_box": free_box(), "double_pendulum": double_pendulum()}))
