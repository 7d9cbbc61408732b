"""The work-precision peer: real Genesis (`genesis-world`) running the scenes of bench_workprecision.py.

Runs in Genesis's own venv (it brings its own Taichi fork), started by bench_workprecision.run_genesis:

    $GENESIS_PYTHON benchmarks/peer_genesis_wp.py --args '{"scene_key": "pendulum", "files": {...},
        "points": [["Euler", 0.01, 1], ...], "n_envs": 0, "repeats": 3, "sample_times": [1.0]}'

Same scenes as genesis_lite's builders there (the same URDF files, the floor a plane at z = 0 with the
scene's friction, damping and armature 0, joint limits off for the arms, gs.init(precision="64"), CPU).
Times the Python loop of scene.step() between the sample times (build, compile, resets and reads excluded),
median of `repeats` after a warm-up run. Prints one JSON line: {"points": [...], "version": ...}.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import scenes as S  # noqa: E402  (numpy and the standard library only)


def _tile(torch, x, n_envs, dtype):
    t = torch.as_tensor(np.asarray(x, dtype=float), dtype=dtype)
    return t.unsqueeze(0).repeat(n_envs, 1) if n_envs else t


def build(gs, torch, key, files, integrator, dt, substeps, n_envs):
    dtype = torch.float64
    rigid = dict(integrator=getattr(gs.integrator, integrator))
    B = max(n_envs, 1)
    if key in ("pendulum", "panda"):
        rigid.update(enable_collision=False, enable_joint_limit=False)
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, substeps=substeps, gravity=(0.0, 0.0, -S.G)),
                     rigid_options=gs.options.RigidOptions(**rigid), show_viewer=False)
    if key in ("pendulum", "panda"):
        robot = scene.add_entity(gs.morphs.URDF(file=files["urdf"], fixed=True))
        scene.build(n_envs=n_envs)
        q0, v0 = (S.PENDULUM_Q0, S.PENDULUM_V0) if key == "pendulum" else (S.PANDA_ARM_HOME, np.zeros(7))
        n = robot.n_dofs

        def reset():
            scene.reset()
            robot.set_dofs_damping(torch.zeros(n, dtype=dtype))
            robot.set_dofs_armature(torch.zeros(n, dtype=dtype))
            robot.set_dofs_position(_tile(torch, q0, n_envs, dtype))
            robot.set_dofs_velocity(_tile(torch, v0, n_envs, dtype))

        def observe():
            return robot.get_dofs_position().cpu().numpy().reshape(B, -1)

    elif key == "box":
        mat = gs.materials.Rigid(friction=S.BOX_MU)
        scene.add_entity(gs.morphs.Plane(), material=mat)
        robot = scene.add_entity(gs.morphs.URDF(file=files["urdf"], fixed=False, pos=(0.0, 0.0, S.BOX_SIZE / 2)),
                                 material=mat)
        scene.build(n_envs=n_envs)

        def reset():
            scene.reset()
            robot.set_dofs_armature(torch.zeros(6, dtype=dtype))
            robot.set_dofs_velocity(_tile(torch, [S.BOX_V0, 0, 0, 0, 0, 0], n_envs, dtype))

        def observe():
            return robot.get_pos().cpu().numpy().reshape(B, 3)[:, :1]

    elif key == "quadruped":
        from bench_contact import BASE_Z, KP, KV, standing_pose

        scene.add_entity(gs.morphs.Plane())
        robot = scene.add_entity(gs.morphs.URDF(file=files["urdf"], fixed=False, pos=(0.0, 0.0, BASE_Z)))
        scene.build(n_envs=n_envs)
        joints = [j for j in robot.joints if j.n_dofs == 1]
        dofs = [j.dofs_idx_local[0] for j in joints]
        q0 = standing_pose([j.name for j in joints])
        target = _tile(torch, q0, n_envs, dtype)

        def reset():
            scene.reset()
            robot.set_dofs_armature(torch.zeros(robot.n_dofs, dtype=dtype))
            robot.set_dofs_damping(torch.zeros(robot.n_dofs, dtype=dtype))
            robot.set_dofs_kp(torch.full((len(dofs),), KP, dtype=dtype), dofs)
            robot.set_dofs_kv(torch.full((len(dofs),), KV, dtype=dtype), dofs)
            robot.set_dofs_position(target, dofs)
            robot.control_dofs_position(target, dofs)

        def observe():
            return robot.get_pos().cpu().numpy().reshape(B, 3)

    else:
        raise KeyError(f"peer_genesis_wp.py has no scene {key!r}")
    return scene, reset, observe


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--args", required=True, help="JSON: scene_key, files, points, n_envs, repeats, sample_times")
    a = json.loads(ap.parse_args().args)
    import genesis as gs
    import torch

    gs.init(backend=gs.cpu, precision="64", logging_level="warning")
    out = []
    for integ, dt, sub in a["points"]:
        rec = {"integrator": integ, "dt": dt, "substeps": sub}
        try:
            chunks, prev = [], 0
            for t in a["sample_times"]:
                n = int(round(t / dt))
                chunks.append(n - prev)
                prev = n
            t0 = time.perf_counter()
            scene, reset, observe = build(gs, torch, a["scene_key"], a["files"], integ, dt, sub, a["n_envs"])
            reset()
            for _ in range(min(48, sum(chunks))):  # compiles, and warms the loop up
                scene.step()
            observe()
            rec["build_s"] = time.perf_counter() - t0
            walls, obs = [], None
            for _ in range(a["repeats"]):
                reset()
                wall, got = 0.0, []
                for n in chunks:
                    ts = time.perf_counter()
                    for _ in range(n):
                        scene.step()
                    wall += time.perf_counter() - ts
                    got.append(observe())
                walls.append(wall)
                obs = np.concatenate(got, axis=1)
            rec.update(wall=statistics.median(walls), walls=walls, obs=obs.tolist(), steps=sum(chunks))
        except Exception as e:  # a diverged or unsupported run is a result, not a crash of the sweep
            rec.update(wall=None, obs=None, failed=f"{type(e).__name__}: {str(e).splitlines()[0][:160] if str(e) else ''}")
        out.append(rec)
    print(json.dumps({"points": out, "version": getattr(gs, "__version__", "")}), flush=True)


if __name__ == "__main__":
    main()
