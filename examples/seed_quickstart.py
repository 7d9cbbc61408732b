"""The quick start of Genesis's differentiable-simulation page, with only the import changed and a
real URDF named: gradients of the final base position with respect to the initial dof positions.
(Around it: --quick / --out, and the gradient written to <out>/gradient.txt.)

    python examples/seed_quickstart.py [--quick] [--out out/seed_quickstart]
"""
import os
import sys
import time

import genesis_lite as gs  # before torch: its OpenMP threads then sleep between ops (README)
import torch

from genesis_lite.morphs import URDF  # noqa: F401  (gs.morphs.URDF below, as in the original)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from example_utils import parse_args, summary, write_text  # noqa: E402

t_start = time.time()
args = parse_args("seed_quickstart", __doc__)
n_steps = 20 if args.quick else 100

gs.init()

# enable gradient tracking
scene = gs.Scene(
    sim_options=gs.options.SimOptions(
        dt=0.01,
        requires_grad=True,  # differentiable
    ),
)

# the original names "robot.urdf"; a free-floating 4-dof arm here, so get_pos() moves
robot = scene.add_entity(gs.morphs.URDF(file="assets/urdf/arm.urdf"))
scene.build()

# forward simulation
initial_pos = torch.tensor([0.0, 0.0, 0.0], requires_grad=True, device=gs.device)
forces = torch.tensor([0.5, -0.2, 0.1], device=gs.device)
robot.set_dofs_position(initial_pos, dofs_idx_local=[6, 7, 8])
for i in range(n_steps):
    robot.control_dofs_force(forces, dofs_idx_local=[6, 7, 8])
    scene.step()

# loss
final_pos = robot.get_pos()
target = torch.tensor([1.0, 0.0, 0.5], device=gs.device)
loss = torch.nn.functional.mse_loss(final_pos, target)

# backward
loss.backward()

# gradients
print(initial_pos.grad)

written = []
write_text(args.out, "gradient.txt", f"steps {n_steps}\nloss {loss.item():.9g}\n"
           f"d loss / d initial_pos {initial_pos.grad.tolist()}", written)
summary("seed_quickstart", [f"{n_steps} steps, loss {loss.item():.6g}, d loss / d initial_pos "
                            f"{[round(g, 6) for g in initial_pos.grad.tolist()]}"], written, t_start)
