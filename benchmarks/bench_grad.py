"""Gradient cost of genesis_lite: backward/forward time, first-backward compile time, memory against horizon.

    python benchmarks/bench_grad.py [--quick] [--skip-first] [--skip-memory] [--skip-genesis]
                                    [--out benchmarks/results/grad.md] [--plot grad.png] [--json out.json]

The scene: example-robot-data's Panda without visuals and collisions (common.write_stripped_panda: the
same file real Genesis gets; no meshes, so what is timed is articulated dynamics and its adjoint), fixed
base, gs.init(precision="64"), dt = 0.01 s, RigidOptions(enable_collision=False) and the default
integrator (implicitfast), SimOptions(requires_grad=True). The rollout timed everywhere:

    scene.reset(); robot.set_dofs_position(q0)            # q0 requires grad
    for t in range(T): robot.control_dofs_force(controls[t]); scene.step()   # controls require grad
    loss = (robot.get_links_pos()[..., -1, :] ** 2).sum() # last link, summed over envs
    loss.backward()

forward = reset .. loss, backward = loss.backward(). Controls are fixed small random torques (N m).
1. backward / forward time, 1 env and 1024 envs, without and with checkpointing (checkpoint_every=10),
   medians after a warm-up rollout; without checkpoints also with the controls fed as the rows of
   controls.unbind(0) instead of controls[t] (both are views of the controls, whose gradients the setters
   route to the controls themselves, genesis_lite/grad/views.py; torch's own backward of controls[t] would
   fill a zero tensor of the whole (T, envs, dofs) sequence per step), and the forward time per step against
   the plain requires_grad=False rollout (same calls) so the cost of recording is visible.
2. the first backward of a fresh process (compile included) with an empty Taichi kernel cache, then the
   second and third process on the same cache directory.
3. memory (VmRSS / VmHWM of the process, one fresh process per configuration) against the horizon, with
   and without checkpointing, and requires_grad=False.
4. real Genesis (genesis-world, in its venv: $GENESIS_PYTHON, else /work/genesis_venv or /tmp/gvenv): the same
   1-env rollout.
Every measurement runs in its own child process (one gs.init per process; a failure there leaves the
other rows). Children other than part 2's end with ti.reset() so Taichi writes its offline kernel cache
and later children skip compilation (see the note printed with part 2).
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

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parents[1]))  # genesis_lite without an install
from common import (DT, PANDA_HOME, Timer, genesis_python, print_table, pyplot, run_python, save_figure,  # noqa: E402
                    write_stripped_panda)

HERE = Path(__file__).resolve().parent
GENESIS_PYTHON = genesis_python()
GOAL_RATIO, GOAL_RATIO_CKPT, GOAL_FIRST_S = 2.5, 3.5, 5.0
GENESIS_RATIO_REF, GENESIS_FIRST_REF = 6.5, 18.0  # real Genesis, as measured for issue #3
CTRL_SCALE = 1.0  # N m: the random control torques' standard deviation


def _controls(T, n_envs, n_dofs):
    rng = np.random.default_rng(0)
    shape = (T, n_envs, n_dofs) if n_envs else (T, n_dofs)
    return rng.normal(0.0, CTRL_SCALE, shape)


def _q0(n_envs, n_dofs):
    q = np.asarray(PANDA_HOME[:n_dofs], dtype=float)
    return np.tile(q, (n_envs, 1)) if n_envs else q.copy()


def _mem() -> dict:
    """VmRSS and VmHWM (peak RSS) of this process, MiB."""
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(("VmRSS:", "VmHWM:")):
                out[line.split(":")[0]] = int(line.split()[1]) / 1024.0
    return out


def _heap_in_use() -> float | None:
    """Bytes malloc has handed out and not taken back (glibc mallinfo2: main arena + mmapped chunks), MiB.
    Unlike RSS it does not hide growth that refills holes left by freed memory."""
    try:
        import ctypes

        class MallInfo2(ctypes.Structure):
            _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                      "fsmblks", "uordblks", "fordblks", "keepcost")]

        libc = ctypes.CDLL("libc.so.6")
        libc.mallinfo2.restype = MallInfo2
        m = libc.mallinfo2()
        return (m.uordblks + m.hblkhd) / 2**20
    except (OSError, AttributeError):
        return None


def _reset_peak() -> bool:
    """Reset VmHWM to the current RSS (Linux >= 4.0), so the next peak is this rollout's alone."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _flush_kernel_cache():
    """Make Taichi write its offline kernel cache now (see the note of part 2)."""
    import taichi as ti

    ti.reset()


