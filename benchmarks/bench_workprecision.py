"""Work-precision: run time against error for each integrator of genesis_lite, MuJoCo and real Genesis.

    python benchmarks/bench_workprecision.py [--quick] [--scenes pendulum,panda] [--envs 1024] [--no-genesis]

For every scene (the registry SCENES; a row is pluggable: an entry whose engine is missing says why and is
skipped), every engine and every integrator (gs.integrator.Euler / implicitfast / RK4, MuJoCo's Euler /
implicitfast / RK4, Genesis's Euler / implicitfast), the harness sweeps the time step dt and the substeps,
runs the scene for t_end seconds of simulated time and records
- the error: max abs difference of the scene's observables (joint angles, positions) at its sample times
  from a tight reference the table names (an analytic solution, Pinocchio + DOP853, or the same engine in
  float64 at a far smaller dt, with that reference's own change when its dt is halved);
- the wall time of the stepping loop (build, compile, resets and reads of the observables excluded): the
  median of `repeats` runs (one run when the first takes over LONG_RUN_S). genesis_lite: a Python loop of
  scene.step(); MuJoCo: mujoco.rollout (C loop; 1 thread for 1 env, 2 threads for the batch); Genesis: a Python
  loop of scene.step().
A scene's error is the mean over its environments of each one's error. Most scenes start every environment
from the same state; the quadrupeds start them from QUAD_STARTS different ones (env i from start i % 16, start 0
the one-env row's), each measured against its own reference, so that one start whose error happens to cross
zero at the sample times (a contact scene's error swings in sign as the gait settles) does not set an engine's
front alone.

Each genesis_lite sweep runs in a child process (one gs.init per process); Genesis runs in its own venv
(peer_genesis_wp.py). run_all.py calls `run()` and writes the tables and plots.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import json
import math
import os
import statistics
import sys
import tempfile
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(HERE.parent))  # genesis_lite without an install
from common import Timer, genesis_python, print_table, progress, pyplot, run_python, save_figure  # noqa: E402
import scenes as S  # noqa: E402

INTEGRATORS = ("Euler", "implicitfast", "RK4")
GENESIS_INTEGRATORS = ("Euler", "implicitfast")  # Genesis 1.4.5 has no RK4
LONG_RUN_S = 20.0  # a run whose first timing exceeds this is timed once (its median of one): the noise of a
# run that long is a few per cent, and the deep sweeps' runs of minutes would otherwise cost three times as much
MJ_CHUNK = 200  # steps per mujoco.rollout call: bounds the state output array (n_envs x chunk x nstate)
DIVERGED = 1e3  # an error above this (rad or m) is a blown-up run, whatever its floats say
ERR_CAP = 0.1  # equal-error comparisons only at errors <= 0.1 (rad or m): larger ones are no useful accuracy
PANDA_T = 0.5  # s: the free swing folds the arm with up to 25 rad/s by then (40 rad/s at 1 s: chaotic)


# --- the sweep ---------------------------------------------------------------------------------------------


def sweep(engine: str, batched: bool, quick: bool, deep: int = 0) -> list[tuple[str, float, int]]:
    """(integrator, dt, substeps) points. Full: dt halves from 0.02 s (to 0.625 ms for first-order methods in
    1 env, 1.25 ms batched, 2.5 ms for RK4, whose error is far smaller), plus dt = 0.02 s with the substeps that
    give each of those steps (2, 4, 8, ...; until 2026-12-06 only 4 and 16): the same numbers for fewer steps,
    which at 1,024 envs is much cheaper than the Python-level steps alone would say: one step is one launch over
    every env, and each launch streams every env's working set through the caches (the quadruped at 2.5 ms,
    1,024 envs: 400 steps 2.6 s, 50 steps of 8 substeps 1.6 s; at 64 envs the same time); MuJoCo's rollout
    runs each env's steps back to back already. --deep: that many more halvings.
    Genesis: Euler and implicitfast only; its build is slow, so a shorter dt range. Quick: dt = 0.02 and 0.005 s."""
    pts = []
    integs = GENESIS_INTEGRATORS if engine == "genesis" else INTEGRATORS
    for integ in integs:
        if quick:
            dts, subs = [0.02, 0.005], []
        elif engine == "genesis":
            dts, subs = [0.01, 0.005, 0.0025, 0.00125], []
        else:
            n = (4 if integ == "RK4" else (5 if batched else 6)) + deep
            dts = [0.02 / 2**k for k in range(n)]
            subs = [] if engine == "mujoco" else [2**k for k in range(1, n)]
        pts += [(integ, dt, 1) for dt in dts] + [(integ, 0.02, s) for s in subs]
    return pts


# --- scenes ------------------------------------------------------------------------------------------------


@dataclass
class Reference:
    kind: str  # "analytic", "pinocchio" or "fine"
    label: str
    obs: Optional[list] = None  # the reference observables, or None for kind "fine" (each engine runs its own)
    fine: Optional[tuple] = None  # (integrator, dt) of the fine float64 run
    check: Optional[tuple] = None  # (integrator, dt) of a second fine run: its difference bounds the reference's error


@dataclass
class WPScene:
    """One row of the work-precision study. files(tmp) writes what every engine reads and returns a dict of
    paths; reference(files) gives the tight reference; gl_build / mj_build set the scene up per engine."""

    key: str
    title: str
    t_end: float  # s
    sample_times: tuple  # s, multiples of every dt of the sweep
    error_label: str
    files: Callable
    reference: Callable
    gl_build: Optional[Callable] = None  # (gs, files, integrator, dt, substeps, n_envs) -> (scene, reset, observe)
    # (files, integrator, dt) -> (model, qpos0, qvel0, observe(states), controls held or None)
    mj_build: Optional[Callable] = None
    genesis: bool = False  # peer_genesis_wp.py knows the scene
    available: Callable = field(default=lambda: None)  # -> None, or the reason the row cannot run yet
    note: str = ""
    sweep: Optional[Callable] = None  # (engine, batched, quick) -> points; None: the module's sweep() of integrators
    batched: bool = True  # False: 1 env only (the batched run would cost too much for what it adds)
    quick_reference: Optional[Callable] = None  # --quick's (cheaper) reference, named in its table
    starts: int = 1  # distinct initial states: env i starts from start i % starts (the builders set them)


def _gl_tile(x, n_envs, dtype):
    import torch

    t = torch.as_tensor(np.asarray(x, dtype=float), dtype=dtype)
    return t.unsqueeze(0).repeat(n_envs, 1) if n_envs else t


# RigidOptions fields (JSON) every genesis_lite build sets (rigid_options, --rigid): in the environment, so that the
# worker processes (run_gl) see them too
RIGID_ENV = "GS_WP_RIGID"


def _gl_opts(gs, integrator, dt, substeps, collision, limits=True):
    extra = json.loads(os.environ.get(RIGID_ENV) or "{}")
    return dict(sim_options=gs.options.SimOptions(dt=dt, substeps=substeps, gravity=(0.0, 0.0, -S.G)),
                rigid_options=gs.options.RigidOptions(integrator=getattr(gs.integrator, integrator),
                                                      enable_collision=collision, enable_joint_limit=limits, **extra))


@contextlib.contextmanager
def rigid_options(**fields):
    """The genesis_lite builders called inside, in this process or in the workers it starts, set these RigidOptions
    fields too (contact_damping=1e4, say): the convergence studies' variations of a scene, and --rigid."""
    before = os.environ.get(RIGID_ENV)
    os.environ[RIGID_ENV] = json.dumps({**json.loads(before or "{}"), **fields})
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(RIGID_ENV, None)
        else:
            os.environ[RIGID_ENV] = before


