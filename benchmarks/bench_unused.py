"""The cost of what a scene does not use: the MPM solver, gradient storage, collision detection.

    python benchmarks/bench_unused.py [--quick]

Every measurement runs in a fresh child process (warm Taichi kernel cache), f64, CPU.
1. MPM never imported: a rigid-only scene (the full Panda URDF of example-robot-data + a plane) built and
   stepped in a normal process, and in one where an import hook makes `import solvers.mpm` fail (so it can be
   neither imported nor used). Build time (Scene() to the end of the first step), RSS after the build, step
   time (median of 5 x 500 steps). The check that genesis_lite does not import the MPM package for a rigid
   scene: 'solvers.mpm' not in sys.modules after `import genesis_lite` and after build + steps.
2. requires_grad: memory and time of a 10,000-step rollout (--quick: 1,000) of the stripped Panda (the rollout
   of bench_grad.py: q0 + random torques, loss on the last link) in a scene built with requires_grad=False,
   with requires_grad=True but nothing requiring grad, and with q0 and controls requiring grad (with and
   without checkpoint_every=100; --quick: the first and the third only). Growth of RSS and of malloc's heap over the rollout (bench_grad's probes).
3. Collision: ANYmal (its URDF's collision shapes) with a fixed base 2 m above a ground plane under PD, so
   collision pairs exist but none is in reach, against enable_collision=False and against no plane at all.
   Step time, median of 5 x 1,000 steps (--quick: 200).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(HERE.parent))  # genesis_lite without an install
from common import Timer, panda_urdf, print_table, progress, run_python, write_stripped_panda  # noqa: E402

MPM_PACKAGE = "solvers.mpm"


class _BlockMPM:
    """A meta-path finder that refuses solvers.mpm and its submodules: the process cannot use the MPM solver."""

    def find_spec(self, name, path=None, target=None):
        if name == MPM_PACKAGE or name.startswith(MPM_PACKAGE + "."):
            raise ImportError(f"{name} is blocked in this benchmark process (measuring a process without MPM)")
        return None


def _rss_mib():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return None


def worker_mpm(block, steps, repeats) -> dict:
    if block:
        sys.meta_path.insert(0, _BlockMPM())
    import importlib.util

    exists = importlib.util.find_spec("solvers") is not None and (HERE.parent / "solvers" / "mpm").is_dir()
    rss0 = _rss_mib()
    import genesis_lite as gs

    after_import = MPM_PACKAGE in sys.modules
    gs.init(backend=gs.cpu, precision="64")
    rss_init = _rss_mib()
    with Timer() as tb:
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
        scene.add_entity(gs.morphs.Plane())
        robot = scene.add_entity(gs.morphs.URDF(file=str(panda_urdf()), fixed=True))
        scene.build()
        scene.step()
    rss_build = _rss_mib()

    def once():
        scene.reset()
        t0 = time.perf_counter()
        for _ in range(steps):
            scene.step()
        return (time.perf_counter() - t0) / steps

    once()
    step_s = statistics.median(once() for _ in range(repeats))
    del robot
    return {"mpm_dir_exists": exists, "blocked": block, "imported_after_import": after_import,
            "imported_after_build": MPM_PACKAGE in sys.modules, "build_s": tb.seconds, "rss_import_init": rss_init - rss0,
            "rss_build": rss_build - rss_init, "rss_total": rss_build, "step_us": 1e6 * step_s}


def worker_grad(urdf, horizon, mode, ckpt) -> dict:
    """mode: "off" (requires_grad=False), "unused" (requires_grad=True, nothing requires grad), "on"."""
    import gc

    import bench_grad as bg
    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")
    scene, robot = bg._gl_build(gs, urdf, 0, mode != "off", ckpt if mode == "on" else None)
    n = robot.n_dofs
    grad = mode == "on"
    bg._gl_rollout(scene, robot, bg._controls(min(horizon, 200), 0, n), bg._q0(0, n), grad, feed="unbind")  # compile
    base = {}

    def probe(out, when):
        if when == "start":
            gc.collect()
            base["rss"], base["heap"] = bg._mem()["VmRSS"], bg._heap_in_use()
            return
        if when == "fwd":
            m, h = bg._mem()["VmRSS"], bg._heap_in_use()
            out["rss_fwd"] = m - base["rss"]
            out["heap_fwd"] = h - base["heap"] if h is not None and base["heap"] is not None else None

    out = bg._gl_rollout(scene, robot, bg._controls(horizon, 0, n), bg._q0(0, n), grad, probe, feed="unbind")
    out.update(horizon=horizon, mode=mode, ckpt=ckpt)
    bg._flush_kernel_cache()
    return out


def worker_collision(mode, steps, repeats) -> dict:
    """mode: "far" (plane 2 m below a fixed-base ANYmal, collision on), "off" (same, enable_collision=False),
    "none" (no plane, collision on: no pairs at all)."""
    import genesis_lite as gs
    from bench_contact import KP, KV, anymal_urdf, standing_pose

    gs.init(backend=gs.cpu, precision="64")
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01),
                     rigid_options=gs.options.RigidOptions(enable_collision=mode != "off"))
    if mode != "none":
        scene.add_entity(gs.morphs.Plane())
    robot = scene.add_entity(gs.morphs.URDF(file=str(anymal_urdf()), fixed=True, pos=(0.0, 0.0, 2.0)))
    scene.build()
    names = [j.name for j in robot.joints if j.n_dofs == 1]
    dofs = [j.dof_start_local for j in robot.joints if j.n_dofs == 1]
    q0 = standing_pose(names)
    robot.set_dofs_kp(np.full(len(dofs), KP), dofs)
    robot.set_dofs_kv(np.full(len(dofs), KV), dofs)
    robot.set_dofs_position(q0, dofs)
    state = scene.get_state()

    def once():
        scene.reset(state)
        robot.control_dofs_position(q0, dofs)
        t0 = time.perf_counter()
        for _ in range(steps):
            scene.step()
        return (time.perf_counter() - t0) / steps

    once()
    step_s = statistics.median(once() for _ in range(repeats))
    s = scene.rigid_solver
    return {"mode": mode, "step_us": 1e6 * step_s, "contact_solver": s.contact is not None,
            "n_stages": len(s.dynamics_stages), "n_geoms": robot.n_geoms,
            "lowest_link_z": float(robot.get_links_pos()[:, 2].min())}


WORKERS = {"mpm": worker_mpm, "grad": worker_grad, "collision": worker_collision}


def _child(worker, timeout=1800, **kw):
    return run_python([str(Path(__file__).resolve()), "--worker", worker, json.dumps(kw)], timeout=timeout)


def run(quick, tmp: Path, log=print, parts=None) -> dict:
    horizon = 1000 if quick else 10000
    steps = 200 if quick else 1000
    urdf = write_stripped_panda(tmp)
    jobs = ([("mpm", dict(block=b, steps=500 if not quick else 100, repeats=5)) for b in (False, True)]
            + [("grad", dict(urdf=str(urdf), horizon=horizon, mode=m, ckpt=c))
               for m, c in ((("off", None), ("on", None)) if quick else
                            (("off", None), ("unused", None), ("on", None), ("on", 100)))]
            + [("collision", dict(mode=m, steps=steps, repeats=5)) for m in ("far", "off", "none")])
    jobs = [j for j in jobs if not parts or j[0] in parts]
    res = {"mpm": [], "grad": [], "collision": []}
    for worker, kw in progress(jobs, desc="unused features"):
        r, err = _child(worker, **kw)
        if r is None:
            log(f"  {worker} {kw}: FAILED: {err}")
            r = {"error": err, **kw}
        res[worker].append(r)
    res["horizon"], res["steps"] = horizon, steps
    return res


def tables(res) -> list[str]:
    out = []
    rows = []
    for r in res["mpm"]:  # (a part that did not run has no table)
        if r.get("error"):
            rows.append({"what": "blocked" if r.get("block") else "normal", "note": r["error"]})
            continue
        rows.append({"what": ("import of solvers.mpm blocked" if r["blocked"] else "normal process"),
                     "build_s": r["build_s"], "rss_build": r["rss_build"], "rss_total": r["rss_total"],
                     "step_us": r["step_us"],
                     "imported": f"{r['imported_after_import']} / {r['imported_after_build']}",
                     "ok": "PASS" if not r["imported_after_build"] else "FAIL",
                     "note": "solvers/mpm exists" if r["mpm_dir_exists"] else
                             "solvers/mpm does not exist yet: both rows measure the same code"})
    ok = [r for r in res["mpm"] if not r.get("error")]
    if len(ok) == 2:
        rows.append({"what": "ratio normal / blocked", "build_s": ok[0]["build_s"] / ok[1]["build_s"],
                     "rss_build": ok[0]["rss_build"] / max(ok[1]["rss_build"], 1e-9),
                     "rss_total": ok[0]["rss_total"] / ok[1]["rss_total"], "step_us": ok[0]["step_us"] / ok[1]["step_us"]})
    if rows:
        out.append(print_table(rows, [
            ("what", "process", ""), ("build_s", "build + 1st step s", ".2f"), ("rss_build", "RSS of the build MiB", ".1f"),
            ("rss_total", "process RSS MiB", ".1f"), ("step_us", "us/step", ".1f"),
            ("imported", "solvers.mpm in sys.modules (after import / after build)", ""),
            ("ok", "rigid scene leaves MPM unimported", ""), ("note", "note", "")],
            title="Rigid-only scene (full Panda + plane, 1 env) with and without the MPM package importable"))
    rows = []
    labels = {"off": "requires_grad=False", "unused": "requires_grad=True, no input requires grad",
              "on": "requires_grad=True, q0 + controls require grad"}
    for r in res["grad"]:
        if r.get("error"):
            rows.append({"what": labels.get(r.get("mode"), "?"), "note": r["error"]})
            continue
        rows.append({"what": labels[r["mode"]] + (f", checkpoint_every={r['ckpt']}" if r.get("ckpt") else ""),
                     "rss": r["rss_fwd"], "heap": r.get("heap_fwd"),
                     "kib_step": 1024 * r["heap_fwd"] / r["horizon"] if r.get("heap_fwd") is not None else None,
                     "fwd": r["fwd"], "bwd": r.get("bwd")})
    if rows:
        out.append(print_table(rows, [
            ("what", "scene", ""), ("rss", "RSS growth over the rollout MiB", ".1f"), ("heap", "heap growth MiB", ".1f"),
            ("kib_step", "heap KiB/step", ".2f"), ("fwd", "forward s", ".2f"), ("bwd", "backward s", ".2f"),
            ("note", "note", "")], title=f"Memory of a {res['horizon']:,}-step rollout (stripped Panda, 1 env), measured "
                                         "after the forward, before backward"))
    rows = []
    labels = {"far": "plane 2 m below the robot, enable_collision=True (pairs exist, none in reach)",
              "off": "plane 2 m below, enable_collision=False", "none": "no plane, enable_collision=True (no pairs)"}
    base = next((r["step_us"] for r in res["collision"] if r.get("mode") == "off" and "step_us" in r), None)
    for r in res["collision"]:
        if r.get("error"):
            rows.append({"what": labels.get(r.get("mode"), "?"), "note": r["error"]})
            continue
        rows.append({"what": labels[r["mode"]], "step_us": r["step_us"], "ratio": r["step_us"] / base if base else None,
                     "contact": "yes" if r["contact_solver"] else "none", "stages": r["n_stages"],
                     "note": f"{r['n_geoms']} geoms, lowest link {r['lowest_link_z']:.2f} m"})
    if rows:
        out.append(print_table(rows, [
            ("what", "scene (ANYmal, fixed base, PD)", ""), ("step_us", "us/step", ".1f"),
            ("ratio", "ratio to collision off", ".2f"), ("contact", "contact solver built", ""),
            ("stages", "dynamics stages", "d"), ("note", "note", "")],
            title=f"Collision detection with no pair in reach (median of 5 x {res['steps']:,} steps)"))
    return out


def main():
    if len(sys.argv) > 3 and sys.argv[1] == "--worker":
        print(json.dumps(WORKERS[sys.argv[2]](**json.loads(sys.argv[3]))), flush=True)
        return
    import tempfile

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_unused_") as tmp:
        tables(run(a.quick, Path(tmp)))


if __name__ == "__main__":
    main()
