"""Joint limits: Genesis's (and MuJoCo's) soft limit constraint, the default (solvers/rigid/actuation.py,
func_limit_constraint and func_limit_release).

- Against MuJoCo on the same file: a double pendulum thrown into narrowed limits (both joints past a limit,
  pushed back and released) follows MuJoCo's mj_step with its default solref / solimp to round-off, with
  either integrator; the constraint's inverse weights are MuJoCo's dof_invweight0.
- Every path that computes a step gives the same numbers: the fused step, the gradient path's op-by-op
  launches, a scene with a plane the arm never reaches (the contact solve's own release rounds, and the
  gradient path's lazy contact check), a specialised core (the unrolled factorisation).
- The springs stay available (RigidOptions(joint_limit_stiffness=...)), and without limits nothing is
  computed for them.
Gradients through active and released limits, and through the inverse weights' dependence on the armature,
are in the gradient matrix (tests/gradient_cases.py, the arm_limit cases).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import genesis_lite as gs

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import scenes as S  # noqa: E402

DT = 0.01
LIMITS = ((-0.5, 0.5), (-0.7, 0.4))  # rad: the pendulum's two joints
Q0, V0 = np.array([0.3, -0.2]), np.array([4.0, -3.0])  # thrown into both upper limits, then the lower of joint 1


@pytest.fixture(scope="module")
def pendulum_urdf(tmp_path_factory):
    """assets/urdf/double_pendulum.urdf with its wide limits narrowed to LIMITS."""
    text = S.PENDULUM_URDF.read_text()
    for lo, hi in LIMITS:
        text = text.replace('lower="-12.566" upper="12.566"', f'lower="{lo}" upper="{hi}"', 1)
    path = tmp_path_factory.mktemp("limits") / "double_pendulum_limited.urdf"
    path.write_text(text)
    return path


def _pendulum(urdf, n_steps, integrator="approximate_implicitfast", requires_grad=False, plane=False, **rigid):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT, gravity=(0.0, 0.0, -S.G), requires_grad=requires_grad),
                     rigid_options=gs.options.RigidOptions(integrator=getattr(gs.integrator, integrator), **rigid))
    if plane:  # 2 m below the pivot: the pendulum (0.9 m long) never reaches it
        scene.add_entity(gs.morphs.Plane(pos=(0.0, 0.0, -2.0)))
    p = scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=True))
    scene.build()
    p.set_dofs_armature(np.zeros(2))
    p.set_dofs_damping(np.zeros(2))
    p.set_dofs_position(torch.tensor(Q0))
    p.set_dofs_velocity(torch.tensor(V0))
    out = []
    for _ in range(n_steps):
        scene.step()
        out.append(np.concatenate([p.get_dofs_position().detach().numpy(), p.get_dofs_velocity().detach().numpy()]))
    return np.array(out), scene


@pytest.mark.parametrize("integrator", ["Euler", "implicitfast"])
def test_limits_follow_mujoco(pendulum_urdf, integrator):
    """150 steps of 10 ms: ours against MuJoCo's mj_step on the same URDF (default solref (0.02, 1) and solimp
    (0.9, 0.95, 0.001, 0.5, 2), the model's dof_invweight0). Measured 2026-11-29: 9e-15 rad apart over the
    whole run. With the penalty springs the default was before (1e4 N m/rad, 1e2 N m s/rad) the run ends up to
    0.33 rad away from MuJoCo's (Euler)."""
    import mujoco

    ours, scene = _pendulum(pendulum_urdf, 150, integrator)
    m = S.mujoco_from_urdf(pendulum_urdf, limits=True, contacts=False)
    S.set_mujoco_integrator(m, integrator, DT)
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = Q0, V0
    theirs = []
    for _ in range(150):
        mujoco.mj_step(m, d)
        theirs.append(np.concatenate([d.qpos, d.qvel]))
    theirs = np.array(theirs)
    q = ours[:, :2]
    # the run does what it is for: joint 1 past both of its limits, joint 2 past its upper one
    assert q[:, 0].max() > LIMITS[0][1] + 0.01 and q[:, 0].min() < LIMITS[0][0] - 0.005
    assert q[:, 1].max() > LIMITS[1][1] + 0.01
    np.testing.assert_allclose(scene._rigid.params["invweight"][0].numpy(), m.dof_invweight0, rtol=1e-9)
    np.testing.assert_allclose(ours[:, :2], theirs[:, :2], rtol=0, atol=1e-10)
    np.testing.assert_allclose(ours[:, 2:], theirs[:, 2:], rtol=0, atol=1e-8)


