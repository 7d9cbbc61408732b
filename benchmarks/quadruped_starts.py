"""Which drops of the quadruped does each engine integrate badly? Per-start errors of bench_workprecision.py's
quadruped with armature (issue #24).

The batched work-precision rows start their envs from 16 drops (bench_workprecision.quad_starts). This script
runs one env per start, in both engines, at a few steps of implicitfast, and prints each start's error (the
largest base-position error over t = 0.5, 0.6 .. 1 s against the same engine's RK4 at 0.1 ms, and that
reference's own error against RK4 at 0.2 ms). `--set decomposed` replaces the drawn starts by one
perturbation each (yaw, roll, pitch, height, a translation, single joints), which tells the physics' invariances
(a yawed or translated drop must give the level drop's errors) from the landings that are hard to integrate.
`--rigid key=value` sets RigidOptions fields for genesis_lite's runs (contact_damping=1e4, say). `--restart NAME`
(a decomposed start) instead restarts genesis_lite from its reference's state at t = 0.5 s (standing) and prints
the error a step makes over the standing phase alone, from the same state.

    python benchmarks/quadruped_starts.py [--set drawn|decomposed] [--rigid contact_damping=1e4 ...]
    python benchmarks/quadruped_starts.py --restart "pitch 0.1 rad" [--rigid ...]
"""
import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(HERE.parent))

import bench_workprecision as W  # noqa: E402

DRAWN = W.quad_starts
POINTS = [("RK4", 1e-4, 1), ("RK4", 2e-4, 1), ("implicitfast", 0.005, 1), ("implicitfast", 0.00125, 1),
          ("implicitfast", 0.0003125, 1)]


def decomposed_starts(joint_names, n):
    """Start 0 the level drop; then one perturbation each (names in DECOMPOSED)."""
    from scipy.spatial.transform import Rotation

    pos, quat, q = (np.repeat(a[:1], n, axis=0) for a in DRAWN(joint_names, 1))
    for i, (_, kind, value) in enumerate(DECOMPOSED[1:n], start=1):
        if kind in ("roll", "pitch", "yaw"):
            rpy = np.zeros(3)
            rpy["roll pitch yaw".split().index(kind)] = value
            quat[i] = np.roll(Rotation.from_euler("xyz", rpy).as_quat(), 1)
        elif kind in ("x", "z"):
            pos[i, "xyz".index(kind)] += value
        elif kind == "joints":
            q[i] += value
        else:
            q[i, joint_names.index(kind)] += value
    return pos, quat, q


DECOMPOSED = [("level", None, 0.0), ("yaw 0.5 rad", "yaw", 0.5), ("yaw 2 rad", "yaw", 2.0), ("x +0.1 m", "x", 0.1),
              ("z -0.03 m", "z", -0.03), ("z +0.03 m", "z", 0.03), ("roll 0.1 rad", "roll", 0.1),
              ("roll 0.02 rad", "roll", 0.02), ("pitch 0.1 rad", "pitch", 0.1), ("pitch 0.02 rad", "pitch", 0.02),
              ("LF_HAA +0.1 rad", "LF_HAA", 0.1), ("LF_HFE +0.1 rad", "LF_HFE", 0.1), ("LF_KFE +0.1 rad", "LF_KFE", 0.1),
              ("RH_KFE +0.02 rad", "RH_KFE", 0.02), ("all joints +0.05 rad", "joints", 0.05),
              ("yaw 0.5 rad again", "yaw", 0.5)]


