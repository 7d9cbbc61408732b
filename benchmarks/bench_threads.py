"""Taichi's CPU worker threads pinned to a core each (gs.init's default where the threads span the cores,
solvers/taichi_compat/threads.py) against left to the scheduler (GS_PIN_THREADS=0): the cost of one
parallel loop, fresh processes alternated.

Each child process runs gs.init (float64, default threads) and times, as medians of 200 launches, a kernel
with one parallel loop over 1,024 items doing ~nothing (the dispatch: waking the workers and waiting for
them) and doing 1,024 x 100 sines (~1.4 ms on one thread here: whether the second worker helps), each launched back to back
and after ~1 ms of Python in between. The end-to-end effect on the MPM cube and the batched rigid scenes is
measured with their own scripts (bench_mpm.py --worker, bench_batched.py) under GS_PIN_THREADS=0 and unset:
benchmarks/results/threads.md.

    python benchmarks/bench_threads.py [--rounds 3] [--out benchmarks/results/threads_dispatch.md]
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from common import REPO_ROOT, print_table  # noqa: E402

# inner steps of the working loop: 1,024 x 100 sines, ~1.4 ms on one thread of this project's machine
WORK_STEPS = 100


def child():
    sys.path.insert(0, str(REPO_ROOT))
    import numpy as np
    import taichi as ti

    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")

    @ti.kernel
    def loop(x: ti.types.ndarray(), m: ti.i32):
        for i in x:
            a = x[i]
            for _ in range(m):
                a = ti.sin(a) + 0.5
            x[i] = a

    x = np.zeros(1024)

    def spin(s):
        t = time.perf_counter()
        while time.perf_counter() - t < s:
            pass

    def median_us(m, gap, n=200):
        loop(x, m)
        ts = []
        for _ in range(n):
            spin(gap)
            t = time.perf_counter()
            loop(x, m)
            ts.append(time.perf_counter() - t)
        return 1e6 * statistics.median(ts)

    m = WORK_STEPS
    out = {"pinning": gs.thread_pinning["why"], "threads": gs.cpu_threads, "m": m}
    for gap in (0.0, 1e-3):
        out[f"empty_{gap}"] = median_us(1, gap)
        out[f"work_{gap}"] = median_us(m, gap)
    print(json.dumps(out))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default=str(HERE / "results" / "threads_dispatch.md"))
    ap.add_argument("--child", action="store_true")
    args = ap.parse_args()
    if args.child:
        return child()
    rows = []
    for r in range(args.rounds):
        for pin in ("", "0"):
            env = dict(os.environ, GS_PIN_THREADS=pin)
            done = subprocess.run([sys.executable, __file__, "--child"], env=env, capture_output=True, text=True,
                                  timeout=600)
            if done.returncode:
                raise SystemExit(done.stderr[-2000:])
            res = json.loads(done.stdout.strip().splitlines()[-1])
            rows.append({"round": r + 1, "workers": "pinned" if res["pinning"] == "pinned" else "not pinned", "threads": res["threads"],
                         "empty0": f"{res['empty_0.0']:.0f}", "empty1": f"{res['empty_0.001']:.0f}",
                         "work0": f"{res['work_0.0']:.0f}", "work1": f"{res['work_0.001']:.0f}"})
            print(rows[-1], flush=True)
    cols = [("round", "round", ""), ("workers", "Taichi's workers", ""), ("threads", "threads", ""),
            ("empty0", "empty loop, back to back, us", ""), ("empty1", "empty loop, 1 ms apart, us", ""),
            ("work0", "1.4 ms loop, back to back, us", ""), ("work1", "1.4 ms loop, 1 ms apart, us", "")]
    table = print_table(rows, cols, title="one parallel loop over 1,024 items, medians of 200 launches")
    if args.out:
        Path(args.out).write_text(f"# Taichi's CPU workers pinned or not: one parallel loop\n\n"
                                  f"`python benchmarks/bench_threads.py --rounds {args.rounds}`, "
                                  f"{time.strftime('%Y-%m-%d %H:%M')}\n\n{table}\n")


if __name__ == "__main__":
    main()