def _gl_build_arm(urdf_key, q0, v0):
    """genesis_lite builder of a fixed-base arm without collisions or joint limits, started at (q0, v0)."""

    def build(gs, files, integrator, dt, substeps, n_envs):
        scene = gs.Scene(**_gl_opts(gs, integrator, dt, substeps, collision=False, limits=False))
        robot = scene.add_entity(gs.morphs.URDF(file=str(files[urdf_key]), fixed=True))
        scene.build(n_envs=n_envs)
        n = robot.n_dofs
        robot.set_dofs_damping(np.zeros(n))
        robot.set_dofs_armature(np.zeros(n))
        robot.set_dofs_frictionloss(np.zeros(n))
        robot.set_dofs_position(_gl_tile(q0, n_envs, gs.tc_float))
        robot.set_dofs_velocity(_gl_tile(v0, n_envs, gs.tc_float))
        state = scene.get_state()

        def reset():
            scene.reset(state)

        def observe():
            return robot.get_dofs_position().detach().cpu().numpy().reshape(max(n_envs, 1), -1)

        return scene, reset, observe

    return build


def _mj_build_arm(urdf_key, q0, v0):
    def build(files, integrator, dt):
        m = S.mujoco_from_urdf(files[urdf_key], limits=False, contacts=False)
        S.set_mujoco_integrator(m, integrator, dt)
        qs, _ = S.mujoco_state_slices(m)
        return m, np.asarray(q0, float), np.asarray(v0, float), lambda st: st[:, qs], None

    return build


def _pinocchio_reference(urdf_key, q0, v0, t_end):
    """q(t_end) of DOP853 (rtol = atol = 1e-12) on Pinocchio's forward dynamics (crba + rnea) of the URDF."""

    def ref(files):
        import pinocchio as pin
        from scipy.integrate import solve_ivp

        model = pin.buildModelFromUrdf(str(files[urdf_key]))
        model.gravity = pin.Motion(np.array([0.0, 0.0, -S.G]), np.zeros(3))
        data = model.createData()
        n = model.nv
        assert model.nq == n, "the reference assumes 1-dof joints"

        def rhs(t, y):
            q, v = y[:n], y[n:]
            M = pin.crba(model, data, q)
            M = np.triu(M) + np.triu(M, 1).T
            b = pin.rnea(model, data, q, v, np.zeros(n))
            return np.concatenate([v, np.linalg.solve(M, -b)])

        sol = solve_ivp(rhs, (0.0, t_end), np.concatenate([q0, v0]), method="DOP853", rtol=1e-12, atol=1e-12)
        assert sol.success, sol.message
        loose = solve_ivp(rhs, (0.0, t_end), np.concatenate([q0, v0]), method="DOP853", rtol=1e-10, atol=1e-10)
        names = [model.names[j] for j in range(1, model.njoints)]
        return Reference("pinocchio", "Pinocchio 3 crba/rnea + scipy DOP853, rtol = atol = 1e-12 "
                         f"(differs from rtol 1e-10 by {np.abs(loose.y[:n, -1] - sol.y[:n, -1]).max():.1e} rad)",
                         obs=sol.y[:n, -1].tolist()), names

    return ref


# double pendulum ---------------------------------------------------------------------------------------------


def _pendulum_files(tmp):
    return {"urdf": S.PENDULUM_URDF}


def _pendulum_ref(files):
    r, names = _pinocchio_reference("urdf", S.PENDULUM_Q0, S.PENDULUM_V0, 1.0)(files)
    assert names == ["joint1", "joint2"]
    return r


# Panda ---------------------------------------------------------------------------------------------------------


def _panda_files(tmp):
    return {"urdf": S.write_panda_arm(tmp)}


def _panda_ref(files):
    r, names = _pinocchio_reference("urdf", S.PANDA_ARM_HOME, np.zeros(7), PANDA_T)(files)
    assert names == [f"panda_joint{i}" for i in range(1, 8)], names
    return r


# box sliding to rest --------------------------------------------------------------------------------------------

BOX_SAMPLES = (0.2, 1.0)  # s: mid-slide, and at rest (the box stops at v0 / (mu g) = 0.41 s)


def _box_files(tmp):
    return {"urdf": S.write_box_urdf(tmp)}


def _box_ref(files):
    return Reference("analytic", f"analytic Coulomb sliding x(t) = v0 t - mu g t^2 / 2 until v = 0 (v0 = {S.BOX_V0} m/s, "
                     f"mu = {S.BOX_MU}), at t = {BOX_SAMPLES} s", obs=S.box_slide_analytic(BOX_SAMPLES).tolist())


def _gl_build_box(gs, files, integrator, dt, substeps, n_envs):
    scene = gs.Scene(**_gl_opts(gs, integrator, dt, substeps, collision=True))
    mat = gs.materials.Rigid(friction=S.BOX_MU)
    scene.add_entity(gs.morphs.Plane(), material=mat)
    box = scene.add_entity(gs.morphs.URDF(file=str(files["urdf"]), fixed=False, pos=(0.0, 0.0, S.BOX_SIZE / 2)),
                           material=mat)
    scene.build(n_envs=n_envs)
    box.set_dofs_velocity(_gl_tile([S.BOX_V0, 0, 0, 0, 0, 0], n_envs, gs.tc_float))
    state = scene.get_state()

    def reset():
        scene.reset(state)

    def observe():
        return box.get_pos().detach().cpu().numpy().reshape(max(n_envs, 1), 3)[:, :1]

    return scene, reset, observe


def _mj_build_box(files, integrator, dt):
    m = S.mujoco_from_urdf(files["urdf"], free=True, floor_mu=S.BOX_MU)
    S.set_mujoco_integrator(m, integrator, dt)
    qs, _ = S.mujoco_state_slices(m)
    q0 = np.array([0.0, 0.0, S.BOX_SIZE / 2, 1.0, 0.0, 0.0, 0.0])
    v0 = np.array([S.BOX_V0, 0, 0, 0, 0, 0])
    return m, q0, v0, lambda st: st[:, qs][:, :1], None


# quadruped dropped on the ground --------------------------------------------------------------------------------

QUAD_REF = ("RK4", 1e-4)
QUAD_ARMATURE = 0.1  # kg m^2: Genesis's default_armature, genesis_lite's since 2026-11-28
QUAD_REF_CHECK = ("RK4", 2e-4)
# the base position every 0.1 s from t = 0.5 s (standing; the drop lands at ~0.2 s), not at t = 1 s alone: at rest
# one sample's error swings with the phase of the settling (2026-12-01, the armature row: ours, implicitfast,
# 1.2e-5 m at dt = 20 ms and 3e-4 m at 5 ms; MuJoCo's RK4 1.7e-7 m at 10 ms and 6.3e-5 m at 5 ms), so that lucky
# runs set an engine's front. Samples before the landing measure the free fall alone, where the two engines'
# Euler steps are the same algorithm (the same errors to four digits at t = 0.1 s, 0.49 dt m)
QUAD_SAMPLES = tuple(round(0.1 * k, 10) for k in range(5, 11))
# Even so, one start's error at the six samples can be small by chance (2026-12-02, the armature row: MuJoCo's RK4
# at 10 ms 4.9e-6 m where its 5 and 2.5 ms runs gave 7.0e-5 and 1.0e-4 m, and that one run set MuJoCo's front
# below 7e-5 m). So the batched rows start 16 drops (quad_starts), and the error is the mean of theirs.
QUAD_STARTS = 16
QUAD_ERROR = (f"max over t = 0.5, 0.6 .. 1 s of norm(base pos - ref) (m); batched: the mean over the envs, which start "
              f"from {QUAD_STARTS} different drops, of each one's against its own reference")


