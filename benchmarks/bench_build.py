"""Build time, a second robot in the same process, and the first backward, in fresh processes with an
empty and with a warm Taichi kernel cache.

    python benchmarks/bench_build.py [--quick] [--repeats 3] [--cold-repeats 1] [--precision 32] [--json out.json]

Every measurement runs in its own child process (`python -c ...`, so the import is timed from a bare
interpreter). "cold": TI_OFFLINE_CACHE_FILE_PATH (Taichi's kernels) and GS_CACHE_DIR (genesis_lite's
loaded URDF models, genesis_lite/loaders/cache.py) point to new, empty folders; "warm": later processes
reuse the folders the cold one left (Taichi writes its cache when the process exits). Reported are the
medians over the repeats and, for each quantity, the spread (min..max).

1. Import floor: `import torch` and then `import taichi` alone (what genesis_lite cannot go below).
2. Build: import genesis_lite, gs.init, a plane and example-robot-data's full Panda URDF (meshes),
   build(), first step() (build and step split into Taichi's front end -- Python AST to IR, which runs
   at every first launch in a process, cached or not --, the first launches -- offline-cache load or
   compile, LLVM JIT, run -- and the rest); then in the same process a second, different robot (UR5,
   full URDF) over a
   plane, then the Panda and the UR5 without a plane (no collision pairs), each add_entity + build +
   first step. (A scene reuses the kernels of an earlier, dropped scene of its class: the UR5 over a
   plane those of the Panda over a plane, whose contact kernels keep their core; the Panda alone then
   takes a new core of the class, the UR5 alone that one.)
3. First backward: a fresh process builds the full Panda without collision, requires_grad, runs 50
   steps under control_dofs_force from a leaf tensor, loss = |hand position|^2, and times the
   forward (compile included) and loss.backward().
Goals (issue #10, item 4): warm import to first step <= 4 s, second robot <= 1 s, first backward
<= 1.5 s warm and <= 5 s cold.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import find_robots_dir, print_table, run_python  # noqa: E402

GOALS = {"first_step": 4.0, "second_robot": 1.0, "first_bwd_warm": 1.5, "first_bwd_cold": 5.0}

FLOOR_CODE = """
import time, json
t0 = time.perf_counter()
import torch
t1 = time.perf_counter()
import taichi
t2 = time.perf_counter()
print(json.dumps({"torch": t1 - t0, "taichi": t2 - t1, "both": t2 - t0}))
"""

BUILD_CODE = """
import time, json
t0 = time.perf_counter()
import genesis_lite as gs
t1 = time.perf_counter()
gs.init(backend=gs.cpu, precision={precision!r})
t2 = time.perf_counter()
out = {{"import": t1 - t0, "init": t2 - t1}}

# time spent in Taichi's front end (Python AST -> IR) and in kernel launches (a first launch loads the
# kernel from the offline cache or compiles it, JITs it, then runs it)
from solvers import taichi_compat
acc = taichi_compat.time_kernel_work()

def scene_of(urdf, plane, parts=None):
    ta = time.perf_counter()
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
    if plane:
        scene.add_entity(gs.morphs.Plane())
    scene.add_entity(gs.morphs.URDF(file=urdf, fixed=True))
    tb = time.perf_counter()
    a0 = dict(acc)
    scene.build()
    tc = time.perf_counter()
    a1 = dict(acc)
    scene.step()
    td = time.perf_counter()
    if parts is not None:
        for k in acc:
            parts["build_" + k] = a1[k] - a0[k]
            parts["step_" + k] = acc[k] - a1[k]
        parts["build_python"] = (tc - tb) - parts["build_frontend"] - parts["build_launch"]
        parts["step_python"] = (td - tc) - parts["step_frontend"] - parts["step_launch"]
    return scene, (tb - ta, tc - tb, td - tc, td - ta)

scene, (out["load"], out["build"], out["step"], _) = scene_of({panda!r}, True, out)
out["first_step"] = time.perf_counter() - t0
del scene
_, (_, _, _, out["second_robot"]) = scene_of({ur5!r}, True)
_, (_, _, _, out["first_noplane"]) = scene_of({panda!r}, False)
_, (_, _, _, out["second_robot_noplane"]) = scene_of({ur5!r}, False)
print(json.dumps(out))
"""

BACKWARD_CODE = """
import time, json
t0 = time.perf_counter()
import torch
import genesis_lite as gs
gs.init(backend=gs.cpu, precision={precision!r})
scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True),
                 rigid_options=gs.options.RigidOptions(enable_collision=False))
