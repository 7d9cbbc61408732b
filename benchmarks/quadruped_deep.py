"""The work-precision quadruped (ANYmal B dropped from 0.62 m, PD holding the standing pose) at 1,024 envs, down to
errors of 1e-5 m, genesis_lite against MuJoCo (issue #24's "down to errors of 1e-5"); --scene quadruped_armature
for the same with Genesis's default armature (0.1 kg m^2 on every joint) in both engines.

bench_workprecision.py's sweep stops at first-order steps of 0.625 ms, where both engines' errors are ~1e-4 m, and
its references (each engine's RK4 at 0.1 ms) are themselves off by 0.9-1.9e-5 m. This script:
- gives each engine a reference good to ~1e-6 m: its semi-implicit Euler at dt = 2.44 us (0.01 s / 4096), the
  check run at twice that step. On the 16 starts, both engines' changes per halving of dt are first order for
  Euler, implicitfast and RK4 (measured 2026-12-06: Euler's change at 9.8 us is 2.0e-6 m ours, 4.3e-6 m
  MuJoCo's), so a run's error is about its change from the step twice as long, and Euler is the cheapest per
  step;
- extends each engine's most accurate first-order integrator to 2^10 steps per 20 ms (19.5 us) and its RK4 to
  2^7 (156 us); the third integrator keeps the default sweep's range (2^5). On the quadruped, the most accurate
  first-order integrator at fine steps is MuJoCo's Euler (per halving, at the 16 starts and 9.8 us: 4.3e-6 m,
  implicitfast 7.4e-6; ours 3.2e-6 implicitfast, 2.0e-6 Euler), and ours is extended in implicitfast, the
  faster of our two at the default sweep's errors; with armature both engines' is implicitfast (PLANS). genesis_lite
  takes the finer steps as substeps of dt = 20 ms (the same arithmetic as dt halving, with equal errors, and at
  1,024 envs about half the time: one launch per substep over every env); MuJoCo takes them as dt (its rollout
  runs each env's steps back to back; it has no substeps);
- reports each engine's time to an error and the ratio (bench_workprecision.time_to_error, equal_error_ratio).

    python benchmarks/quadruped_deep.py [--scene quadruped] [--envs 1024] [--json F] [--md F] [--from-json F]
    # ~47 min a scene at 1,024 envs (2 cores)
"""
import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_workprecision as W  # noqa: E402

REF, CHECK = ("Euler", 0.01 / 4096, 1), ("Euler", 0.01 / 2048, 1)
# per scene, engine and integrator: the finest of 2^0 .. 2^k steps per 20 ms. With armature, MuJoCo's most accurate
# first-order integrator is implicitfast (the default sweep at 1 env, 0.3125 ms: 8.4e-6 m against Euler's 3.5e-5)
PLANS = {"quadruped": {"genesis_lite": {"implicitfast": 10, "RK4": 7, "Euler": 5},
                       "mujoco": {"Euler": 10, "RK4": 7, "implicitfast": 5}},
         "quadruped_armature": {"genesis_lite": {"implicitfast": 10, "RK4": 7, "Euler": 5},
                                "mujoco": {"implicitfast": 10, "RK4": 7, "Euler": 5}}}
LEVELS = (1e-3, 3e-4, 1e-4, 3e-5, 2e-5, 1e-5)


def points(key, engine, quick=False):
    out = []
    for integ, k in PLANS[key][engine].items():
        k = min(k, 2) if quick else k
        if engine == "genesis_lite":
            out += [(integ, 0.02, 2**j) for j in range(k + 1)]
        else:
            out += [(integ, 0.02 / 2**j, 1) for j in range(k + 1)]
    return out


