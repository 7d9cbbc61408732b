"""Rigid-body stepping speed and build time of genesis_lite, with MuJoCo as the peer in the same run.

    python benchmarks/bench_rigid.py [--quick] [--precision 64] [--skip-build] [--plot out.png] [--json out.json]

The scene: example-robot-data's Panda without visuals and collisions (the same URDF file for every
engine), fixed base, gravity, zero control, semi-implicit Euler at dt = 0.01 s, damping and armature 0,
joint limits on, starting from the "ready" pose. Rates are medians of 5 repeats:
- 1 env: steps/s of a Python loop of `scene.step()` / `mujoco.mj_step`;
- 1024 envs: env-steps/s of `build(n_envs=1024)` + 100 `scene.step()` / `mujoco.rollout.rollout`
  (1024 initial states, 100 steps, 2 threads). The machine is shared and its load changes within a
  run, so the genesis_lite child also runs MuJoCo itself (its mj_step loop at 1 env, its rollout for
  the batch), alternating run for run: the "paired ratio" is the median of those per-pair ratios (the
  "ratio" column divides medians taken minutes apart);
- real Genesis (`genesis-world`, CPU) when a separate venv has it ($GENESIS_PYTHON, else /work/genesis_venv
  or /tmp/gvenv).
Build time: `import genesis_lite`, `gs.init`, a scene with the full Panda URDF (meshes) and a plane,
`build()`, first `step()`, in a fresh process, with an empty Taichi kernel cache and with a warm one.
Each genesis_lite measurement runs in its own process, so a failure there still leaves MuJoCo's rows.
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parents[1]))  # genesis_lite without an install
from common import (DT, PANDA_HOME, Timer, genesis_python, median_rate, mujoco_model, panda_urdf,  # noqa: E402
                    plot_rates, print_table, run_python, write_stripped_panda)

HERE = Path(__file__).resolve().parent
GENESIS_PYTHON = genesis_python()


# --- MuJoCo ----------------------------------------------------------------------------------------


def mujoco_step_runner(urdf, n_steps=5000):
    """once(): seconds of n_steps mujoco.mj_step in a Python loop, 1 env, from the ready pose."""
    import mujoco

    m = mujoco_model(urdf)
    d = mujoco.MjData(m)

    def once():
        mujoco.mj_resetData(m, d)
        d.qpos[:] = PANDA_HOME
        with Timer() as t:
            for _ in range(n_steps):
                mujoco.mj_step(m, d)
        assert np.all(np.isfinite(d.qpos)), "MuJoCo diverged"
        return t.seconds

    return once


def mujoco_step_loop(urdf, n_steps=5000, repeats=5) -> float:
    """Steps/s of mujoco.mj_step in a Python loop, 1 env."""
    once = mujoco_step_runner(urdf, n_steps)
    once()  # warm-up
    return median_rate(once, n_steps, repeats)


def mujoco_rollout(urdf, n_envs=1024, n_steps=100, threads=2, repeats=5) -> float:
    """Env-steps/s of mujoco.rollout.rollout from n_envs initial states on `threads` threads."""
    once, shutdown = mujoco_rollout_runner(urdf, n_envs, n_steps, threads)
    try:
        once()  # warm-up (creates the thread pool)
        return median_rate(once, n_envs * n_steps, repeats)
    finally:
        shutdown()


def mujoco_rollout_runner(urdf, n_envs=1024, n_steps=100, threads=2):
    """(once, shutdown): once() runs mujoco.rollout.rollout of n_envs initial states for n_steps on
    `threads` threads and returns its seconds; shutdown() ends its thread pool."""
    import mujoco
    from mujoco import rollout

    m = mujoco_model(urdf)
    d = mujoco.MjData(m)
    d.qpos[:] = PANDA_HOME
    mujoco.mj_forward(m, d)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    s0 = np.empty(mujoco.mj_stateSize(m, spec))
    mujoco.mj_getState(m, d, s0, spec)
    init = np.tile(s0, (n_envs, 1))
    rng = np.random.default_rng(0)
    init[:, 1:1 + m.nq] += rng.normal(0.0, 0.01, (n_envs, m.nq))  # [time, qpos, qvel, ...]
    datas = [mujoco.MjData(m) for _ in range(threads)]
    out = np.empty((n_envs, n_steps, s0.size))

    def once():
        with Timer() as t:
            rollout.rollout(m, datas, init, nstep=n_steps, state=out, persistent_pool=True)
        assert np.all(np.isfinite(out[:, -1])), "MuJoCo rollout diverged"
        return t.seconds

    return once, rollout.shutdown_persistent_pool


def mujoco_build_time(urdf) -> dict:
    """MuJoCo's load + first step of the stripped Panda in a fresh process (a reference for build time)."""
    code = (
        "import time; t0 = time.perf_counter(); import mujoco; "
        f"m = mujoco.MjModel.from_xml_path({str(urdf)!r}); d = mujoco.MjData(m); mujoco.mj_step(m, d); "
        "import json; print(json.dumps({'seconds': time.perf_counter() - t0}))"
    )
    res, err = run_python(["-c", code], timeout=300)
    return {"seconds": res["seconds"] if res else None, "error": err}


