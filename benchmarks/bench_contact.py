"""Contact: stepping speed of a quadruped on the ground against MuJoCo, the cost of collision in a scene
without collision pairs, and a stability stress table.

    python benchmarks/bench_contact.py [--quick] [--envs 1024] [--precision 64] [--skip-stress] [--plot out.png] [--json out.json]

Speed scene (same for both engines): example-robot-data's ANYmal B (URDF with its box, cylinder and
sphere collision shapes, 41 geoms) with a free base on a ground plane, every robot geom against the
plane (no self-collision), PD position control of the 12 joints holding the standing pose (kp 100,
kv 5), dt = 0.01 s, implicit-in-PD integrator (genesis_lite's implicitfast, MuJoCo's
implicitfast), starting from a pose settled on the ground. MuJoCo loads the same URDF (visuals
dropped, fixed links fused, non-positive-definite dummy inertias diagonalised) and gets a floor plane,
a free joint and position actuators. Rates are medians of 5 repeats:
- 1 env: steps/s of a Python loop of `scene.step()` / `mujoco.mj_step`;
- N envs: env-steps/s of `scene.step()` on `build(n_envs=N)` / `mujoco.rollout.rollout` (2 threads).
  The genesis_lite child also runs MuJoCo's rollout itself, alternating run for run, and reports the
  median of the per-pair ratios ("paired ratio"): this machine's load changes within a run.

No collision pairs: the same robot without a ground plane, built with RigidOptions(enable_collision=True)
and =False; the solver compiles no contact stages when no two geoms can touch, so both step equally fast.

Stress (each in its own genesis_lite scene, defaults unless said): 10,000 steps of the quadruped under
random PD targets; a 1,000 kg box on a 1 kg box; the 30-link chain (assets/urdf/chain30.urdf) falling on
the ground (substeps=4: at dt = 0.01 its free swing diverges without contact too, as in MuJoCo); a
sphere hitting the ground at 20 m/s. Each genesis_lite measurement runs in one child process.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parents[1]))  # genesis_lite without an install
from common import Timer, find_robots_dir, median_rate, plot_rates, print_table, run_python  # noqa: E402

DT = 0.01
# MuJoCo's implicitfast treats a position actuator's kv implicitly but its kp explicitly: with kp = 300
# the light shanks are marginal at dt = 0.01 (h sqrt(kp / I) ~ 1.4) and its robot hops with intermittent
# contacts. At these gains both engines' robots stand on the ground with their feet in contact.
KP, KV = 100.0, 5.0
BASE_Z = 0.62  # m, where the robot is dropped from before settling
REPO = Path(__file__).resolve().parents[1]


def anymal_urdf() -> Path:
    return find_robots_dir() / "anymal_b_simple_description" / "robots" / "anymal.urdf"


def standing_pose(joint_names):
    """ANYmal's standing pose: HAA 0, HFE +-0.4, KFE -+0.8 (front legs bend one way, hind legs the other)."""
    q = []
    for n in joint_names:
        front = n[1] == "F"
        q.append(0.0 if "HAA" in n else (0.4 if front else -0.4) if "HFE" in n else (-0.8 if front else 0.8))
    return np.array(q)


# --- MuJoCo ----------------------------------------------------------------------------------------


def mujoco_quadruped(urdf: Path):
    """MuJoCo model of the quadruped on a floor: (model, joint names in qpos order)."""
    import mujoco

    tree = ET.parse(urdf)
    root = tree.getroot()
    for link in root.findall("link"):
        for e in link.findall("visual"):
            link.remove(e)
    for ine in root.iter("inertia"):
        keys = (("ixx", "ixy", "ixz"), ("ixy", "iyy", "iyz"), ("ixz", "iyz", "izz"))
        inertia = np.array([[float(ine.get(a, 0)) for a in row] for row in keys])
        if np.linalg.eigvalsh(inertia).min() <= 0:  # the file's 1e-6 dummy inertias are singular
            for a in ("ixy", "ixz", "iyz"):
                ine.set(a, "0")
    mj = ET.SubElement(root, "mujoco")
    ET.SubElement(mj, "compiler", {"discardvisual": "true", "fusestatic": "true", "balanceinertia": "true",
                                   "meshdir": str(urdf.parent)})
    tmp = Path(tempfile.mkdtemp(prefix="bench_contact_")) / "robot.urdf"
    tree.write(tmp, encoding="unicode")
    spec = mujoco.MjSpec.from_file(str(tmp))
    base = spec.worldbody.first_body()
    base.add_freejoint()
    base.pos = [0.0, 0.0, BASE_Z]
    for g in spec.geoms:  # robot geoms touch the floor only, as genesis_lite without self-collision
        g.contype, g.conaffinity = 1, 0
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], contype=1, conaffinity=1)
    names = []
    for j in spec.joints:
        if j.type == mujoco.mjtJoint.mjJNT_HINGE:
            a = spec.add_actuator()
            a.target, a.trntype = j.name, mujoco.mjtTrn.mjTRN_JOINT
            a.set_to_position(kp=KP, kv=KV)
            names.append(j.name)
    m = spec.compile()
    m.opt.timestep = DT
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    return m, names