def quad_starts(joint_names, n):
    """n initial states of the drop: (base positions (n, 3), base quaternions w x y z (n, 4), joint angles
    (n, 12)). Start 0 is the scene's own (level, at BASE_Z, the standing pose); the others move it by a seeded
    draw: height +-3 cm, roll and pitch +-0.1 rad, yaw +-pi, each joint +-0.1 rad (all within the joint limits;
    the feet stay clear of the floor)."""
    from bench_contact import BASE_Z, standing_pose
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(20261205)
    q0 = standing_pose(joint_names)
    pos = np.tile([0.0, 0.0, BASE_Z], (n, 1))
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    q = np.tile(q0, (n, 1))
    for i in range(1, n):
        pos[i, 2] += rng.uniform(-0.03, 0.03)
        xyzw = Rotation.from_euler("xyz", rng.uniform([-0.1, -0.1, -np.pi], [0.1, 0.1, np.pi])).as_quat()
        quat[i] = np.roll(xyzw, 1)
        q[i] += rng.uniform(-0.1, 0.1, len(q0))
    return pos, quat, q


def _quad_files(tmp):
    return {"urdf": S.write_anymal(tmp)}


def _quad_ref(files):
    return Reference("fine", f"the same engine, float64, {QUAD_REF[0]} at dt = {QUAD_REF[1]:g} s "
                     f"(its difference from dt = {QUAD_REF_CHECK[1]:g} s is shown as the reference's error)",
                     fine=QUAD_REF, check=QUAD_REF_CHECK)


def _gl_build_quad(gs, files, integrator, dt, substeps, n_envs, armature=None):
    """armature: None, the file's (none), as MuJoCo reads the URDF; a number, Genesis's default_armature on
    every joint (the quadruped_armature row gives MuJoCo's joints the same). Env i starts from quad_starts' i %
    QUAD_STARTS (one env: start 0)."""
    import torch
    from bench_contact import BASE_Z, KP, KV, standing_pose

    scene = gs.Scene(**_gl_opts(gs, integrator, dt, substeps, collision=True))
    scene.add_entity(gs.morphs.Plane())
    robot = scene.add_entity(gs.morphs.URDF(file=str(files["urdf"]), fixed=False, pos=(0.0, 0.0, BASE_Z),
                                            default_armature=armature))
    scene.build(n_envs=n_envs)
    names = [j.name for j in robot.joints if j.n_dofs == 1]
    dofs = [j.dof_start_local for j in robot.joints if j.n_dofs == 1]
    q0 = standing_pose(names)
    robot.set_dofs_kp(np.full(len(dofs), KP), dofs)
    robot.set_dofs_kv(np.full(len(dofs), KV), dofs)
    if n_envs:
        pos, quat, q = (torch.as_tensor(a[np.arange(n_envs) % QUAD_STARTS], dtype=gs.tc_float)
                        for a in quad_starts(names, QUAD_STARTS))
        robot.set_pos(pos)
        robot.set_quat(quat)
        robot.set_dofs_position(q, dofs)
    else:
        robot.set_dofs_position(_gl_tile(q0, n_envs, gs.tc_float), dofs)
    state = scene.get_state()
    target = _gl_tile(q0, n_envs, gs.tc_float)

    def reset():
        scene.reset(state)
        robot.control_dofs_position(target, dofs)  # reset() clears controls

    def observe():
        return robot.get_pos().detach().cpu().numpy().reshape(max(n_envs, 1), 3)

    return scene, reset, observe


def _mj_build_quad(files, integrator, dt, armature=None):
    from bench_contact import BASE_Z, mujoco_quadruped, standing_pose

    m, names = mujoco_quadruped(files["urdf"])  # the same URDF and floor; position actuators kp, kv
    if armature is not None:
        m.dof_armature[6:] = armature  # the 12 joints (the free joint's 6 dofs first)
    S.set_mujoco_integrator(m, integrator, dt)
    qs, _ = S.mujoco_state_slices(m)
    pos, quat, q = quad_starts(names, QUAD_STARTS)
    q0 = np.concatenate([pos, quat, q], axis=1)  # one row a start (run_mj: env i from row i % QUAD_STARTS)
    assert m.nq == q0.shape[1] and abs(BASE_Z - q0[0, 2]) < 1e-15
    return m, q0, np.zeros(m.nv), lambda st: st[:, qs][:, :3], standing_pose(names)  # targets held throughout


# a Panda pushing a box ---------------------------------------------------------------------------------------------

PUSH_T = 1.0  # s
PUSH_SAMPLES = (0.5, 1.0)  # s: mid-push, and after
PUSH_REF = ("RK4", 1e-4)
PUSH_REF_CHECK = ("RK4", 2e-4)


def _push_files(tmp):
    return {"arm": S.write_panda_pusher(tmp),
            "box": S.write_box_urdf(tmp, size=S.PUSH_BOX_SIZE, mass=S.PUSH_BOX_MASS, name="push_box")}


def _push_ref(files):
    return Reference("fine", f"the same engine, float64, {PUSH_REF[0]} at dt = {PUSH_REF[1]:g} s "
                     f"(its difference from dt = {PUSH_REF_CHECK[1]:g} s is shown as the reference's error)",
                     fine=PUSH_REF, check=PUSH_REF_CHECK)


def _gl_build_push(gs, files, integrator, dt, substeps, n_envs):
    """The arm (joint limits off, as in MuJoCo's model: the start pose is near joint 6's; gravity compensated, so
    that the PD holds the sphere's height) and the box on a floor, every geom of friction PUSH_MU; the PD's target
    held from the start."""
    scene = gs.Scene(**_gl_opts(gs, integrator, dt, substeps, collision=True, limits=False))
    mat = gs.materials.Rigid(friction=S.PUSH_MU)
    scene.add_entity(gs.morphs.Plane(), material=mat)
    arm = scene.add_entity(gs.morphs.URDF(file=str(files["arm"]), fixed=True),
                           material=gs.materials.Rigid(friction=S.PUSH_MU, gravity_compensation=1.0))
    box = scene.add_entity(gs.morphs.URDF(file=str(files["box"]), fixed=False, pos=S.PUSH_BOX_POS), material=mat)
    scene.build(n_envs=n_envs)
    n = arm.n_dofs
    arm.set_dofs_damping(np.zeros(n))
    arm.set_dofs_armature(np.full(n, S.PUSH_ARMATURE))
    arm.set_dofs_frictionloss(np.zeros(n))
    arm.set_dofs_kp(np.full(n, S.PUSH_KP))
    arm.set_dofs_kv(np.full(n, S.PUSH_KV))
    arm.set_dofs_position(_gl_tile(S.PUSH_Q0, n_envs, gs.tc_float))
    state = scene.get_state()
    target = _gl_tile(S.PUSH_QT, n_envs, gs.tc_float)

    def reset():
        scene.reset(state)
        arm.control_dofs_position(target)  # reset() clears controls

    def observe():
        return box.get_pos().detach().cpu().numpy().reshape(max(n_envs, 1), 3)

    return scene, reset, observe


