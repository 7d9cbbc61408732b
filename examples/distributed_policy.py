"""A small torch policy trained through the simulator, data-parallel over processes: an MLP maps the
4-dof arm's joint angles, velocities and the tool's offset from a target point to joint torques at
every step, and is trained by backpropagation through the whole batched rollout (no reinforcement-
learning estimator) to bring the tool to the target. Every epoch draws new targets for all
environments; the environments are split over torch.distributed ranks, each rank simulates its share
in its own batched scene, and the policy, wrapped in DistributedDataParallel (gloo on CPU), gets the
gradient averaged over ranks. One process without torchrun trains on all the environments itself,
to the same numbers up to rounding.

    python examples/distributed_policy.py [--quick] [--envs 32] [--epochs 200] [--steps 40]
    torchrun --nproc_per_node=2 examples/distributed_policy.py [--quick]

Per rank: its environments are a contiguous share of the global indices, and environment k's target
in epoch i comes from a generator seeded with (seed, i, k), so the split does not change what is
simulated; the policy's initial weights come from torch.manual_seed(seed) on every rank (DDP would
broadcast rank 0's anyway). Rank 0 writes loss.csv, policy.pt and distributed_policy.png (training
loss, tool distance to held-out targets before and after training).
"""
import os
import sys
import time

import numpy as np
import genesis_lite as gs  # before torch: its OpenMP threads then sleep between ops (README)
import torch


sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from example_utils import parse_args, progress, pyplot, repo_path, save_figure, summary, write_csv  # noqa: E402

F64 = dict(dtype=torch.float64)
TORQUE = torch.tensor([6.0, 12.0, 8.0, 2.0], **F64)  # N m at the policy's full output, per joint
EVAL_SEED = 12345


def extra(ap):
    ap.add_argument("--envs", type=int, default=32, help="environments over all ranks (--quick: 4)")
    ap.add_argument("--epochs", type=int, default=200, help="Adam steps (--quick: 10; with the default armature 3 do not yet bring the tool closer)")
    ap.add_argument("--steps", type=int, default=40, help="steps of 10 ms per rollout (--quick: 15)")
    ap.add_argument("--seed", type=int, default=0)


def setup_distributed():
    """(rank, world size): a gloo process group under torchrun, rank 0 of 1 alone."""
    if "RANK" not in os.environ:
        return 0, 1
    import torch.distributed as dist

    dist.init_process_group("gloo")
    return dist.get_rank(), dist.get_world_size()


def targets(seed, epoch, envs):
    """Target points (E, 3) of the global environments `envs` in `epoch`: around the tool's rest
    position, a function of (seed, epoch, k) alone."""
    pts = [np.random.default_rng([seed, epoch, int(k)]).uniform([-0.35, -0.35, 0.55], [0.35, 0.35, 0.85]) for k in envs]
    return torch.tensor(np.stack(pts), **F64)


class Policy(torch.nn.Module):
    def __init__(self, n_dofs, hidden=64):
        super().__init__()
        self.net = torch.nn.Sequential(torch.nn.Linear(2 * n_dofs + 3, hidden), torch.nn.Tanh(),
                                       torch.nn.Linear(hidden, hidden), torch.nn.Tanh(),
                                       torch.nn.Linear(hidden, n_dofs), torch.nn.Tanh())

    def forward(self, q, qd, error):
        """Torques (E, n_dofs) from joint angles (rad), velocities (rad/s) and tool minus target (m)."""
        return self.net(torch.cat([q, 0.3 * qd, 3.0 * error], -1)) * TORQUE