# --- genesis_lite children ---------------------------------------------------------------------------


def _gl_build(gs, urdf, n_envs, requires_grad, checkpoint_every):
    scene = gs.Scene(
        sim_options=gs.options.SimOptions(dt=DT, requires_grad=requires_grad, checkpoint_every=checkpoint_every),
        rigid_options=gs.options.RigidOptions(enable_collision=False),
    )
    robot = scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=True))
    if n_envs:
        scene.build(n_envs=n_envs)
    else:
        scene.build()
    return scene, robot


def _gl_rollout(scene, robot, controls_np, q0_np, grad: bool, probe=None, feed="index") -> dict:
    """One timed rollout (see the module docstring); grad=False: same calls, nothing requires grad.
    probe(out, "start" | "fwd" | "bwd") runs once the inputs exist, after the forward and after the backward
    (outside the timings).
    feed="index": controls[t] each step; "unbind": the rows of controls.unbind(0) (see part 3)."""
    import torch

    q0 = torch.tensor(q0_np, dtype=torch.float64, requires_grad=grad)
    controls = torch.tensor(controls_np, dtype=torch.float64, requires_grad=grad)
    rows = controls.unbind(0) if feed == "unbind" else controls
    out = {}
    if probe:
        probe(out, "start")
    t0 = time.perf_counter()
    scene.reset()
    robot.set_dofs_position(q0)
    for t in range(controls.shape[0]):
        robot.control_dofs_force(rows[t])
        scene.step()
    loss = (robot.get_links_pos()[..., -1, :] ** 2).sum()
    t1 = time.perf_counter()
    out.update(fwd=t1 - t0, bwd=None, loss=float(loss.detach()))
    if probe:
        probe(out, "fwd")
    if grad:
        t1 = time.perf_counter()
        loss.backward()
        out["bwd"] = time.perf_counter() - t1
        if probe:
            probe(out, "bwd")
    if not np.isfinite(out["loss"]):
        raise RuntimeError("the rollout diverged (loss is not finite)")
    if grad:
        if q0.grad is None or controls.grad is None:
            raise RuntimeError("q0 or controls received no gradient")
        out["grad_norm"] = float(q0.grad.norm()) + float(controls.grad.norm())
    return out


def worker_ratio(urdf, n_envs, steps, repeats, ckpts, feeds=("index",)) -> dict:
    """Backward/forward medians for each checkpoint setting and control feed (the feed only without
    checkpoints), and the no-grad rollout, in one process."""
    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")
    res = {"rows": []}
    for ck in ckpts:
        scene, robot = _gl_build(gs, urdf, n_envs, True, ck)
        ctrl, q0 = _controls(steps, n_envs, robot.n_dofs), _q0(n_envs, robot.n_dofs)
        with Timer() as tw:
            _gl_rollout(scene, robot, ctrl, q0, True)  # compiles (or loads) the kernels
        for feed in feeds if ck is None else feeds[:1]:
            runs = [_gl_rollout(scene, robot, ctrl, q0, True, feed=feed) for _ in range(repeats)]
            fwd = statistics.median(r["fwd"] for r in runs)
            bwd = statistics.median(r["bwd"] for r in runs)
            ratio = statistics.median(r["bwd"] / r["fwd"] for r in runs)
            res["rows"].append({"ckpt": ck, "feed": feed, "fwd": fwd, "bwd": bwd, "ratio": ratio,
                                "warmup_s": tw.seconds, "loss": runs[-1]["loss"], "repeats": repeats})
        del scene, robot
    scene, robot = _gl_build(gs, urdf, n_envs, False, None)
    ctrl, q0 = _controls(steps, n_envs, robot.n_dofs), _q0(n_envs, robot.n_dofs)
    _gl_rollout(scene, robot, ctrl, q0, False)
    res["nograd_fwd"] = statistics.median(_gl_rollout(scene, robot, ctrl, q0, False)["fwd"] for _ in range(repeats))
    _flush_kernel_cache()
    return res


