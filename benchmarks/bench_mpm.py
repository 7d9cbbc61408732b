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

    python benchmarks/bench_mpm.py --bare [--quick] [--threads N] [--rounds R]

Against a bare textbook Taichi MLS-MPM kernel (bare_mpm.py: APIC, fixed-corotated through ti.svd, dense
grid, one launch per substep) on the same cube, float32, and on a domain the material fills (--scene
filled: a 0.4 m cube of 64,000 particles in [0, 0.5]^3, 33^3 nodes). Each engine runs in fresh processes
with the same number of Taichi CPU threads (cpu_max_num_threads; genesis_lite through GS_NUM_THREADS),
alternated R times (which one starts alternates too); the rows give the median rate of each and the
median of the per-round ratios. The table is written into the output file's section between the
markers `<!-- bare -->` and `<!-- /bare -->` (appended if absent), leaving the rest of the file alone.
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
SCENES = {  # MPMOptions bounds, cube centre (edge from the particle count, edge_for)
    "cube": ((1, 1, 1), (0.5, 0.5, 0.4)),
    "filled": ((0.5, 0.5, 0.5), (0.25, 0.25, 0.25)),
}


def worker(precision, particles, steps, repeats, grad_steps, memory, memory_particles=10000, scene_name="cube"):
    sys.path.insert(0, str(REPO))
    import numpy as np
    import taichi as ti
    import torch

    import genesis_lite as gs

    t0 = time.perf_counter()
    gs.init(backend=gs.cpu, precision=precision)
    init_s = time.perf_counter() - t0

    upper, centre = SCENES[scene_name]

    def build(edge, requires_grad, checkpoint_every=None):
        t0 = time.perf_counter()
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT, substeps=SUBSTEPS, requires_grad=requires_grad,
                                                           checkpoint_every=checkpoint_every),
                         mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=upper, grid_density=64))
        cube = scene.add_entity(gs.morphs.Box(pos=centre, size=(edge,) * 3),
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
               "threads": gs.cpu_threads, "scene": scene_name, "runs_s": secs,
               "first_run_s": first, "rate": cube.n_particles * SUBSTEPS * steps / statistics.median(secs),
               "step_ms": 1e3 * statistics.median(secs) / steps}
        rows.append(row)
        if not grad_steps:  # speed only (run_all.py --quick leaves the gradient to its grad section)
            print(f"genesis_lite MPM f{precision} {row['n_particles']:,} particles: {row['rate'] / 1e6:.2f} M "
                  f"particle-substeps/s, build {build_s:.1f} s", file=sys.stderr, flush=True)
            continue
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
        print(f"genesis_lite MPM f{precision} {row['n_particles']:,} particles: {row['rate'] / 1e6:.2f} M "
              f"particle-substeps/s, build {build_s:.1f} s, backward/forward {row['bwd_over_fwd']:.2f}",
              file=sys.stderr, flush=True)
    mem = []
    for horizon in memory:
        for ck in (None, 10):
            scene, cube, _ = build(edge_for(memory_particles), True, ck)
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
def _run(cmd, env=None):
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, env=env)
    sys.stderr.write(out.stderr[-2000:])
    lines = [l for l in out.stdout.splitlines() if l.startswith("{")]
    if out.returncode != 0 or not lines:
        return {"error": (out.stderr.strip().splitlines() or ["no output"])[-1][:300]}
    return json.loads(lines[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="8,000 particles, fewer repeats, 100-step memory rows")
    ap.add_argument("--out", default=str(HERE / "results" / "mpm.md"))
    ap.add_argument("--worker", nargs=6, metavar=("PREC", "PARTICLES", "STEPS", "REPEATS", "GRAD_STEPS", "MEMORY"),
                    help="one process's rows; PARTICLES and MEMORY may be empty, GRAD_STEPS 0 skips the gradient")
    ap.add_argument("--memory-particles", type=int, default=10000, help="cube of the memory rows (worker)")
    ap.add_argument("--scene", default="cube", choices=tuple(SCENES), help="the worker's scene (see --bare)")
    ap.add_argument("--bare", action="store_true", help="only the comparison with the bare kernel (bare_mpm.py)")
    ap.add_argument("--threads", type=int, default=os.cpu_count(), help="CPU threads of both engines (--bare)")
    ap.add_argument("--rounds", type=int, default=None, help="alternated process pairs per scene (--bare; 5, quick 3)")
    args = ap.parse_args()
    if args.worker:
        p, parts, steps, reps, gsteps, memory = args.worker
        return worker(p, [int(x) for x in parts.split(",") if x], int(steps), int(reps), int(gsteps),
                      [int(x) for x in memory.split(",") if x], args.memory_particles, args.scene)
    if args.bare:
        return bare_comparison(args.quick, args.threads, args.rounds or (3 if args.quick else 5), args.out)
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


def bare_comparison(quick, threads, rounds, out):
    """genesis_lite against bare_mpm.py, float32, in alternated fresh processes (see the module docstring)."""
    env = dict(os.environ, GS_NUM_THREADS=str(threads))
    t_start = time.time()
    rows = []
    for scene, parts, steps, reps in (("cube", "8000", "20" if quick else "50", "3" if quick else "5"),
                                      ("filled", "64000", "5" if quick else "10", "3")):
        ours, bare, ratios = [], [], []
        for r in range(rounds):
            cmds = [("ours", [sys.executable, str(HERE / "bench_mpm.py"), "--worker", "32", parts, steps, reps, "0", "",
                              "--scene", scene], env),
                    ("bare", [sys.executable, str(HERE / "bare_mpm.py"), "--threads", str(threads), "--scene", scene,
                              "--particles", parts, "--steps", steps, "--repeats", reps], None)]
            got = {}
            for name, cmd, e in (cmds if r % 2 == 0 else cmds[::-1]):
                res = _run(cmd, e)
                if "error" in res:
                    raise SystemExit(f"{name} ({scene}): {res['error']}")
                got[name] = res["rows"][0] if name == "ours" else res
            ours.append(got["ours"])
            bare.append(got["bare"])
            ratios.append(got["ours"]["rate"] / got["bare"]["rate"])
            print(f"  {scene} round {r + 1}: genesis_lite {got['ours']['rate'] / 1e6:.2f} M/s ({got['ours']['threads']} "
                  f"threads), bare {got['bare']['rate'] / 1e6:.2f} M/s ({got['bare']['threads']} threads), "
                  f"ratio {ratios[-1]:.2f}", file=sys.stderr, flush=True)
        rows.append({"scene": scene, "n_particles": ours[0]["n_particles"], "bare_particles": bare[0]["n_particles"],
                     "threads": (ours[0]["threads"], bare[0]["threads"]), "steps": int(steps), "rounds": rounds,
                     "ours": statistics.median(o["rate"] for o in ours), "bare": statistics.median(b["rate"] for b in bare),
                     "ratio": statistics.median(ratios), "ratio_range": (min(ratios), max(ratios))})
    desc = {"cube": "cube (8,000 particles, 65^3 nodes on [0, 1]^3)",
            "filled": "filled (64,000 particles, 33^3 nodes on [0, 0.5]^3)"}
    lines = ["<!-- bare -->", "## Against a bare textbook Taichi MLS-MPM kernel (bench_mpm.py --bare)", "",
             f"`python benchmarks/bench_mpm.py --bare{' --quick' if quick else ''} --threads {threads}`, "
             f"{time.strftime('%Y-%m-%d %H:%M')}, {os.cpu_count()} CPU cores "
             f"({platform.processor() or platform.machine()}), load average {os.getloadavg()[0]:.1f} at the end, "
             f"total {time.time() - t_start:.0f} s. float32, dt 2e-3 s, 10 substeps; the peer is "
             "benchmarks/bare_mpm.py (APIC, fixed-corotated through ti.svd, dense grid). Fresh processes, the two "
             "engines alternated; rates are medians over the rounds (each a median of warm repeats), the ratio the "
             "median of the per-round ratios (range in brackets).", "",
             "| scene | Taichi threads (ours / bare) | rounds x steps | genesis_lite M p-substeps/s | bare M p-substeps/s "
             "| ratio |", "| --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {desc[r['scene']]} | {r['threads'][0]} / {r['threads'][1]} | {r['rounds']} x {r['steps']} | "
                     f"{r['ours'] / 1e6:.2f} | {r['bare'] / 1e6:.2f} | {r['ratio']:.2f}x ({r['ratio_range'][0]:.2f}-"
                     f"{r['ratio_range'][1]:.2f}) |")
    lines.append("<!-- /bare -->")
    section = "\n".join(lines)
    path = Path(out)
    text = path.read_text() if path.exists() else ""
    if "<!-- bare -->" in text and "<!-- /bare -->" in text:
        head, rest = text.split("<!-- bare -->", 1)
        text = head + section + rest.split("<!-- /bare -->", 1)[1]
    else:
        text = text.rstrip("\n") + ("\n\n" if text else "") + section + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    print(section)
    print(json.dumps(rows))


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
    old = Path(out).read_text() if Path(out).exists() else ""
    tail = ""
    if "<!-- bare -->" in old and "<!-- /bare -->" in old:  # keep the --bare section and the notes after it
        bare, tail = old.split("<!-- bare -->", 1)[1].split("<!-- /bare -->", 1)
        lines += ["", "<!-- bare -->" + bare + "<!-- /bare -->"]
    Path(out).write_text("\n".join(lines) + ("\n" + tail.lstrip("\n") if tail.strip() else "\n"))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