def _mj_build_push(files, integrator, dt):
    """MuJoCo's model of the same files: the arm's sphere and the box collide with each other and the floor
    (elliptic cones, friction PUSH_MU on every geom), position actuators kp / kv on the 7 joints."""
    import mujoco

    spec = mujoco.MjSpec.from_file(str(files["arm"]))
    for j in spec.joints:
        j.limited = mujoco.mjtLimited.mjLIMITED_FALSE
    for g in spec.geoms:
        g.contype, g.conaffinity = 1, 0  # the sphere: against the floor and the box, as in genesis_lite
        g.friction = [S.PUSH_MU, g.friction[1], g.friction[2]]
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], contype=1, conaffinity=1,
                            friction=[S.PUSH_MU, 0.005, 0.0001])
    names = [j.name for j in spec.joints]
    for b in spec.bodies:
        b.gravcomp = 1.0  # the arm's links (the box comes after): full gravity compensation, as in genesis_lite
    box = S.mujoco_free_box(spec, "push_box", S.PUSH_BOX_POS, S.PUSH_BOX_SIZE, S.PUSH_BOX_MASS)
    box.geoms[0].friction = [S.PUSH_MU, 0.005, 0.0001]
    for name in names:
        a = spec.add_actuator()
        a.target, a.trntype = name, mujoco.mjtTrn.mjTRN_JOINT
        a.set_to_position(kp=S.PUSH_KP, kv=S.PUSH_KV)
    m = spec.compile()
    m.opt.gravity[:] = (0.0, 0.0, -S.G)
    m.dof_damping[:] = 0.0
    m.dof_frictionloss[:] = 0.0
    m.dof_armature[:] = 0.0
    m.dof_armature[:7] = S.PUSH_ARMATURE
    m.opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    S.set_mujoco_integrator(m, integrator, dt)
    qs, _ = S.mujoco_state_slices(m)
    q0 = np.zeros(m.nq)
    q0[:7] = S.PUSH_Q0
    q0[7:] = [*S.PUSH_BOX_POS, 1.0, 0.0, 0.0, 0.0]
    return m, q0, np.zeros(m.nv), lambda st: st[:, qs][:, 7:10], S.PUSH_QT  # targets held throughout


# elastic MPM block -------------------------------------------------------------------------------------------------
# A 0.1 m elastic cube (1,000 particles on the 0.01 m lattice, 64 cells per metre on [0, 0.5]^3), the bench's
# material (E = 3e5 Pa, nu = 0.2, rho = 1000 kg/m^3: waves at 18 m/s, so the CFL check of genesis_lite allows
# substeps up to 0.9 dx / c = 0.77 ms), thrown with a stretching and spinning velocity field under gravity: it rings
# (breathing period ~10 ms) while it falls and turns, touching no wall by t = 0.05 s. MLS-MPM has one time scheme
# (explicit symplectic Euler on the grid; gs.integrator is the rigid solver's), so the sweep is over the step and
# the substeps, labelled "Euler"; the error is that of time stepping alone: the reference runs the same particles
# on the same grid with far shorter substeps. What the row shows (measured while writing it): the spin alone
# converges at first order (error / 3.6 per substep / 4), but the elastic ringing does not converge as the substep
# shrinks at this fixed grid: the change from halving the substep grows (0.1 mm from 3 to 5 substeps of 2 ms, 0.8
# mm from 40 to 80, 1.0 mm from 320 to 640), because each particle-grid transfer damps the ringing and more
# substeps make more transfers (the swing of the cube's x extent over 50-100 ms, stretch alone: 6.7 mm with 4
# substeps, 4.7 with 32, 3.5 with 256). The reference's own error (its difference from half its substeps) is
# printed with the table and drawn on the plot.

MPM_T = 0.05  # s
MPM_SAMPLES = (0.02, 0.05)  # s: whole steps of 2 and 5 ms
MPM_STRETCH = 40.0  # 1/s: v = MPM_STRETCH * (dx, dy, -dz) about the centre (edge speeds 2 m/s, strains ~7 %)
MPM_SPIN = (3.0, -2.0, 5.0)  # rad/s
MPM_CENTRE = (0.25, 0.25, 0.3)  # m
MPM_REF = ("Euler", 2e-3, 640)  # (scheme, dt, substeps): substep 3.1 us
MPM_REF_CHECK = ("Euler", 2e-3, 320)
MPM_REF_QUICK, MPM_REF_CHECK_QUICK = ("Euler", 2e-3, 32), ("Euler", 2e-3, 16)  # --quick: a cheap, loose one


def _mpm_sweep(engine, batched, quick):
    """(scheme, dt, substeps): substeps from just inside the CFL limit (0.67 ms at dt = 2 ms with 3 substeps) down
    to 25 us, at dt = 2 ms and at dt = 5 ms (the same substeps reached with fewer Python-level steps)."""
    if quick:
        return [("Euler", 2e-3, 4), ("Euler", 2e-3, 8)]
    return ([("Euler", 2e-3, n) for n in (3, 5, 10, 20, 40, 80)] +
            [("Euler", 5e-3, n) for n in (8, 32, 128)])


def _mpm_files(tmp):
    return {}


def _mpm_ref(files, quick=False):
    fine, check = (MPM_REF_QUICK, MPM_REF_CHECK_QUICK) if quick else (MPM_REF, MPM_REF_CHECK)
    return Reference("fine", f"genesis_lite, float64, the same particles and grid with dt = {fine[1]:g} s and "
                     f"{fine[2]} substeps (a substep of {fine[1] / fine[2] * 1e6:.1f} us; its difference from "
                     f"{check[2]} substeps is shown as the reference's error)" + (" (--quick's reference)" if quick else ""),
                     fine=fine, check=check)


def _gl_build_mpm(gs, files, integrator, dt, substeps, n_envs):
    import torch

    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, substeps=substeps, gravity=(0.0, 0.0, -S.G)),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.5, 0.5, 0.5),
                                                       grid_density=64))
    cube = scene.add_entity(gs.morphs.Box(pos=MPM_CENTRE, size=(0.1, 0.1, 0.1)),
                            material=gs.materials.MPM.Elastic(E=3e5, nu=0.2, rho=1000.0))
    scene.build(n_envs=n_envs)
    x = cube.get_particles_pos()
    d = x - torch.as_tensor(MPM_CENTRE, dtype=x.dtype)
    w = torch.as_tensor(MPM_SPIN, dtype=x.dtype).expand_as(d)
    v = MPM_STRETCH * d * torch.as_tensor([1.0, 1.0, -1.0], dtype=x.dtype) + torch.cross(w, d, dim=-1)
    cube.set_particles_vel(v)
    state = scene.get_state()

    def reset():
        scene.reset(state)

    def observe():
        return cube.get_particles_pos().detach().cpu().numpy().reshape(max(n_envs, 1), -1)

    return scene, reset, observe


