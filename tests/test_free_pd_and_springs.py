"""PD control of a free joint's dofs and joint springs (set_dofs_stiffness, MJCF stiffness), each checked
against something this library did not compute:
- a free cube held by PD on its six dofs follows the closed-form damped oscillator m x'' = kp (x* - x) - kv x'
  on a translational dof, and I th'' = -kp th - kv th' on its rotation about a fixed axis (a cube's inertia is
  isotropic, so the rotation stays about that axis and the law's error is exactly -th n), converging at
  first order in dt; from any start it settles at a target pose given, as in Genesis, by world xyz and
  intrinsic x-y-z Euler angles (scipy's 'XYZ'), and its first torque is Genesis's law kp rotvec(q^-1 q*)
  about the body's axes (scipy's rotation algebra);
- get_dofs_position's rotational entries are scipy's intrinsic 'XYZ' Euler angles;
- a pendulum with a joint spring k oscillates at sqrt((k + m g l) / I) for small angles (zero crossings);
- an MJCF model with hinge and slide springs (stiffness, springref) follows MuJoCo's own trajectory step
  by step (both with the semi-implicit Euler integrator, the same dt).
"""
from __future__ import annotations

import os
import tempfile

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import genesis_lite as gs
from genesis_lite.errors import GenesisException, GenesisWarning


def _np(x):
    return x.detach().cpu().numpy().astype(np.float64) if hasattr(x, "detach") else np.asarray(x, float)


def _scipy_quat(q_wxyz):
    return Rotation.from_quat(np.roll(np.asarray(q_wxyz, float), -1))  # scipy is (x, y, z, w)


def _wxyz(rot):
    return np.roll(rot.as_quat(), 1)


def _angle_between(q1, q2):
    return float((_scipy_quat(q1) * _scipy_quat(q2).inv()).magnitude())


def _oscillator(e0, k, c, m, t):
    """Error e(t) of m e'' + c e' + k e = 0 from e(0) = e0, e'(0) = 0, underdamped."""
    w = np.sqrt(k / m)
    z = c / (2 * np.sqrt(k * m))
    wd = w * np.sqrt(1 - z * z)
    return e0 * np.exp(-z * w * t) * (np.cos(wd * t) + z * w / wd * np.sin(wd * t))


# a 0.1 m cube of 1000 kg/m^3: 1 kg, I = m a^2 / 6 about every axis through its centre
SIDE, MASS = 0.1, 1.0
INERTIA = MASS * SIDE**2 / 6
KP_LIN, KV_LIN = 100.0, 4.0  # w = 10 rad/s, damping ratio 0.2
KP_ROT = 100.0 * INERTIA  # the same w and ratio on the rotation
KV_ROT = 4.0 * INERTIA


def _cube_scene(dt):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, gravity=(0.0, 0.0, 0.0)), show_viewer=False)
    cube = scene.add_entity(gs.morphs.Box(size=(SIDE,) * 3, pos=(0.0, 0.0, 1.0)), material=gs.materials.Rigid(rho=1000.0))
    scene.build()
    assert abs(float(cube.get_mass()) - MASS) < 1e-12
    np.testing.assert_allclose(_np(cube.get_links_inertia())[0], INERTIA * np.eye(3), rtol=1e-12, atol=1e-15)
    cube.set_dofs_kp([KP_LIN] * 3 + [KP_ROT] * 3)
    cube.set_dofs_kv([KV_LIN] * 3 + [KV_ROT] * 3)
    return scene, cube


def test_free_joint_gains_default_to_zero_and_targets_warn():
    """Genesis gives a free joint kp = kv = 0 (no actuator); a target on them warns that it does nothing."""
    scene = gs.Scene(show_viewer=False)
    cube = scene.add_entity(gs.morphs.Box(size=(SIDE,) * 3, pos=(0.0, 0.0, 1.0)))
    scene.build()
    assert np.all(_np(cube.get_dofs_kp()) == 0) and np.all(_np(cube.get_dofs_kv()) == 0)
    with pytest.warns(GenesisWarning, match="kp is 0"):
        cube.control_dofs_position(np.zeros(6))