def mujoco_settled(m, q0):
    import mujoco

    d = mujoco.MjData(m)
    d.qpos[7:] = q0
    d.ctrl[:] = q0
    for _ in range(200):
        mujoco.mj_step(m, d)
    return d


def mujoco_rates(urdf, n_envs, steps_1, steps_b, threads, repeats):
    import mujoco
    from mujoco import rollout

    m, names = mujoco_quadruped(urdf)
    q0 = standing_pose(names)
    d0 = mujoco_settled(m, q0)
    d = mujoco.MjData(m)

    def once():
        mujoco.mj_copyData(d, m, d0)
        with Timer() as t:
            for _ in range(steps_1):
                mujoco.mj_step(m, d)
        assert np.all(np.isfinite(d.qpos)), "MuJoCo diverged"
        return t.seconds

    once()
    r1 = median_rate(once, steps_1, repeats)
    once_b, shutdown = mujoco_rollout_runner(urdf, n_envs, steps_b, threads)
    try:
        once_b()
        rb = median_rate(once_b, n_envs * steps_b, repeats)
    finally:
        shutdown()
    return {"rate_1": r1, "rate_b": rb, "ncon": d0.ncon, "version": mujoco.__version__}


def mujoco_rollout_runner(urdf, n_envs, steps_b, threads):
    """(once, shutdown): once() runs mujoco.rollout.rollout of n_envs quadrupeds settled on the ground
    for steps_b steps on `threads` threads and returns its seconds; shutdown() ends its thread pool."""
    import mujoco
    from mujoco import rollout

    m, names = mujoco_quadruped(urdf)
    q0 = standing_pose(names)
    d0 = mujoco_settled(m, q0)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    s0 = np.empty(mujoco.mj_stateSize(m, spec))
    mujoco.mj_getState(m, d0, s0, spec)
    init = np.tile(s0, (n_envs, 1))
    ctrl = np.tile(q0, (n_envs, steps_b, 1))
    datas = [mujoco.MjData(m) for _ in range(threads)]
    out = np.empty((n_envs, steps_b, s0.size))

    def once_b():
        with Timer() as t:
            rollout.rollout(m, datas, init, ctrl, nstep=steps_b, state=out, persistent_pool=True)
        assert np.all(np.isfinite(out[:, -1])), "MuJoCo rollout diverged"
        return t.seconds

    return once_b, rollout.shutdown_persistent_pool


# --- genesis_lite (child process: --worker) ---------------------------------------------------------


def _gl_quadruped(gs, n_envs, plane=True, collision=True):
    import torch

    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT),
                     rigid_options=gs.options.RigidOptions(integrator=gs.integrator.implicitfast,
                                                           enable_collision=collision))
    if plane:
        scene.add_entity(gs.morphs.Plane())
    robot = scene.add_entity(gs.morphs.URDF(file=str(anymal_urdf()), fixed=False, pos=(0.0, 0.0, BASE_Z),
                                            default_armature=None))  # MuJoCo reads the URDF without
    scene.build(n_envs=n_envs)
    names = [j.name for j in robot.joints if j.n_dofs == 1]
    dofs = [j.dof_start_local for j in robot.joints if j.n_dofs == 1]
    q0 = torch.as_tensor(standing_pose(names), dtype=gs.tc_float)
    robot.set_dofs_kp(torch.full((len(dofs),), KP, dtype=gs.tc_float), dofs)
    robot.set_dofs_kv(torch.full((len(dofs),), KV, dtype=gs.tc_float), dofs)
    robot.set_dofs_position(q0, dofs)
    robot.control_dofs_position(q0, dofs)
    for _ in range(200):
        scene.step()
    return scene, robot, dofs, q0