robot = scene.add_entity(gs.morphs.URDF(file={panda!r}, fixed=True))
scene.build()
t1 = time.perf_counter()
dt = gs.tc_float
gen = torch.Generator().manual_seed(0)
q0 = torch.tensor([0.1, -0.5, 0.2, -2.0, 0.1, 1.5, 0.7, 0.02, 0.02], dtype=dt, requires_grad=True)
u = (2.0 * torch.rand(50, robot.n_dofs, generator=gen) - 1.0).to(dt).requires_grad_()
scene.reset()
robot.set_dofs_position(q0)
for t in range(50):
    robot.control_dofs_force(u[t])
    scene.step()
loss = (robot.get_links_pos()[-1] ** 2).sum()
t2 = time.perf_counter()
loss.backward()
t3 = time.perf_counter()
assert q0.grad is not None and bool(torch.isfinite(u.grad).all())
print(json.dumps({{"import_build": t1 - t0, "first_fwd": t2 - t1, "first_bwd": t3 - t2}}))
"""


def _run(code: str, cache: str | None):
    env = {"TI_OFFLINE_CACHE_FILE_PATH": os.path.join(cache, "taichi"), "GS_CACHE_DIR": os.path.join(cache, "gs")} \
        if cache else {}
    t = time.perf_counter()
    res, err = run_python(["-c", code], env=env, timeout=1800)
    if res is not None:
        res["process"] = time.perf_counter() - t
    return res, err


def measure(code: str, cold_repeats: int, warm_repeats: int, label: str):
    """[(cold runs), (warm runs)]: each cold run in a new empty cache folder, the warm runs in the last."""
    cold, warm, errors = [], [], []
    cache = None
    for i in range(cold_repeats):
        if cache:
            shutil.rmtree(cache, ignore_errors=True)
        cache = tempfile.mkdtemp(prefix="gl_bench_build_")
        print(f"  {label}: cold {i + 1}/{cold_repeats} ...", flush=True)
        res, err = _run(code, cache)
        (cold.append(res) if res else errors.append(err))
    for i in range(warm_repeats):
        print(f"  {label}: warm {i + 1}/{warm_repeats} ...", flush=True)
        res, err = _run(code, cache)
        (warm.append(res) if res else errors.append(err))
    if cache:
        shutil.rmtree(cache, ignore_errors=True)
    for e in errors:
        print(f"  {label}: FAILED: {e}", flush=True)
    return cold, warm, errors


def summary(runs, key):
    vals = [r[key] for r in runs if r.get(key) is not None]
    if not vals:
        return None
    return {"median": statistics.median(vals), "min": min(vals), "max": max(vals), "n": len(vals)}


def _fmt(s):
    if s is None:
        return "-"
    return f"{s['median']:.2f}" + (f" ({s['min']:.2f}..{s['max']:.2f})" if s["n"] > 1 else "")


def load_average() -> str:
    try:
        return " ".join(f"{x:.1f}" for x in os.getloadavg())
    except OSError:
        return "?"


def main():
    ap = argparse.ArgumentParser(description="genesis_lite build / second robot / first backward times")
    ap.add_argument("--quick", action="store_true", help="one cold and one warm run of each")
    ap.add_argument("--repeats", type=int, default=3, help="warm runs")
    ap.add_argument("--cold-repeats", type=int, default=1, help="cold runs (each in a new empty cache)")
    ap.add_argument("--precision", default="32", choices=["32", "64"], help="gs.init precision (default: Genesis' 32)")
    ap.add_argument("--skip-backward", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    warm_n, cold_n = (1, 1) if args.quick else (args.repeats, args.cold_repeats)
    robots = find_robots_dir()
    panda = str(robots / "panda_description" / "urdf" / "panda.urdf")
    ur5 = str(robots / "ur_description" / "urdf" / "ur5_robot.urdf")
    data = {"load_before": load_average(), "precision": args.precision, "cpus": os.cpu_count()}
    print(f"load average before: {data['load_before']} ({os.cpu_count()} CPUs)", flush=True)

    print("1. import floor ...", flush=True)
    floor = [r for r in (_run(FLOOR_CODE, None)[0] for _ in range(warm_n)) if r]
    data["floor"] = {k: summary(floor, k) for k in ("torch", "taichi", "both")}

    print("2. build ...", flush=True)
    cold, warm, err = measure(BUILD_CODE.format(precision=args.precision, panda=panda, ur5=ur5), cold_n, warm_n, "build")
    keys = ("import", "init", "load", "build", "build_frontend", "build_launch", "build_python", "step",
            "step_frontend", "step_launch", "step_python", "first_step", "second_robot", "first_noplane",
            "second_robot_noplane", "process")
    data["build"] = {"cold": {k: summary(cold, k) for k in keys}, "warm": {k: summary(warm, k) for k in keys},
                     "errors": err}

    if not args.skip_backward:
        print("3. first backward ...", flush=True)
        cold_b, warm_b, err_b = measure(BACKWARD_CODE.format(precision=args.precision, panda=panda), cold_n, warm_n,
                                        "backward")
        keys_b = ("import_build", "first_fwd", "first_bwd", "process")
        data["backward"] = {"cold": {k: summary(cold_b, k) for k in keys_b},
                            "warm": {k: summary(warm_b, k) for k in keys_b}, "errors": err_b}
    data["load_after"] = load_average()

    fl = data["floor"]
    print_table([{"what": k, "s": _fmt(fl[k])} for k in ("torch", "taichi", "both")],
                [("what", "import alone", ""), ("s", "seconds", "")], title="1. Import floor (fresh process)")
    rows = []
    names = {"import": "import genesis_lite", "init": "gs.init", "load": "plane + Panda URDF (add_entity)",
             "build": "scene.build()", "build_frontend": "  of which Taichi front end (AST -> IR)",
             "build_launch": "  of which first launches (cache load / compile, JIT, run)",
             "build_python": "  of which the rest (Python, field allocation)",
             "step": "first scene.step()", "step_frontend": "  of which Taichi front end (AST -> IR)",
             "step_launch": "  of which first launches (cache load / compile, JIT, run)",
             "step_python": "  of which the rest (Python)", "first_step": "import to end of first step",
             "second_robot": "UR5 + plane next in the same process (load+build+step)",
             "first_noplane": "then Panda alone (no collision pairs)",
             "second_robot_noplane": "then UR5 alone (no collision pairs)", "process": "whole process"}
    goal_of = {"first_step": GOALS["first_step"], "second_robot": GOALS["second_robot"],
               "second_robot_noplane": GOALS["second_robot"]}
    for k in keys:
        c, w = data["build"]["cold"][k], data["build"]["warm"][k]
        g = goal_of.get(k)
        rows.append({"what": names[k], "cold": _fmt(c), "warm": _fmt(w), "goal": f"<= {g} s (warm)" if g else "",
                     "met": ("yes" if w["median"] <= g else "NO") if g and w else ""})
    print_table(rows, [("what", "what", ""), ("cold", "cold cache s", ""), ("warm", "warm cache s", ""),
                       ("goal", "goal", ""), ("met", "met", "")],
                title=f"2. Build, fresh process, precision {args.precision} (median (min..max) of {cold_n} cold, "
                      f"{warm_n} warm)")
    if "backward" in data:
        rows = []
        for k, name in (("import_build", "import + init + build"), ("first_fwd", "first 50-step forward"),
                        ("first_bwd", "first backward"), ("process", "whole process")):
            c, w = data["backward"]["cold"][k], data["backward"]["warm"][k]
            rows.append({"what": name, "cold": _fmt(c), "warm": _fmt(w)})
        b = data["backward"]
        met = []
        if b["warm"]["first_bwd"]:
            met.append(f"warm {'met' if b['warm']['first_bwd']['median'] <= GOALS['first_bwd_warm'] else 'NOT met'}")
        if b["cold"]["first_bwd"]:
            met.append(f"cold {'met' if b['cold']['first_bwd']['median'] <= GOALS['first_bwd_cold'] else 'NOT met'}")
        print_table(rows, [("what", "what", ""), ("cold", "cold cache s", ""), ("warm", "warm cache s", "")],
                    title=f"3. First backward, Panda 50 steps, precision {args.precision} (goals <= "
                          f"{GOALS['first_bwd_warm']} s warm, <= {GOALS['first_bwd_cold']} s cold: {', '.join(met)})")
    print(f"\nload average before / after: {data['load_before']} / {data['load_after']}")
    if args.json:
        args.json.write_text(json.dumps(data, indent=2))


if __name__ == "__main__":
    main()