SCENES: dict[str, WPScene] = {
    "pendulum": WPScene(
        "pendulum", "double pendulum (assets/urdf/double_pendulum.urdf), q0 = (0.9, -0.6) rad, v0 = (0, 0.8) rad/s",
        1.0, (1.0,), "max abs(q - q_ref) at t = 1 s (rad)", _pendulum_files, _pendulum_ref,
        _gl_build_arm("urdf", S.PENDULUM_Q0, S.PENDULUM_V0), _mj_build_arm("urdf", S.PENDULUM_Q0, S.PENDULUM_V0),
        genesis=True),
    "panda": WPScene(
        "panda", "Panda arm swinging freely from the ready pose under gravity (7 dofs, fingers welded, no limits)",
        PANDA_T, (PANDA_T,), f"max abs(q - q_ref) at t = {PANDA_T} s (rad)", _panda_files, _panda_ref,
        _gl_build_arm("urdf", S.PANDA_ARM_HOME, np.zeros(7)), _mj_build_arm("urdf", S.PANDA_ARM_HOME, np.zeros(7)),
        genesis=True),
    "box": WPScene(
        "box", f"box sliding to rest ({S.BOX_SIZE} m cube, {S.BOX_MASS} kg, v0 = {S.BOX_V0} m/s, mu = {S.BOX_MU})",
        1.0, BOX_SAMPLES, "max abs(x - x_ref) at t = 0.2 and 1 s (m)", _box_files, _box_ref, _gl_build_box,
        _mj_build_box, genesis=True),
    "quadruped": WPScene(
        "quadruped", "ANYmal B dropped on the ground from 0.62 m, PD holding the standing pose (kp 100, kv 5)",
        1.0, QUAD_SAMPLES, QUAD_ERROR, _quad_files, _quad_ref,
        _gl_build_quad, _mj_build_quad, genesis=True, starts=QUAD_STARTS),
    "quadruped_armature": WPScene(
        "quadruped_armature", "the quadruped with Genesis's default armature (0.1 kg m^2 on each of the 12 joints; "
        "genesis_lite's default too) in both engines",
        1.0, QUAD_SAMPLES, QUAD_ERROR, _quad_files, _quad_ref,
        functools.partial(_gl_build_quad, armature=QUAD_ARMATURE),
        functools.partial(_mj_build_quad, armature=QUAD_ARMATURE), genesis=False, starts=QUAD_STARTS),
    "push": WPScene(
        "push", f"Panda pushing a box ({S.PUSH_BOX_SIZE} m cube, {S.PUSH_BOX_MASS} kg, mu = {S.PUSH_MU}) with a sphere "
        f"on its hand, PD (kp {S.PUSH_KP:g}, kv {S.PUSH_KV:g}, armature {S.PUSH_ARMATURE:g}) to a pose 0.14 m ahead",
        PUSH_T, PUSH_SAMPLES, f"norm(box pos - ref) at t = {PUSH_SAMPLES} s (m)", _push_files, _push_ref,
        _gl_build_push, _mj_build_push),
    "mpm": WPScene(
        "mpm", f"elastic MPM cube (0.1 m, 1,000 particles, E = 3e5 Pa, nu = 0.2; 64 cells/m) set stretching "
        f"({MPM_STRETCH:g} 1/s) and spinning under gravity; MLS-MPM's explicit scheme, dt x substeps swept",
        MPM_T, MPM_SAMPLES, f"max abs(x - x_ref) over particles at t = {MPM_SAMPLES} s (m)", _mpm_files, _mpm_ref,
        _gl_build_mpm, None, sweep=_mpm_sweep, batched=False, quick_reference=lambda files: _mpm_ref(files, True),
        note="genesis_lite only (MuJoCo has no MPM; real Genesis's MPM is timed in the MPM section). At this fixed "
             "grid the ringing does not converge as the substep shrinks: each particle-grid transfer damps it, so more "
             "substeps damp it more (measured: the x-extent swing over 50-100 ms is 6.7 mm with 4 substeps of 2 ms, "
             "3.5 mm with 256; see bench_workprecision.py)"),
}


def _error(obs, ref, key):
    """Mean over environments of each one's error measure (its max over the sample times and observables), env i
    against the reference's row i % rows (one row, or one a start: WPScene.starts); inf when the run diverged."""
    obs = np.asarray(obs, dtype=float)
    obs = obs.reshape(-1, obs.shape[-1])
    ref = np.asarray(ref, dtype=float).reshape(-1, obs.shape[1])
    if not np.all(np.isfinite(obs)):
        return math.inf
    d = obs - ref[np.arange(len(obs)) % len(ref)]
    if key.startswith("quadruped") or key == "push":  # positions (x, y, z) at each sample time
        return float(np.linalg.norm(d.reshape(d.shape[0], -1, 3), axis=2).max(axis=1).mean())
    return float(np.abs(d).max(axis=1).mean())


def _samples(scene: WPScene, dt):
    """Steps between consecutive sample times (an exact multiple of dt is required)."""
    out, prev = [], 0
    for t in scene.sample_times:
        n = t / dt
        if abs(n - round(n)) > 1e-6:
            raise ValueError(f"{scene.key}: sample time {t} s is not a multiple of dt = {dt} s")
        out.append(int(round(n)) - prev)
        prev = int(round(n))
    return out


def _time_again(walls, repeats) -> bool:
    """Whether to time a run once more: `repeats` timings, or one when the first took over LONG_RUN_S."""
    return len(walls) < repeats and not (walls and walls[0] > LONG_RUN_S)


# --- genesis_lite worker (child process) ---------------------------------------------------------------------


def worker_gl(scene_key, files, points, n_envs, repeats, precision="64") -> dict:
    """Run each (integrator, dt, substeps) point of one scene: observables and stepping wall times."""
    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision=precision)
    wps = SCENES[scene_key]
    files = {k: Path(v) for k, v in files.items()}
    out = []
    for integ, dt, sub in points:
        rec = {"integrator": integ, "dt": dt, "substeps": sub}
        try:
            with Timer() as tb:
                scene, reset, observe = wps.gl_build(gs, files, integ, dt, sub, n_envs)
                reset()
                scene.step()  # compiles (or loads) the step kernels
            rec["build_s"] = tb.seconds
            chunks = _samples(wps, dt)
            # warm-up past the periodic NaN check (every 16 steps) and the getters, which compile on first use
            reset()
            for _ in range(min(48, sum(chunks))):
                scene.step()
            observe()
            walls, obs = [], None
            while _time_again(walls, repeats):
                reset()
                wall, got = 0.0, []
                for n in chunks:
                    t0 = time.perf_counter()
                    for _ in range(n):
                        scene.step()
                    wall += time.perf_counter() - t0
                    got.append(observe())
                walls.append(wall)
                obs = np.concatenate(got, axis=1)
            rec.update(wall=statistics.median(walls), walls=walls, obs=obs.tolist(), steps=sum(chunks))
        except Exception as e:  # a diverged run (SimulationNaNError) is a result, not a crash of the sweep
            rec.update(wall=None, obs=None, failed=f"{type(e).__name__}: {str(e).splitlines()[0][:160]}")
        out.append(rec)
        del rec
    return {"points": out}


def _worker_main(argv):
    ap = argparse.ArgumentParser()
    ap.add_argument("--worker", required=True, choices=["gl"])
    ap.add_argument("--args", required=True)
    a = ap.parse_args(argv)
    print(json.dumps(worker_gl(**json.loads(a.args))), flush=True)


def run_gl(scene_key, files, points, n_envs, repeats, timeout=3600, precision="64"):
    return run_python([str(Path(__file__).resolve()), "--worker", "gl", "--args",
                       json.dumps({"scene_key": scene_key, "files": {k: str(v) for k, v in files.items()},
                                   "points": points, "n_envs": n_envs, "repeats": repeats,
                                   "precision": precision})], timeout=timeout)


# --- MuJoCo (in this process) ------------------------------------------------------------------------------------