def worker_speed(n_envs, steps_1, steps_b, repeats, paired_threads=0, precision="64"):
    """genesis_lite's rates; with paired_threads > 0 the batched one alternates run for run with MuJoCo's
    rollout on that many threads in this process (both under the same load; see bench_rigid.py)."""
    import statistics

    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision=precision)
    out = {}
    with Timer() as tb:
        scene, robot, dofs, q0 = _gl_quadruped(gs, 0)
    out["build_1"] = tb.seconds
    out["rate_1"] = _gl_rate_ctrl(scene, robot, dofs, q0, scene.get_state(), steps_1, 0, repeats)
    c = scene.rigid_solver.contact
    out["slots"] = c.n_slots
    out["ncon"] = int((c.read()["fn"][0] > 0).sum())
    with Timer() as tb:
        scene_b, robot_b, _, _ = _gl_quadruped(gs, n_envs)
    out["build_b"] = tb.seconds
    state_b = scene_b.get_state()
    if not paired_threads:
        out["rate_b"] = _gl_rate_ctrl(scene_b, robot_b, dofs, q0, state_b, steps_b, n_envs, repeats)
    else:
        gl_once = _gl_once_ctrl(scene_b, robot_b, dofs, q0, state_b, steps_b)
        mj_once, shutdown = mujoco_rollout_runner(anymal_urdf(), n_envs, steps_b, paired_threads)
        try:
            gl_once()
            mj_once()
            pairs = [(mj_once(), gl_once()) for _ in range(2 * repeats)]
        finally:
            shutdown()
        n = n_envs * steps_b
        out["rate_b"] = statistics.median(n / g for _, g in pairs)
        out["mj_rate_b"] = statistics.median(n / m for m, _ in pairs)
        out["paired_ratio"] = statistics.median(m / g for m, g in pairs)
    # no collision pairs: the robot alone, collision on and off
    for key, coll in (("nopair_on", True), ("nopair_off", False)):
        s, r, d, q = _gl_quadruped(gs, 0, plane=False, collision=coll)
        out[key] = _gl_rate_ctrl(s, r, d, q, s.get_state(), steps_1, 0, repeats)
        out[key + "_stages"] = len(s.rigid_solver.dynamics_stages)
        out[key + "_contact"] = s.rigid_solver.contact is not None
    return out


def _gl_once_ctrl(scene, robot, dofs, q0, state, n_steps):
    def once():
        scene.reset(state)
        robot.control_dofs_position(q0, dofs)
        with Timer() as t:
            for _ in range(n_steps):
                scene.step()
        return t.seconds

    return once


def _gl_rate_ctrl(scene, robot, dofs, q0, state, n_steps, n_envs, repeats):
    once = _gl_once_ctrl(scene, robot, dofs, q0, state, n_steps)
    once()
    return median_rate(once, max(n_envs, 1) * n_steps, repeats)