def measure(key, n_envs, quick, log=print):
    wps = W.SCENES[key]
    fine, check = (REF, CHECK) if not quick else (("Euler", 0.02 / 64, 1), ("Euler", 0.02 / 32, 1))
    out = {"scene": key, "envs": n_envs, "reference": f"each engine's {fine[0]} at dt = {fine[1]:.4g} s (16 starts), "
                                                      f"its check at {check[1]:.4g} s", "engines": {}}
    with tempfile.TemporaryDirectory(prefix="quad_deep_") as tmp:
        files = wps.files(Path(tmp))
        for engine in PLANS[key]:
            t0 = time.time()
            ref, self_err, err = W._fine_reference(engine, wps, files, W.Reference("fine", "", fine=fine, check=check))
            if err:
                raise SystemExit(f"quadruped_deep.py: {engine}'s reference failed: {err}")
            ref = np.asarray(ref)
            log(f"{engine}: reference in {time.time() - t0:.0f} s; its check run differs by {self_err:.2e} m")
            t0 = time.time()
            res, err = W.run_engine(engine, wps, files, points(key, engine, quick), n_envs, 1 if quick else 3,
                                    timeout=3 * 3600)
            if res is None:
                raise SystemExit(f"quadruped_deep.py: {engine}'s run failed: {err}")
            pts = res["points"]
            for p in pts:
                p["error"] = None if p.get("obs") is None else W._error(p["obs"], ref, key)
                p["diverged"] = bool(p.get("failed")) or p["error"] is None or p["error"] > W.DIVERGED
                p.pop("obs", None)
            log(f"{engine}: {len(pts)} runs in {time.time() - t0:.0f} s")
            out["engines"][engine] = {"ref_self_error": self_err, "points": pts}
    return out


def report(res) -> str:
    e = lambda x: "-" if x is None or not math.isfinite(x) else f"{x:.3g}"  # noqa: E731
    ours, theirs = (res["engines"][k]["points"] for k in ("genesis_lite", "mujoco"))
    lines = [f"Scene: {res.get('scene', 'quadruped')}. Reference: {res['reference']}; the check run's difference (an upper bound of the reference's own "
             "error, which at first order is about half of it): "
             + ", ".join(f"{k} {v['ref_self_error']:.1e} m" for k, v in res["engines"].items()) + ".", "",
             f"Time to an error at {res['envs']} envs (least over the integrators, log-log between the runs that "
             "bracket it):", "", "| error (m) | genesis_lite s | MuJoCo s | ratio |", "| --- | --- | --- | --- |"]
    for lv in LEVELS:
        a, b = W.time_to_error(ours, lv), W.time_to_error(theirs, lv)
        r = a / b if math.isfinite(a) and math.isfinite(b) else None
        lines.append(f"| {lv:g} | {e(a)} | {e(b)} | {'-' if r is None else f'{r:.2f}'} |")
    r = W.equal_error_ratio(ours, theirs)
    if r:
        lines += ["", f"Equal-error ratio over the errors both reach ({r[2][0]:.1e} .. {r[2][1]:.1e} m): max "
                  f"{r[0]:.2f}, median {r[1]:.2f}."]
    lines += ["", "| engine | integrator | dt s | substeps | error (m) | wall s (median) | runs timed |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for engine, v in res["engines"].items():
        for p in v["points"]:
            err = "diverged" if p["diverged"] else f"{p['error']:.3e}"
            lines.append(f"| {engine} | {p['integrator']} | {p['dt']:.4g} | {p['substeps']} | {err} | "
                         f"{e(p.get('wall'))} | {len(p.get('walls') or [])} |")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="quadruped", choices=["quadruped", "quadruped_armature"])
    ap.add_argument("--envs", type=int, default=1024)
    ap.add_argument("--quick", action="store_true", help="three steps an integrator and a coarse reference")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--md", type=Path, default=None)
    ap.add_argument("--from-json", type=Path, default=None, help="no run: report an earlier --json file")
    a = ap.parse_args()
    res = json.loads(a.from_json.read_text()) if a.from_json else measure(a.scene, a.envs, a.quick)
    if a.json and not a.from_json:
        a.json.write_text(json.dumps(res, indent=1))
    text = report(res)
    print(text)
    if a.md:
        a.md.write_text(text + "\n")


if __name__ == "__main__":
    main()