def test_dofs_position_of_a_free_joint_is_xyz_and_intrinsic_xyz_euler_angles():
    scene = gs.Scene(show_viewer=False)
    cube = scene.add_entity(gs.morphs.Box(size=(SIDE,) * 3, pos=(0.0, 0.0, 1.0)))
    scene.build()
    rng = np.random.default_rng(3)
    for _ in range(5):
        rot = Rotation.random(random_state=rng)
        pos = rng.uniform(-1, 1, 3)
        cube.set_pos(pos)
        cube.set_quat(_wxyz(rot))
        dp = _np(cube.get_dofs_position())
        np.testing.assert_allclose(dp[:3], pos, atol=1e-14)
        np.testing.assert_allclose(dp[3:], rot.as_euler("XYZ"), atol=1e-12)
        # and back: set_dofs_position with Euler angles gives scipy's rotation
        e = rng.uniform([-3, -1.5, -3], [3, 1.5, 3])
        cube.set_dofs_position(np.concatenate([pos, e]))
        assert _angle_between(_np(cube.get_quat()), _wxyz(Rotation.from_euler("XYZ", e))) < 1e-12
        np.testing.assert_allclose(_np(cube.get_dofs_position())[3:], e, atol=1e-12)


def test_first_pd_torque_of_a_free_joint_is_genesis_law():
    """At rest, the translational dofs' actuator force is kp (x* - x), and the rotational dofs' torque is
    Genesis's: kp rotvec(q^-1 q*) on its body-frame angular dofs, i.e. R times that in world axes, the
    frame of ours."""
    scene, cube = _cube_scene(1e-3)
    rng = np.random.default_rng(7)
    start, target_e = Rotation.random(random_state=rng), np.array([0.4, -0.9, 2.5])
    x0, x_t = np.array([0.1, -0.2, 1.0]), np.array([0.3, 0.1, 0.7])
    cube.set_pos(x0)
    cube.set_quat(_wxyz(start))
    cube.control_dofs_position(np.concatenate([x_t, target_e]))
    scene.step()
    tau = _np(cube.get_dofs_control_force())
    np.testing.assert_allclose(tau[:3], KP_LIN * (x_t - x0), rtol=1e-12)
    body = (start.inv() * Rotation.from_euler("XYZ", target_e)).as_rotvec()  # Genesis's error
    np.testing.assert_allclose(tau[3:], start.apply(KP_ROT * body), rtol=1e-10, atol=1e-14)


def _pd_response(dt, t_end, e_lin0, axis, th0):
    scene, cube = _cube_scene(dt)
    x_t = np.array([0.0, 0.0, 1.0])
    cube.set_pos(x_t + e_lin0)
    cube.set_quat(_wxyz(Rotation.from_rotvec(th0 * axis)))
    cube.control_dofs_position(np.concatenate([x_t, np.zeros(3)]))
    n = int(round(t_end / dt))
    xs, ths = [], []
    for _ in range(n):
        scene.step()
        xs.append(_np(cube.get_pos()) - x_t)
        r = _scipy_quat(_np(cube.get_quat())).as_rotvec()
        ths.append(r)
    t = dt * np.arange(1, n + 1)
    return t, np.array(xs), np.array(ths)