def worker_stress(quadruped_steps):
    """The stress scenarios; returns rows for the table."""
    import genesis_lite as gs
    import torch

    gs.init(backend=gs.cpu, precision="64")
    rows = []
    f = gs.tc_float
    # quadruped under random PD targets
    with Timer() as t:
        scene, robot, dofs, q0 = _gl_quadruped(gs, 0)
        rng = np.random.default_rng(0)
        zmin, vmax, pen = 1e9, 0.0, 0.0
        c = scene.rigid_solver.contact
        for i in range(quadruped_steps):
            if i % 50 == 0:
                robot.control_dofs_position(q0 + torch.as_tensor(rng.uniform(-0.5, 0.5, len(dofs)), dtype=f), dofs)
            scene.step()
            if i % 10 == 0:
                zmin = min(zmin, float(robot.get_pos()[2]))
                vmax = max(vmax, float(robot.get_dofs_velocity().abs().max()))
                r = c.read()
                on = r["fn"][0] > 0
                pen = max(pen, float(r["depth"][0][on].max()) if on.any() else 0.0)
    rows.append({"scenario": f"ANYmal, {quadruped_steps} steps of random PD targets (+-0.5 rad every 0.5 s)",
                 "finite": bool(torch.isfinite(robot.get_qpos()).all()),
                 "figures": f"base z >= {zmin:.3f} m, max |qvel| {vmax:.1f}, max penetration {pen * 1e3:.2f} mm",
                 "seconds": t.seconds})
    # a 1,000 kg box on a 1 kg box
    with Timer() as t:
        scene = gs.Scene()
        scene.add_entity(gs.morphs.Plane())
        light = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)), material=gs.materials.Rigid(rho=125.0))
        heavy = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.305)),
                                 material=gs.materials.Rigid(rho=125000.0))
        scene.build()
        for _ in range(1000):
            scene.step()
        zl, zh = float(light.get_pos()[2]), float(heavy.get_pos()[2])
        v = max(float(light.get_vel().abs().max()), float(heavy.get_vel().abs().max()))
    rows.append({"scenario": "1,000 kg box dropped 5 mm onto a 1 kg box, 1,000 steps",
                 "finite": bool(np.isfinite([zl, zh]).all()),
                 "figures": f"light box in ground {(0.1 - zl) * 1e3:.2f} mm, heavy in light {(0.3 - zh + zl - 0.1) * 1e3:.2f} mm, "
                            f"final |v| {v:.1e} m/s",
                 "seconds": t.seconds})
    # the 30-link chain falling on the ground
    with Timer() as t:
        scene = gs.Scene(sim_options=gs.options.SimOptions(substeps=4))
        scene.add_entity(gs.morphs.Plane())
        chain = scene.add_entity(gs.morphs.URDF(file=str(REPO / "assets" / "urdf" / "chain30.urdf"), fixed=False,
                                                pos=(0, 0, 3.2), default_armature=None))
        scene.build()
        e0 = float(chain.get_total_energy())
        emax, zmin = e0, 1e9
        for _ in range(1000):
            scene.step()
            emax = max(emax, float(chain.get_total_energy()))
            zmin = min(zmin, float(chain.get_links_pos()[:, 2].min()))
        e1 = float(chain.get_total_energy())
    rows.append({"scenario": "30-link chain falling 0.2 m onto the ground (substeps=4), 1,000 steps",
                 "finite": bool(np.isfinite(e1)),
                 "figures": f"energy {e0:.1f} J -> max {emax:.1f} J -> {e1:.2f} J at rest, lowest link origin {zmin * 1e3:.1f} mm",
                 "seconds": t.seconds})
    # a sphere at 20 m/s
    with Timer() as t:
        zmins, ups = [], []
        for z0 in (0.39, 0.45, 0.5):  # the step lands at different depths
            scene = gs.Scene()
            scene.add_entity(gs.morphs.Plane())
            ball = scene.add_entity(gs.morphs.Sphere(radius=0.1, pos=(0, 0, z0)))
            scene.build()
            ball.set_dofs_velocity(torch.tensor([0, 0, -20.0, 0, 0, 0], dtype=f))
            zmin, up = 1e9, 0.0
            for _ in range(200):
                scene.step()
                zmin = min(zmin, float(ball.get_pos()[2]))
                up = max(up, float(ball.get_vel()[2]))
            zmins.append(zmin)
            ups.append(up)
    rows.append({"scenario": "sphere r = 0.1 m hitting the ground at 20 m/s (3 landing phases)",
                 "finite": bool(np.isfinite(zmins).all()),
                 "figures": f"lowest centre {min(zmins) * 1e3:.1f} mm (no tunnelling: > -100), max rebound {max(ups):.2f} m/s",
                 "seconds": t.seconds})
    return {"rows": rows}


