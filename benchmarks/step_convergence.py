"""Does a work-precision scene converge as dt halves, in each engine and integrator? (issue #24)

Runs one scene of bench_workprecision.py (its starts as envs: 16 for the quadrupeds, 1 for the push) with Euler
and implicitfast at dt = 0.3125 ms / 2^k and RK4 at 0.625 ms / 2^k (k = 0 .. 5), and prints each run's change from
the run at twice its step (the scene's own error measure, bench_workprecision._error). At first order the change
halves with dt and is about the coarser run's error; a change that does not shrink means no reference of that
engine can be trusted below it.

    python benchmarks/step_convergence.py [--scene push] [--engine mujoco|genesis_lite]   # seconds to minutes
"""
import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_workprecision as W  # noqa: E402

PLAN = {"Euler": [0.3125e-3 / 2**k for k in range(6)], "implicitfast": [0.3125e-3 / 2**k for k in range(6)],
        "RK4": [0.625e-3 / 2**k for k in range(6)]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="push", choices=["push", "quadruped", "quadruped_armature"])
    ap.add_argument("--engine", default="mujoco", choices=["mujoco", "genesis_lite"])
    a = ap.parse_args()
    wps = W.SCENES[a.scene]
    with tempfile.TemporaryDirectory(prefix="step_conv_") as tmp:
        files = wps.files(Path(tmp))
        for integ, dts in PLAN.items():
            pts, t0 = [(integ, dt, 1) for dt in dts], time.time()
            if a.engine == "mujoco":
                res = W.run_mj(wps, files, pts, wps.starts, 1)
            else:
                res, err = W.run_gl(a.scene, files, pts, wps.starts, 1)
                if res is None:
                    raise SystemExit(f"step_convergence.py: the run failed: {err}")
            obs = [p.get("obs") for p in res["points"]]
            print(f"{a.engine} {integ} ({time.time() - t0:.0f} s)", flush=True)
            for i in range(1, len(dts)):
                ch = (W._error(obs[i - 1], np.asarray(obs[i]), a.scene) if obs[i] is not None and obs[i - 1]
                      is not None else float("nan"))
                print(f"  dt {dts[i]:.3e} s: change from 2 dt {ch:.3e}", flush=True)


if __name__ == "__main__":
    main()