def test_free_cube_pd_follows_the_damped_oscillator():
    """Every translational dof and the rotation angle follow the closed form; the gap shrinks ~2x when
    dt halves (semi-implicit Euler with the gains implicit: first order)."""
    e_lin0 = np.array([0.05, -0.03, 0.02])
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    th0 = 1.0  # rad: the rotation error is the exact rotation vector, so no small-angle limit
    gaps = []
    for dt in (2e-3, 1e-3):
        t, xs, ths = _pd_response(dt, 2.0, e_lin0, axis, th0)
        x_ref = np.outer(_oscillator(1.0, KP_LIN, KV_LIN, MASS, t), e_lin0)
        th_ref = _oscillator(th0, KP_ROT, KV_ROT, INERTIA, t)
        # the rotation stays about its axis (isotropic inertia)
        np.testing.assert_allclose(ths - np.outer(ths @ axis, axis), 0.0, atol=1e-12)
        gaps.append((np.abs(xs - x_ref).max() / np.abs(e_lin0).max(), np.abs(ths @ axis - th_ref).max() / th0))
    (lin2, rot2), (lin1, rot1) = gaps
    assert lin1 < 0.02 and rot1 < 0.02, gaps
    assert 1.7 < lin2 / lin1 < 2.3 and 1.7 < rot2 / rot1 < 2.3, gaps


def test_free_cube_settles_at_a_target_pose():
    scene, cube = _cube_scene(2e-3)
    rng = np.random.default_rng(11)
    cube.set_pos([0.4, -0.3, 1.2])
    cube.set_quat(_wxyz(Rotation.random(random_state=rng)))
    cube.set_dofs_velocity([0.5, 0.2, -0.1, 3.0, -2.0, 1.0])
    target = np.array([-0.2, 0.5, 0.8, 2.8, -1.2, -2.9])  # Euler angles near +-pi: the short way round
    for _ in range(4000):  # 8 s: exp(-z w t) = 1e-7
        cube.control_dofs_position(target)
        scene.step()
    np.testing.assert_allclose(_np(cube.get_pos()), target[:3], atol=1e-6)
    assert _angle_between(_np(cube.get_quat()), _wxyz(Rotation.from_euler("XYZ", target[3:]))) < 1e-6
    np.testing.assert_allclose(_np(cube.get_dofs_position())[3:], target[3:], atol=1e-6)
    assert np.abs(_np(cube.get_dofs_velocity())).max() < 1e-5


PENDULUM = ('<robot name="pendulum"><link name="base"/><link name="bob"><inertial><origin xyz="0 0 -{l}"/>'
            '<mass value="{m}"/><inertia ixx="{i}" iyy="{i}" izz="{i}" ixy="0" ixz="0" iyz="0"/></inertial></link>'
            '<joint name="hinge" type="continuous"><parent link="base"/><child link="bob"/><axis xyz="0 1 0"/>'
            '</joint></robot>')


def test_pendulum_with_a_joint_spring_oscillates_at_the_small_angle_frequency():
    """I th'' = -(k + m g l) th: period 2 pi sqrt(I / (k + m g l)), I = m l^2 + I_bob + the default armature
    (0.1 kg m^2, Genesis's, on every URDF joint), from the zero crossings of a 0.01 rad swing."""
    m, l, i_bob, g, k = 2.0, 0.5, 1e-3, 9.81, 7.0
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "pendulum.urdf")
        with open(path, "w") as f:
            f.write(PENDULUM.format(l=l, m=m, i=i_bob))
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=1e-3, gravity=(0.0, 0.0, -g)), show_viewer=False)
        pend = scene.add_entity(gs.morphs.URDF(file=path, fixed=True))
        scene.build()
    pend.set_dofs_stiffness([k])
    np.testing.assert_allclose(_np(pend.get_dofs_stiffness()), [k])
    pend.set_dofs_position([0.01])
    th = []
    for _ in range(4000):
        scene.step()
        th.append(float(pend.get_dofs_position()[0]))
    th = np.array(th)
    t = 1e-3 * np.arange(1, len(th) + 1)
    s = np.nonzero(np.sign(th[1:]) != np.sign(th[:-1]))[0]
    crossings = t[s] - th[s] * (t[s + 1] - t[s]) / (th[s + 1] - th[s])  # linear interpolation
    period = 2 * np.mean(np.diff(crossings))
    inertia = m * l * l + i_bob + 0.1
    ref = 2 * np.pi * np.sqrt(inertia / (k + m * g * l))
    assert abs(period / ref - 1) < 1e-3, (period, ref)
    # without the spring it swings at the gravity pendulum's frequency: the spring is what changed it
    assert ref < 0.8 * 2 * np.pi * np.sqrt(inertia / (m * g * l))


