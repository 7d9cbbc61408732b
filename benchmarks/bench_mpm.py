"""MPM speed, gradient cost and memory of genesis_lite, with real Genesis as the peer in the same run.

    python benchmarks/bench_mpm.py [--quick] [--out benchmarks/results/mpm.md]

The scene (the same for both engines, see peer_genesis_mpm.py): MPMOptions(lower_bound=(0, 0, 0),
upper_bound=(1, 1, 1), grid_density=64), SimOptions(dt=2e-3, substeps=10), gravity -9.81 z, one elastic
cube (E = 3e5, nu = 0.2, corotated) on the regular lattice of spacing 0.01 m centred at (0.5, 0.5, 0.4):
edge 0.2 m = 8,000 particles, 0.3 m = 27,000. Each engine and precision runs in its own process (one
init per process), genesis_lite with this repository's venv, Genesis with $GENESIS_PYTHON (default
/work/genesis_venv/bin/python; rows say "not run" without it).
Measured per row: build (Scene() to end of build(), first scene of the process: kernel compilation or
cache loading included); particle-substeps/s warm, median of repeats of 50 steps (x 10 substeps);
backward / forward of a 20-step rollout with loss = sum(x^2) (requires_grad scene, medians); and, for
genesis_lite only, memory kept for backward against the horizon (100, 1,000 steps, 10,000 particles)
with and without checkpointing, from torch's saved tensors and the checkpoint buffer.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
DT, SUBSTEPS, SPACING = 2e-3, 10, 0.01


def edge_for(n):
    return round(n ** (1.0 / 3.0)) * SPACING


# ------------------------------------------------------------------------------------------ one process
def worker(precision, particles, steps, repeats, grad_steps, memory):
    sys.path.insert(0, str(REPO))
    import numpy as np
    import taichi as ti
    import torch

    import genesis_lite as gs

    t0 = time.perf_counter()
    gs.init(backend=gs.cpu, precision=precision)
    init_s = time.perf_counter() - t0

    def build(edge, requires_grad, checkpoint_every=None):
        t0 = time.perf_counter()
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT, substeps=SUBSTEPS, requires_grad=requires_grad,
                                                           checkpoint_every=checkpoint_every),
                         mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(1, 1, 1), grid_density=64))
        cube = scene.add_entity(gs.morphs.Box(pos=(0.5, 0.5, 0.4), size=(edge,) * 3),
                                material=gs.materials.MPM.Elastic(E=3e5, nu=0.2))
        scene.build()
        return scene, cube, time.perf_counter() - t0

    rows = []
    for target in particles:
        edge = edge_for(target)
        scene, cube, build_s = build(edge, False)

        def once():
            scene.reset()
            ti.sync()
            t0 = time.perf_counter()
            for _ in range(steps):
                scene.step()
            ti.sync()
            dt = time.perf_counter() - t0
            assert torch.isfinite(cube.get_particles_pos()).all()
            return dt

        t0 = time.perf_counter()
        once()
        first = time.perf_counter() - t0
        secs = [once() for _ in range(repeats)]
        row = {"target": target, "precision": precision, "n_particles": cube.n_particles, "build_s": build_s,
               "first_run_s": first, "rate": cube.n_particles * SUBSTEPS * steps / statistics.median(secs),
               "step_ms": 1e3 * statistics.median(secs) / steps}
        gscene, gcube, gbuild = build(edge, True)

        def grad_once():
            gscene.reset()
            x0 = gcube.get_particles_pos().detach().clone().requires_grad_(True)
            t0 = time.perf_counter()
            gcube.set_particles_pos(x0)
            for _ in range(grad_steps):
                gscene.step()
            loss = (gcube.get_particles_pos() ** 2).sum()
            t1 = time.perf_counter()
            loss.backward()
            t2 = time.perf_counter()
            assert torch.isfinite(x0.grad).all()
            return t1 - t0, t2 - t1

        first_g = grad_once()
        runs = [grad_once() for _ in range(max(2, repeats // 2))]
        row.update({"grad_build_s": gbuild, "grad_first_fwd_s": first_g[0], "grad_first_bwd_s": first_g[1],
                    "fwd_s": statistics.median(r[0] for r in runs), "bwd_s": statistics.median(r[1] for r in runs),
                    "bwd_over_fwd": statistics.median(r[1] / r[0] for r in runs), "grad_steps": grad_steps})
        rows.append(row)
        print(f"genesis_lite MPM f{precision} {row['n_particles']:,} particles: {row['rate'] / 1e6:.2f} M "
              f"particle-substeps/s, build {build_s:.1f} s, backward/forward {row['bwd_over_fwd']:.2f}",
              file=sys.stderr, flush=True)
    mem = []
    for horizon in memory:
        for ck in (None, 10):
            scene, cube, _ = build(edge_for(10000), True, ck)
            v = torch.zeros(3, dtype=gs.tc_float, requires_grad=True)
            saved = {}

            def pack(t):
                saved[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
                return t

            t0 = time.perf_counter()
            with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
                cube.set_velocity(v)
                for _ in range(horizon):
                    scene.step()
                loss = cube.get_particles_pos()[:, 2].sum()
            fwd = time.perf_counter() - t0
            buf = scene._simulator.buffer
            ckpt = sum(sum(x.numel() * x.element_size() for s in st for x in s) for st in buf.checkpoints.values())
            t0 = time.perf_counter()
            loss.backward()
            bwd = time.perf_counter() - t0
            state = cube.n_particles * 24 * (8 if precision == "64" else 4)
            mem.append({"horizon": horizon, "checkpoint_every": ck, "n_particles": cube.n_particles,
                        "saved_MiB": sum(saved.values()) / 2**20, "checkpoints_MiB": ckpt / 2**20,
                        "state_KiB": state / 1024, "fwd_s": fwd, "bwd_s": bwd, "replayed": buf.n_replayed})
            print(f"  memory {horizon} steps, checkpoint_every={ck}: saved {mem[-1]['saved_MiB']:.1f} MiB, "
                  f"checkpoints {mem[-1]['checkpoints_MiB']:.1f} MiB", file=sys.stderr, flush=True)
            del scene, cube, loss
    print(json.dumps({"init_s": init_s, "rows": rows, "memory": mem}))


# ------------------------------------------------------------------------------------------ the run
def _run(cmd):
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    sys.stderr.write(out.stderr[-2000:])
    lines = [l for l in out.stdout.splitlines() if l.startswith("{")]
    if out.returncode != 0 or not lines:
        return {"error": (out.stderr.strip().splitlines() or ["no output"])[-1][:300]}
    return json.loads(lines[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="8,000 particles, fewer repeats, 100-step memory rows")
    ap.add_argument("--out", default=str(HERE / "results" / "mpm.md"))
    ap.add_argument("--worker", nargs=6, metavar=("PREC", "PARTICLES", "STEPS", "REPEATS", "GRAD_STEPS", "MEMORY"))
    args = ap.parse_args()
    if args.worker:
        p, parts, steps, reps, gsteps, memory = args.worker
        return worker(p, [int(x) for x in parts.split(",")], int(steps), int(reps), int(gsteps),
                      [int(x) for x in memory.split(",") if x])
    parts = "8000" if args.quick else "8000,27000"
    steps, reps = ("20", "3") if args.quick else ("50", "5")
    gpy = os.environ.get("GENESIS_PYTHON", "/work/genesis_venv/bin/python")
    results = {}
    t_start = time.time()
    for prec in ("32", "64"):
        memory = ("100" if args.quick else "100,1000") if prec == "64" else ""
        results[("genesis_lite", prec)] = _run([sys.executable, str(HERE / "bench_mpm.py"), "--worker", prec, parts,
                                                steps, reps, "20", memory])
        if Path(gpy).exists() and (HERE / "peer_genesis_mpm.py").exists():
            results[("genesis", prec)] = _run([gpy, str(HERE / "peer_genesis_mpm.py"), "--precision", prec,
                                              "--particles", parts, "--steps", steps, "--repeats", reps, "--grad"])
        else:
            results[("genesis", prec)] = {"error": f"not run: no Genesis at {gpy}"}
    write_report(results, args.out, time.time() - t_start, args.quick)


def write_report(results, out, wall, quick):
    import torch

    lines = [f"# MPM: genesis_lite against real Genesis", "",
             f"`python benchmarks/bench_mpm.py{' --quick' if quick else ''}`, {time.strftime('%Y-%m-%d %H:%M')}, "
             f"{os.cpu_count()} CPU cores ({platform.processor() or platform.machine()}), load average "
             f"{os.getloadavg()[0]:.1f} at the end, total {wall:.0f} s; torch {torch.__version__}. Elastic cube on "
             "a 64^3 grid, dt 2e-3 s, 10 substeps (see the script's docstring). Rates are medians of repeated "
             "warm runs; each engine and precision in its own process.", "",
             "| particles | precision | genesis_lite M p-substeps/s | Genesis M p-substeps/s | ratio | build s (ours / Genesis) "
             "| backward/forward (ours / Genesis) |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for prec in ("32", "64"):
        ours, peer = results[("genesis_lite", prec)], results[("genesis", prec)]
        if "rows" not in ours:
            lines.append(f"| - | f{prec} | error: {ours.get('error')} | | | | |")
            continue
        peer_rows = {r["target"]: r for r in peer.get("rows", [])}
        for r in ours["rows"]:
            g = peer_rows.get(r["target"], {})
            gr = g.get("rate")
            ratio = f"{r['rate'] / gr:.2f}x" if gr else "-"
            lines.append(f"| {r['n_particles']:,} | f{prec} | {r['rate'] / 1e6:.2f} | "
                         f"{gr / 1e6:.2f} | {ratio} | " if gr else
                         f"| {r['n_particles']:,} | f{prec} | {r['rate'] / 1e6:.2f} | {g.get('error', peer.get('error', '-'))} | - | ")
            lines[-1] += (f"{r['build_s']:.1f} / {g['build_s']:.1f} | " if "build_s" in g else f"{r['build_s']:.1f} / - | ")
            lines[-1] += (f"{r['bwd_over_fwd']:.2f} / {g['bwd_over_fwd']:.2f} |" if "bwd_over_fwd" in g
                          else f"{r['bwd_over_fwd']:.2f} / - |")
    mem = results[("genesis_lite", "64")].get("memory", [])
    if mem:
        lines += ["", "Memory kept for backward (float64, 10,000-particle cube; one particle state = "
                  f"{mem[0]['state_KiB']:.0f} KiB: x, v, C, F):", "",
                  "| steps | checkpoint_every | saved by torch MiB | checkpoints MiB | states replayed | forward s | backward s |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
        for m in mem:
            lines.append(f"| {m['horizon']:,} | {m['checkpoint_every'] or 'none'} | {m['saved_MiB']:.1f} | "
                         f"{m['checkpoints_MiB']:.1f} | {m['replayed']} | {m['fwd_s']:.1f} | {m['bwd_s']:.1f} |")
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