def main():
    t_start = time.time()
    args = parse_args("distributed_policy", __doc__, extra)
    rank, world = setup_distributed()
    n_envs, epochs, steps = (4, 10, 15) if args.quick else (args.envs, args.epochs, args.steps)
    if n_envs < world:
        raise SystemExit(f"{n_envs} environments cannot be split over {world} ranks")
    gs.init(backend=gs.cpu, precision="64")  # this rank's share of the cores (gs.cpu_threads)
    mine = np.array_split(np.arange(n_envs), world)[rank]

    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True),
                     rigid_options=gs.options.RigidOptions(enable_collision=False))
    arm = scene.add_entity(gs.morphs.URDF(file=repo_path("assets", "urdf", "arm.urdf"), fixed=True))
    scene.build(n_envs=len(mine))
    arm.set_dofs_damping(torch.full((arm.n_dofs,), 0.5, **F64))

    torch.manual_seed(args.seed)  # the same initial weights on every rank
    policy = Policy(arm.n_dofs).to(torch.float64)
    model = policy
    if world > 1:
        model = torch.nn.parallel.DistributedDataParallel(policy)  # averages the gradients over ranks
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)

    def rollout(goal, net):
        """Sum over this rank's environments of the squared tool-to-target distance (m^2), averaged
        over the last quarter of the rollout, and of a small torque penalty."""
        scene.reset()
        cost = torch.zeros((), **F64)
        tail = max(1, steps // 4)
        for t in range(steps):
            tau = net(arm.get_dofs_position(), arm.get_dofs_velocity(), arm.get_links_pos()[:, -1] - goal)
            arm.control_dofs_force(tau)
            scene.step()
            cost = cost + 1e-5 * (tau ** 2).sum() / steps
            if t >= steps - tail:
                cost = cost + ((arm.get_links_pos()[:, -1] - goal) ** 2).sum() / tail
        return cost

    def evaluate():
        """Mean final tool distance (m) over held-out targets, over all ranks."""
        with torch.no_grad():
            goal = targets(EVAL_SEED, 0, mine)
            scene.reset()
            for _ in range(steps):
                arm.control_dofs_force(policy(arm.get_dofs_position(), arm.get_dofs_velocity(),
                                              arm.get_links_pos()[:, -1] - goal))
                scene.step()
            d = torch.stack([(arm.get_links_pos()[:, -1] - goal).norm(dim=-1).sum(), torch.tensor(float(len(mine)), **F64)])
            if world > 1:
                torch.distributed.all_reduce(d)
            return (d[0] / d[1]).item()

    dist_before = evaluate()
    history, times = [], []
    bar = progress(range(epochs), desc=f"Adam ({world} rank{'s' if world > 1 else ''})", total=epochs, disable=rank != 0)
    for epoch in bar:
        t0 = time.perf_counter()
        # each rank's loss is its share of the global mean times the world size: DDP's average over
        # ranks is then the global mean, whatever the split
        local = rollout(targets(args.seed, epoch, mine), model) * (world / n_envs)
        optimizer.zero_grad()
        local.backward()
        optimizer.step()
        report = local.detach() / world
        if world > 1:
            torch.distributed.all_reduce(report)
        history.append(report.item())
        times.append(time.perf_counter() - t0)
        if hasattr(bar, "set_postfix"):
            bar.set_postfix(loss=f"{history[-1]:.4g}")
    dist_after = evaluate()
    if world > 1:
        torch.distributed.destroy_process_group()
    if not dist_after < dist_before:
        raise SystemExit(f"training did not bring the tool closer: {dist_before:.4f} -> {dist_after:.4f} m")
    if rank != 0:
        return

    written = []
    write_csv(args.out, "loss.csv", ["epoch", "loss_m2"], [np.arange(epochs), history], written)
    path = os.path.join(args.out, "policy.pt")
    torch.save(policy.state_dict(), path)
    written.append(path)
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    ax[0].semilogy(history, "o-", ms=3)
    ax[0].set_xlabel("epoch (new targets each)")
    ax[0].set_ylabel("mean squared tool distance (m^2)")
    ax[0].set_title(f"{n_envs} environments over {world} rank(s)")
    ax[1].bar(["before", "after"], [dist_before, dist_after])
    ax[1].set_ylabel("mean final distance to held-out targets (m)")
    save_figure(fig, args.out, "distributed_policy.png", written)
    summary("distributed_policy", [
        f"{n_envs} environments of {steps} steps over {world} rank(s) ({len(mine)} on rank 0, {gs.cpu_threads} CPU "
        f"thread(s) per rank); one epoch (rollout, backward, Adam) {np.median(times):.3f} s (median)",
        f"loss {history[0]:.4e} -> {history[-1]:.4e} m^2 in {epochs} epochs; mean final distance to held-out targets "
        f"{dist_before:.4f} -> {dist_after:.4f} m"], written, t_start)


if __name__ == "__main__":
    main()