def worker_first(urdf, steps, flush) -> dict:
    """Fresh process: import + init + build + first rollout forward, then the first backward."""
    t0 = time.perf_counter()
    import torch  # noqa: F401

    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")
    t_init = time.perf_counter()
    scene, robot = _gl_build(gs, urdf, 0, True, None)
    t_build = time.perf_counter()
    r = _gl_rollout(scene, robot, _controls(steps, 0, robot.n_dofs), _q0(0, robot.n_dofs), True)
    out = {"import_init": t_init - t0, "build": t_build - t_init, "first_fwd": r["fwd"],
           "fwd_total": t_build - t0 + r["fwd"], "first_bwd": r["bwd"]}
    # the second rollout: what it costs once everything is compiled
    r2 = _gl_rollout(scene, robot, _controls(steps, 0, robot.n_dofs), _q0(0, robot.n_dofs), True)
    out["second_fwd"], out["second_bwd"] = r2["fwd"], r2["bwd"]
    if flush:
        _flush_kernel_cache()
    return out


def worker_memory(urdf, horizon, ckpt, grad, feed) -> dict:
    """Memory of one rollout of `horizon` steps (after a compiled warm-up rollout)."""
    import gc

    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")
    scene, robot = _gl_build(gs, urdf, 0, grad, ckpt if grad else None)
    n = robot.n_dofs
    q0 = _q0(0, n)
    _gl_rollout(scene, robot, _controls(min(horizon, 2 * (ckpt or 10)), 0, n), q0, grad)  # compile
    ctrl = _controls(horizon, 0, n)
    buf = scene._simulator.buffer
    replayed0 = buf.n_replayed if buf is not None else 0  # the counter spans rollouts
    base = {}

    def probe(out, when):
        if when == "start":  # the inputs (T control rows) exist: what follows is the simulator's
            gc.collect()
            base["m0"] = _mem()
            base["peak_reset"] = _reset_peak()
            base["m0b"], base["h0"] = _mem(), _heap_in_use()
            return
        m0b, h0 = base["m0b"], base["h0"]
        m = _mem()
        out[f"rss_{when}"], out[f"hwm_{when}"] = m["VmRSS"] - m0b["VmRSS"], m["VmHWM"] - m0b["VmRSS"]
        h = _heap_in_use()
        out[f"heap_{when}"] = h - h0 if h is not None and h0 is not None else None
        if buf is not None:
            out[f"n_stored_{when}"], out["n_ckpts"] = buf.n_stored, len(buf.checkpoints)
            out["n_replayed"] = buf.n_replayed - replayed0

    out = _gl_rollout(scene, robot, ctrl, q0, grad, probe, feed)
    out.update(horizon=horizon, ckpt=ckpt, grad=grad, rss0=base["m0"]["VmRSS"], hwm0=base["m0"]["VmHWM"],
               peak_reset=base["peak_reset"],
               state_bytes=8 * scene._rigid.B * (scene._rigid.n_qs + scene._rigid.n_dofs))
    _flush_kernel_cache()
    return out


# --- real Genesis child (runs under GENESIS_PYTHON; imports neither genesis_lite nor common's peers) ----


