"""The scenes the harness (run_all.py) shares between engines: URDF files written once and read by every
engine, and MuJoCo models built from those files with the same floor.

Only numpy, the standard library and (inside the MuJoCo builders) mujoco are imported here, so the
peer scripts that run in real Genesis's own venv can import this module too.

Conventions shared by every engine:
- the floor is a plane through the origin with normal +z; its friction is the scene's mu, and so is every
  geom's (genesis_lite and MuJoCo both combine two geoms' coefficients with max);
- joint damping, armature and friction loss are 0 unless a scene says otherwise;
- a "free" URDF gets a floating base: genesis_lite `URDF(fixed=False)`, MuJoCo a free joint on the root.
"""
from __future__ import annotations

import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO_ROOT = HERE.parent
PENDULUM_URDF = REPO_ROOT / "assets" / "urdf" / "double_pendulum.urdf"
CHAIN30_URDF = REPO_ROOT / "assets" / "urdf" / "chain30.urdf"
G = 9.81  # m/s^2

# The double pendulum's large non-linear swing (tests/test_integrators.py uses the same state).
PENDULUM_Q0 = np.array([0.9, -0.6])  # rad
PENDULUM_V0 = np.array([0.0, 0.8])  # rad/s
# Panda's "ready" pose for its 7 arm joints.
PANDA_ARM_HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])

# The box that slides to rest: 1 kg, 0.2 m cube, launched along +x at BOX_V0 on a floor with friction BOX_MU.
BOX_SIZE = 0.2  # m
BOX_MASS = 1.0  # kg
BOX_MU = 0.5
BOX_V0 = 2.0  # m/s


def _tmpdir(out_dir, prefix):
    d = Path(out_dir) if out_dir is not None else Path(tempfile.mkdtemp(prefix=prefix))
    d.mkdir(parents=True, exist_ok=True)
    return d


def _mujoco_compiler(root, **attrs):
    """Add <mujoco><compiler .../></mujoco> for MuJoCo's URDF importer (other parsers ignore the element)."""
    mj = ET.SubElement(root, "mujoco")
    ET.SubElement(mj, "compiler", {k: str(v).lower() if isinstance(v, bool) else str(v) for k, v in attrs.items()})


def write_panda_arm(out_dir=None) -> Path:
    """example-robot-data's Panda without visuals and collisions, its two finger joints welded (fixed) and
    the <mimic> removed: a 7-dof arm that Pinocchio, MuJoCo, genesis_lite and Genesis read identically
    (fixed links are merged into their parents by each). Unlimited free fingers would slide off under
    gravity, which is no test of the arm's dynamics."""
    from common import panda_urdf

    tree = ET.parse(panda_urdf())
    root = tree.getroot()
    for link in root.findall("link"):
        for tag in ("visual", "collision"):
            for e in link.findall(tag):
                link.remove(e)
    for joint in root.findall("joint"):
        if "finger" in joint.get("name", ""):
            joint.set("type", "fixed")
            for tag in ("mimic", "limit", "axis", "dynamics"):
                for e in joint.findall(tag):
                    joint.remove(e)
    _mujoco_compiler(root, discardvisual=True, fusestatic=True)
    path = _tmpdir(out_dir, "bench_panda_arm_") / "panda_arm7.urdf"
    tree.write(path, encoding="unicode")
    return path


