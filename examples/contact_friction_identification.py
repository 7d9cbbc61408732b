"""Identify a friction coefficient through contact: a box is launched along the ground and slides to
rest; starting from a wrong guess, gradient descent on `box.set_friction(mu)` recovers the mu that
reproduces the observed stopping point (and, for comparison, the closed form v^2 / (2 mu g)).

    python examples/contact_friction_identification.py [--iters 8] [--out out/contact_friction]

Writes the loss and estimate per iteration and the box trajectories (guess, fit, observed) as PNG.
"""
import sys
import os
import time

import torch

import genesis_lite as gs

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from example_utils import parse_args, summary  # noqa: E402

args = parse_args("contact_friction_identification", __doc__, lambda ap: ap.add_argument("--iters", type=int, default=8))
if args.quick:
    args.iters = 2

gs.init(backend=gs.cpu, precision="64")
f64 = torch.float64
scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True))
ground = scene.add_entity(gs.morphs.Plane(), material=gs.materials.Rigid(friction=0.0))
box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0.0, 0.0, 0.1)))
scene.build()
with torch.no_grad():  # settle onto the ground first
    for _ in range(20):
        scene.step()
start = scene.get_state()
V0, T = 2.5, 100
TRUE_MU = 0.45


def rollout(mu):
    """x of the box over T steps after launching it at V0 (m/s) with friction mu (the ground's is 0:
    a contact uses the larger coefficient of its two geoms)."""
    scene.reset(start)
    box.set_friction(mu)
    box.set_dofs_velocity(torch.tensor([V0, 0, 0, 0, 0, 0], dtype=f64))
    xs = []
    for _ in range(T):
        scene.step()
        xs.append(box.get_pos()[0])
    return torch.stack(xs)


with torch.no_grad():
    observed = rollout(torch.tensor(TRUE_MU, dtype=f64))
log_mu = torch.log(torch.tensor(0.15, dtype=f64)).requires_grad_()
with torch.no_grad():
    guess = rollout(log_mu.exp())
opt = torch.optim.LBFGS([log_mu], lr=1.0, max_iter=1, history_size=10, line_search_fn="strong_wolfe")
history = []
t0 = time.time()


def closure():
    opt.zero_grad()
    loss = ((rollout(log_mu.exp()) - observed) ** 2).mean()
    loss.backward()
    return loss


for it in range(args.iters):
    loss = opt.step(closure)
    history.append((float(loss), float(log_mu.exp())))
    print(f"iter {it + 1:3d}/{args.iters}  loss {history[-1][0]:.3e}  mu {history[-1][1]:.4f}  "
          f"({time.time() - t0:.1f} s)", flush=True)
mu_fit = float(log_mu.exp())
print(f"true mu {TRUE_MU}, fitted {mu_fit:.4f}; the closed form v^2 / (2 g d) from the observed stopping distance "
      f"gives {V0 ** 2 / (2 * 9.81 * float(observed[-1])):.4f}")

with torch.no_grad():
    fit = rollout(log_mu.exp())
t = torch.arange(1, T + 1, dtype=f64) * 0.01
csv = os.path.join(args.out, "trajectories.csv")
np_data = torch.stack([t, observed, guess, fit], 1).numpy()
with open(csv, "w") as fh:
    fh.write("t,x_observed,x_guess,x_fit\n")
    for row in np_data:
        fh.write(",".join(f"{v:.6f}" for v in row) + "\n")
print(f"wrote {csv}")
try:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot(t, observed, "k", lw=3, label=f"observed (mu = {TRUE_MU})")
    ax[0].plot(t, guess, "--", label="initial guess (mu = 0.15)")
    ax[0].plot(t, fit, ":", lw=2, label=f"fit (mu = {mu_fit:.3f})")
    ax[0].set_xlabel("t (s)")
    ax[0].set_ylabel("box x (m)")
    ax[0].legend()
    ax[1].semilogy([h[0] for h in history], label="loss")
    ax2 = ax[1].twinx()
    ax2.plot([h[1] for h in history], "r", label="mu")
    ax[1].set_xlabel("iteration")
    ax[1].set_ylabel("loss (m^2)")
    ax2.set_ylabel("mu", color="r")
    fig.tight_layout()
    fig.savefig(os.path.join(args.out, "friction_identification.png"), dpi=110)
    print(f"wrote {os.path.join(args.out, 'friction_identification.png')}")
except ImportError:
    print("matplotlib is not installed: no figure")
summary("contact_friction_identification", [f"true mu {TRUE_MU}, fitted {mu_fit:.4f}"], [csv], t0)
