"""Parameter identification from many trajectories, data-parallel over processes: the two masses, the
joint damping and the joint (dry) friction of a double pendulum (assets/urdf/double_pendulum.urdf)
from N recorded trajectories, each with its own start and its own torques, observed with 0.5 mrad of
noise. The trajectories are split over torch.distributed ranks: each rank builds its own batched
scene of its share, runs its rollouts and backpropagates, and the loss and the gradients of the six
shared parameters are summed over ranks (all_reduce, gloo on CPU); every rank then takes the same
L-BFGS-B step. One process without torchrun runs all N trajectories itself and gets the same loss
and gradients up to rounding (sums in another order; over a long fit enough to change L-BFGS-B's
path, measured: 56 iterations in one process, 68 over two ranks, the same fitted values).

    python examples/distributed_identification.py [--quick] [--trajectories 32] [--iters 100]
    torchrun --nproc_per_node=2 examples/distributed_identification.py [--quick]

What is per rank and what is not: the environments a rank simulates are a contiguous share of the
global trajectory indices (np.array_split), and everything random about trajectory k (its start, its
torques, its noise) comes from a generator seeded with (seed, k), so any split over any number of
ranks simulates the same N trajectories. gs.init gives each of the N ranks of a node cores // N
threads. Rank 0 writes fit.md, loss.csv and distributed_identification.png (loss curve, parameters
per iteration, observed against fitted angles of a few trajectories).
"""
import os
import sys
import time

import numpy as np
import genesis_lite as gs  # before torch: its OpenMP threads then sleep between ops (README)
import torch


sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from example_utils import (identification_table, parse_args, progress, pyplot, repo_path, save_figure,  # noqa: E402
                           summary, write_csv, write_text)

F64 = dict(dtype=torch.float64)
NAMES = ["mass link1", "mass link2", "damping joint1", "damping joint2", "friction joint1", "friction joint2"]
UNITS = ["kg", "kg", "N m s/rad", "N m s/rad", "N m", "N m"]
NOISE = 5e-4  # rad


def extra(ap):
    ap.add_argument("--trajectories", type=int, default=32, help="trajectories over all ranks (--quick: 4)")
    ap.add_argument("--steps", type=int, default=200, help="steps of 10 ms per trajectory (--quick: 30)")
    ap.add_argument("--iters", type=int, default=100, help="L-BFGS-B iterations (--quick: 2)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the trajectories' starts, torques and noise")


def setup_distributed():
    """(rank, world size, reduce function). Under torchrun (RANK in the environment) a gloo process
    group (NCCL would serve CUDA tensors); alone, rank 0 of 1 and a reduce that does nothing."""
    if "RANK" not in os.environ:
        return 0, 1, lambda t: t
    import torch.distributed as dist

    dist.init_process_group("gloo")

    def reduce_sum(t):
        dist.all_reduce(t)  # in place, the same sum on every rank
        return t

    return dist.get_rank(), dist.get_world_size(), reduce_sum


def trajectory_inputs(k, steps, dt, seed):
    """Start angles (2,), torques (steps, 2) and observation noise (steps, 2) of global trajectory k:
    a function of (seed, k) alone, whichever rank simulates it."""
    rng = np.random.default_rng([seed, k])
    q0 = rng.uniform([-0.6, -0.6], [0.6, 0.6])
    amp, freq, phase = rng.uniform(1.0, 6.0, (2, 2)), rng.uniform(0.4, 2.5, (2, 2)), rng.uniform(0, 2 * np.pi, (2, 2))
    t = np.arange(steps)[:, None] * dt
    u = sum(amp[i] * np.sin(2 * np.pi * freq[i] * t + phase[i]) for i in range(2))
    return q0, u, rng.normal(0.0, NOISE, (steps, 2))