def test_every_step_path_gives_the_same_limits(pendulum_urdf):
    """The fused step (no gradients), the gradient path's op-by-op launches, a plane in the scene (the contact
    solve and its release rounds; on the gradient path the lazy check runs the core's kernels), and a
    specialised core (its factorisation unrolled): the same trajectory to round-off."""
    ref, _ = _pendulum(pendulum_urdf, 60)
    for kw in (dict(requires_grad=True), dict(plane=True), dict(plane=True, requires_grad=True),
               dict(specialize_kernels=True), dict(plane=True, specialize_kernels=True)):
        got, _ = _pendulum(pendulum_urdf, 60, **kw)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12, err_msg=str(kw))


def test_springs_on_request_and_nothing_without_limits(pendulum_urdf):
    """RigidOptions(joint_limit_stiffness=...) keeps the penalty springs (another trajectory, still held near
    the limits); enable_joint_limit=False lets the joints through."""
    con, _ = _pendulum(pendulum_urdf, 60)
    spr, scene = _pendulum(pendulum_urdf, 60, joint_limit_stiffness=1e4, joint_limit_damping=1e2)
    free, _ = _pendulum(pendulum_urdf, 60, enable_joint_limit=False)
    assert np.abs(spr[:, :2] - con[:, :2]).max() > 1e-3
    assert spr[:, 0].max() < LIMITS[0][1] + 0.15
    assert free[:, 0].max() > LIMITS[0][1] + 0.3
    assert scene._rigid.solver.limit_model == 1  # the springs
    with pytest.raises(ValueError, match="joint_limit_stiffness"):
        gs.options.RigidOptions(joint_limit_stiffness=-1.0)
    with pytest.raises(ValueError, match="constraint_timeconst"):
        gs.options.RigidOptions(constraint_timeconst=0.0)


MASSLESS_ARM = """<robot name="massless_arm">
  <link name="base"/>
  <link name="tip">
    <inertial><origin xyz="0 0 0.2"/><mass value="1.0"/>
      <inertia ixx="0" iyy="0" izz="0" ixy="0" ixz="0" iyz="0"/></inertial>
  </link>
  <joint name="hinge" type="revolute">
    <parent link="base"/><child link="tip"/><axis xyz="0 0 1"/>
    <limit lower="-0.5" upper="0.5" effort="10" velocity="5"/>
  </joint>
</robot>
"""


def test_a_joint_that_moves_no_mass_needs_an_armature(tmp_path):
    """The limit constraint's impedance divides by the dof's inverse weight (M0 + armature)^-1: a limited hinge
    turning a point mass on its own axis moves no mass (M0 = 0) and has one only through its armature.
    With the default armature (0.1 kg m^2) the inverse weight is 1 / 0.1; without one, the build, and an
    armature set to 0 later, raise GenesisException naming the entity and the remedies."""
    urdf = tmp_path / "massless_arm.urdf"
    urdf.write_text(MASSLESS_ARM)

    def build(**morph):
        scene = gs.Scene(rigid_options=gs.options.RigidOptions(enable_collision=False))
        arm = scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=True, **morph))
        scene.build()
        return arm

    arm = build()
    np.testing.assert_allclose(arm.get_dofs_invweight()[0].numpy(), [10.0], rtol=1e-12)
    with pytest.raises(gs.GenesisException, match="massless_arm.*singular.*armature"):
        arm.set_dofs_armature(np.zeros(1))
    with pytest.raises(gs.GenesisException, match="massless_arm.*singular.*joint_limit_stiffness"):
        build(default_armature=None)