def worker_genesis(urdf, steps, repeats) -> dict:
    import genesis as gs
    import torch

    t0 = time.perf_counter()
    gs.init(backend=gs.cpu, precision="64", logging_level="warning")
    scene = gs.Scene(
        sim_options=gs.options.SimOptions(dt=DT, requires_grad=True),
        # Genesis differentiates only approximate_implicitfast
        rigid_options=gs.options.RigidOptions(enable_collision=False,
                                              integrator=gs.integrator.approximate_implicitfast),
        show_viewer=False,
    )
    robot = scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=True))
    scene.build()
    build_s = time.perf_counter() - t0
    n = robot.n_dofs
    ctrl_np, q0_np = _controls(steps, 0, n), _q0(0, n)
    solver = scene.sim.rigid_solver

    def once():
        # Genesis 1.4.5 gives set_dofs_position no gradient, but in a requires_grad scene a q0 that does not
        # require grad segfaults its kernel: pass one that does
        q0 = torch.tensor(q0_np, dtype=torch.float64, requires_grad=True)
        controls = torch.tensor(ctrl_np, dtype=torch.float64, requires_grad=True)
        ta = time.perf_counter()
        scene.reset()
        robot.set_dofs_position(q0)
        for t in range(steps):
            robot.control_dofs_force(controls[t])
            scene.step()
        # robot.get_links_pos() is not in Genesis' autograd graph; a queried solver state is
        loss = (solver.get_state().links_pos[..., -1, :] ** 2).sum()
        tb = time.perf_counter()
        loss.backward()
        tc = time.perf_counter()
        if controls.grad is None or not torch.isfinite(controls.grad).all():
            raise RuntimeError("no finite gradient of the controls")
        return tb - ta, tc - tb

    first = once()
    runs = [once() for _ in range(repeats)]
    return {"version": getattr(gs, "__version__", ""), "build_s": build_s, "first_fwd": first[0],
            "first_bwd": first[1], "fwd": statistics.median(r[0] for r in runs),
            "bwd": statistics.median(r[1] for r in runs), "ratio": statistics.median(r[1] / r[0] for r in runs),
            "repeats": repeats}


WORKERS = {"ratio": worker_ratio, "first": worker_first, "memory": worker_memory, "genesis": worker_genesis}


def _worker_main(argv):
    ap = argparse.ArgumentParser()
    ap.add_argument("--worker", required=True, choices=list(WORKERS))
    ap.add_argument("--args", required=True, help="JSON keyword arguments")
    a = ap.parse_args(argv)
    print(json.dumps(WORKERS[a.worker](**json.loads(a.args))), flush=True)


def _child(worker, python=None, env=None, timeout=1200, **kw):
    with Timer() as t:
        res, err = run_python([str(Path(__file__).resolve()), "--worker", worker, "--args", json.dumps(kw)],
                              python=python, env=env, timeout=timeout)
    if err:
        print(f"  {worker} {kw}: FAILED: {err}", flush=True)
    return res, err, t.seconds


def _ckpt_name(ck):
    return "none" if ck is None else str(ck)


# --- parts ---------------------------------------------------------------------------------------------


def part_ratio(urdf, quick, tables, data):
    steps = 100
    rows = []
    configs = [(0, 3 if quick else 7)] + ([] if quick else [(1024, 3)])  # 1024 envs: fewer, slower repeats
    for n_envs, repeats in configs:
        print(f"[1] backward/forward, {max(n_envs, 1)} env(s), {repeats} repeats ...", flush=True)
        res, err, wall = _child("ratio", urdf=str(urdf), n_envs=n_envs, steps=steps, repeats=repeats,
                                ckpts=[None, 10], feeds=["index", "unbind"])
        if res is None:
            rows.append({"envs": max(n_envs, 1), "ckpt": "-", "note": err})
            continue
        ng = res["nograd_fwd"]
        for r in res["rows"]:
            goal = GOAL_RATIO if r["ckpt"] is None else GOAL_RATIO_CKPT
            rows.append({
                "envs": max(n_envs, 1), "ckpt": _ckpt_name(r["ckpt"]), "feed": r["feed"],
                "fwd_ms": 1e3 * r["fwd"],
                "bwd_ms": 1e3 * r["bwd"], "ratio": r["ratio"], "goal": f"<= {goal}",
                "met": "yes" if r["ratio"] <= goal else "NO",
                "step_grad_us": 1e6 * r["fwd"] / steps, "step_nograd_us": 1e6 * ng / steps,
                "overhead": r["fwd"] / ng, "repeats": r["repeats"],
                "note": f"warm-up {r['warmup_s']:.1f} s",
            })
        print(f"    ({wall:.0f} s)", flush=True)
    data["ratio"] = rows
    tables.append(print_table(rows, [
        ("envs", "envs", "d"), ("ckpt", "checkpoint_every", ""), ("feed", "controls fed as", ""),
        ("fwd_ms", "forward ms", ".1f"),
        ("bwd_ms", "backward ms", ".1f"), ("ratio", "backward/forward", ".2f"), ("goal", "goal", ""),
        ("met", "met", ""), ("step_grad_us", "fwd us/step, grad", ",.0f"),
        ("step_nograd_us", "us/step, no grad", ",.0f"), ("overhead", "grad fwd / no-grad fwd", ".2f"),
        ("repeats", "repeats", "d"), ("note", "note", "")],
        title=f"1. Panda, {steps} steps, dt={DT}, f64, backward / forward (medians after a warm-up rollout); "
              f"real Genesis: {GENESIS_RATIO_REF}"))