def run_mj(wps: WPScene, files, points, n_envs, repeats) -> dict:
    import mujoco
    from mujoco import rollout

    out = []
    threads = 1 if n_envs <= 1 else min(2, os.cpu_count() or 1)
    for integ, dt, sub in points:
        rec = {"integrator": integ, "dt": dt, "substeps": sub}
        try:
            m, q0, v0, observe, ctrl0 = wps.mj_build(files, integ, dt)
            B = max(n_envs, 1)
            init = S.mujoco_initial_states(m, q0, v0, B)
            ctrl = None if ctrl0 is None else np.tile(np.asarray(ctrl0, float), (B, 1, 1))
            datas = [mujoco.MjData(m) for _ in range(threads)]
            chunks = _samples(wps, dt)
            bufs = {}

            def once(warm_up=False):
                state, wall, got = init.copy(), 0.0, []
                for n in ([min(chunks[0], MJ_CHUNK)] if warm_up else chunks):
                    left = n
                    while left:
                        k = min(left, MJ_CHUNK)
                        buf = bufs.setdefault(k, np.empty((B, k, init.shape[1])))
                        t0 = time.perf_counter()
                        rollout.rollout(m, datas, state, ctrl, nstep=k, state=buf, persistent_pool=True)
                        wall += time.perf_counter() - t0
                        state = buf[:, -1].copy()
                        left -= k
                    got.append(observe(state))
                return wall, np.concatenate(got, axis=1)

            once(warm_up=True)  # creates the thread pool (one rollout call)
            warned = _mj_bad(datas)
            runs = []
            while _time_again([r[0] for r in runs], repeats):
                runs.append(once())
            rec.update(wall=statistics.median(r[0] for r in runs), walls=[r[0] for r in runs],
                       obs=runs[-1][1].tolist(), steps=sum(chunks))
            if warned or _mj_bad(datas):
                # MuJoCo resets a state whose acceleration blows up and carries on: the run diverged
                rec["failed"] = "MuJoCo warned of NaN / huge qacc (it resets such states and carries on)"
        except Exception as e:
            rec.update(wall=None, obs=None, failed=f"{type(e).__name__}: {str(e).splitlines()[0][:160]}")
        finally:
            rollout.shutdown_persistent_pool()
        out.append(rec)
    return {"points": out, "version": mujoco.__version__, "threads": threads}


def _mj_bad(datas) -> int:
    """How many times MuJoCo flagged a bad qpos / qvel / qacc in these MjData (cumulative counters)."""
    import mujoco

    w = mujoco.mjtWarning
    return sum(int(d.warning[int(k)].number) for d in datas for k in (w.mjWARN_BADQACC, w.mjWARN_BADQPOS,
                                                                       w.mjWARN_BADQVEL))


# --- real Genesis (its own venv) ---------------------------------------------------------------------------------


def run_genesis(scene_key, files, points, n_envs, repeats, timeout=3600):
    py = genesis_python()
    if not Path(py).exists():
        return None, f"real Genesis not installed ({py} not found; set GENESIS_PYTHON)"
    return run_python([str(HERE / "peer_genesis_wp.py"), "--args",
                       json.dumps({"scene_key": scene_key, "files": {k: str(v) for k, v in files.items()},
                                   "points": points, "n_envs": n_envs, "repeats": repeats,
                                   "sample_times": list(SCENES[scene_key].sample_times)})],
                      python=py, timeout=timeout)


# --- the study ----------------------------------------------------------------------------------------------------


def run_engine(engine, wps: WPScene, files, points, n_envs, repeats, timeout=3600):
    """(result, None), or (None, why the run failed), of one engine's runs of `points` (integrator, dt, substeps) on
    scene wps: genesis_lite in float64, or "genesis_lite_f32" in float32, in a worker process (from the scene's key);
    MuJoCo in this process, from wps.mj_build (so a changed copy of the scene runs its own model); real Genesis in
    its own venv."""
    if engine.startswith("genesis_lite"):
        return run_gl(wps.key, files, points, n_envs, repeats, timeout=timeout,
                      precision="32" if engine == "genesis_lite_f32" else "64")
    if engine == "mujoco":
        return run_mj(wps, files, points, n_envs, repeats), None
    return run_genesis(wps.key, files, points, n_envs, repeats, timeout=timeout)


def _fine_reference(engine, wps, files, ref: Reference):
    """(obs, self-difference, note) of an engine's own fine float64 run (and its check run)."""
    pts = [(*ref.fine, 1)[:3], (*ref.check, 1)[:3]]  # (integrator, dt[, substeps])
    n = wps.starts if wps.starts > 1 else 0  # one env a start (real Genesis: start 0 alone, its one-env rows')
    if engine == "genesis":
        pts, n = [("implicitfast", ref.fine[1], 1), ("implicitfast", ref.check[1], 1)], 0  # no RK4 in Genesis
    res, err = run_engine(engine, wps, files, pts, n, 1)
    if res is None:
        return None, None, err
    a, b = res["points"]
    if a.get("obs") is None or b.get("obs") is None:
        return None, None, a.get("failed") or b.get("failed")
    fa = np.asarray(a["obs"])  # a row a start
    return fa.tolist(), _error(b["obs"], fa, wps.key), None


QUICK_BATCHED = ("panda",)  # --quick runs the batch on these scenes only


def run(scene_keys, env_counts, quick, repeats, with_genesis, tmp: Path, log=print, integrators=None,
        f32=False, deep=0) -> dict:
    """The whole study: {scene: {"reference": ..., "envs": {n: {engine: [points with error]}}}}. Real Genesis
    runs 1 env only (its CPU backend with 1,024 envs would take the better part of an hour per scene here), and not
    in --quick (its first scene compiles for minutes); --quick runs the batch on QUICK_BATCHED only. f32: also
    genesis_lite in float32 (gs.init's default precision, and Genesis's), engine "genesis_lite_f32", its errors
    against the float64 reference."""
    results = {}
    def counts(key):
        return [n for n in env_counts if n <= 1 or (SCENES[key].batched and (not quick or key in QUICK_BATCHED))]

    bar = progress(total=sum(len(counts(k)) for k in scene_keys), desc="work-precision")
    for key in scene_keys:
        wps = SCENES[key]
        entry = {"title": wps.title, "error_label": wps.error_label, "envs": {}, "notes": []}
        results[key] = entry
        why = wps.available()
        if why:
            entry["skipped"] = why
            bar.update(len(counts(key)))
            continue
        files = wps.files(tmp)
        ref = (wps.quick_reference if quick and wps.quick_reference else wps.reference)(files)
        entry["reference"] = ref.label
        refs = {}
        engines = (["genesis_lite"] + (["genesis_lite_f32"] if f32 and wps.sweep is None else [])
                   + (["mujoco"] if wps.mj_build else [])
                   + (["genesis"] if with_genesis and wps.genesis and not quick else []))
        if wps.note:
            entry["notes"].append(wps.note)
        if not wps.batched and any(n > 1 for n in env_counts):
            entry["notes"].append("1 env only: the batched run is not part of this row")
        for engine in engines:
            if engine == "genesis_lite_f32":
                refs[engine] = refs["genesis_lite"]  # float32 runs measured against the float64 reference
            elif ref.kind == "fine":
                obs, self_err, err = _fine_reference(engine, wps, files, ref)
                refs[engine] = obs
                entry.setdefault("ref_self_error", {})[engine] = self_err
                if err:
                    entry["notes"].append(f"{engine}: no reference ({err})")
                elif engine == "genesis" and ref.fine[0] == "RK4":
                    entry["notes"].append(f"Genesis has no RK4: its reference is its implicitfast at dt = "
                                          f"{ref.fine[1]:g} s (and {ref.check[1]:g} s for the reference's error)")
            else:
                refs[engine] = ref.obs
        for n_envs in counts(key):
            per = {}
            for engine in engines:
                if engine == "genesis" and n_envs > 1:
                    continue
                if wps.sweep is not None:  # the scene's own sweep (its scheme is not one of INTEGRATORS' choices)
                    pts = wps.sweep(engine, n_envs > 1, quick)
                else:
                    pts = [p for p in sweep(engine, n_envs > 1, quick, deep) if not integrators or p[0] in integrators]
                res, err = run_engine(engine, wps, files, pts, n_envs, repeats)
                if res is None:
                    per[engine] = {"error": err, "points": []}
                    log(f"  {key} {n_envs} envs {engine}: FAILED: {err}")
                    continue
                for p in res["points"]:
                    p["error"] = None if p.get("obs") is None or refs[engine] is None else _error(p["obs"], refs[engine], key)
                    p["diverged"] = bool(p.get("failed")) or p["error"] is None or p["error"] > DIVERGED
                    p.pop("obs", None)
                per[engine] = {k: v for k, v in res.items() if k != "points"}
                per[engine]["points"] = res["points"]
            entry["envs"][str(max(n_envs, 1))] = per
            bar.update(1)
    bar.close()
    return results