def test_stiffness_setter_checks_and_free_joint_warning():
    scene = gs.Scene(show_viewer=False)
    cube = scene.add_entity(gs.morphs.Box(size=(SIDE,) * 3, pos=(0.0, 0.0, 1.0)))
    scene.build()
    assert np.all(_np(cube.get_dofs_stiffness()) == 0)
    with pytest.raises(GenesisException, match="stiffness must be >= 0"):
        cube.set_dofs_stiffness([-1.0] * 6)
    with pytest.warns(GenesisWarning, match="free joint has no spring"):
        cube.set_dofs_stiffness([5.0] * 6)
    np.testing.assert_allclose(_np(cube.get_dofs_stiffness()), 5.0)  # kept, as Genesis keeps it
    cube.set_dofs_velocity([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    for _ in range(10):
        scene.step()
    np.testing.assert_allclose(_np(cube.get_dofs_velocity())[5], 1.0, rtol=1e-12)  # no spring torque


SPRING_MJCF = """<mujoco><compiler angle="radian"/><option timestep="{dt}" integrator="Euler" gravity="0 0 -9.81"/><worldbody>
  <body name="a" pos="0 0 1"><joint name="h1" type="hinge" axis="0 1 0" stiffness="20" springref="0.3"/>
    <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
    <body name="b" pos="0.3 0 0"><joint name="h2" type="hinge" axis="0 0.6 0.8" stiffness="0.5" springref="-0.5"/>
      <geom type="sphere" size="0.05"/>
      <body name="c" pos="0.1 0 0"><joint name="s3" type="slide" axis="1 0 0" stiffness="300" springref="0.02"/>
        <geom type="box" size="0.02 0.02 0.02"/></body></body></body></worldbody></mujoco>"""


def test_mjcf_springs_follow_mujoco_trajectory(tmp_path):
    """Hinge and slide springs with springref: 1 s of our Euler steps against MuJoCo's mj_step (Euler, same
    dt, contacts off on both sides), from a state away from rest."""
    mujoco = pytest.importorskip("mujoco")
    dt, n = 1e-3, 1000
    path = tmp_path / "springs.xml"
    path.write_text(SPRING_MJCF.format(dt=dt))
    m = mujoco.MjModel.from_xml_path(str(path))
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    np.testing.assert_allclose(m.qpos_spring, [0.3, -0.5, 0.02])  # the reference reads the file as we do
    m.dof_armature[:] = 0.1  # genesis_lite's default (Genesis's) on joints whose element names no armature
    d = mujoco.MjData(m)
    q0, v0 = np.array([-0.2, 0.4, -0.03]), np.array([0.5, -1.0, 0.1])
    d.qpos[:], d.qvel[:] = q0, v0
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, gravity=(0, 0, -9.81)),
                     rigid_options=gs.options.RigidOptions(integrator=gs.integrator.Euler), show_viewer=False)
    robot = scene.add_entity(gs.morphs.MJCF(file=str(path)))
    scene.build()
    np.testing.assert_allclose(_np(robot.get_dofs_stiffness()), [20.0, 0.5, 300.0])
    robot.set_dofs_position(q0)
    robot.set_dofs_velocity(v0)
    ours, ref = [], []
    for _ in range(n):
        mujoco.mj_step(m, d)
        scene.step()
        ref.append(d.qpos.copy())
        ours.append(_np(robot.get_dofs_position()))
    ours, ref = np.array(ours), np.array(ref)
    gap = np.abs(ours - ref).max()
    assert gap < 1e-8, gap
    # the springs matter: without them the trajectory leaves MuJoCo's by far more
    m.jnt_stiffness[:] = 0.0
    d2 = mujoco.MjData(m)
    d2.qpos[:], d2.qvel[:] = q0, v0
    free = []
    for _ in range(n):
        mujoco.mj_step(m, d2)
        free.append(d2.qpos.copy())
    assert np.abs(np.array(free) - ref).max() > 0.05


