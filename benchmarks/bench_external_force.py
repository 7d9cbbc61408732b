"""What external link forces cost a rigid scene: step rate and cold compile, Panda without collisions.

    python benchmarks/bench_external_force.py [--modes base,always,used] [--envs 1024] [--repeats 5]

Modes, each in fresh processes with an empty Taichi kernel cache (so the first-step time is a cold compile):
- base:   a plain scene (no external wrench stage: what every scene that applies no force runs);
- always: the same scene forced onto a scene core with the rigid-MPM coupler's external-wrench stage
          (ExternalWrench, a dof x link stage per evaluation; the design where every rigid scene carries it,
          measured by passing external_wrench=True to the solver);
- applied: the same scene with the applied-wrench stage (AppliedWrench: a link stage folded into the bias
          forces) from build, applying nothing (what every scene would run if every scene carried it);
- used:   the scene applies a force and a torque to the hand every step (apply_links_external_force/_torque),
          the path a Genesis script takes.
Rows: 1 env (steps/s of a Python loop of scene.step(), 1000 steps) and n envs (env-steps/s, 100 steps), the
seconds from build() to the end of the first step (compile, cold cache). Medians of `repeats` loops. The
machine is shared: run the modes alternately (the default order does) and compare within one run.
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


def worker(urdf, mode, n_envs, n_steps, repeats):
    import torch

    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")
    if mode == "always":
        import genesis_lite.bridges.rigid as br

        orig = br.RigidSolver
        br.RigidSolver = lambda *a, **k: orig(*a, **{**k, "external_wrench": True})
    elif mode == "applied":
        import genesis_lite.bridges.rigid as br

        orig = br.RigidSolver
        br.RigidSolver = lambda *a, **k: orig(*a, **{**k, "applied_wrench": True})
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT, substeps=1),
                     rigid_options=gs.options.RigidOptions(integrator=gs.integrator.Euler))
    robot = scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=True))
    with Timer() as tb:
        scene.build(n_envs=n_envs)
    B = max(n_envs, 1)
    shape = (n_envs, robot.n_dofs) if n_envs else (robot.n_dofs,)
    home = torch.as_tensor(np.broadcast_to(PANDA_HOME, shape).copy(), dtype=torch.float64)
    hand = robot.links[-3].idx  # link7
    f = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(B, 1, 3).clone()
    t = torch.tensor([0.0, 0.1, 0.0], dtype=torch.float64).expand(B, 1, 3).clone()
    if not n_envs:
        f, t = f[0], t[0]
    solver = scene.sim.rigid_solver

    def step():
        if mode == "used":
            solver.apply_links_external_force(f, [hand])
            solver.apply_links_external_torque(t, [hand])
        scene.step()

    robot.set_dofs_position(home)
    with Timer() as tc:
        step()
    compile_s = tb.seconds + tc.seconds

    def once():
        robot.set_dofs_position(home)
        robot.set_dofs_velocity(torch.zeros(shape, dtype=torch.float64))
        with Timer() as tt:
            for _ in range(n_steps):
                step()
        assert torch.isfinite(robot.get_dofs_position()).all()
        return tt.seconds

    once()
    rate = statistics.median(B * n_steps / once() for _ in range(repeats))
    return {"rate": rate, "compile_s": compile_s}


def main():
    if "--worker" in sys.argv:
        ap = argparse.ArgumentParser()
        ap.add_argument("--worker", action="store_true")
        ap.add_argument("--urdf")
        ap.add_argument("--mode")
        ap.add_argument("--envs", type=int)
        ap.add_argument("--steps", type=int)
        ap.add_argument("--repeats", type=int)
        a = ap.parse_args()
        print(json.dumps(worker(a.urdf, a.mode, a.envs, a.steps, a.repeats)), flush=True)
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--modes", default="base,always,applied,used")
    ap.add_argument("--envs", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=1, help="alternate the modes this many times")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_extf_"))
    urdf = write_stripped_panda(tmp)
    modes = args.modes.split(",")
    results = {}
    for _ in range(args.rounds):
        for n_envs, steps in ((0, 1000), (args.envs, 100)):
            for mode in modes:
                cache = tempfile.mkdtemp(prefix="extf_cache_")
                res, err = run_python([str(Path(__file__).resolve()), "--worker", "--urdf", str(urdf), "--mode", mode,
                                       "--envs", str(n_envs), "--steps", str(steps), "--repeats", str(args.repeats)],
                                      env={"TI_OFFLINE_CACHE_FILE_PATH": cache}, timeout=1800)
                shutil.rmtree(cache, ignore_errors=True)
                if err:
                    print(f"{mode} {n_envs}: {err}", flush=True)
                    continue
                results.setdefault((mode, max(n_envs, 1)), []).append(res)
                print(mode, max(n_envs, 1), res, flush=True)
    rows = []
    for (mode, B), rs in results.items():
        rows.append({"mode": mode, "envs": B, "rate": statistics.median(r["rate"] for r in rs),
                     "compile": statistics.median(r["compile_s"] for r in rs)})
    print_table(rows, [("mode", "mode", "s"), ("envs", "envs", "d"), ("rate", "(env-)steps/s", ",.0f"),
                       ("compile", "build + first step, cold cache (s)", ".1f")],
                title="external forces: Panda, f64, Euler, CPU")
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