def main():
    t_start = time.time()
    args = parse_args("distributed_identification", __doc__, extra)
    rank, world, reduce_sum = setup_distributed()
    n_traj, steps, iters = (4, 30, 2) if args.quick else (args.trajectories, args.steps, args.iters)
    if n_traj < world:
        raise SystemExit(f"{n_traj} trajectories cannot be split over {world} ranks")
    dt = 0.01
    gs.init(backend=gs.cpu, precision="64")  # this rank's share of the cores (gs.cpu_threads)
    mine = np.array_split(np.arange(n_traj), world)[rank]  # this rank's global trajectory indices

    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, requires_grad=True),
                     rigid_options=gs.options.RigidOptions(enable_collision=False, enable_joint_limit=False))
    pend = scene.add_entity(gs.morphs.URDF(file=repo_path("assets", "urdf", "double_pendulum.urdf"), fixed=True))
    scene.build(n_envs=len(mine))
    links = [pend.get_link(n).idx_local for n in ("link1", "link2")]
    inputs = [trajectory_inputs(int(k), steps, dt, args.seed) for k in mine]
    q0 = torch.tensor(np.stack([i[0] for i in inputs]), **F64)                   # (E, 2)
    u = torch.tensor(np.stack([i[1] for i in inputs], 1), **F64)                 # (steps, E, 2)
    noise = torch.tensor(np.stack([i[2] for i in inputs], 1), **F64)             # (steps, E, 2)

    def rollout(p):
        """Joint angles (steps, E, 2) of this rank's trajectories for p = [m1, m2 (kg), damping1,
        damping2 (N m s/rad), friction1, friction2 (N m)], shared by every trajectory."""
        scene.reset()
        pend.set_links_mass(p[0:2], links_idx_local=links)
        pend.set_dofs_damping(p[2:4])
        pend.set_dofs_frictionloss(p[4:6])
        pend.set_dofs_position(q0)
        qs = []
        for k in range(steps):
            pend.control_dofs_force(u[k])
            scene.step()
            qs.append(pend.get_dofs_position())
        return torch.stack(qs)

    true = torch.tensor([1.0, 0.7, 0.4, 0.15, 0.3, 0.1], **F64)
    init = true * torch.tensor([1.4, 0.6, 0.6, 1.5, 1.5, 0.6], **F64)
    lo, hi = np.array([0.05, 0.05, 0.01, 0.01, 0.01, 0.01]), np.array([5.0, 5.0, 2.0, 2.0, 2.0, 2.0])
    with torch.no_grad():
        observed = rollout(true) + noise
    scale = 1.0 / (n_traj * steps * 2 * NOISE ** 2)  # the global mean over noise variance: ~1 at the optimum
    evals, cache = [], {}

    def fun(x):
        """Global loss and its gradient with respect to log(p): this rank's sum, summed over ranks."""
        if x.tobytes() in cache:
            return cache[x.tobytes()]
        t0 = time.perf_counter()
        leaf = torch.tensor(x, **F64, requires_grad=True)
        local = ((rollout(leaf.exp()) - observed) ** 2).sum() * scale
        (g,) = torch.autograd.grad(local, leaf)
        buf = reduce_sum(torch.cat([local.detach().reshape(1), g]))
        evals.append(time.perf_counter() - t0)
        cache[x.tobytes()] = buf[0].item(), buf[1:].numpy().copy()
        return cache[x.tobytes()]

    from scipy.optimize import minimize

    x0 = np.log(init.numpy())
    losses, trace = [fun(x0)[0]], [init.numpy().copy()]
    bar = progress(total=iters, desc=f"L-BFGS-B ({world} rank{'s' if world > 1 else ''})", disable=rank != 0)

    def callback(x):
        # every rank holds the same x: the same reduced loss and gradient, bit for bit, drive the same steps
        losses.append(fun(x)[0])
        trace.append(np.exp(x))
        if hasattr(bar, "update"):
            bar.update(1)
            bar.set_postfix(loss=f"{losses[-1]:.4g}")

    minimize(fun, x0, jac=True, method="L-BFGS-B", callback=callback, bounds=list(zip(np.log(lo), np.log(hi))),
             options=dict(maxiter=iters))
    if hasattr(bar, "close"):
        bar.close()
    fitted = torch.tensor(trace[-1], **F64)
    if world > 1:  # the ranks must have stepped in lockstep; a difference here would be a bug
        import torch.distributed as dist

        spread = torch.tensor(trace[-1], **F64)
        lo_x, hi_x = spread.clone(), spread.clone()
        dist.all_reduce(lo_x, op=dist.ReduceOp.MIN)
        dist.all_reduce(hi_x, op=dist.ReduceOp.MAX)
        if not torch.equal(lo_x, hi_x):
            raise SystemExit(f"rank {rank}: the ranks' parameters differ: {lo_x.tolist()} vs {hi_x.tolist()}")
    with torch.no_grad():
        guess, fit = rollout(init), rollout(fitted)
    if not losses[-1] < losses[0]:
        raise SystemExit(f"the loss did not decrease: {losses[0]:.4e} -> {losses[-1]:.4e}")
    if world > 1:
        torch.distributed.destroy_process_group()
    if rank != 0:
        return

    table, worst = identification_table(NAMES, true.numpy(), init.numpy(), fitted.numpy(), UNITS)
    written = []
    write_text(args.out, "fit.md", table, written)
    tr = np.array(trace)
    write_csv(args.out, "loss.csv", ["iteration", "loss_over_noise_var"] + [n.replace(" ", "_") for n in NAMES],
              [np.arange(len(tr)), losses] + [tr[:, k] for k in range(6)], written)
    plt = pyplot()
    fig, ax = plt.subplots(1, 3, figsize=(16, 4))
    ax[0].semilogy(losses, "o-")
    ax[0].set_xlabel("L-BFGS-B iteration")
    ax[0].set_ylabel("mean (q - q_obs)^2 / (0.5 mrad)^2")
    ax[0].set_title(f"loss over {n_traj} trajectories, {world} rank(s)")
    for k, n in enumerate(NAMES):
        ax[1].plot(tr[:, k] / true[k].item(), "o-", ms=3, label=n)
    ax[1].axhline(1.0, c="gray", ls="--")
    ax[1].set_xlabel("L-BFGS-B iteration")
    ax[1].set_ylabel("value / true value")
    ax[1].legend(fontsize=7)
    tt = (np.arange(steps) + 1) * dt
    for e in range(min(3, len(mine))):
        line, = ax[2].plot(tt, observed[:, e, 0].numpy(), ".", ms=2, label=f"trajectory {mine[e]}: observed")
        ax[2].plot(tt, fit[:, e, 0].numpy(), "-", c=line.get_color(), label="fitted")
        ax[2].plot(tt, guess[:, e, 0].numpy(), ":", c=line.get_color(), label="initial guess")
    ax[2].set_xlabel("t (s)")
    ax[2].set_ylabel("joint 1 angle (rad)")
    ax[2].set_title("rank 0's trajectories")
    ax[2].legend(fontsize=6)
    save_figure(fig, args.out, "distributed_identification.png", written)
    summary("distributed_identification", [
        f"{n_traj} trajectories of {steps} steps of {dt} s over {world} rank(s) ({len(mine)} on rank 0, "
        f"{gs.cpu_threads} CPU thread(s) per rank); one loss-and-gradient evaluation {np.median(evals):.3f} s (median)",
        f"loss (mean (q - q_obs)^2 / noise^2) {losses[0]:.4e} -> {losses[-1]:.4e} in {len(losses) - 1} L-BFGS-B "
        f"iterations; largest error {worst:.3f} %", table], written, t_start)
    if not args.quick and worst > 2.0:
        raise SystemExit(f"an identified value is {worst:.2f} % off (more than 2 %)")


if __name__ == "__main__":
    main()