# A Panda pushing a box (work-precision's manipulation row): the 7-dof arm of write_panda_arm with a sphere on
# the hand between the fingertips (its only collision shape), PD-driven (Genesis's default gains, its default
# armature) from a pose with the sphere touching the box's back face to one 0.14 m further on; the box slides on
# the floor ahead of it. Joint angles from genesis_lite's inverse kinematics of panda_link7 (z axis down) at
# x = 0.33 and 0.47 m, z = 0.292 m: the sphere's centre at z = 0.085 m, 5.5 cm above the floor. The arm's gravity
# is compensated in both engines (genesis_lite's gravity_compensation, MuJoCo's gravcomp): under the PD alone it
# sagged 3-6 cm and the sphere dragged on the floor.
PUSH_Q0 = np.array([0.2405, -0.0088, -0.2434, -2.936, -0.01, 2.9274, 0.0069])  # rad
PUSH_QT = np.array([0.1539, 0.2644, -0.1388, -2.4944, 0.096, 2.7548, -0.0692])  # rad
PUSH_SPHERE = (0.03, 0.1)  # m: radius, and its offset along the hand's z axis from the hand's origin
PUSH_BOX_SIZE, PUSH_BOX_MASS = 0.1, 0.4  # m, kg
PUSH_BOX_POS = (0.41, 0.0, 0.05)  # m: its back face at the sphere's front
PUSH_MU = 0.5
PUSH_KP, PUSH_KV, PUSH_ARMATURE = 100.0, 10.0, 0.1  # N m/rad, N m s/rad, kg m^2


def write_panda_pusher(out_dir=None) -> Path:
    """write_panda_arm's 7-dof Panda with one collision sphere on panda_hand (PUSH_SPHERE); the hand is merged
    into panda_link7 by every reader."""
    path = write_panda_arm(out_dir)
    tree = ET.parse(path)
    for link in tree.getroot().findall("link"):
        if link.get("name") == "panda_hand":
            c = ET.SubElement(link, "collision")
            ET.SubElement(c, "origin", {"xyz": f"0 0 {PUSH_SPHERE[1]}", "rpy": "0 0 0"})
            ET.SubElement(ET.SubElement(c, "geometry"), "sphere", {"radius": str(PUSH_SPHERE[0])})
    out = path.parent / "panda_pusher.urdf"
    tree.write(out, encoding="unicode")
    return out


def write_box_urdf(out_dir=None, size=BOX_SIZE, mass=BOX_MASS, name="box") -> Path:
    """A single-link URDF: a solid cube of edge `size` (m) and `mass` (kg) with its box collision shape."""
    i = mass * (2 * size * size) / 12.0
    s = f"{size:.6g} {size:.6g} {size:.6g}"
    text = f"""<?xml version="1.0"?>
<robot name="{name}">
  <link name="{name}">
    <inertial><origin xyz="0 0 0" rpy="0 0 0"/><mass value="{mass:.9g}"/>
      <inertia ixx="{i:.9g}" ixy="0" ixz="0" iyy="{i:.9g}" iyz="0" izz="{i:.9g}"/></inertial>
    <collision><origin xyz="0 0 0" rpy="0 0 0"/><geometry><box size="{s}"/></geometry></collision>
  </link>
  <mujoco><compiler discardvisual="true" fusestatic="false"/></mujoco>
</robot>
"""
    path = _tmpdir(out_dir, "bench_box_") / f"{name}.urdf"
    path.write_text(text)
    return path


def write_anymal(out_dir=None) -> Path:
    """example-robot-data's ANYmal B ("simple": boxes, cylinders and spheres for collision) without its <visual>
    meshes: real Genesis's URDF reader fails on their package:// paths, and no engine here simulates visuals
    (genesis_lite ignores them, MuJoCo discards them), so every engine reads this one file."""
    from common import find_robots_dir

    src = find_robots_dir() / "anymal_b_simple_description" / "robots" / "anymal.urdf"
    tree = ET.parse(src)
    for link in tree.getroot().findall("link"):
        for e in link.findall("visual"):
            link.remove(e)
    path = _tmpdir(out_dir, "bench_anymal_") / "anymal_novisual.urdf"
    tree.write(path, encoding="unicode")
    return path


def box_slide_analytic(t):
    """x(t) (m) of the box's centre under exact Coulomb friction: decelerates at mu g, stops for good."""
    t = np.asarray(t, dtype=float)
    t_stop = BOX_V0 / (BOX_MU * G)
    tc = np.minimum(t, t_stop)
    return BOX_V0 * tc - 0.5 * BOX_MU * G * tc * tc


# --- MuJoCo ----------------------------------------------------------------------------------------------