# --- genesis_lite (runs in a child process: `--worker NAME`) ----------------------------------------


def _gl_scene(urdf, n_envs, precision, plane=False):
    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision=precision)
    scene = gs.Scene(
        sim_options=gs.options.SimOptions(dt=DT, substeps=1, gravity=(0.0, 0.0, -9.81)),
        rigid_options=gs.options.RigidOptions(integrator=gs.integrator.Euler),
    )
    if plane:
        scene.add_entity(gs.morphs.Plane())
    robot = scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=True, default_armature=None))
    if n_envs:
        scene.build(n_envs=n_envs)
    else:
        scene.build()
    return gs, scene, robot


def _gl_set(robot, setter, values, n_envs):
    """Call a setter with a tensor of the solver's dtype: per-dof values, tiled over envs if needed."""
    import torch

    dtype = robot.get_dofs_velocity().dtype
    v = np.asarray(values, dtype=float)
    try:
        setter(torch.as_tensor(v, dtype=dtype))
    except Exception:
        if not n_envs:
            raise
        setter(torch.as_tensor(np.tile(v, (n_envs, 1)), dtype=dtype))


def _gl_reset(robot, n_envs):
    import torch

    dtype = robot.get_dofs_velocity().dtype
    shape = (n_envs, robot.n_dofs) if n_envs else (robot.n_dofs,)
    robot.set_dofs_position(torch.as_tensor(np.broadcast_to(PANDA_HOME, shape).copy(), dtype=dtype))
    robot.set_dofs_velocity(torch.zeros(shape, dtype=dtype))


def worker_gl_steps(urdf, n_envs, n_steps, repeats, precision, paired_threads=0) -> dict:
    """Steps/s (n_envs == 0: 1 env, no batch axis) or env-steps/s of a loop of scene.step().
    paired_threads > 0: MuJoCo runs the same env and step counts in this process too (1 env: its
    mj_step loop in Python; a batch: its rollout on paired_threads threads), alternating with
    genesis_lite's runs, so that both see the same load; the ratio is the median of the per-pair
    ratios (this machine's load changes faster than a whole run)."""
    with Timer() as tb:
        gs, scene, robot = _gl_scene(urdf, n_envs, precision)
        _gl_set(robot, robot.set_dofs_damping, np.zeros(robot.n_dofs), n_envs)
        _gl_set(robot, robot.set_dofs_armature, np.zeros(robot.n_dofs), n_envs)
        _gl_reset(robot, n_envs)
        scene.step()  # compiles the step kernels
    build_s = tb.seconds

    def once():
        _gl_reset(robot, n_envs)
        with Timer() as t:
            for _ in range(n_steps):
                scene.step()
        q = robot.get_dofs_position().detach().cpu().numpy()
        assert np.all(np.isfinite(q)), "genesis_lite diverged"
        return t.seconds

    once()
    n = max(n_envs, 1) * n_steps
    if not paired_threads:
        return {"rate": median_rate(once, n, repeats), "build_s": build_s}
    if n_envs:
        mj_once, shutdown = mujoco_rollout_runner(urdf, n_envs, n_steps, paired_threads)
    else:
        mj_once, shutdown = mujoco_step_runner(urdf, n_steps), (lambda: None)
    try:
        mj_once()
        pairs = [(mj_once(), once()) for _ in range(repeats)]
    finally:
        shutdown()
    return {"rate": statistics.median(n / g for _, g in pairs), "mj_rate": statistics.median(n / m for m, _ in pairs),
            "paired_ratio": statistics.median(m / g for m, g in pairs), "build_s": build_s}