MJCF_CHAIN = """<mujoco model="limited_chain">
  <compiler angle="radian"/>
  <option timestep="0.01" gravity="0 0 -9.81"/>
  <worldbody>
    <body name="a" pos="0 0 1">
      <joint name="j1" type="hinge" axis="0 1 0" range="-0.3 0.3" limited="true"
             solreflimit="0.05 0.6" solimplimit="0.5 0.99 0.02 0.3 3"/>
      <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03" mass="1.2"/>
      <body name="b" pos="0.4 0 0">
        <joint name="j2" type="hinge" axis="0.3 1 0.2" range="-0.2 0.5" limited="true" solimplimit="0 0.99 0.01"/>
        <geom type="box" size="0.15 0.03 0.02" pos="0.15 0 0" mass="0.7"/>
        <body name="c" pos="0.3 0 0">
          <joint name="j3" type="slide" axis="1 0 0" range="-0.05 0.04" limited="true"/>
          <geom type="sphere" size="0.04" mass="0.3"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("integrator,angle", [("Euler", "radian"), ("implicitfast", "radian"), ("Euler", "degree")])
def test_mjcf_joints_own_solref_and_solimp(tmp_path, integrator, angle):
    """An MJCF joint's solreflimit / solimplimit are its limit constraint's, as Genesis reads them: a chain whose
    hinge has its own time constant, damping ratio and a cubic impedance curve, a second hinge (skewed axis) with
    MuJoCo's soft-start impedance (dmin 0), a slide with the defaults, thrown into its limits, follows MuJoCo's
    mj_step on the same file (no armature on either side) to round-off. With the ranges read in degrees (a
    fraction of a degree wide) the three joints are past their limits together, most steps: the set of limits
    that push is then coupled (releasing one drives another back into its limit), and the rounds that release
    and bring back limits reach MuJoCo's (measured 2026-11-29: 9e-10 rad; with releases only, 1.6e-2)."""
    import mujoco

    path = tmp_path / "chain.xml"
    path.write_text(MJCF_CHAIN.replace('angle="radian"', f'angle="{angle}"'))
    q0, v0 = np.array([0.25, 0.4, 0.0]), np.array([2.5, 3.0, 0.6])
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT, gravity=(0.0, 0.0, -9.81)),
                     rigid_options=gs.options.RigidOptions(integrator=getattr(gs.integrator, integrator),
                                                           enable_collision=False))
    chain = scene.add_entity(gs.morphs.MJCF(file=str(path), default_armature=None))
    scene.build()
    chain.set_dofs_position(torch.tensor(q0))
    chain.set_dofs_velocity(torch.tensor(v0))
    m = mujoco.MjModel.from_xml_path(str(path))
    S.set_mujoco_integrator(m, integrator, DT)
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = q0, v0
    ours, theirs = [], []
    for _ in range(120):
        scene.step()
        mujoco.mj_step(m, d)
        ours.append(chain.get_dofs_position().numpy().copy())
        theirs.append(d.qpos.copy())
    ours, theirs = np.array(ours), np.array(theirs)
    lim = m.jnt_range
    # each joint goes past one of its limits at some point
    assert all((ours[:, k] > lim[k, 1] + 1e-3).any() or (ours[:, k] < lim[k, 0] - 1e-3).any() for k in range(3))
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-8)


def _evaluation_values(s):
    """What an evaluation leaves for its adjoint (poses, velocities, composite inertias, M, forces, the limit
    terms, qacc) in scene `s`'s envs."""
    names = ("link_pos", "link_quat", "cvel_w", "cvel_v", "crb_J", "mass_mat", "bias", "force", "dof_lim_D",
             "dof_lim_f", "dof_lim_off")
    out = {k: getattr(s, k).to_numpy()[:s.n_envs] for k in names}
    out["qacc"] = s.qacc.to_numpy()[:, :s.n_envs]
    return out


# with contacts: the contact stages' gradient kernels compiled for this test alone (~25 s); under -m slow
@pytest.mark.parametrize("contacts", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_the_gradient_path_s_evaluation_in_one_loop_gives_the_stage_loops_numbers_to_the_bit(pendulum_urdf, contacts):
    """A gradient scene's forward evaluates its dynamics in one loop over envs with the final solve and its limit
    rounds per env (RigidCore.kernel_evaluate); its adjoint differentiates the stages as separate loops
    (kernel_dynamics_part) with the rounds over all envs. Both forms at every step of a 3-env rollout (the envs
    reach and leave their limits at different steps; with `contacts` boxes landing on a plane beside the
    pendulum, whose contact stages join the loop): the same numbers to the bit."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT, gravity=(0.0, 0.0, -S.G), requires_grad=True))
    if contacts:
        scene.add_entity(gs.morphs.Plane(pos=(0.0, 0.0, -2.5)))  # the pendulum's bob reaches z = -2.05
        for k in range(2):
            scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(1.0 + 0.5 * k, 0.0, -2.35 + 0.25 * k),
                                           euler=(5.0 * k, 10.0, 0.0)))
    p = scene.add_entity(gs.morphs.URDF(file=str(pendulum_urdf), fixed=True))
    scene.build(n_envs=3)
    p.set_dofs_position(torch.tensor(np.tile(Q0, (3, 1))))
    p.set_dofs_velocity(torch.tensor(np.array([V0, 0.5 * V0, -V0])))
    s = scene._rigid.solver.step_core
    changed = 0
    for _ in range(40):
        s.kernel_dynamics(0, 0, DT)
        if s.has_contact:
            s.contact.factor_solve(s, 0)
        else:
            s.kernel_mass_solve(0, False)
            s.release_limits(0)
        stages = _evaluation_values(s)
        s.kernel_evaluate(0, 0, DT)
        if s.has_contact:
            s.contact.factor_solve(s, 0)
        one_loop = _evaluation_values(s)
        for k, a in stages.items():
            assert np.array_equal(a, one_loop[k]), (k, np.abs(a - one_loop[k]).max())
        changed += int(np.any(stages["dof_lim_off"] == 1))
        scene.step()
    assert changed >= 5  # limits released (dof_lim_off) at several of the steps compared
    if contacts:
        assert s.contact.n_slots > 0 and np.abs(stages["force"]).max() > 0