def part_first(urdf, quick, tables, data):
    cache = tempfile.mkdtemp(prefix="gl_grad_ticache_")
    rows = []
    try:
        runs = [("1st process, empty cache", False), ("2nd process, same cache dir", True),
                ("3rd process, same cache dir", False)]
        for label, flush in runs:
            print(f"[2] first backward: {label} ...", flush=True)
            res, err, wall = _child("first", env={"TI_OFFLINE_CACHE_FILE_PATH": cache}, urdf=str(urdf), steps=100,
                                    flush=flush)
            n_files = len(os.listdir(cache)) if os.path.isdir(cache) else 0
            row = {"what": label, "process_s": wall, "cache_files": n_files, "note": err}
            if res:
                row.update(res)
                row["met"] = "yes" if res["first_bwd"] <= GOAL_FIRST_S else "NO"
                row["note"] = ("ends with ti.reset() (flushes the kernel cache)" if flush else "exits normally")
            rows.append(row)
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    data["first"] = rows
    text = print_table(rows, [
        ("what", "run", ""), ("import_init", "import+init s", ".2f"), ("build", "build s", ".2f"),
        ("first_fwd", "1st rollout fwd s", ".2f"), ("fwd_total", "import..loss s", ".2f"),
        ("first_bwd", "1st backward s", ".2f"), ("met", f"<= {GOAL_FIRST_S} s", ""),
        ("second_fwd", "2nd fwd s", ".3f"), ("second_bwd", "2nd bwd s", ".3f"),
        ("process_s", "process wall s", ".1f"), ("cache_files", "cache files after", "d"), ("note", "note", "")],
        title=f"2. First backward of a fresh process (Panda 1 env, 100 steps, compile included); real Genesis: "
              f"{GENESIS_FIRST_REF} s")
    if len(rows) > 1 and rows[0].get("cache_files") == 0:
        note = ("   note: the 1st process exited normally and left NO kernel cache behind, so the 2nd process "
                "compiled again; only a process that calls ti.reset() before exiting writes the cache.")
        print(note)
        text += "\n\n" + note
    tables.append(text)