# --- summaries ----------------------------------------------------------------------------------------------------


def front(points):
    """(errors, times) of the Pareto front: for each error level reached, the least wall time reaching it."""
    ok = sorted((p["wall"], p["error"]) for p in points if not p.get("diverged") and p.get("wall") is not None)
    out, best = [], math.inf
    for t, e in ok:
        if e < best:
            out.append((e, t))
            best = e
    return out


def time_at(fr, e):
    """Least wall time among front points whose error is <= e (inf when none reaches e)."""
    ts = [t for err, t in fr if err <= e]
    return min(ts) if ts else math.inf


def time_at_interp(fr, e):
    """The wall time to reach error e along the front, interpolated log-log between the two runs whose errors
    bracket e (a step between them is a choice the user has: for an integrator of order p, error ~ dt^p and
    time ~ 1 / dt make that a straight line); the cheapest run's time above its error (no extrapolation to a
    cheaper run), inf below the smallest error. time_at is the step function of the runs alone, which made two
    engines running the same algorithm at the same dt (the double pendulum's Euler at 20 ms: 0.016770 rad for
    both, to rounding) differ by a whole halving of dt at the grid's edge."""
    if not fr or e < fr[-1][0]:
        return math.inf
    if e >= fr[0][0]:
        return fr[0][1]
    for (e0, t0), (e1, t1) in zip(fr, fr[1:]):
        if e1 <= e <= e0:
            if e0 <= e1 or e1 <= 0.0 or t0 <= 0.0:  # no line through an error of 0 (or a time of 0)
                return t1
            return math.exp(math.log(t0) + (math.log(t1) - math.log(t0)) * (math.log(e0) - math.log(e))
                            / (math.log(e0) - math.log(e1)))
    return fr[-1][1]


def time_to_error(points, e, interpolate=True):
    """The least time an engine needs to reach error e: along each integrator's own front (time_at_interp; a
    user choosing a step moves along one integrator's runs), the least over its integrators (time_at's steps
    with interpolate=False). Until 2026-12-06 the interpolation ran along the front of all runs together, where
    a run of another integrator that lands between two runs of one raised the time between them (and a line
    between two integrators' runs is no step a user can choose): the quadruped at 1,024 envs, Euler at 20 ms / 16
    substeps (7.38e-4 m in 3.04 s) between implicitfast's 8.94e-4 m in 1.63 s and 4.23e-4 m in 3.08 s, gave 3.04 s
    at 7.4e-4 m, not 1.9 s."""
    at = time_at_interp if interpolate else time_at
    fams = {}
    for p in points:
        fams.setdefault(p.get("integrator"), []).append(p)
    return min((at(front(f), e) for f in fams.values()), default=math.inf)


def equal_error_ratio(points_a, points_b, n=25, interpolate=True):
    """Run-time ratio a / b at equal error: on a log grid of error levels both fronts reach (from the larger of
    their best errors to the smaller of their worst), time_to_error(a, e) / time_to_error(b, e). Returns (max,
    median, (e_lo, e_hi)) or None when the ranges do not overlap."""
    fa, fb = front(points_a), front(points_b)
    if not fa or not fb:
        return None
    lo = max(min(e for e, _ in fa), min(e for e, _ in fb))
    hi = min(max(e for e, _ in fa), max(e for e, _ in fb), ERR_CAP)
    if not lo <= hi:
        return None
    grid = np.geomspace(lo, hi, n) if hi > lo else np.array([lo])
    r = [time_to_error(points_a, e, interpolate) / time_to_error(points_b, e, interpolate) for e in grid]
    return max(r), float(np.median(r)), (lo, hi)


def tables(results) -> list[str]:
    """Markdown: per scene a summary (best error and the time of each engine's front), and all points."""
    out = []
    for key, entry in results.items():
        lines = [f"#### {key}: {entry['title']}"]
        if entry.get("skipped"):
            lines.append(f"Skipped: {entry['skipped']}.")
            out.append("\n".join(lines))
            continue
        lines.append(f"Error: {entry['error_label']}. Reference: {entry.get('reference')}.")
        if entry.get("ref_self_error"):
            lines.append("Reference's own error (fine run vs the same at twice its step or substep): " + ", ".join(
                f"{k} {v:.1e}" if v is not None else f"{k} -" for k, v in entry["ref_self_error"].items()) + ".")
        for note in entry.get("notes", []):
            lines.append(f"Note: {note}.")
        rows = []
        for n, per in entry["envs"].items():
            for engine, res in per.items():
                for integ in INTEGRATORS:
                    pts = [p for p in res.get("points", []) if p["integrator"] == integ]
                    if not pts:
                        continue
                    fr = front(pts)
                    div = [p for p in pts if p.get("diverged")]
                    rows.append({"envs": int(n), "engine": engine, "integrator": integ, "points": len(pts),
                                 "best_err": fr[-1][0] if fr else None, "best_t": fr[-1][1] if fr else None,
                                 "t_1e3": _fmt_t(time_at(fr, 1e-3)), "t_1e6": _fmt_t(time_at(fr, 1e-6)),
                                 "failed": ", ".join(f"dt={p['dt']:g}x{p['substeps']}" for p in div) or "-"})
                if res.get("error"):
                    rows.append({"envs": int(n), "engine": engine, "failed": res["error"]})
        lines.append(print_table(rows, [
            ("envs", "envs", "d"), ("engine", "engine", ""), ("integrator", "integrator", ""), ("points", "runs", "d"),
            ("best_err", "smallest error", ".2e"), ("best_t", "its wall s", ".3g"),
            ("t_1e3", "wall s to error <= 1e-3", ""), ("t_1e6", "wall s to error <= 1e-6", ""),
            ("failed", "diverged / failed runs", "")]))
        pts_rows = []
        for n, per in entry["envs"].items():
            for engine, res in per.items():
                for p in res.get("points", []):
                    pts_rows.append({"envs": int(n), "engine": engine, **p,
                                     "error_s": p.get("error") if p.get("error") is not None else "-",
                                     "div": "yes" if p.get("diverged") else "",
                                     "note": p.get("failed", "")})
        lines.append("\n<details><summary>every run</summary>\n")
        lines.append(print_table(pts_rows, [
            ("envs", "envs", "d"), ("engine", "engine", ""), ("integrator", "integrator", ""), ("dt", "dt s", "g"),
            ("substeps", "substeps", "d"), ("steps", "steps", "d"), ("error_s", "error", ".3e"),
            ("div", "diverged", ""), ("wall", "wall s (median)", ".4f"), ("build_s", "build+compile s", ".2f"),
            ("note", "note", "")]))
        lines.append("\n</details>")
        out.append("\n".join(lines))
    return out


def _fmt_t(t):
    return "not reached" if not math.isfinite(t) else f"{t:.3g}"


STYLE = {"genesis_lite": ("-", "o"), "mujoco": ("--", "s"), "genesis": (":", "^")}
COLOR = {"Euler": "tab:blue", "implicitfast": "tab:orange", "RK4": "tab:green"}


