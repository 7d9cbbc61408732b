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
