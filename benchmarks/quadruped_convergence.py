"""Does the quadruped drop of bench_workprecision.py converge as dt shrinks? (issue #24)

The work-precision benchmark measures each engine's error against that engine's own fine run. This script
runs its scene (ANYmal B dropped from 0.62 m, PD holding the standing pose, float64, 1 env) at halving steps
and prints the base position's largest change per halving, over the whole run and over its standing part
(t >= 0.5 s): with the defaults (Genesis's armature of 0.1 on every joint; since 2026-12-05 the contact of
1e5 N/m per point critically damped for the mass it moves, RigidOptions(contact_damping_ratio=1) with at least
4 k h) for implicitfast and RK4 from 5 ms down, and without armature; then the contact of before (1e6 N/m, a
fixed damper of 4e4 N s/m, where a light foot's damping time m / c ~ 1e-5 s is what no practical step
resolves) and variants of it; then restarts a run from the defaults' fine run (no armature) at t = 0.5 s with a
coarse and a fine step, to tell a steady-state error of the step from a history (the landing) that the step
changes.

    python benchmarks/quadruped_convergence.py [--quick] [--out benchmarks/results/quadruped_convergence.md]
"""
import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(HERE.parent))

import bench_workprecision as W  # noqa: E402
from common import progress  # noqa: E402

T_END = 1.0
SAMPLE = 0.1  # s between recorded base positions


def build(gs, files, dt, damping=None, integrator="RK4"):
    """`damping`: RigidOptions fields to set ({"contact_damping_ratio": 1.0}), or None for the defaults; its
    "armature" entry, if any, is the URDF's default_armature instead (None: the file's, none)."""
    damping = dict(damping or {})  # (an empty dict: the defaults, without armature)
    armature = damping.pop("armature", None)
    with W.rigid_options(**damping):
        return W._gl_build_quad(gs, files, integrator, dt, 1, 0, armature=armature)


def run(gs, files, dt, damping=None, start=None, t_end=T_END, integrator="RK4"):
    """Base positions every SAMPLE s up to t_end (from `start` = (qpos, dofs velocity) if given)."""
    scene, reset, observe = build(gs, files, dt, damping, integrator)
    reset()
    robot = scene.entities[1]
    if start is not None:
        robot.set_qpos(start[0])
        robot.set_dofs_velocity(start[1])
    every = int(round(SAMPLE / dt))
    out = []
    for i in progress(range(int(round(t_end / dt))), desc=f"dt={dt:g}"):
        scene.step()
        if (i + 1) % every == 0:
            out.append(observe().ravel().copy())
    return np.array(out), robot


