"""What external link forces cost a rigid scene: step rate and cold compile, Panda without collisions.

    python benchmarks/bench_external_force.py [--envs 1024] [--repeats 7] [--compile-rounds 2]

Modes:
- base:    a plain scene (no external wrench stage: what every scene that applies no force runs);
- always:  the same scene forced onto a scene core with the rigid-MPM coupler's external-wrench stage
           (ExternalWrench, a dof x link stage per evaluation; the design where every rigid scene carries it,
           measured by passing external_wrench=True to the solver);
- applied: the same scene with the applied-wrench stage (AppliedWrench: a link stage folded into the bias
           forces) from build, applying nothing (what every scene would run if every scene carried it);
- used:    the scene applies a force and a torque to link7 every step (apply_links_external_force/_torque,
           world frame at the link origin: the path of Genesis's example script).
Step rates: all four scenes live in one process and their timing loops alternate (this machine is shared
and its load changes faster than a run), 1 env (steps/s, 1000 steps a loop) and n envs (env-steps/s, 100
steps); medians over the repeats, and the median of the per-round ratios to base. Compile: build + first
step of one scene in a fresh process with an empty Taichi kernel cache, per mode, alternating.
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parents[1]))
from common import DT, PANDA_HOME, Timer, print_table, run_python, write_stripped_panda  # noqa: E402

MODES = ("base", "always", "applied", "used")


def _scene(gs, urdf, mode, n_envs):
    import genesis_lite.bridges.rigid as br

    orig = br.RigidSolver
    extra = {"always": {"external_wrench": True}, "applied": {"applied_wrench": True}}.get(mode, {})
    br.RigidSolver = lambda *a, **k: orig(*a, **{**k, **extra})
    try:
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT, substeps=1),
                         rigid_options=gs.options.RigidOptions(integrator=gs.integrator.Euler))
        robot = scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=True))
        scene.build(n_envs=n_envs)
    finally:
        br.RigidSolver = orig
    return scene, robot


def _stepper(scene, robot, mode, n_envs):
    import torch

    B = max(n_envs, 1)
    link7 = robot.get_link("panda_link7").idx
    f = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(B, 1, 3).clone()
    t = torch.tensor([0.0, 0.1, 0.0], dtype=torch.float64).expand(B, 1, 3).clone()
    if not n_envs:
        f, t = f[0], t[0]
    solver = scene.sim.rigid_solver

    def step():
        if mode == "used":
            solver.apply_links_external_force(f, [link7])
            solver.apply_links_external_torque(t, [link7])
        scene.step()

    return step


def worker_rates(urdf, n_envs, n_steps, repeats):
    import torch

    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")
    runs = {}
    for mode in MODES:
        scene, robot = _scene(gs, urdf, mode, n_envs)
        shape = (n_envs, robot.n_dofs) if n_envs else (robot.n_dofs,)
        home = torch.as_tensor(np.broadcast_to(PANDA_HOME, shape).copy(), dtype=torch.float64)
        runs[mode] = (scene, robot, _stepper(scene, robot, mode, n_envs), home, shape)

    def once(mode):
        scene, robot, step, home, shape = runs[mode]
        robot.set_dofs_position(home)
        robot.set_dofs_velocity(torch.zeros(shape, dtype=torch.float64))
        with Timer() as tt:
            for _ in range(n_steps):
                step()
        assert torch.isfinite(robot.get_dofs_position()).all()
        return tt.seconds

    for mode in MODES:
        once(mode)  # compiles
    secs = {m: [] for m in MODES}
    for _ in range(repeats):
        for mode in MODES:
            secs[mode].append(once(mode))
    B = max(n_envs, 1)
    return {m: {"rate": statistics.median(B * n_steps / s for s in secs[m]),
                "ratio": statistics.median(s / b for b, s in zip(secs["base"], secs[m]))} for m in MODES}


def worker_compile(urdf, mode, n_envs):
    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")
    with Timer() as t:
        scene, robot = _scene(gs, urdf, mode, n_envs)
        _stepper(scene, robot, mode, n_envs)()
    return {"compile_s": t.seconds}


def main():
    if "--worker" in sys.argv:
        ap = argparse.ArgumentParser()
        ap.add_argument("--worker", choices=["rates", "compile"])
        ap.add_argument("--urdf")
        ap.add_argument("--mode", default="base")
        ap.add_argument("--envs", type=int)
        ap.add_argument("--steps", type=int, default=100)
        ap.add_argument("--repeats", type=int, default=5)
        a = ap.parse_args()
        res = (worker_rates(a.urdf, a.envs, a.steps, a.repeats) if a.worker == "rates"
               else worker_compile(a.urdf, a.mode, a.envs))
        print(json.dumps(res), flush=True)
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--compile-rounds", type=int, default=2)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_extf_"))
    urdf = write_stripped_panda(tmp)
    me = str(Path(__file__).resolve())
    rows = {}
    for n_envs, steps in ((0, 1000), (args.envs, 100)):
        B = max(n_envs, 1)
        res, err = run_python([me, "--worker", "rates", "--urdf", str(urdf), "--envs", str(n_envs), "--steps", str(steps),
                               "--repeats", str(args.repeats)], timeout=3600)
        print(B, res or err, flush=True)
        for m in MODES:
            rows[(m, B)] = dict(res[m]) if res else {"error": err}
        for _ in range(args.compile_rounds):
            for m in MODES:
                cache = tempfile.mkdtemp(prefix="extf_cache_")
                r, e = run_python([me, "--worker", "compile", "--urdf", str(urdf), "--mode", m, "--envs", str(n_envs)],
                                  env={"TI_OFFLINE_CACHE_FILE_PATH": cache, "GS_CHECK_AD_STACK": "0"}, timeout=1800)
                shutil.rmtree(cache, ignore_errors=True)
                print(m, B, r or e, flush=True)
                if r:
                    rows[(m, B)].setdefault("compiles", []).append(r["compile_s"])
    table = []
    for (m, B), r in rows.items():
        table.append({"mode": m, "envs": B, "rate": r.get("rate"), "ratio": r.get("ratio"),
                      "compile": statistics.median(r["compiles"]) if r.get("compiles") else None})
    print_table(table, [("mode", "mode", "s"), ("envs", "envs", "d"), ("rate", "(env-)steps/s", ",.0f"),
                        ("ratio", "time vs base (paired)", ".2f"),
                        ("compile", "build + first step, cold cache (s)", ".1f")],
                title="external forces: Panda (stripped), f64, Euler, CPU")
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
