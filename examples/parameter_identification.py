"""Parameter identification: recover the payload mass (the last link) and the joint damping of the
4-dof arm from a recorded joint trajectory by gradient descent through the simulator. (The base link's
mass does not move anything and a serial chain's masses are identifiable only in combinations, so
the example estimates the identifiable ones.)

    python examples/parameter_identification.py [--iters 40] [--out out/param_id]
"""
import sys
import os
import time

import torch

import genesis_lite as gs

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from example_utils import parse_args, summary  # noqa: E402

args = parse_args("parameter_identification", __doc__, lambda ap: ap.add_argument("--iters", type=int, default=25))
if args.quick:
    args.iters = 2

gs.init(backend=gs.cpu, precision="64")
scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True),
                 rigid_options=gs.options.RigidOptions(enable_collision=False, enable_joint_limit=False))
arm = scene.add_entity(gs.morphs.URDF(file="assets/urdf/arm.urdf", fixed=True))
scene.build()
T = 60
u = 1.0 * torch.sin(torch.linspace(0, 6, T, dtype=torch.float64)[:, None] * torch.arange(1, 5, dtype=torch.float64))
true_mass = arm.get_links_mass().detach()[-1:].clone()
PAYLOAD = [arm.n_links - 1]
true_damp = torch.tensor([0.4, 0.8, 0.3, 0.2], dtype=torch.float64)


def rollout(mass, damping):
    scene.reset()
    arm.set_links_mass(mass, links_idx_local=PAYLOAD)
    arm.set_dofs_damping(damping)
    qs = []
    for t in range(T):
        arm.control_dofs_force(u[t])
        scene.step()
        qs.append(arm.get_dofs_position())
    return torch.stack(qs)


with torch.no_grad():
    observed = rollout(true_mass, true_damp)

log_mass = torch.log(true_mass * 2.0).requires_grad_()      # start twice as heavy
log_damp = torch.log(torch.full((4,), 0.1, dtype=torch.float64)).requires_grad_()
# a smooth least-squares fit: quasi-Newton converges where plain gradient steps crawl along the
# valley in which payload mass and shoulder damping trade off
opt = torch.optim.LBFGS([log_mass, log_damp], lr=1.0, max_iter=1, history_size=20, line_search_fn="strong_wolfe")
t0 = time.time()


def closure():
    opt.zero_grad()
    loss = ((rollout(log_mass.exp(), log_damp.exp()) - observed) ** 2).mean()
    loss.backward()
    return loss


for it in range(args.iters):
    loss = opt.step(closure)
    if it % 5 == 0 or it == args.iters - 1:
        print(f"iter {it:3d}: loss {loss.item():.3e}  payload mass err {((log_mass.exp() - true_mass).abs() / true_mass).max().item():.2e}"
              f"  damping err {(log_damp.exp() - true_damp).abs().max().item():.2e}  ({time.time() - t0:.1f} s)")
with open(os.path.join(args.out, "estimate.txt"), "w") as f:
    f.write(f"true mass {true_mass.tolist()}\nestimated {log_mass.exp().tolist()}\n"
            f"true damping {true_damp.tolist()}\nestimated {log_damp.exp().tolist()}\n")
summary("parameter_identification", [f"payload mass {log_mass.exp().tolist()} (true {true_mass.tolist()})", f"damping {log_damp.exp().tolist()} (true {true_damp.tolist()})"], [os.path.join(args.out, "estimate.txt")], t0)