def part_memory(urdf, quick, tables, data):
    horizons = [100, 1000] if quick else [100, 1000, 10000]
    configs = [(True, ck, T, "unbind") for ck in (None, 100) for T in horizons]
    configs += [(False, None, T, "unbind") for T in horizons]
    configs += [(True, None, horizons[-1], "index")]  # the cost of indexing one controls leaf per step
    rows = []
    for grad, ck, T, feed in configs:
        print(f"[3] memory: requires_grad={grad}, checkpoint_every={ck}, {T} steps, controls {feed} ...", flush=True)
        res, err, wall = _child("memory", urdf=str(urdf), horizon=T, ckpt=ck, grad=grad, feed=feed)
        row = {"grad": str(grad), "ckpt": _ckpt_name(ck) if grad else "-", "T": T, "note": err,
               "feed": "controls[t]" if feed == "index" else "unbind(0)[t]"}
        if res:
            row.update({k: res.get(k) for k in ("rss_fwd", "hwm_fwd", "heap_fwd", "rss_bwd", "hwm_bwd", "heap_bwd",
                                                "fwd", "bwd", "n_stored_fwd", "n_ckpts", "n_stored_bwd",
                                                "n_replayed")})
            if res.get("heap_fwd") is not None:
                row["kb_per_step"] = 1024 * res["heap_fwd"] / T
            row["state_kb"] = res["state_bytes"] / 1024
            row["note"] = f"{wall:.0f} s" + ("" if res["peak_reset"] else ", VmHWM not reset (peak mixed)")
        rows.append(row)
    data["memory"] = rows
    text = print_table(rows, [
        ("grad", "requires_grad", ""), ("ckpt", "checkpoint_every", ""), ("T", "steps", ",d"),
        ("feed", "controls fed", ""),
        ("rss_fwd", "RSS growth fwd MiB", ".1f"), ("hwm_fwd", "peak RSS growth fwd MiB", ".1f"),
        ("heap_fwd", "heap growth fwd MiB", ".1f"), ("kb_per_step", "heap KiB/step", ".2f"),
        ("state_kb", "one state KiB", ".2f"),
        ("hwm_bwd", "peak RSS growth fwd+bwd MiB", ".1f"), ("heap_bwd", "heap growth after bwd MiB", ".1f"),
        ("n_ckpts", "checkpoints", "d"), ("n_stored_fwd", "states held after fwd", "d"),
        ("n_stored_bwd", "states held after bwd", "d"), ("n_replayed", "steps replayed", ",d"),
        ("fwd", "forward s", ".2f"), ("bwd", "backward s", ".2f"), ("note", "process", "")],
        title="3. Memory against horizon (Panda 1 env, one fresh process per row, a single rollout each, after a "
              "compiled warm-up rollout; growth over the values before the rollout)")
    note = ("   RSS: VmRSS/VmHWM; heap: glibc mallinfo2 bytes in use (RSS misses growth that refills freed memory). "
            "'controls fed unbind(0)[t]': rows of controls.unbind(0); 'controls[t]' indexes the (T, n_dofs) leaf "
            "each step (both views, whose gradients the setters route to the leaf: one fill of it a backward).")
    print(note, flush=True)
    tables.append(text + "\n\n" + note)


def part_genesis(urdf, quick, tables, data):
    if not Path(GENESIS_PYTHON).exists():
        print(f"[4] real Genesis: {GENESIS_PYTHON} not found, skipped", flush=True)
        return
    print("[4] real Genesis (genesis-world) 1 env ...", flush=True)
    res, err, wall = _child("genesis", python=GENESIS_PYTHON, timeout=1200, urdf=str(urdf), steps=100,
                            repeats=3 if quick else 5)
    ours = next((r for r in data.get("ratio", []) if r["envs"] == 1 and r["ckpt"] == "none" and r.get("fwd_ms")), None)
    rows = []
    if ours:
        rows.append({"engine": "genesis_lite (implicitfast, q0 + controls require grad)", "fwd_ms": ours["fwd_ms"],
                     "bwd_ms": ours["bwd_ms"], "ratio": ours["ratio"], "note": "from table 1"})
    row = {"engine": f"Genesis {res['version'] if res else ''} (approximate_implicitfast, controls require grad)",
           "note": err}
    if res:
        row.update(fwd_ms=1e3 * res["fwd"], bwd_ms=1e3 * res["bwd"], ratio=res["ratio"], first_bwd=res["first_bwd"],
                   note=f"build {res['build_s']:.1f} s, 1st fwd {res['first_fwd']:.2f} s, median of {res['repeats']},"
                        f" process {wall:.0f} s")
    rows.append(row)
    data["genesis"] = rows
    tables.append(print_table(rows, [
        ("engine", "engine", ""), ("fwd_ms", "forward ms", ".1f"), ("bwd_ms", "backward ms", ".1f"),
        ("ratio", "backward/forward", ".2f"), ("first_bwd", "1st backward s (in process)", ".2f"),
        ("note", "note", "")],
        title="4. Peer: real Genesis, Panda 1 env, 100 steps, f64, CPU (its kernel cache as left by earlier runs)"))


