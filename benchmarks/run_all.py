"""Run every benchmark and write benchmarks/results.md with PNG plots beside it (issue #9).

    python benchmarks/run_all.py            # the full suite (about an hour on 2 cores)
    python benchmarks/run_all.py --quick    # a few minutes: fewer points, repeats and steps
    python benchmarks/run_all.py --quick --sections stress --stress-rows impact,grad --out-dir /tmp/b

Sections (each a module of this folder that can also run alone):
- speed (bench_rigid.py's measurements): Panda steps/s, 1 env and batched, against MuJoCo and real Genesis, and
  the build time with a cold and a warm kernel cache;
- workprecision (bench_workprecision.py): run time against error, 1 env and --envs envs;
- grad (bench_grad.py): backward / forward, the first backward of a fresh process, memory against horizon (rigid
  Panda, and genesis_lite's MPM cube through bench_mpm.py's worker);
- stress (bench_stress.py): stability scenes with pass / fail, largest dt survived, gradient norm vs horizon;
- unused (bench_unused.py): the cost of the MPM package, requires_grad and collision when a scene uses none;
- mpm (bench_mpm.py's worker, peer_genesis_mpm.py): genesis_lite's MPM speed, build and backward / forward beside
  real Genesis's in the same run;
- headline: the goals of the issue, each with its figure, its peer measured in the same run and met / NOT MET,
  from the sections above that ran (speed, build, backward / forward, MPM, equal-error run time).
Real Genesis runs in its own venv ($GENESIS_PYTHON, else /work/genesis_venv/bin/python): where it is missing,
its rows say so. Numbers are medians over repeated runs; ratios are against the peer measured in this run.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(HERE.parent))
from common import genesis_python, machine_info, print_table, progress, run_python, write_stripped_panda  # noqa: E402

SECTIONS = ("speed", "workprecision", "grad", "stress", "unused", "mpm", "headline")
GOAL_BATCH_RATIO, GOAL_BATCH_RATIO_NEXT = 1.0, 2.0  # Panda 1,024 envs against MuJoCo's rollout: ahead, then 2x
GOAL_GENESIS_1ENV = 3.0
GOAL_BUILD_WARM_S = 5.0
GOAL_BWD_FWD = 2.5
GOAL_MPM_GENESIS = 1.5
GOAL_EQUAL_ERROR = 1.0  # genesis_lite's run time / MuJoCo's at equal error, batched


def _git_label() -> str:
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE.parent, capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=HERE.parent,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "no git checkout"
    return f"commit {rev}" + (" + uncommitted changes" if dirty else "")


def _met(ok):
    return "met" if ok else "NOT MET"


# --- sections -------------------------------------------------------------------------------------------------


def section_speed(a, tmp, data, log):
    """Panda stepping speed (1 env and batched) with MuJoCo and real Genesis, and build time: bench_rigid.py's
    measurements."""
    import bench_rigid as br
    import mujoco

    urdf = write_stripped_panda(tmp)
    steps_1 = 200 if a.quick else 1000
    steps_mj = 1000 if a.quick else 5000
    steps_b = 20 if a.quick else 100
    repeats = 5
    n = a.envs or 1024
    out = {"envs": n, "steps_b": steps_b, "repeats": repeats}
    jobs = ["mujoco", "gl1", "glb", "genesis", "build"]
    for job in progress(jobs, desc="speed"):
        if job == "mujoco":
            out["mj1"] = br.mujoco_step_loop(urdf, steps_mj, repeats)
            out["mjb"] = br.mujoco_rollout(urdf, n, steps_b, 2, repeats)
            out["mj_version"] = mujoco.__version__
        elif job in ("gl1", "glb"):
            envs = 0 if job == "gl1" else n
            res, err = br._child("gl_steps", urdf, envs=envs, steps=steps_1 if envs == 0 else steps_b, repeats=repeats,
                                 precision="64")
            out[job] = res["rate"] if res else None
            out[job + "_err"] = err
        elif job == "genesis":
            if a.no_genesis or not Path(genesis_python()).exists():
                out["genesis_err"] = ("skipped (--no-genesis)" if a.no_genesis else
                                      f"real Genesis not installed ({genesis_python()} not found)")
                continue
            br.GENESIS_PYTHON = genesis_python()
            res, err = br.peer_genesis(urdf, steps_1, repeats, "64")
            out["genesis"] = res["rate"] if res else None
            out["genesis_version"] = res.get("version") if res else None
            out["genesis_build_s"] = res.get("build_s") if res else None
            out["genesis_err"] = err
        elif job == "build":
            out["build"] = br.genesis_lite_build_time("64")
            out["mj_build"] = br.mujoco_build_time(urdf)
    data["speed"] = out
    rows = [
        {"engine": f"MuJoCo {out['mj_version']} mj_step loop", "envs": 1, "rate": out["mj1"]},
        {"engine": "MuJoCo rollout (2 threads)", "envs": n, "rate": out["mjb"]},
        {"engine": "genesis_lite (f64)", "envs": 1, "rate": out.get("gl1"), "ratio": _r(out.get("gl1"), out["mj1"]),
         "note": out.get("gl1_err") or ""},
        {"engine": "genesis_lite (f64)", "envs": n, "rate": out.get("glb"), "ratio": _r(out.get("glb"), out["mjb"]),
         "note": out.get("glb_err") or ""},
        {"engine": f"Genesis {out.get('genesis_version') or ''} (f64, CPU)", "envs": 1, "rate": out.get("genesis"),
         "ratio": _r(out.get("genesis"), out["mj1"]),
         "note": out.get("genesis_err") or (f"build {out['genesis_build_s']:.1f} s" if out.get("genesis_build_s") else "")},
    ]
    t = [print_table(rows, [("engine", "engine", ""), ("envs", "envs", "d"), ("rate", "steps/s (env-steps/s)", ",.0f"),
                            ("ratio", "ratio to MuJoCo", ".2f"), ("note", "note", "")],
                     title=f"Panda (stripped URDF, fixed base, Euler, dt = 0.01 s): steps/s, median of {repeats}; "
                           f"{n} envs: {steps_b} steps per run")]
    brow = [{"what": r["what"], "seconds": r["seconds"], "process_s": r.get("process_s"), "error": r.get("error")}
            for r in out["build"]]
    brow.append({"what": "MuJoCo: stripped Panda load + first step", "seconds": out["mj_build"]["seconds"],
                 "error": out["mj_build"]["error"]})
    t.append(print_table(brow, [("what", "what", ""), ("seconds", "seconds (import to end of 1st step)", ".2f"),
                                ("process_s", "whole process s", ".2f"), ("error", "error", "")],
                         title="Build time, fresh process (genesis_lite: its own Taichi kernel cache directory, "
                               "first empty, then warm)"))
    return t


def _r(a, b):
    return a / b if a and b else None


def section_grad(a, tmp, data, log):
    import bench_grad as bg

    bg.GENESIS_PYTHON = genesis_python()
    urdf = write_stripped_panda(tmp)
    tables, gdata = [], {}
    parts = [("ratio", bg.part_ratio), ("first", bg.part_first)]
    if not a.quick:  # --quick: the memory of a 1,000-step rollout is in the unused-feature section
        parts.append(("memory", bg.part_memory))
    if not a.no_genesis:
        parts.append(("genesis", bg.part_genesis))
    mpm_n = int(_mpm_particles(a).split(",")[0])
    mem = (a.mpm_memory[:-1], a.mpm_memory[-1]) if a.mpm_memory else None
    parts.append(("mpm", lambda *args: bg.part_mpm(*args, particles=mpm_n, memory=mem)))
    parts = [(n, f) for n, f in parts if not a.grad_parts or n in a.grad_parts]
    for name, fn in progress(parts, desc="gradient cost"):
        fn(urdf, a.quick, tables, gdata)
    data["grad"] = gdata
    if a.quick:
        tables.append("Panda memory against horizon (100 to 10,000 steps, with and without checkpointing): full run only.")
    if a.no_genesis:
        tables.append("Real Genesis's backward / forward: skipped (--no-genesis).")
    return tables


def section_workprecision(a, tmp, data, log):
    import bench_workprecision as wp

    envs = [0] + ([a.envs] if a.envs else [])
    scenes = a.scenes or list(wp.SCENES)
    res = wp.run(scenes, envs, a.quick, 3, not a.no_genesis, tmp, log=log, integrators=a.integrators, f32=not a.quick)
    data["workprecision"] = res
    out = []
    plots = []
    for n in ["1"] + ([str(a.envs)] if a.envs else []):
        name = f"workprecision_{n}env.png"
        if wp.plot(res, n, a.out_dir / name, f"work-precision, {n} env{'s' if n != '1' else ''} (f64, CPU)"):
            plots.append((n, name))
    out.append("Error against wall time of the stepping loop, log-log. Every genesis_lite and MuJoCo point is the "
               "median of 3 runs; MuJoCo steps in C (`mujoco.rollout`, 1 thread for 1 env, 2 for the batch), "
               "genesis_lite and Genesis in a Python loop of `scene.step()`. A diverged run is listed but not plotted.")
    for n, name in plots:
        out.append(f"![work-precision, {n} env]({name})")
    eq = equal_error_rows(res, str(a.envs) if a.envs else "1")
    data["equal_error"] = eq
    out.append(print_table(eq, [
        ("scene", "scene", ""), ("envs", "envs", ""), ("peer", "peer", ""), ("prec", "genesis_lite precision", ""),
        ("range", "error range compared", ""),
        ("max", "max time ratio genesis_lite / peer", ".2f"), ("median", "median ratio", ".2f"),
        ("met", f"no worse at equal error (<= {GOAL_EQUAL_ERROR})", "")],
        title="Run time at equal error: the least time each engine needs to reach an error (any integrator, dt or "
              "substeps; interpolated log-log between the two runs of its front that bracket the error), compared on "
              f"a log grid of errors both reach (<= {wp.ERR_CAP})"))
    out += wp.tables(res)
    return out


def equal_error_rows(res, n_envs: str):
    import bench_workprecision as wp

    rows = []
    for key, entry in res.items():
        if entry.get("skipped"):
            rows.append({"scene": key, "envs": n_envs, "met": "pending: " + entry["skipped"]})
            continue
        for r in wp.equal_error_rows({key: entry}, n_envs):
            row = {k: r[k] for k in ("scene", "envs", "peer", "prec")}
            if r["range"] is None:
                rows.append({**row, "met": "no common error range"})
            else:
                rows.append({**row, "range": f"{r['range'][0]:.1e} .. {r['range'][1]:.1e}", "max": r["max"],
                             "median": r["median"], "met": _met(r["max"] <= GOAL_EQUAL_ERROR)})
    return rows


def section_stress(a, tmp, data, log):
    import bench_stress as bs

    rows = a.stress_rows or list(bs.ALL_ROWS)
    out = bs.run(rows, a.quick, not a.no_bisect, log=log)
    data["stress"] = out
    t = bs.tables(out)
    text = ["Each rigid scene at dt = 0.01 s (genesis_lite defaults: implicitfast, contact stiffness 1e6 N/m; MuJoCo "
            "the same bodies and floor with implicitfast and its default soft contacts, elliptic cones); the MPM block "
            f"at dt = 2e-3 s with {bs.MPM_SUBSTEPS} substeps, its largest dt bisected between {bs.MPM_BISECT[0]:g} and "
            f"{bs.MPM_BISECT[1]:g} s with the same substeps and the build's CFL check bypassed, beside the CFL estimate. "
            + ("Largest dt survived: not bisected (--no-bisect). " if a.no_bisect else
               f"Largest dt survived: {2 if a.quick else bs.BISECT[2]} bisection steps in log dt between "
               f"{bs.BISECT[0]:g} and {bs.BISECT[1]:g} s on the same pass criterion (energy rows: up to 0.2 s, over "
               f"{bs.ENERGY_BISECT_T:g} s)" + (f", in --quick for the {', '.join(bs.QUICK_BISECT_ROWS)} rows only. "
                                               if a.quick else ". "))
            + ("Energy drift: 10,000 steps in --quick (100,000 in the full run)." if a.quick else ""), t[0]]
    if len(t) > 1:
        text.append("Gradient norm against horizon on the chaotic double pendulum (semi-implicit Euler, dt = 0.01 s, "
                    "loss = q1 + q2 at the horizon, d loss / d q0): the norm grows exponentially (chaos, confirmed by "
                    "central differences and by MuJoCo's one-step Jacobians); the last column says whether "
                    "genesis_lite warned where it exploded.")
        text.append(t[1])
    return text


def section_unused(a, tmp, data, log):
    import bench_unused as bu

    res = bu.run(a.quick, tmp, log=log, parts=a.unused_parts)
    data["unused"] = res
    return bu.tables(res)


MPM_PARTICLES, MPM_PARTICLES_QUICK = "8000,27000", "8000"
MPM_GRAD_STEPS = 20


def _mpm_particles(a):
    return a.mpm_particles or (MPM_PARTICLES_QUICK if a.quick else MPM_PARTICLES)


def section_mpm(a, tmp, data, log):
    """genesis_lite's MPM (bench_mpm.py's worker) beside real Genesis's (peer_genesis_mpm.py), the same elastic cube,
    grid and steps, each engine and precision in its own process; the ratio of their warm rates in this run."""
    py = genesis_python()
    g_why = ("skipped (--no-genesis)" if a.no_genesis else
             None if Path(py).exists() else f"real Genesis not installed ({py} not found)")
    parts = _mpm_particles(a)
    precs = ["32"] if a.quick else ["32", "64"]
    steps, reps = ("10", "3") if a.quick else ("50", "5")
    grad = not a.quick  # --quick: backward / forward in the grad section only (genesis_lite's, smaller)
    rows, errs, version = [], [], None
    for prec in progress(precs, desc="MPM"):
        ours, err = run_python([str(HERE / "bench_mpm.py"), "--worker", prec, parts, steps, reps,
                                str(MPM_GRAD_STEPS) if grad else "0", ""], timeout=3600)
        if ours is None:
            errs.append(f"genesis_lite f{prec}: {err}")
        peer = None
        if g_why is None:
            peer, perr = run_python([str(HERE / "peer_genesis_mpm.py"), "--precision", prec, "--particles", parts,
                                     "--steps", steps, "--repeats", reps] + (["--grad"] if grad else []),
                                    python=py, timeout=3600)
            if peer is None:
                errs.append(f"Genesis f{prec}: {perr}")
            else:
                version = peer.get("version")
        g_rows = {r["target"]: r for r in (peer or {}).get("rows", [])}
        o_rows = {r["target"]: r for r in (ours or {}).get("rows", [])}
        for target in (int(x) for x in parts.split(",")):
            o, g = o_rows.get(target, {}), g_rows.get(target, {})
            ratio = _r(o.get("rate"), g.get("rate"))
            rows.append({"precision": prec, "target": target, "n_particles": o.get("n_particles"),
                         "g_particles": g.get("n_particles"), "gl_rate": o.get("rate"), "g_rate": g.get("rate"),
                         "ratio": ratio, "gl_build_s": o.get("build_s"), "g_build_s": g.get("build_s"),
                         "gl_step_ms": o.get("step_ms"), "g_step_ms": g.get("step_ms"),
                         "gl_bwd_fwd": o.get("bwd_over_fwd"), "g_bwd_fwd": g.get("bwd_over_fwd"),
                         "gl_fwd_s": o.get("fwd_s"), "gl_bwd_s": o.get("bwd_s"), "g_fwd_s": g.get("fwd_s"),
                         "g_bwd_s": g.get("bwd_s"), "gl_first_bwd_s": o.get("grad_first_bwd_s"),
                         "goal": _met(ratio >= GOAL_MPM_GENESIS) if ratio else "not measured",
                         "note": "; ".join(x for x in (o.get("error"), g.get("error") or g_why) if x)})
    data["mpm"] = {"rows": rows, "errors": errs, "version": version, "genesis": g_why or "run", "steps": int(steps),
                   "repeats": int(reps), "grad": grad}
    fmt = [{**r, "gl_m": r["gl_rate"] / 1e6 if r.get("gl_rate") else None,
            "g_m": r["g_rate"] / 1e6 if r.get("g_rate") else None} for r in rows]
    cols = [("precision", "precision", ""), ("n_particles", "particles", ",d"),
            ("gl_m", "genesis_lite M particle-substeps/s", ".2f"), ("g_m", f"Genesis {version or ''}".strip() + " M particle-substeps/s", ".2f"),
            ("ratio", "ratio", ".2f"), ("goal", f">= {GOAL_MPM_GENESIS:g}x Genesis", ""),
            ("gl_build_s", "build s (genesis_lite)", ".1f"), ("g_build_s", "build s (Genesis)", ".1f")]
    if grad:
        cols += [("gl_bwd_fwd", f"backward/forward {MPM_GRAD_STEPS} steps (genesis_lite)", ".2f"),
                 ("g_bwd_fwd", "backward/forward (Genesis)", ".2f"),
                 ("gl_first_bwd_s", "genesis_lite 1st backward s", ".1f")]
    cols.append(("note", "note", ""))
    t = print_table(fmt, cols, title=(
        "MPM: elastic cube (E = 3e5 Pa, nu = 0.2, rho = 1000 kg/m^3, corotated) on the 0.01 m lattice centred at "
        "(0.5, 0.5, 0.4), 64^3 grid on [0, 1]^3, gravity, dt = 2e-3 s, 10 substeps; rates: median of "
        f"{reps} warm runs of {steps} steps (genesis_lite: bench_mpm.py's worker, Genesis: peer_genesis_mpm.py), "
        "build: Scene() to the end of build() in the first scene of a fresh process (kernel cache as left by "
        "earlier runs)"))
    text = [t]
    if a.quick:
        text.append(f"--quick: f32, {parts.replace(',', ', ')} particles, no backward here (the full run: 8,000 and 27,000 "
                    "particles, f32 and f64, and "
                    f"the backward / forward of a {MPM_GRAD_STEPS}-step rollout with loss = sum of squared particle "
                    "positions; genesis_lite's MPM backward / forward is in the gradient section).")
    if errs:
        text.append("Failed: " + "; ".join(errs))
    return text


def headline(a, data) -> list[dict]:
    rows = []
    sp = data.get("speed")
    if sp:
        r = _r(sp.get("glb"), sp.get("mjb"))
        rows.append({"goal": f"Panda, {sp['envs']} envs: ahead of MuJoCo's rollout (on the way to 2x)",
                     "measured": f"{sp['glb']:,.0f} env-steps/s" if sp.get("glb") else sp.get("glb_err"),
                     "peer": f"MuJoCo rollout, 2 threads: {sp['mjb']:,.0f}", "ratio": r,
                     "target": f">= {GOAL_BATCH_RATIO:g}x (then {GOAL_BATCH_RATIO_NEXT:g}x)",
                     "met": (_met(r >= GOAL_BATCH_RATIO) + ("" if r >= GOAL_BATCH_RATIO_NEXT else
                             f"; 2x NOT MET")) if r else "NOT MET (no figure)"})
        r = _r(sp.get("gl1"), sp.get("genesis"))
        rows.append({"goal": "Panda, 1 env: >= 3x real Genesis",
                     "measured": f"{sp['gl1']:,.0f} steps/s" if sp.get("gl1") else sp.get("gl1_err"),
                     "peer": (f"Genesis {sp.get('genesis_version')}: {sp['genesis']:,.0f}" if sp.get("genesis")
                              else f"Genesis: {sp.get('genesis_err')}"),
                     "ratio": r, "target": f">= {GOAL_GENESIS_1ENV:g}x",
                     "met": _met(r >= GOAL_GENESIS_1ENV) if r else "not measured (no Genesis figure)"})
        warm = next((b for b in sp.get("build", []) if "warm" in b["what"]), None)
        cold = next((b for b in sp.get("build", []) if "cold" in b["what"]), None)
        if warm:
            rows.append({"goal": "build (import to first step, full Panda + plane), warm kernel cache",
                         "measured": f"{warm['seconds']:.2f} s" if warm.get("seconds") else warm.get("error"),
                         "peer": (f"cold cache {cold['seconds']:.2f} s; " if cold and cold.get("seconds") else "")
                                 + (f"Genesis build + 1st step {sp['genesis_build_s']:.1f} s" if sp.get("genesis_build_s")
                                    else ""),
                         "target": f"<= {GOAL_BUILD_WARM_S:g} s",
                         "met": _met(warm["seconds"] <= GOAL_BUILD_WARM_S) if warm.get("seconds") else "NOT MET (failed)"})
    gr = data.get("grad", {})
    for r in gr.get("ratio", []):
        if r.get("ckpt") != "none" or r.get("ratio") is None:
            continue
        gen = next((g for g in gr.get("genesis", []) if g["engine"].startswith("Genesis") and g.get("ratio")), None)
        rows.append({"goal": f"backward <= 2.5x forward (Panda, 100 steps, {r['envs']} env{'s' if r['envs'] > 1 else ''})",
                     "measured": f"{r['ratio']:.2f}x ({r['fwd_ms']:.0f} ms / {r['bwd_ms']:.0f} ms)",
                     "peer": f"Genesis: {gen['ratio']:.2f}x" if gen and r["envs"] == 1 else "",
                     "ratio": r["ratio"], "target": f"<= {GOAL_BWD_FWD:g}x", "met": _met(r["ratio"] <= GOAL_BWD_FWD)})
    for r in gr.get("mpm", {}).get("ratio", []):
        if r.get("ratio") is None:
            continue
        g = next((m for m in (data.get("mpm") or {}).get("rows", []) if m["precision"] == "64"
                  and m["target"] == r["n_particles"] and m.get("g_bwd_fwd")), None)
        rows.append({"goal": f"backward <= 2.5x forward (MPM elastic cube, {r['n_particles']:,} particles, "
                             f"{r['steps']} steps, f64)",
                     "measured": f"{r['ratio']:.2f}x ({r['fwd_ms']:.0f} ms / {r['bwd_ms']:.0f} ms)",
                     "peer": f"Genesis {data['mpm'].get('version')}, f64: {g['g_bwd_fwd']:.2f}x" if g else "",
                     "ratio": r["ratio"], "target": f"<= {GOAL_BWD_FWD:g}x", "met": _met(r["ratio"] <= GOAL_BWD_FWD)})
    mp = data.get("mpm")
    if mp is not None:
        r8 = next((r for r in mp.get("rows", []) if r["precision"] == "32" and r["target"] == 8000), None)
        if r8 is None:
            r8 = next((r for r in mp.get("rows", []) if r["precision"] == "32"), None)
        if r8 is not None:
            n = r8.get("n_particles") or r8["target"]
            rows.append({"goal": f"MPM: >= {GOAL_MPM_GENESIS:g}x real Genesis (elastic cube, {n:,} particles, f32, "
                                 "particle-substeps/s)",
                         "measured": (f"{r8['gl_rate'] / 1e6:.2f} M particle-substeps/s" if r8.get("gl_rate")
                                      else r8.get("note") or "failed"),
                         "peer": (f"Genesis {mp.get('version')}: {r8['g_rate'] / 1e6:.2f} M particle-substeps/s"
                                  if r8.get("g_rate") else f"Genesis: {r8.get('note') or mp.get('genesis')}"),
                         "ratio": r8.get("ratio"), "target": f">= {GOAL_MPM_GENESIS:g}x",
                         "met": (_met(r8["ratio"] >= GOAL_MPM_GENESIS) if r8.get("ratio") else
                                 "NOT MET (failed)" if not r8.get("gl_rate") else "not measured (no Genesis figure)")})
    eq = data.get("equal_error")
    if eq:
        # the verdict on the float64 runs; with --f32 the float32-or-float64 figure beside each
        mj = [r for r in eq if r.get("peer") == "mujoco" and r.get("max") is not None and r.get("prec", "f64") == "f64"]
        either = {r["scene"]: r["max"] for r in eq
                  if r.get("peer") == "mujoco" and r.get("max") is not None and r.get("prec") == "f64 or f32"}
        if mj:
            worst = max(mj, key=lambda r: r["max"])
            n = eq[0]["envs"]
            rows.append({"goal": f"at equal error, run time no worse than MuJoCo's ({n} env{'s' if n != '1' else ''} "
                                 "work-precision, float64)",
                         "measured": "; ".join(f"{r['scene']} {r['max']:.2f}x" + (
                             f" (float32 or 64: {either[r['scene']]:.2f}x)" if r["scene"] in either else "")
                             for r in mj),
                         "peer": "MuJoCo rollout, same scenes, its Euler / implicitfast / RK4",
                         "ratio": worst["max"], "target": f"max time ratio <= {GOAL_EQUAL_ERROR:g}",
                         "met": _met(all(r["max"] <= GOAL_EQUAL_ERROR for r in mj))})
    return rows


def write_results(a, data, texts, t_total, out_path: Path):
    info = data["machine"]
    lines = [f"# genesis_lite benchmarks{' (--quick: provisional, reduced)' if a.quick else ''}", ""]
    lines.append(f"`python benchmarks/run_all.py{' ' + ' '.join(a.argv) if a.argv else ''}`, "
                 f"{time.strftime('%Y-%m-%d %H:%M')}, {_git_label()}, total {t_total / 60:.1f} min. "
                 "Generated by the script: do not edit by hand.")
    lines.append("")
    lines.append("## Machine")
    load0, load1 = info.get("load"), data.get("load_end")
    lines.append(f"{info.get('cpu')}, {info.get('cores')} cores, {info.get('mem_gib', 0):.0f} GiB; {info.get('os')}; "
                 f"Python {info.get('python')}, numpy {info.get('numpy')}, torch {info.get('torch')}, taichi "
                 f"{info.get('taichi')}, mujoco {info.get('mujoco')}, pinocchio {info.get('pinocchio')}, scipy "
                 f"{info.get('scipy')}; real Genesis: {data.get('genesis_version') or 'not installed'} "
                 f"({data.get('genesis_python')}). Load average (1 min) at the start {load0[0]:.2f}, at the end "
                 f"{load1[0]:.2f}" + (" -- the machine was busy: timings are provisional." if max(load0[0], load1[0]) >= 1.5
                                       else "."))
    lines.append("")
    if "headline" in data:
        lines.append("## Headline")
        lines.append(print_table(data["headline"], [
            ("goal", "goal", ""), ("measured", "genesis_lite", ""), ("peer", "peer (same run)", ""),
            ("ratio", "ratio", ".2f"), ("target", "target", ""), ("met", "met", "")]))
        if (a.out_dir / f"workprecision_{a.envs}env.png").exists():
            lines.append(f"\n![work-precision, {a.envs} envs](workprecision_{a.envs}env.png)")
        lines.append("")
    titles = {"speed": "Stepping speed and build time", "workprecision": "Work-precision: run time against error",
              "grad": "Gradient cost", "stress": "Stability under stress", "unused": "The cost of what a scene does not use",
              "mpm": "MPM: genesis_lite against real Genesis"}
    for key, text in texts:
        lines.append(f"## {titles[key]}")
        lines.append("")
        for t in text:
            lines.append(t.strip("\n"))
            lines.append("")
    out_path.write_text("\n".join(lines) + "\n")


def genesis_version():
    py = genesis_python()
    if not Path(py).exists():
        return None
    try:
        p = subprocess.run([py, "-c", "import importlib.metadata as m; print(m.version('genesis-world'))"],
                           capture_output=True, text=True, timeout=120)
        return p.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a run of a few minutes (fewer points, steps and repeats)")
    ap.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated subset of {','.join(SECTIONS)}")
    ap.add_argument("--scenes", default=None, help="work-precision scenes (default: all)")
    ap.add_argument("--stress-rows", default=None, help="stress rows (default: all)")
    ap.add_argument("--integrators", default=None, help="work-precision integrators (default: Euler,implicitfast,RK4)")
    ap.add_argument("--unused-parts", default=None, help="bench_unused parts: mpm,grad,collision (default: all)")
    ap.add_argument("--grad-parts", default=None, help="bench_grad parts: ratio,first,memory,genesis,mpm (default: all)")
    ap.add_argument("--mpm-memory", default=None, help="MPM memory rows: horizons then the cube's particles, e.g. "
                    "100,1000,1000 (default: 100,1000 steps of 1,000 particles; --quick 100 steps)")
    ap.add_argument("--mpm-particles", default=None, help="MPM section's cube sizes, e.g. 8000,27000 (default: "
                    f"{MPM_PARTICLES}, --quick {MPM_PARTICLES_QUICK})")
    ap.add_argument("--envs", type=int, default=1024, help="batched environments (0: 1 env only)")
    ap.add_argument("--no-genesis", action="store_true", help="skip real Genesis even where it is installed")
    ap.add_argument("--no-bisect", action="store_true", help="skip the largest-dt bisection of the stress table")
    ap.add_argument("--out-dir", type=Path, default=HERE, help="where results.md, results.json and the PNGs go")
    a = ap.parse_args(argv)
    a.argv = argv
    a.sections = [s for s in a.sections.split(",") if s]
    bad = set(a.sections) - set(SECTIONS)
    if bad:
        ap.error(f"unknown sections {sorted(bad)}; choose from {', '.join(SECTIONS)}")
    a.scenes = a.scenes.split(",") if a.scenes else None
    a.stress_rows = a.stress_rows.split(",") if a.stress_rows else None
    a.grad_parts = a.grad_parts.split(",") if a.grad_parts else None
    a.mpm_memory = [int(x) for x in a.mpm_memory.split(",")] if a.mpm_memory else None
    if a.mpm_memory is not None and len(a.mpm_memory) < 2:
        ap.error("--mpm-memory needs at least one horizon and the particle count, e.g. 100,1000")
    a.integrators = a.integrators.split(",") if a.integrators else None
    a.unused_parts = a.unused_parts.split(",") if a.unused_parts else None
    a.out_dir = a.out_dir.resolve()
    a.out_dir.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("OMP_NUM_THREADS", "1")

    t0 = time.time()
    data = {"machine": machine_info(), "genesis_python": genesis_python(),
            "genesis_version": None if a.no_genesis else genesis_version()}
    texts = []
    log = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    order = [s for s in SECTIONS if s in a.sections and s != "headline"]
    fns = {"speed": section_speed, "workprecision": section_workprecision, "grad": section_grad,
           "stress": section_stress, "unused": section_unused, "mpm": section_mpm}
    tmp = Path(tempfile.mkdtemp(prefix="bench_all_"))
    cwd = os.getcwd()
    os.chdir(tmp)  # MuJoCo writes MUJOCO_LOG.TXT into the working directory when a run diverges
    try:
        for s in progress(order, desc="sections"):
            log(f"\n=== {s} ===")
            ts = time.time()
            try:
                texts.append((s, fns[s](a, tmp, data, log)))
            except Exception as e:  # a broken section is reported in the results, not hidden
                import traceback

                traceback.print_exc()
                texts.append((s, [f"**This section failed**: {type(e).__name__}: {e}"]))
            data.setdefault("section_s", {})[s] = time.time() - ts
    finally:
        os.chdir(cwd)
        shutil.rmtree(tmp, ignore_errors=True)
    if "headline" in a.sections:
        data["headline"] = headline(a, data)
    try:
        data["load_end"] = os.getloadavg()
    except OSError:
        data["load_end"] = (math.nan,) * 3
    write_results(a, data, texts, time.time() - t0, a.out_dir / "results.md")
    (a.out_dir / "results.json").write_text(json.dumps(data, indent=1, default=str))
    log(f"\nwrote {a.out_dir / 'results.md'} ({(time.time() - t0) / 60:.1f} min)")
    return data


if __name__ == "__main__":
    main()
