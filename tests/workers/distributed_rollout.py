"""Worker for tests/test_distributed.py: the loss and the gradients of a double pendulum's shared
parameters over N_ENVS environments, data-parallel over torch.distributed ranks (gloo) when started
by torchrun, over all of them in one process otherwise. Prints one JSON line (rank 0 only under
torchrun): {"loss", "grad", "world", "envs", "threads"}.

Environment k (global index) starts at its own angles and is driven by its own torques; the shared
parameters are the two link masses and the two joint dampings. Rank r of W simulates environments
[r N/W, (r+1) N/W); its loss is its environments' sum divided by N, so the sum over ranks
(all_reduce) of the losses and of the gradients is the single-process mean over N environments.
"""
import json
import os
from pathlib import Path

import torch

import genesis_lite as gs

F64 = dict(dtype=torch.float64)
URDF = str(Path(__file__).resolve().parents[2] / "assets" / "urdf" / "double_pendulum.urdf")
N_ENVS = 4
T = 12
DT = 0.01
PARAMS = (1.1, 0.8, 0.2, 0.1)  # m1, m2 (kg), damping1, damping2 (N m s/rad): where the gradient is taken


def env_inputs(envs):
    """Initial angles (E, 2) and torques (T, E, 2) of the global environments `envs`: a function of
    the global index only, so any split over ranks simulates the same environments."""
    k = torch.as_tensor(envs, **F64)[:, None]
    q0 = torch.cat([0.3 + 0.1 * k, -0.2 + 0.07 * k], 1)
    t = torch.arange(T, **F64)[:, None, None] * DT
    u = torch.cat([4.0 * torch.sin(6.0 * t + 0.5 * k), 2.0 * torch.cos(9.0 * t - 0.3 * k)], 2)
    return q0, u


def local_loss(envs, n_total, params):
    """Sum over the environments `envs` of the squared joint angles over T steps, over n_total:
    one process's share of the mean over all n_total environments."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT, requires_grad=True),
                     rigid_options=gs.options.RigidOptions(enable_collision=False, enable_joint_limit=False))
    pend = scene.add_entity(gs.morphs.URDF(file=URDF, fixed=True))
    scene.build(n_envs=len(envs))
    links = [pend.get_link(n).idx_local for n in ("link1", "link2")]
    q0, u = env_inputs(envs)
    pend.set_links_mass(params[0:2], links_idx_local=links)
    pend.set_dofs_damping(params[2:4])
    pend.set_dofs_position(q0)
    loss = torch.zeros((), **F64)
    for k in range(T):
        pend.control_dofs_force(u[k])
        scene.step()
        loss = loss + (pend.get_dofs_position() ** 2).sum()
    return loss / n_total


def main():
    distributed = "RANK" in os.environ  # set by torchrun
    if distributed:
        import torch.distributed as dist

        dist.init_process_group("gloo")
        rank, world = dist.get_rank(), dist.get_world_size()
    else:
        rank, world = 0, 1
    gs.init(backend=gs.cpu, precision="64")
    per = N_ENVS // world
    envs = list(range(rank * per, (rank + 1) * per))
    params = torch.tensor(PARAMS, **F64, requires_grad=True)
    loss = local_loss(envs, N_ENVS, params)
    loss.backward()
    out = torch.cat([loss.detach().reshape(1), params.grad])
    if distributed:
        dist.all_reduce(out)  # sums: the losses and the gradients of the shared parameters
        dist.destroy_process_group()
    if rank == 0:
        print(json.dumps({"loss": out[0].item(), "grad": out[1:].tolist(), "world": world, "envs": N_ENVS,
                          "threads": gs.cpu_threads}), flush=True)


if __name__ == "__main__":
    main()
