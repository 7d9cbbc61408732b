"""The work-precision push (bench_workprecision.py's "push": a Panda pushing a box with a sphere on its hand) at 1
env, float64: implicitfast at halving steps from 1.25 ms to 39 us, each against RK4 at 25 us and against the
benchmark's reference (RK4 at 0.1 ms), and that reference against RK4 at 25 us. Shows where the first-order runs'
error plateaus and where it converges (README, #24 row).

    python benchmarks/push_convergence.py        # ~30 s
"""
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_workprecision as W  # noqa: E402

DTS = (1.25e-3, 6.25e-4, 3.125e-4, 1.5625e-4, 7.8125e-5, 3.90625e-5)
FINE, REF = ("RK4", 2.5e-5, 1), ("RK4", W.PUSH_REF[1], 1)


def main():
    with tempfile.TemporaryDirectory(prefix="push_conv_") as tmp:
        files = W.SCENES["push"].files(Path(tmp))
        res, err = W.run_engine("genesis_lite", W.SCENES["push"], files,
                                [FINE, REF] + [("implicitfast", dt, 1) for dt in DTS], 0, 1)
    if res is None:
        raise SystemExit(f"push_convergence.py: the run failed: {err}")
    obs = [np.asarray(p["obs"]) for p in res["points"]]
    fine, ref = obs[0], obs[1]
    print(f"the benchmark's reference (RK4 at {REF[1]:g} s) against RK4 at {FINE[1]:g} s: "
          f"{W._error(ref.tolist(), fine, 'push'):.2e} m")
    print("| implicitfast dt s | error against RK4 at 25 us (m) | against the benchmark's reference (m) |")
    print("| --- | --- | --- |")
    for dt, o in zip(DTS, obs[2:]):
        print(f"| {dt:.4g} | {W._error(o.tolist(), fine, 'push'):.2e} | {W._error(o.tolist(), ref, 'push'):.2e} |")


if __name__ == "__main__":
    main()