MPM_GRAD_STEPS = 20
# (horizons, particles of the memory rows): each step is 10 substeps; the two 1,000-step rows of bench_mpm.py's
# 10,000-particle cube would take ~45 min here (extrapolated from 1,000 particles x 20 steps, f64: 0.5 s forward,
# 2.2 s backward), so the horizon sweep uses a 1,000-particle cube
MPM_MEMORY = {"quick": ([100], 1000), "full": ([100, 1000], 1000)}


def part_mpm(urdf, quick, tables, data, particles=None, memory=None):
    """genesis_lite's MPM: backward / forward of a 20-step rollout (f64, the elastic cube of bench_mpm.py, loss = sum
    of squared particle positions, d loss / d initial positions) and the memory kept for backward against the horizon
    with and without checkpointing (torch's saved tensors and the checkpoint buffer), by bench_mpm.py's worker in one
    child process. particles: the cube of the ratio row (default 8,000); memory: (horizons, particles)."""
    particles = particles or 8000
    horizons, mem_parts = memory or MPM_MEMORY["quick" if quick else "full"]
    print(f"[5] MPM backward/forward ({particles:,} particles) and memory ({mem_parts:,} particles, "
          f"{horizons} steps) ...", flush=True)
    with Timer() as t:
        res, err = run_python([str(HERE / "bench_mpm.py"), "--worker", "64", str(particles), "5", "2" if quick else "5",
                               str(MPM_GRAD_STEPS), ",".join(str(h) for h in horizons),
                               "--memory-particles", str(mem_parts)], timeout=7200)
    ratio_rows, mem_rows = [], []
    if res is None:
        ratio_rows.append({"what": "genesis_lite MPM", "note": err})
    for r in (res or {}).get("rows", []):
        ratio_rows.append({"what": "genesis_lite MPM, f64", "n_particles": r["n_particles"], "steps": r["grad_steps"],
                           "fwd_ms": 1e3 * r["fwd_s"], "bwd_ms": 1e3 * r["bwd_s"], "ratio": r["bwd_over_fwd"],
                           "goal": f"<= {GOAL_RATIO}", "met": "yes" if r["bwd_over_fwd"] <= GOAL_RATIO else "NO",
                           "first_bwd_s": r["grad_first_bwd_s"],
                           "note": f"medians of {max(2, (2 if quick else 5) // 2)} after a warm-up rollout"})
    for m in (res or {}).get("memory", []):
        state_mib = m["state_KiB"] / 1024
        mem_rows.append({**m, "ckpt": _ckpt_name(m["checkpoint_every"]), "bwd_over_fwd": m["bwd_s"] / m["fwd_s"],
                         "held_MiB": m["saved_MiB"] + m["checkpoints_MiB"],
                         "kib_per_step": 1024 * (m["saved_MiB"] + m["checkpoints_MiB"]) / m["horizon"],
                         "states": (m["saved_MiB"] + m["checkpoints_MiB"]) / state_mib})
    data["mpm"] = {"ratio": ratio_rows, "memory": mem_rows, "process_s": t.seconds}
    tables.append(print_table(ratio_rows, [
        ("what", "solver", ""), ("n_particles", "particles", ",d"), ("steps", "steps (x 10 substeps)", "d"),
        ("fwd_ms", "forward ms", ".0f"), ("bwd_ms", "backward ms", ".0f"), ("ratio", "backward/forward", ".2f"),
        ("goal", "goal", ""), ("met", "met", ""), ("first_bwd_s", "1st backward s (in process)", ".1f"),
        ("note", "note", "")],
        title="5. MPM backward / forward: elastic cube (bench_mpm.py), 64^3 grid, dt = 2e-3 s, 10 substeps, f64, "
              "loss = sum of squared particle positions, d loss / d initial positions"))
    if mem_rows:
        tables.append(print_table(mem_rows, [
            ("horizon", "steps", ",d"), ("ckpt", "checkpoint_every", ""), ("n_particles", "particles", ",d"),
            ("saved_MiB", "saved by torch MiB", ".1f"), ("checkpoints_MiB", "checkpoints MiB", ".1f"),
            ("states", "particle states held", ".1f"), ("replayed", "steps replayed in backward", ",d"),
            ("kib_per_step", "KiB held per step", ",.0f"), ("fwd_s", "forward s", ".1f"), ("bwd_s", "backward s", ".1f")],
            title=f"6. MPM memory kept for backward against horizon (f64, one state = x, v, C, F = "
                  f"{mem_rows[0]['state_KiB']:.0f} KiB; loss = sum of particle heights, d loss / d initial velocity; "
                  "a single rollout per row in one process: the first rows' times include compiling)"))
        if max(horizons) < 10000:
            tables.append(f"MPM horizons above {max(horizons):,} steps (of 10 substeps each) are not run, to keep the "
                          "benchmark within the hour on this machine ('KiB held per step': the memory held divided by "
                          "the horizon).")