MJ_INTEGRATORS = {"Euler": "mjINT_EULER", "implicitfast": "mjINT_IMPLICITFAST", "implicit": "mjINT_IMPLICIT",
                  "RK4": "mjINT_RK4"}


def set_mujoco_integrator(m, integrator: str, dt: float):
    """Set MuJoCo's integrator by genesis_lite's name (Euler / implicitfast / RK4; or MuJoCo's implicit) and its time
    step (s)."""
    import mujoco

    m.opt.integrator = getattr(mujoco.mjtIntegrator, MJ_INTEGRATORS[integrator])
    m.opt.timestep = dt
    return m


def mujoco_from_urdf(urdf, free=False, base_pos=(0.0, 0.0, 0.0), floor_mu=None, limits=True, contacts=True,
                     elliptic=True):
    """MuJoCo's model of a URDF the way genesis_lite sets up the same file.

    free: a free joint on the root body at base_pos (m); floor_mu: a ground plane at z = 0 whose friction and
    every geom's sliding friction are floor_mu (None: no floor); limits=False unlimits every joint;
    contacts=False disables contacts. Joint damping, armature and friction loss are zeroed; gravity -9.81 z.
    Elliptic friction cones (a true Coulomb cone, like genesis_lite's isotropic friction) unless told not to.
    Robot geoms collide with the floor only (no self-collision), as in genesis_lite's default."""
    import mujoco

    spec = mujoco.MjSpec.from_file(str(urdf))
    if limits is False:
        for j in spec.joints:
            j.limited = mujoco.mjtLimited.mjLIMITED_FALSE
    if free:
        base = spec.worldbody.first_body()
        base.add_freejoint()
        base.pos = list(base_pos)
    for g in spec.geoms:
        g.contype, g.conaffinity = 1, 0
        if floor_mu is not None:
            g.friction = [floor_mu, g.friction[1], g.friction[2]]
    if floor_mu is not None:
        spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], contype=1, conaffinity=1,
                                friction=[floor_mu, 0.005, 0.0001])
    m = spec.compile()
    m.opt.gravity[:] = (0.0, 0.0, -G)
    m.dof_damping[:] = 0.0
    m.dof_armature[:] = 0.0
    m.dof_frictionloss[:] = 0.0
    if m.neq:
        m.eq_active0[:] = 0
    if not contacts:
        m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    if elliptic:
        m.opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    return m


def mujoco_initial_states(m, qpos, qvel, n_envs: int):
    """(n_envs, nstate) full-physics states of MuJoCo's rollout, every env starting from (qpos, qvel); qpos with a
    row a start: env i from row i % rows."""
    import mujoco

    d = mujoco.MjData(m)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    rows = np.atleast_2d(np.asarray(qpos, dtype=float))
    starts = np.empty((len(rows), mujoco.mj_stateSize(m, spec)))
    for k, q in enumerate(rows):
        mujoco.mj_resetData(m, d)
        d.qpos[:] = q
        d.qvel[:] = qvel
        mujoco.mj_forward(m, d)
        mujoco.mj_getState(m, d, starts[k], spec)
    return starts[np.arange(n_envs) % len(rows)]


def mujoco_state_slices(m):
    """Slices of qpos and qvel inside a full-physics state vector ([time, qpos, qvel, act, ...])."""
    return slice(1, 1 + m.nq), slice(1 + m.nq, 1 + m.nq + m.nv)


def mujoco_on_floor(spec, dt):
    """Compile a mujoco.MjSpec with a ground plane added, stepped like genesis_lite's defaults: implicitfast
    at dt, elliptic friction cones (MuJoCo's own soft contacts)."""
    import mujoco

    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1])
    m = spec.compile()
    m.opt.timestep = dt
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    m.opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    return m


def mujoco_free_box(spec, name, pos, size, mass):
    """A free-floating cube of edge `size` (m) and `mass` (kg) at `pos` in a mujoco.MjSpec."""
    import mujoco

    b = spec.worldbody.add_body(name=name, pos=list(pos))
    b.add_freejoint()
    b.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[size / 2] * 3, mass=mass)
    return b
