"""Data-parallel throughput on this machine: one process with N environments against torchrun ranks
that share the N environments, for a batched rigid rollout and its backward.

    python benchmarks/bench_distributed.py [--envs 256] [--steps 50] [--repeats 5] [--rounds 3] [--quick]
                                           [--out benchmarks/results/distributed.md]

The workload (the `--worker` mode, one per process): the stripped Panda (common.write_stripped_panda,
9 dofs, no geometry), fixed base, float64, dt = 0.01 s, the default integrator; every environment has
its own joint torques (requires grad) and all share the link masses (requires grad, as in parameter
identification); loss = the last link's squared position summed over environments and steps; one
repeat = reset, `steps` steps, backward, and the all_reduce of the shared masses' gradient over ranks
(gloo). Each rank's repeats start together (a barrier) and a repeat's time is the slowest rank's;
throughput = N x steps / that time (env-steps/s, forward and backward together), the median over
`repeats` repeats after a warm-up repeat (kernels compiled or loaded). Configurations, in this order
in every round:
- 1 process, N envs, 1 thread; 1 process, N envs, every core (Taichi's and torch's default);
- torchrun --nproc_per_node=2, N/2 envs each, gs.init's default share (cores // 2 threads each);
- the same with GS_NUM_THREADS=<cores> (every rank takes every core: oversubscribed);
- two torchrun agents on this host with --nnodes=2 --nproc_per_node=1 --rdzv_backend=c10d (the
  multi-node command line, both "nodes" here), N/2 envs each.
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def worker(a):
    import torch

    import genesis_lite as gs

    distributed = "RANK" in os.environ
    if distributed:
        import torch.distributed as dist

        dist.init_process_group("gloo")
        rank, world = dist.get_rank(), dist.get_world_size()
    else:
        rank, world = 0, 1
    gs.init(backend=gs.cpu, precision="64", **({"num_threads": a.threads} if a.threads else {}))
    n_local = a.envs // world
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True),
                     rigid_options=gs.options.RigidOptions(enable_collision=False))
    robot = scene.add_entity(gs.morphs.URDF(file=a.urdf, fixed=True))
    scene.build(n_envs=n_local)
    f64 = dict(dtype=torch.float64)
    mass0 = robot.get_links_mass()[0].detach().clone()
    gen = torch.Generator().manual_seed(1000 + rank)  # per-rank torques: a rank's own environments
    torques = 2.0 * torch.randn(a.steps, n_local, robot.n_dofs, generator=gen, **f64)

    def repeat():
        mass = mass0.clone().requires_grad_(True)
        u = torques.clone().requires_grad_(True)
        if distributed:
            dist.barrier()
        t0 = time.perf_counter()
        scene.reset()
        robot.set_links_mass(mass)
        loss = torch.zeros((), **f64)
        for t in range(a.steps):
            robot.control_dofs_force(u[t])
            scene.step()
            loss = loss + (robot.get_links_pos()[:, -1] ** 2).sum()
        loss.backward()
        g = mass.grad.clone()
        if distributed:
            dist.all_reduce(g)
        dt = torch.tensor([time.perf_counter() - t0], **f64)
        if distributed:
            dist.all_reduce(dt, op=dist.ReduceOp.MAX)  # a data-parallel step lasts as long as its slowest rank
        return dt.item()

    warm = repeat()
    times = [repeat() for _ in range(a.repeats)]
    if distributed:
        dist.destroy_process_group()
    if rank == 0:
        print(json.dumps({"times": times, "warmup": warm, "world": world, "envs_per_rank": n_local,
                          "threads": gs.cpu_threads}), flush=True)


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(cmds, env_extra, timeout=900):
    """Start the commands together; (JSON line of the one that prints it, error or None)."""
    env = {**os.environ, "PYTHONPATH": str(HERE.parent), **env_extra}
    procs = [subprocess.Popen(c, cwd=HERE.parent, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for c in cmds]
    outs = [p.communicate(timeout=timeout) for p in procs]
    result, err = None, None
    for p, (out, errtext) in zip(procs, outs):
        lines = [ln for ln in out.splitlines() if ln.startswith("{")]
        if lines:
            result = json.loads(lines[-1])
        if p.returncode != 0:
            err = f"exit {p.returncode}: " + (errtext.strip().splitlines() or ["no output"])[-1]
    return result, err


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", type=int, default=256)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="one round, 16 envs, 10 steps, 2 repeats (a smoke run)")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "distributed.md")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--urdf", help=argparse.SUPPRESS)
    ap.add_argument("--threads", type=int, default=0, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        return worker(a)
    if a.quick:
        a.envs, a.steps, a.repeats, a.rounds = 16, 10, 2, 1

    from common import machine_info, print_table, write_stripped_panda

    info = machine_info()
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    t_start = time.time()
    load0 = info.get("load", (float("nan"),))[0]
    urdf = str(write_stripped_panda(tempfile.mkdtemp()))
    me = [sys.executable, str(Path(__file__).resolve()), "--worker", "--urdf", urdf, "--envs", str(a.envs),
          "--steps", str(a.steps), "--repeats", str(a.repeats)]
    trun = [sys.executable, "-m", "torch.distributed.run"]

    def multinode():
        port = _free_port()
        common = ["--nnodes=2", "--nproc_per_node=1", "--rdzv_backend=c10d", f"--rdzv_endpoint=127.0.0.1:{port}",
                  f"--rdzv_id=bench{port}"]
        return [trun + common + me[1:], trun + common + me[1:]]

    configs = [
        ("1 process", "1", lambda: [me + ["--threads", "1"]], {}),
        ("1 process", "all cores", lambda: [me], {}),
        ("torchrun, 2 processes", "cores // 2 each (default)", lambda: [trun + ["--standalone", "--nproc_per_node=2"] + me[1:]], {}),
        ("torchrun, 2 processes", f"{cores} each (GS_NUM_THREADS)", lambda: [trun + ["--standalone", "--nproc_per_node=2"] + me[1:]],
         {"GS_NUM_THREADS": str(cores)}),
        ("torchrun --nnodes=2 (c10d, both on this host)", "cores // 1 each", multinode, {}),
    ]
    rows = []
    for rnd in range(1, a.rounds + 1):
        for name, threads, cmds, env in configs:
            res, err = _run(cmds(), env)
            row = {"round": rnd, "config": name, "threads": threads}
            if res is None:
                row["note"] = err or "no result"
            else:
                med = statistics.median(res["times"])
                row.update(world=res["world"], envs=res["envs_per_rank"], cores=res["threads"], ms=1e3 * med,
                           rate=a.envs * a.steps / med, warm=res["warmup"], note=err or "")
            rows.append(row)
            print(json.dumps(row), flush=True)
    base = {r["round"]: r["rate"] for r in rows if r["config"] == "1 process" and r["threads"] == "all cores" and "rate" in r}
    for r in rows:
        if "rate" in r and r["round"] in base:
            r["speedup"] = r["rate"] / base[r["round"]]
    load1 = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    cols = [("round", "round", ""), ("config", "configuration", ""), ("world", "processes", ""),
            ("envs", "envs / process", ""), ("cores", "threads / process", ""), ("threads", "threads setting", ""),
            ("ms", "rollout+backward ms (median)", ".1f"), ("rate", "env-steps/s", ",.0f"),
            ("speedup", "vs 1 process, all cores", ".2f"), ("note", "note", "")]
    title = (f"{a.envs} envs in total, {a.steps} steps, float64, forward + backward + all_reduce of the shared "
             f"gradient; median of {a.repeats} repeats after a warm-up")
    table = print_table(rows, cols, title)
    summary = []
    for name, threads, _, _ in configs:
        rates = [r["rate"] for r in rows if r["config"] == name and r["threads"] == threads and "rate" in r]
        if rates:
            summary.append(f"- {name}, threads {threads}: median {statistics.median(rates):,.0f} env-steps/s over "
                           f"{len(rates)} round(s), range {min(rates):,.0f}-{max(rates):,.0f}")
    text = (f"# genesis_lite data-parallel throughput (torch.distributed, gloo)\n\n"
            f"`python benchmarks/bench_distributed.py{' --quick' if a.quick else ''} --envs {a.envs} --steps {a.steps} "
            f"--repeats {a.repeats} --rounds {a.rounds}`, {time.strftime('%Y-%m-%d %H:%M')}, {info.get('cpu', '?')}, "
            f"{cores} cores, torch {info.get('torch')}, taichi {info.get('taichi')}; load (1 min) {load0:.2f} at the "
            f"start, {load1:.2f} at the end; total {(time.time() - t_start) / 60:.1f} min. Stripped Panda (9 dofs), "
            f"fixed base, dt = 0.01 s, per-env torques and shared link masses requiring grad.\n"
            f"{table}\n\n" + "\n".join(summary) + "\n")
    if not a.quick:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(text)
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