def main():
    if "--worker" in sys.argv:
        return _worker_main(sys.argv[1:])
    ap = argparse.ArgumentParser(description="genesis_lite gradient cost: time ratio, first backward, memory")
    ap.add_argument("--quick", action="store_true", help="a smoke run: 1 env only, fewer repeats and horizons")
    ap.add_argument("--skip-ratio", action="store_true")
    ap.add_argument("--skip-first", action="store_true")
    ap.add_argument("--skip-memory", action="store_true")
    ap.add_argument("--skip-genesis", action="store_true")
    ap.add_argument("--out", type=str, default=str(HERE / "results" / "grad.md"), help="Markdown tables ('' for none)")
    ap.add_argument("--plot", type=Path, default=None, help="write a PNG of memory against horizon (needs matplotlib)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    t0 = time.time()
    tmp = Path(tempfile.mkdtemp(prefix="bench_grad_"))
    urdf = write_stripped_panda(tmp)
    print(f"stripped Panda URDF (no visuals/collisions, fixed base): {urdf}", flush=True)
    tables, data = [], {}
    try:
        if not args.skip_ratio:
            part_ratio(urdf, args.quick, tables, data)
        if not args.skip_first:
            part_first(urdf, args.quick, tables, data)
        if not args.skip_memory:
            part_memory(urdf, args.quick, tables, data)
        if not args.skip_genesis:
            part_genesis(urdf, args.quick, tables, data)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    total = time.time() - t0
    print(f"\ntotal {total:.0f} s", flush=True)
    header = (f"# genesis_lite gradient benchmark{' (--quick)' if args.quick else ''}\n\n"
              f"`python benchmarks/bench_grad.py{' --quick' if args.quick else ''}`, "
              f"{time.strftime('%Y-%m-%d %H:%M')}, "
              f"{os.cpu_count()} CPU cores, total {total:.0f} s. Stripped Panda URDF (common.write_stripped_panda), "
              "fixed base, f64, dt=0.01, enable_collision=False, default integrator (implicitfast); q0 and controls "
              "require grad; loss = squared position of the last link summed over envs.\n"
              "Repeats: 1-env rows of table 1 are medians of 7 (3 with --quick), 1024-env rows of 3 (to keep the run "
              "under ~10 minutes); every memory row is a single rollout.\n")
    if args.out:  # '' (Path('') would be the working directory): no file
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(header + "\n".join(tables) + "\n")
        print(f"wrote {args.out}")
    if args.json:
        args.json.write_text(json.dumps(data, indent=2))
    if args.plot:
        _plot(data.get("memory", []), args.plot)


def _plot(rows, path):
    plt = pyplot()
    if plt is None:
        return
    fig, ax = plt.subplots(figsize=(6, 4))
    for key in sorted({(r["grad"], r["ckpt"]) for r in rows}):
        pts = [(r["T"], r["rss_fwd"]) for r in rows if (r["grad"], r["ckpt"]) == key and r.get("rss_fwd") is not None]
        if pts:
            ax.plot(*zip(*pts), marker="o", label=f"requires_grad={key[0]}, checkpoint_every={key[1]}")
    ax.set_xscale("log")
    ax.set_xlabel("steps")
    ax.set_ylabel("RSS growth after the forward (MiB)")
    ax.set_title("genesis_lite, Panda 1 env")
    ax.legend(fontsize=8)
    save_figure(fig, path)


if __name__ == "__main__":
    main()