# slow: ~50 s on empty caches (the cubes and the arm make a scene whose contacts couple moving bodies, whose
# adjoint kernels are the largest), 13 s warm; the matrix's free_box_pd case checks a free joint's PD by default
@pytest.mark.slow
def test_free_joint_pd_of_several_bodies_on_the_gradient_path():
    """Two free cubes with an arm between them (free joints at links 0 and 3 + n, their dofs not the first of
    the scene for the second): in a requires_grad scene (whose generalised force reads each free joint's
    rotation error from a stage of its own, actuation.func_free_rot_errors) the first PD torques are
    Genesis's law for both cubes, and the gradient of both cubes' motion after 8 steps in the second cube's
    Euler-angle targets (unequal rotational gains) and its start orientation matches central differences
    (the gains' own gradient: the matrix's free_box_pd case)."""
    import torch

    from conftest import ASSETS_DIR

    def build():
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, gravity=(0.0, 0.0, 0.0), requires_grad=True),
                         show_viewer=False)
        a = scene.add_entity(gs.morphs.Box(size=(SIDE,) * 3, pos=(0.0, -1.0, 1.0)), material=gs.materials.Rigid(rho=1000.0))
        scene.add_entity(gs.morphs.URDF(file=str(ASSETS_DIR / "urdf" / "arm.urdf"), fixed=True))
        b = scene.add_entity(gs.morphs.Box(size=(SIDE,) * 3, pos=(0.0, 1.0, 1.0)), material=gs.materials.Rigid(rho=1000.0))
        scene.build()
        for c in (a, b):
            c.set_dofs_kp([KP_LIN] * 3 + [KP_ROT] * 3)
            c.set_dofs_kv([KV_LIN] * 3 + [KV_ROT] * 3)
        return scene, a, b

    scene, a, b = build()
    rng = np.random.default_rng(11)
    starts = [Rotation.random(random_state=rng) for _ in range(2)]
    targets = [np.array([0.4, -0.9, 2.5]), np.array([-1.2, 0.3, 0.7])]
    for c, st, tg, y in zip((a, b), starts, targets, (-1.0, 1.0)):
        c.set_quat(_wxyz(st))
        c.control_dofs_position(np.concatenate([[0.0, y, 1.0], tg]))
    scene.step()
    for c, st, tg in zip((a, b), starts, targets):
        tau = _np(c.get_dofs_control_force())
        body = (st.inv() * Rotation.from_euler("XYZ", tg)).as_rotvec()
        np.testing.assert_allclose(tau[3:], st.apply(KP_ROT * body), rtol=1e-10, atol=1e-14)

    quat_a, quat_b = (torch.tensor(_wxyz(st), dtype=torch.float64) for st in starts)
    kp_rot_b = torch.tensor([KP_ROT * 1.3, KP_ROT * 0.8, KP_ROT * 1.1], dtype=torch.float64)  # unequal gains

    def rollout(target_b, kp_rot_b, quat_b):
        scene.reset()
        a.set_quat(quat_a)
        b.set_quat(quat_b)
        b.set_dofs_kp(torch.cat([torch.full((3,), KP_LIN, dtype=torch.float64), kp_rot_b]))
        a.control_dofs_position(torch.tensor([0.0, -1.0, 1.0, *targets[0]], dtype=torch.float64))
        b.control_dofs_position(torch.cat([torch.tensor([0.0, 1.0, 1.0], dtype=torch.float64), target_b]))
        for _ in range(8):
            scene.step()
        return (b.get_quat() ** 3).sum() + (b.get_ang() ** 2).sum() + (a.get_ang() ** 2).sum()

    report = gs.grad.check(lambda target_b, quat_b: rollout(target_b, kp_rot_b, quat_b),
                           {"target_b": torch.tensor(targets[1]), "quat_b": quat_b}, tol=1e-6)
    print(report)
    assert report.ok, str(report)