def foot_mass(gs, files):
    """A line: the vertical effective mass 1 / (J M^-1 J^T)_zz of the left front shank's centre of mass (the foot's
    link) at the standing pose with the default armature, M the joint-space mass matrix of the whole robot
    (floating base included), and the contact's critical damping 2 sqrt(k m) at the default stiffness."""
    import torch

    scene, _, _ = build(gs, files, 5e-3, {"armature": 0.1}, "implicitfast")
    ent = scene.entities[1]
    sim = ent._sim
    dofs = slice(ent._dof_start, ent._dof_start + ent.n_dofs)
    M = sim.mass_at_qpos0(ent) + torch.diag_embed(sim.params["armature"][:1, dofs].double())
    q = ent.get_qpos().double().reshape(1, -1)
    i = [ln.name for ln in ent.links].index("LF_SHANK")
    J = ent._jacobian_at(q, i, sim.param_base["com"][0, ent._link_start + i].double())[:, :3]
    m = 1.0 / float((J @ torch.linalg.inv(M) @ J.transpose(-1, -2))[0, 2, 2])
    k = gs.options.RigidOptions().contact_stiffness
    return (f"LF_SHANK (0.348 kg, its foot sphere): vertical effective mass {m:.2f} kg at the standing pose, "
            f"critical damping 2 sqrt(k m) = {2 * (k * m) ** 0.5:.0f} N s/m at the default k = {k:g} N/m, the "
            f"default damper since 2026-12-05 (m / c = {m / (2 * (k * m) ** 0.5):.1e} s; it takes this mass through "
            f"the robot at its initial configuration, not the link's own: {2 * (k * 0.348) ** 0.5:.0f} N s/m "
            f"until 2026-12-01). The fixed damper of before (4e4 N s/m on 1e6 N/m): m / c = {m / 4e4:.1e} s.")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="three steps per model, no restart")
    ap.add_argument("--out", default=str(HERE / "results" / "quadruped_convergence.md"))
    args = ap.parse_args()
    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64", logging_level="warning")
    files = W._quad_files(Path(tempfile.mkdtemp()))
    halving = [5e-3 / 2**k for k in range(9)]  # 5 ms .. 19.5 us
    # the variants below the defaults keep friction's slip speed fixed (friction_smoothing_accel=None, the default
    # until 2026-12-06), so that each is the model it names
    eps = {"friction_smoothing_accel": None}
    fixed = {"contact_stiffness": 1e6, "contact_damping": 4e4, **eps}  # the default contact until 2026-12-05
    at_1e6 = {"contact_stiffness": 1e6, **eps}
    models = [("the defaults (Genesis's armature of 0.1 kg m^2 on every joint; since 2026-12-05 the contact 1e5 N/m "
               "per point, critically damped for the mass it moves; friction's load with Coulomb's forces applied; "
               "since 2026-12-06 friction's slip speed at most 0.25 h m/s, below h = 4 ms), implicitfast",
               {"armature": 0.1}, "implicitfast", halving),
              ("the defaults (armature 0.1), RK4", {"armature": 0.1}, "RK4", halving),
              ("armature 0.1, friction's slip speed fixed at 1e-3 m/s (RigidOptions(friction_smoothing_accel=None), "
               "the default until 2026-12-06), implicitfast", {"armature": 0.1, **eps}, "implicitfast", halving),
              ("armature 0.1, the slip speed fixed, RK4", {"armature": 0.1, **eps}, "RK4", halving),
              ("no armature, the defaults, RK4", {}, "RK4", [4e-4, 2e-4, 1e-4, 5e-5, 2.5e-5, 1.25e-5]),
              ("no armature, the slip speed fixed, RK4", dict(eps), "RK4", [4e-4, 2e-4, 1e-4, 5e-5, 2.5e-5, 1.25e-5]),
              ("armature 0.1, the contact of before 2026-12-05 (1e6 N/m, fixed damping 4e4 N s/m), implicitfast",
               {"armature": 0.1, **fixed}, "implicitfast", halving),
              ("armature 0.1, the contact of before (1e6 N/m, 4e4 N s/m), RK4", {"armature": 0.1, **fixed}, "RK4",
               halving),
              ("armature 0.1, the contact of before, friction_load = \"frictionless\" (friction's load from the "
               "frictionless solve, the model before 2026-12-02), implicitfast",
               {"armature": 0.1, **fixed, "friction_load": "frictionless"}, "implicitfast", halving[:8]),
              ("armature 0.1, 1e6 N/m and the damper critical for the mass each contact moves through the robot, "
               "implicitfast", {"armature": 0.1, **at_1e6}, "implicitfast", halving[:8]),
              ("armature 0.1, 1e6 N/m, a fixed contact_damping of 4e3 N s/m (about critical for a foot's effective "
               "mass at 1e6 N/m), implicitfast", {"armature": 0.1, **at_1e6, "contact_damping": 4e3}, "implicitfast",
               halving[:8]),
              ("armature 0.1, 1e6 N/m, a fixed contact_damping of 1e3 N s/m (under-damped), implicitfast",
               {"armature": 0.1, **at_1e6, "contact_damping": 1e3}, "implicitfast", halving[:8]),
              ("no armature, 1e6 N/m, the critical damper (at least 4 k h), RK4", dict(at_1e6), "RK4",
               [4e-4, 2e-4, 1e-4, 5e-5, 2.5e-5, 1.25e-5]),
              ("no armature, the contact of before (1e6 N/m, fixed 4e4 N s/m), RK4", dict(fixed), "RK4",
               [4e-4, 2e-4, 1e-4, 5e-5, 2.5e-5, 1.25e-5])]
    if args.quick:
        models = [(n, d, i, dts[:3]) for n, d, i, dts in models]
    lines = ["# Quadruped drop: convergence of genesis_lite as dt shrinks (issue #24)", "",
             "`benchmarks/quadruped_convergence.py`: the work-precision quadruped (ANYmal B dropped from 0.62 m, PD "
             "kp 100, kv 5 holding the standing pose), float64, 1 env. Base position at t = 1 s, and the largest "
             "change of the base position (norm, sampled every 0.1 s) when dt is halved: over t = 0.1 .. 1 s (the "
             "drop, the landing at ~0.2 s and the settling) and over t = 0.5 .. 1 s (standing).", ""]
    t0 = time.time()
    for name, damping, integrator, dts in models:
        lines += [f"## {name}", "", "| dt s | base z at t = 1 s (m) | change from dt x 2, t = 0.1 .. 1 s (m) | "
                  "t = 0.5 .. 1 s (m) | wall s |", "| --- | --- | --- | --- | --- |"]
        prev = None
        for dt in dts:
            t1 = time.time()
            traj, _ = run(gs, files, dt, damping, integrator=integrator)
            change = "-" if prev is None else f"{np.linalg.norm(traj - prev, axis=1).max():.2e}"
            late = "-" if prev is None else f"{np.linalg.norm(traj[4:] - prev[4:], axis=1).max():.2e}"
            lines.append(f"| {dt:g} | {traj[-1][2]:.7f} | {change} | {late} | {time.time() - t1:.1f} |")
            print(lines[-1], flush=True)
            prev = traj
        lines.append("")
    lines += ["## A foot's effective mass", "", foot_mass(gs, files), ""]
    if not args.quick:
        fine = 1e-4
        defaults = {}  # without armature
        traj, robot = run(gs, files, fine, defaults, t_end=0.5)
        start = (robot.get_qpos().clone(), robot.get_dofs_velocity().clone())
        lines += ["## Restart at t = 0.5 s (no armature, the defaults)", "",
                  f"The state of the dt = {fine:g} s run at t = 0.5 s, continued to t = 1 s with each step:", "",
                  "| dt s | base z at t = 1 s (m) |", "| --- | --- |"]
        for dt in (4e-4, fine):
            tr, _ = run(gs, files, dt, defaults, start=start, t_end=0.5)
            lines.append(f"| {dt:g} | {tr[-1][2]:.6f} |")
            print(lines[-1], flush=True)
        lines.append("")
    lines.append(f"Total wall time {time.time() - t0:.0f} s.")
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