def peer_genesis(urdf, n_steps, repeats, precision):
    """Real Genesis in its own venv (GENESIS_PYTHON): (result dict or None, error or None)."""
    return run_python([str(HERE / "peer_genesis.py"), "--urdf", str(urdf), "--steps", str(n_steps),
                       "--repeats", str(repeats), "--precision", precision], python=GENESIS_PYTHON, timeout=1800)


BUILD_CODE = """
import time
t0 = time.perf_counter()
import genesis_lite as gs
gs.init(backend=gs.cpu, precision={precision!r})
scene = gs.Scene(sim_options=gs.options.SimOptions(dt={dt}))
scene.add_entity(gs.morphs.Plane())
robot = scene.add_entity(gs.morphs.URDF(file={urdf!r}, fixed=True, default_armature=None))
scene.build()
scene.step()
import json
print(json.dumps({{"seconds": time.perf_counter() - t0}}))
"""


def genesis_lite_build_time(precision="64") -> list[dict]:
    """Seconds from `import genesis_lite` to the end of the first step (full Panda + plane), in fresh
    processes: first with an empty Taichi offline kernel cache, then with the cache that run left."""
    cache = tempfile.mkdtemp(prefix="gl_ticache_")
    code = BUILD_CODE.format(precision=precision, dt=DT, urdf=str(panda_urdf()))
    rows = []
    try:
        for label in ("cold kernel cache", "warm kernel cache"):
            with Timer() as t:
                res, err = run_python(["-c", code], env={"TI_OFFLINE_CACHE_FILE_PATH": cache}, timeout=1200)
            rows.append({"what": f"genesis_lite: full Panda + plane, {label}",
                         "seconds": res["seconds"] if res else None,
                         "process_s": t.seconds if res else None, "error": err})
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    return rows


def _worker_main(argv):
    ap = argparse.ArgumentParser()
    ap.add_argument("--worker", required=True, choices=["gl_steps"])
    ap.add_argument("--urdf", required=True)
    ap.add_argument("--envs", type=int, default=0)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--precision", default="64")
    ap.add_argument("--paired-threads", type=int, default=0)
    a = ap.parse_args(argv)
    res = worker_gl_steps(a.urdf, a.envs, a.steps, a.repeats, a.precision, a.paired_threads)
    print(json.dumps(res), flush=True)


def _child(worker, urdf, **kw):
    args = [str(Path(__file__).resolve()), "--worker", worker, "--urdf", str(urdf)]
    for k, v in kw.items():
        args += [f"--{k}", str(v)]
    return run_python(args, timeout=1800)


# --- main ------------------------------------------------------------------------------------------


