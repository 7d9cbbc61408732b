"""Worker of tests/test_adstack.py: six free boxes on a plane (one moving into its neighbours), gradient
of a 3-step loss with respect to the moving box's initial velocity, in a fresh process with default
options; prints {"grad": [...], "fd": [...], "stack": entries} as one JSON line. Before the stacks were
sized by the loops that carry a local, this scene got 4096-entry autodiff stacks and its backward
overflowed the native stack (a segfault, with or without the checked runtime)."""
import json

import numpy as np
import torch

import genesis_lite as gs
from solvers.taichi_compat import adstack

gs.init(backend=gs.cpu, precision="64")
scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True))
scene.add_entity(gs.morphs.Plane())
boxes = [scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1), pos=(0.12 * i, 0.01 * i, 0.06))) for i in range(6)]
scene.build()
v0 = np.array([1.5, 0.2, -0.3, 0.4, -0.6, 0.8])


def loss(v, grad):
    scene.reset()
    vt = torch.tensor(v, dtype=torch.float64, requires_grad=grad)
    boxes[0].set_dofs_velocity(vt)
    states = []
    for _ in range(3):
        scene.step()
        states.append(torch.cat([b.get_qpos() for b in boxes]))
    L = (torch.stack(states) ** 2).sum()
    if grad:
        L.backward()
        return vt.grad.tolist()
    return L.item()


g = loss(v0, True)
# the stiff contact solve leaves ~1e-12 of rounding in the loss, so the differences' step cannot be small
# (h = 1e-6 carries ~1e-6 of the gradient's scale in noise), and the loss curves in the box's vertical
# velocity: central differences at h = 1e-5 are 4.5e-5 off there, at 3e-5 4e-4 (their h^2 term; 2026-11-28,
# with the normal rounds). Richardson's combination of h and h / 2 cancels that term: within ~3e-7.
h = 1e-5


def central(e, step):
    return (loss(v0 + step * e, False) - loss(v0 - step * e, False)) / (2 * step)


fd = [(4.0 * central(e, h / 2) - central(e, h)) / 3.0 for e in np.eye(6)]
print(json.dumps({"grad": g, "fd": fd, "stack": adstack.current()}))
