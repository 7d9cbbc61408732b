"""URDF <mimic> joints follow their leader (issue #2)."""
import numpy as np
import torch

import genesis_lite as gs

from conftest import robot_urdf


def _panda(enable_mimic):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01),
                     rigid_options=gs.options.RigidOptions(enable_collision=False, enable_mimic=enable_mimic))
    arm = scene.add_entity(gs.morphs.URDF(file=str(robot_urdf("panda")), fixed=True))
    scene.build()
    return scene, arm


def test_panda_finger_follows_its_leader():
    scene, arm = _panda(True)
    f1 = arm.get_joint("panda_finger_joint1").dof_idx_local
    f2 = arm.get_joint("panda_finger_joint2").dof_idx_local
    kp = torch.zeros(arm.n_dofs, dtype=torch.float64)
    kp[f1] = 200.0
    arm.set_dofs_kp(kp)
    arm.set_dofs_kv(kp / 10)
    # only the leader is driven; the follower starts elsewhere and must join it
    arm.set_dofs_position(torch.tensor([0.0, 0.035], dtype=torch.float64), dofs_idx_local=[f1, f2])
    target = torch.zeros(arm.n_dofs, dtype=torch.float64)
    target[f1] = 0.03
    arm.control_dofs_position(target[[f1]], dofs_idx_local=[f1])
    for _ in range(200):
        scene.step()
    q = arm.get_dofs_position()
    assert abs(q[f1].item() - 0.03) < 2e-3
    assert abs(q[f2].item() - q[f1].item()) < 1e-3  # multiplier 1, offset 0 in the Panda URDF


def test_mimic_can_be_disabled():
    scene, arm = _panda(False)
    f1 = arm.get_joint("panda_finger_joint1").dof_idx_local
    f2 = arm.get_joint("panda_finger_joint2").dof_idx_local
    arm.set_dofs_position(torch.tensor([0.0, 0.035], dtype=torch.float64), dofs_idx_local=[f1, f2])
    scene.step()
    q = arm.get_dofs_position()
    assert abs(q[f2].item() - q[f1].item()) > 0.03


GRIPPER = """<?xml version="1.0"?>
<robot name="gripper">
  <link name="base"><inertial><mass value="1.0"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="finger_a"><inertial><origin xyz="0.01 0.02 -0.03"/><mass value="{ma}"/>
    <inertia ixx="0.0025" iyy="0.003" izz="0.004" ixy="0.0005" ixz="0" iyz="0.0002"/></inertial></link>
  <link name="finger_b"><inertial><origin xyz="-0.02 0.01 0.01"/><mass value="{mb}"/>
    <inertia ixx="0.003" iyy="0.0025" izz="0.002" ixy="0" ixz="0.0003" iyz="0"/></inertial></link>
  <joint name="joint_a" type="prismatic"><parent link="base"/><child link="finger_a"/>
    <origin xyz="0 0.1 0"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="100" velocity="10"/></joint>
  <joint name="joint_b" type="prismatic"><parent link="base"/><child link="finger_b"/>
    <origin xyz="0 -0.1 0" rpy="0.3 0 0"/><axis xyz="0 -1 0"/><limit lower="-2" upper="2" effort="100" velocity="10"/>
    <mimic joint="joint_a" multiplier="{mult}" offset="0"/></joint>
</robot>
"""


def _gripper(tmp_path, ma=0.3, mb=0.5, mult=2.0, requires_grad=False):
    """A fixed base with two prismatic fingers, b mimicking a (b = mult a), no gravity, no geometry."""
    path = tmp_path / "gripper.urdf"
    path.write_text(GRIPPER.format(ma=ma, mb=mb, mult=mult))
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, gravity=(0.0, 0.0, 0.0), requires_grad=requires_grad))
    robot = scene.add_entity(gs.morphs.URDF(file=str(path), fixed=True))
    scene.build()
    return scene, robot


def test_a_mimic_pair_moves_as_one_body(tmp_path):
    """A follower b = m a is rigidly tied to its leader: a force F on a accelerates the pair as one
    body, a'' = F / (m_a + m^2 m_b) (virtual work: the kinetic energy is (m_a + m^2 m_b) a'^2 / 2), and
    a force G on b gives a'' = m G / (m_a + m^2 m_b). (Copying the leader's motion onto the follower
    after each step, as before 2026-11-28, gave F / m_a and 0.) Each slide's default armature (0.1 kg,
    Genesis's) adds to its mass."""
    mult = 2.0
    scene, robot = _gripper(tmp_path, 0.3, 0.5, mult)
    ma, mb = 0.3 + 0.1, 0.5 + 0.1
    a = robot.get_joint("joint_a").dof_idx_local
    b = robot.get_joint("joint_b").dof_idx_local
    h, n = 0.01, 20
    for force, expected in (([1.5, 0.0], 1.5 / (ma + mult ** 2 * mb)), ([0.0, 0.8], mult * 0.8 / (ma + mult ** 2 * mb))):
        robot.set_dofs_position(np.zeros(2), dofs_idx_local=[a, b])
        robot.set_dofs_velocity(np.zeros(2), dofs_idx_local=[a, b])
        for _ in range(n):
            robot.control_dofs_force(np.array(force), dofs_idx_local=[a, b])
            scene.step()
        v = robot.get_dofs_velocity().numpy()
        q = robot.get_dofs_position().numpy()
        np.testing.assert_allclose(v[a], n * h * expected, rtol=1e-9)
        # semi-implicit Euler under a constant acceleration: q_n = h^2 a n (n + 1) / 2
        np.testing.assert_allclose(q[a], h * h * expected * n * (n + 1) / 2, rtol=1e-9)
        np.testing.assert_allclose([q[b], v[b]], [mult * q[a], mult * v[a]], rtol=1e-12)


def test_grad_through_a_mimic_pair(tmp_path):
    """Gradients of the pair's motion in the forces on each finger, the leader's initial velocity and
    the links' masses, against central finite differences in float64."""
    scene, robot = _gripper(tmp_path, requires_grad=True)
    a = robot.get_joint("joint_a").dof_idx_local
    b = robot.get_joint("joint_b").dof_idx_local
    s0 = scene.get_state()

    def loss(force, v0, mass):
        scene.reset(s0)
        robot.set_links_mass(mass)
        robot.set_dofs_velocity(torch.stack([v0, torch.zeros((), dtype=torch.float64)]), dofs_idx_local=[a, b])
        for t in range(5):
            robot.control_dofs_force(force[t], dofs_idx_local=[a, b])
            scene.step()
        q = robot.get_dofs_position()
        return q[a] + 0.3 * q[b] + 0.2 * robot.get_dofs_velocity()[a]

    force = torch.tensor(np.random.default_rng(3).normal(0, 1, (5, 2)), dtype=torch.float64)
    v0 = torch.tensor(0.2, dtype=torch.float64)
    mass = torch.tensor([1.0, 0.35, 0.45], dtype=torch.float64)
    rep = gs.grad.check(loss, {"force": force, "v0": v0, "mass": mass}, eps=1e-6, tol=1e-6)
    assert rep.ok, str(rep)
    # the follower's force and mass act on the leader
    assert float(rep.autograd[0][:, 1].abs().min()) > 1e-5 and float(rep.autograd[2][2].abs()) > 1e-5