def plot(results, n_envs: str, path: Path, title: str) -> bool:
    """One log-log panel per scene: error against wall time, a line per engine and integrator (substep runs
    as hollow markers). Returns False when there is nothing to plot or no matplotlib."""
    plt = pyplot()
    keys = [k for k, e in results.items() if not e.get("skipped") and n_envs in e["envs"]]
    if plt is None or not keys:
        return False
    from matplotlib.ticker import NullFormatter
    cols = min(2, len(keys))
    rows = (len(keys) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(6.2 * cols, 4.6 * rows), squeeze=False)
    for ax, key in zip(axes.flat, keys):
        for engine, res in results[key]["envs"][n_envs].items():
            ls, mk = STYLE[engine]
            for integ in INTEGRATORS:
                pts = [p for p in res.get("points", []) if p["integrator"] == integ and p.get("wall")
                       and not p.get("diverged") and p["error"] > 0]
                if not pts:
                    continue
                plain = sorted((p for p in pts if p["substeps"] == 1), key=lambda p: -p["dt"])  # a convergence curve
                sub = [p for p in pts if p["substeps"] > 1]
                if not plain:  # a substep sweep (MPM): one curve per step dt, substeps growing along it
                    for k, dt in enumerate(sorted({p["dt"] for p in sub})):
                        c = sorted((p for p in sub if p["dt"] == dt), key=lambda p: p["substeps"])
                        ax.plot([p["wall"] for p in c], [p["error"] for p in c], ls=ls, marker=mk, ms=5,
                                color=f"C{k + 3}", label=f"{engine}, dt = {dt:g} s, substeps {c[0]['substeps']}.."
                                                         f"{c[-1]['substeps']}")
                    continue
                if plain:
                    ax.plot([p["wall"] for p in plain], [p["error"] for p in plain], ls=ls, marker=mk, ms=5,
                            color=COLOR[integ], label=f"{engine} {integ}")
                if sub:
                    ax.plot([p["wall"] for p in sub], [p["error"] for p in sub], ls="none", marker=mk, ms=7,
                            mfc="none", color=COLOR[integ])
        for engine, e in (results[key].get("ref_self_error") or {}).items():
            if e and math.isfinite(e) and e > 0:  # below this line the reference cannot tell errors apart
                ax.axhline(e, color="grey", ls=STYLE[engine][0], lw=0.8, label=f"{engine} reference's own error")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())  # labelled minor ticks ran into each other
        ax.set_xlabel("wall time of the run (s)")
        ax.set_ylabel("error")
        ax.set_title(textwrap.fill(f"{key}: {results[key]['error_label']}", 80), fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(keys):]:
        ax.axis("off")
    fig.suptitle(title + "  (hollow markers: dt = 0.02 s with substeps)", fontsize=10)
    save_figure(fig, path)
    return True


def main():
    global QUAD_REF, QUAD_REF_CHECK, PUSH_REF, PUSH_REF_CHECK
    if "--worker" in sys.argv:
        return _worker_main(sys.argv[1:])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--envs", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-genesis", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--f32", action="store_true", help="also genesis_lite in float32 (gs.init's default precision), "
                    "against the float64 reference")
    ap.add_argument("--md", type=Path, default=None, help="write the equal-error summary and the tables here")
    ap.add_argument("--rigid", default=None, help='RigidOptions fields for every genesis_lite build, as JSON '
                    '(\'{"friction_smoothing_accel": 0.1}\'); named in each scene\'s notes')
    ap.add_argument("--deep", type=int, default=0, help="halve dt this many more times (MuJoCo and genesis_lite)")
    ap.add_argument("--ref-dt", type=float, default=None, help="the fine references' dt (the check run at twice it; "
                    f"default {QUAD_REF[1]:g} s) of the quadrupeds and the push")
    ap.add_argument("--from-json", type=Path, nargs="+", default=None,
                    help="no run: the results of earlier --json files (merged, later files' scenes win)")
    a = ap.parse_args()
    if a.from_json:
        merged = {}
        for f in a.from_json:
            merged.update(json.loads(f.read_text()))
        res = {k: merged[k] for k in list(SCENES) + list(merged) if k in merged}  # the scenes' order
    else:
        if a.ref_dt:
            QUAD_REF = PUSH_REF = ("RK4", a.ref_dt)
            QUAD_REF_CHECK = PUSH_REF_CHECK = ("RK4", 2 * a.ref_dt)
        with rigid_options(**json.loads(a.rigid or "{}")), tempfile.TemporaryDirectory(prefix="bench_wp_") as tmp:
            res = run(a.scenes.split(","), [0, a.envs], a.quick, a.repeats, not a.no_genesis, Path(tmp), f32=a.f32,
                      deep=a.deep)
        for entry in res.values():
            if a.rigid:
                entry.setdefault("notes", []).append(f"genesis_lite with RigidOptions fields {a.rigid}")
            if a.deep:
                entry.setdefault("notes", []).append(f"--deep {a.deep}: the sweep's dt halved {a.deep} more times")
    text = tables(res)
    for t in text:
        print(t)
    if a.json and not a.from_json:
        a.json.write_text(json.dumps(res, indent=1))
    if a.md:
        a.md.write_text("\n\n".join([summary(res)] + text) + "\n")
        print(f"wrote {a.md}")


def equal_error_rows(res, n_envs=None, peers=("mujoco", "genesis")):
    """genesis_lite's run time over each peer's at equal error: a dict per scene, env count (all, or `n_envs`),
    peer and genesis_lite precision (float64 runs; float64 or float32 where the --f32 runs exist, the user picking
    the precision as the step), with the ratio's max, median and error range (None without a common range) and
    each side's smallest error."""
    for key, entry in res.items():
        for n, per in entry.get("envs", {}).items():
            if n_envs is not None and n != n_envs:
                continue
            f64 = per.get("genesis_lite", {}).get("points", [])
            ours = [("f64", f64)]
            if "genesis_lite_f32" in per:
                ours.append(("f64 or f32", f64 + per["genesis_lite_f32"].get("points", [])))
            for peer in peers:
                if peer not in per:
                    continue
                theirs = per[peer].get("points", [])
                for prec, pts in ours:
                    r = equal_error_ratio(pts, theirs)
                    fa, fb = front(pts), front(theirs)
                    yield {"scene": key, "envs": n, "peer": peer, "prec": prec, "max": r[0] if r else None,
                           "median": r[1] if r else None, "range": r[2] if r else None,
                           "best": fa[-1][0] if fa else None, "peer_best": fb[-1][0] if fb else None}


def summary(res) -> str:
    """Markdown: equal_error_rows against MuJoCo for every scene and env count, with the error range both engines
    reach and each engine's smallest error (below the other's, the comparison has no common range)."""
    lines = ["Run time at equal error, genesis_lite / MuJoCo: the least time each engine needs to reach an error (any "
             "integrator, dt or substeps; interpolated log-log between the two runs of an integrator's front that "
             f"bracket the error, the least over the integrators), on a log grid of the errors both reach (<= "
             f"{ERR_CAP}); below the smaller error range's end one engine reaches errors the other does not.", "",
             "| scene | envs | genesis_lite precision | error range compared | max ratio | median ratio | "
             "smallest error genesis_lite | smallest error MuJoCo |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    e = lambda x: "-" if x is None else f"{x:.1e}"  # noqa: E731
    for r in equal_error_rows(res, peers=("mujoco",)):
        cells = ([f"{r['range'][0]:.1e} .. {r['range'][1]:.1e}", f"{r['max']:.2f}", f"{r['median']:.2f}"]
                 if r["range"] else ["no common range", "-", "-"])
        lines.append(f"| {r['scene']} | {r['envs']} | {r['prec']} | " + " | ".join(cells)
                     + f" | {e(r['best'])} | {e(r['peer_best'])} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