def restart(name):
    """genesis_lite from its RK4 0.1 ms reference's state at t = 0.5 s, one env a step size: the base position's
    error at t = 0.6, 0.75 and 1 s against the reference's own continuation."""
    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64", logging_level="warning")
    k = [d[0] for d in DECOMPOSED].index(name)
    W.quad_starts = lambda names, n: tuple(a[[0, k]] for a in decomposed_starts(names, len(DECOMPOSED)))
    files = W.SCENES["quadruped_armature"].files(Path(tempfile.mkdtemp()))

    def run(integrator, dt, t_span, start=None):
        scene, reset, observe = W._gl_build_quad(gs, files, integrator, dt, 1, 2, armature=W.QUAD_ARMATURE)
        reset()
        robot = scene.entities[-1]
        if start is not None:
            robot.set_qpos(start[0])
            robot.set_dofs_velocity(start[1])
        out, every = [], int(round(0.05 / dt))
        for i in range(int(round(t_span / dt))):
            scene.step()
            if (i + 1) % every == 0:
                out.append(observe()[1].copy())
        return np.array(out), (robot.get_qpos().clone(), robot.get_dofs_velocity().clone())

    _, mid = run("RK4", 1e-4, 0.5)
    ref, _ = run("RK4", 1e-4, 0.5, mid)
    print(f"genesis_lite restarted at t = 0.5 s from its reference's state, start '{name}'")
    for integrator, dt in (("implicitfast", 0.005), ("implicitfast", 0.00125), ("implicitfast", 0.0003125),
                           ("RK4", 0.00125), ("Euler", 0.00125)):
        e = np.linalg.norm(run(integrator, dt, 0.5, mid)[0] - ref, axis=1)
        print(f"  {integrator} {dt * 1e3:g} ms: error at t = 0.6 / 0.75 / 1 s {e[1]:.1e} {e[4]:.1e} {e[-1]:.1e} m")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", choices=["drawn", "decomposed"], default="drawn")
    ap.add_argument("--rigid", nargs="*", default=[], help="RigidOptions fields for genesis_lite, key=value")
    ap.add_argument("--restart", default=None, help="a decomposed start's name: the standing phase alone")
    a = ap.parse_args()
    rigid = {k: float(v) for k, v in (kv.split("=", 1) for kv in a.rigid)}
    n = W.QUAD_STARTS
    if a.set == "decomposed":
        W.quad_starts = decomposed_starts  # both engines' builders read it (genesis_lite runs in this process)
        names = [d[0] for d in DECOMPOSED[:n]]
    else:
        names = [f"drawn {i}" + (" (level)" if i == 0 else "") for i in range(n)]
    if a.restart:
        with W.rigid_options(**rigid):
            return restart(a.restart)
    wps = W.SCENES["quadruped_armature"]
    files = wps.files(Path(tempfile.mkdtemp()))
    with W.rigid_options(**rigid):
        gl = W.worker_gl(wps.key, {k: str(v) for k, v in files.items()}, POINTS, n, 1)["points"]
    for p in gl:
        if p.get("failed"):
            raise SystemExit(f"genesis_lite {p['integrator']} dt = {p['dt']}: {p['failed']}")
    mj = W.run_mj(wps, files, POINTS, n, 1)["points"]

    def per_start(a, b):
        d = np.asarray(a["obs"]) - np.asarray(b["obs"])
        return np.linalg.norm(d.reshape(n, -1, 3), axis=2).max(axis=1)

    cols, head = [], []
    for engine, pts in (("genesis_lite", gl), ("MuJoCo", mj)):
        cols.append(per_start(pts[1], pts[0]))
        head.append(f"{engine} reference's own")
        for p in pts[2:]:
            cols.append(per_start(p, pts[0]))
            head.append(f"{engine} {p['integrator']} {p['dt'] * 1e3:g} ms")
    print(f"Per-start error (m), quadruped with armature, {a.set} starts"
          + (f", genesis_lite with RigidOptions {rigid}" if rigid else "") + "\n")
    print("| start | " + " | ".join(head) + " |")
    print("| --- |" + " --- |" * len(head))
    for i, name in enumerate(names):
        print(f"| {name} | " + " | ".join(f"{c[i]:.1e}" for c in cols) + " |")
    print("| mean | " + " | ".join(f"{c.mean():.1e}" for c in cols) + " |")


if __name__ == "__main__":
    main()
