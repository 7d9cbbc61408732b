"""Batched speed in one run: the Panda (no geometry) and ANYmal on the ground, 1,024 envs each, both
paired with MuJoCo's `rollout` in the same process.

    python benchmarks/bench_batched.py [--rounds 3] [--precision 32] [--quick] [--out benchmarks/results/batched.md]

Each round runs, one after the other in fresh child processes:
- bench_rigid.py's `gl_steps` worker: the stripped Panda (common.write_stripped_panda), fixed base, Euler,
  dt = 0.01 s, 100 steps of 1,024 envs, alternating run for run with MuJoCo's rollout (2 threads);
- bench_contact.py's `speed` worker: ANYmal B on the ground under PD, implicitfast, dt = 0.01 s, 100 steps
  of 1,024 envs, alternating with MuJoCo's rollout of the same URDF the same way.
A "paired ratio" is the median of the per-pair ratios MuJoCo time / genesis_lite time of one child. The
table lists every round, so a good Panda round is never shown beside another time's ANYmal round.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_contact as bc  # noqa: E402
import bench_rigid as br  # noqa: E402
from common import machine_info, print_table, progress, write_stripped_panda  # noqa: E402

HERE = Path(__file__).resolve().parent


def _panda(urdf, envs, steps, repeats, precision, threads):
    return br._child("gl_steps", urdf, envs=envs, steps=steps, repeats=repeats, precision=precision,
                     **{"paired-threads": threads})


def _anymal(envs, steps, repeats, precision, threads):
    return bc._child("speed", envs=envs, steps1=50, stepsb=steps, repeats=repeats, precision=precision,
                     **{"paired-threads": threads})


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--envs", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--precision", default="32", choices=["32", "64"])
    ap.add_argument("--threads", type=int, default=2, help="MuJoCo rollout threads")
    ap.add_argument("--quick", action="store_true", help="one round, 64 envs, 20 steps (a smoke run)")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "batched.md")
    a = ap.parse_args()
    if a.rounds < 1 or a.envs < 1 or a.steps < 1:
        ap.error("--rounds, --envs and --steps must be positive")
    if a.quick:
        a.rounds, a.envs, a.steps = 1, 64, 20
    t_start = time.perf_counter()
    load0 = machine_info().get("load", (float("nan"),))[0]
    urdf = write_stripped_panda(Path(tempfile.mkdtemp(prefix="gl_panda_")))
    rows, failed = [], []
    for r in progress(range(1, a.rounds + 1), desc="rounds"):
        for scene, run in (("Panda, no geometry", lambda: _panda(urdf, a.envs, a.steps, 10, a.precision, a.threads)),
                           ("ANYmal on the ground", lambda: _anymal(a.envs, a.steps, 5, a.precision, a.threads))):
            res, err = run()
            if err:
                failed.append(f"round {r}, {scene}: {err}")
                rows.append({"round": r, "scene": scene, "note": f"FAILED: {err}"})
                continue
            gl = res.get("rate", res.get("rate_b"))
            mj = res.get("mj_rate", res.get("mj_rate_b"))
            rows.append({"round": r, "scene": scene, "gl": gl, "mj": mj, "ratio": res["paired_ratio"],
                         "met": "met" if res["paired_ratio"] >= 2.0 else "NOT MET", "note": ""})
    load1 = machine_info().get("load", (float("nan"),))[0]
    cols = [("round", "round", "d"), ("scene", "scene", ""), ("gl", "genesis_lite env-steps/s", ",.0f"),
            ("mj", f"MuJoCo rollout ({a.threads} threads) env-steps/s", ",.0f"),
            ("ratio", "paired ratio", ".2f"), ("met", ">= 2x", ""), ("note", "note", "")]
    title = (f"{a.envs} envs, {a.steps} steps per run, float{a.precision}; paired ratio = median over 10 "
             "alternating runs of MuJoCo time / genesis_lite time")
    table = print_table(rows, cols, title)
    summary = []
    for scene in ("Panda, no geometry", "ANYmal on the ground"):
        rs = [x["ratio"] for x in rows if x["scene"] == scene and "ratio" in x]
        if rs:
            summary.append(f"- {scene}: median paired ratio {statistics.median(rs):.2f} over {len(rs)} round(s), "
                           f"range {min(rs):.2f}-{max(rs):.2f}")
    info = machine_info()
    lines = ["# genesis_lite batched speed against MuJoCo's rollout", "",
             f"`python benchmarks/bench_batched.py{' --quick' if a.quick else ''} --rounds {a.rounds} --precision "
             f"{a.precision}`, {time.strftime('%Y-%m-%d %H:%M')}, {info.get('cpu')}, {info.get('cores')} cores, "
             f"taichi {info.get('taichi')}, mujoco {info.get('mujoco')}; load (1 min) {load0:.2f} at the start, "
             f"{load1:.2f} at the end; total {(time.perf_counter() - t_start) / 60:.1f} min.", "",
             table, "", *summary]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text("\n".join(lines) + "\n")
    print("\n".join(summary))
    print(f"wrote {a.out}")
    if failed:
        print("failed:\n  " + "\n  ".join(failed), file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