def _worker_main(argv):
    ap = argparse.ArgumentParser()
    ap.add_argument("--worker", required=True, choices=["speed", "stress"])
    ap.add_argument("--envs", type=int, default=1024)
    ap.add_argument("--steps1", type=int, default=1000)
    ap.add_argument("--stepsb", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--qsteps", type=int, default=10000)
    ap.add_argument("--paired-threads", type=int, default=0)
    ap.add_argument("--precision", default="64")
    a = ap.parse_args(argv)
    if a.worker == "speed":
        res = worker_speed(a.envs, a.steps1, a.stepsb, a.repeats, a.paired_threads, a.precision)
    else:
        res = worker_stress(a.qsteps)
    print(json.dumps(res), flush=True)


def _child(worker, **kw):
    args = [str(Path(__file__).resolve()), "--worker", worker]
    for k, v in kw.items():
        args += [f"--{k}", str(v)]
    return run_python(args, timeout=3600)


def main():
    if "--worker" in sys.argv:
        return _worker_main(sys.argv[1:])
    ap = argparse.ArgumentParser(description="genesis_lite contact: quadruped speed vs MuJoCo, stress table")
    ap.add_argument("--quick", action="store_true", help="fewer steps (a smoke run)")
    ap.add_argument("--envs", type=int, default=1024)
    ap.add_argument("--threads", type=int, default=2, help="MuJoCo rollout threads")
    ap.add_argument("--precision", default="64", choices=["32", "64"], help="genesis_lite float precision (speed table)")
    ap.add_argument("--skip-stress", action="store_true")
    ap.add_argument("--plot", type=Path, default=None, help="write a bar chart PNG (needs matplotlib)")
    ap.add_argument("--json", type=Path, default=None, help="write the results as JSON")
    args = ap.parse_args()
    steps_1 = 200 if args.quick else 1000
    steps_b = 20 if args.quick else 100
    repeats = 3 if args.quick else 5
    urdf = anymal_urdf()
    t0 = time.time()
    print("MuJoCo ...", flush=True)
    mj = mujoco_rates(urdf, args.envs, steps_1 * 5, steps_b, args.threads, repeats)
    print("genesis_lite ...", flush=True)
    gl, err = _child("speed", envs=args.envs, steps1=steps_1, stepsb=steps_b, repeats=repeats,
                     precision=args.precision, **{"paired-threads": args.threads})
    rows = [
        {"engine": f"MuJoCo {mj['version']} mj_step loop", "envs": 1, "rate": mj["rate_1"], "ratio": 1.0,
         "note": f"{mj['ncon']} contacts"},
        {"engine": f"MuJoCo rollout ({args.threads} threads)", "envs": args.envs, "rate": mj["rate_b"], "ratio": 1.0},
    ]
    if gl:
        rows += [
            {"engine": f"genesis_lite (f{args.precision}, CPU)", "envs": 1, "rate": gl["rate_1"], "ratio": gl["rate_1"] / mj["rate_1"],
             "note": f"{gl['ncon']} contacts of {gl['slots']} slots; build {gl['build_1']:.1f} s"},
            {"engine": f"genesis_lite (f{args.precision}, CPU)", "envs": args.envs, "rate": gl["rate_b"],
             "ratio": gl["rate_b"] / mj["rate_b"], "paired": gl.get("paired_ratio"),
             "note": f"build {gl['build_b']:.1f} s; paired with MuJoCo's rollout in its process: "
                     f"{gl['paired_ratio']:.2f}x (MuJoCo {gl['mj_rate_b']:,.0f} there)"},
        ]
    else:
        rows.append({"engine": "genesis_lite", "envs": 1, "note": err})
    print_table(rows, [("engine", "engine", ""), ("envs", "envs", "d"), ("rate", "steps/s (env-steps/s)", ",.0f"),
                       ("ratio", "ratio to MuJoCo", ".2f"), ("paired", "paired ratio", ".2f"), ("note", "note", "")],
                title=f"ANYmal standing on the ground under PD, dt={DT}, median of {repeats} ({time.time() - t0:.0f} s)")
    nopair = []
    if gl:
        for key, label in (("nopair_on", "enable_collision=True"), ("nopair_off", "enable_collision=False")):
            nopair.append({"scene": f"ANYmal, no ground ({label})", "rate": gl[key],
                           "stages": gl[key + "_stages"], "contact": "yes" if gl[key + "_contact"] else "none",
                           "ratio": gl[key] / gl["nopair_off"]})
        print_table(nopair, [("scene", "scene", ""), ("contact", "contact solver", ""),
                             ("stages", "dynamics stages", "d"), ("rate", "steps/s", ",.0f"),
                             ("ratio", "ratio to collision off", ".2f")],
                    title="A scene without collision pairs launches no collision work")
    stress = []
    if not args.skip_stress:
        print("\nstress ...", flush=True)
        res, err = _child("stress", qsteps=1000 if args.quick else 10000)
        stress = res["rows"] if res else [{"scenario": "stress", "figures": err}]
        print_table(stress, [("scenario", "scenario", ""), ("finite", "finite", ""), ("figures", "figures", ""),
                             ("seconds", "wall s", ".1f")], title="Stability stress (genesis_lite defaults, dt = 0.01 s)")
    if args.json:
        args.json.write_text(json.dumps({"speed": rows, "no_pairs": nopair, "stress": stress}, indent=2))
    if args.plot:
        plot_rates(rows, args.plot, f"ANYmal on the ground under PD, dt={DT}")


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