def main():
    if "--worker" in sys.argv:
        return _worker_main(sys.argv[1:])
    ap = argparse.ArgumentParser(description="genesis_lite vs MuJoCo: Panda stepping speed and build time")
    ap.add_argument("--quick", action="store_true", help="fewer steps (a smoke run)")
    ap.add_argument("--precision", default="64", choices=["32", "64"], help="genesis_lite float precision")
    ap.add_argument("--envs", type=int, default=1024)
    ap.add_argument("--threads", type=int, default=2, help="MuJoCo rollout threads")
    ap.add_argument("--skip-build", action="store_true", help="skip the build-time measurement")
    ap.add_argument("--skip-genesis-lite", action="store_true")
    ap.add_argument("--plot", type=Path, default=None, help="write a bar chart PNG (needs matplotlib)")
    ap.add_argument("--json", type=Path, default=None, help="write the results as JSON")
    args = ap.parse_args()

    steps_1 = 200 if args.quick else 1000
    steps_mj = 1000 if args.quick else 5000
    steps_b = 20 if args.quick else 100
    repeats = 5
    tmp = Path(tempfile.mkdtemp(prefix="bench_rigid_"))
    urdf = write_stripped_panda(tmp)
    print(f"stripped Panda URDF: {urdf}", flush=True)
    import mujoco

    rows = []
    t0 = time.time()
    print("MuJoCo 1 env ...", flush=True)
    mj1 = mujoco_step_loop(urdf, steps_mj, repeats)
    rows.append({"engine": f"MuJoCo {mujoco.__version__} mj_step loop", "envs": 1, "rate": mj1})
    print(f"MuJoCo {args.envs} envs (rollout, {args.threads} threads) ...", flush=True)
    mjb = mujoco_rollout(urdf, args.envs, steps_b, args.threads, repeats)
    rows.append({"engine": f"MuJoCo rollout ({args.threads} threads)", "envs": args.envs, "rate": mjb})
    ref = {1: mj1, args.envs: mjb}

    if not args.skip_genesis_lite:
        for n_envs, n_steps in ((0, steps_1), (args.envs, steps_b)):
            print(f"genesis_lite {max(n_envs, 1)} env(s) ...", flush=True)
            paired = args.threads if n_envs else 1
            res, err = _child("gl_steps", urdf, envs=n_envs, steps=n_steps, repeats=repeats if not paired else 2 * repeats,
                              precision=args.precision, **({"paired-threads": paired} if paired else {}))
            note = err or f"build+compile {res['build_s']:.1f} s"
            if res and "paired_ratio" in res:
                peer = "rollout" if n_envs else "mj_step loop"
                note += (f"; paired with MuJoCo's {peer} in its process: {res['paired_ratio']:.2f}x "
                         f"(MuJoCo {res['mj_rate']:,.0f} there)")
            rows.append({"engine": f"genesis_lite (f{args.precision}, CPU)", "envs": max(n_envs, 1),
                         "rate": res["rate"] if res else None, "paired": res.get("paired_ratio") if res else None,
                         "note": note})
    if Path(GENESIS_PYTHON).exists():
        print("Genesis (genesis-world) 1 env ...", flush=True)
        res, err = peer_genesis(urdf, steps_1, repeats, args.precision)
        rows.append({"engine": f"Genesis {res.get('version', '') if res else ''} (CPU)".replace("  ", " "),
                     "envs": 1, "rate": res["rate"] if res else None,
                     "note": err or f"f{res.get('precision', '?')}, build {res.get('build_s', 0):.1f} s"})
    for r in rows:
        r["ratio"] = r["rate"] / ref[r["envs"]] if r.get("rate") and r["envs"] in ref else None
    print_table(rows, [("engine", "engine", ""), ("envs", "envs", "d"), ("rate", "steps/s (env-steps/s)", ",.0f"),
                       ("ratio", "ratio to MuJoCo", ".3f"), ("paired", "paired ratio", ".2f"), ("note", "note", "")],
                title=f"Panda, dt={DT}, median of {repeats} ({time.time() - t0:.0f} s)")

    build_rows = []
    if not args.skip_build:
        print("\nbuild time ...", flush=True)
        mjt = mujoco_build_time(urdf)
        build_rows.append({"what": "MuJoCo: stripped Panda load + first step", "seconds": mjt["seconds"],
                           "error": mjt["error"]})
        if not args.skip_genesis_lite:
            build_rows += genesis_lite_build_time(args.precision)
        print_table(build_rows, [("what", "what", ""), ("seconds", "seconds (in process)", ".2f"),
                                 ("process_s", "seconds (whole process)", ".2f"), ("error", "error", "")],
                    title="Build time: fresh process, import to end of the first step")

    if args.json:
        args.json.write_text(json.dumps({"speed": rows, "build": build_rows}, indent=2))
    if args.plot:
        plot_rates(rows, args.plot, f"Panda, dt={DT}")
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
