"""Genesis's kinematics API (issue #25): forward_kinematics at any configuration, get_jacobian and
inverse_kinematics, against references nobody here wrote:
- the link poses of the scene's own state (the solver's kinematics kernel) and Pinocchio's frame placements
  and frame Jacobians (LOCAL_WORLD_ALIGNED) on the Panda of example-robot-data;
- for a free base, J v against the solver's link velocity for a random velocity;
- IK: the solver's link pose at the returned configuration hits the target; d FK(IK(p)) / dp is the
  identity (what any exact IK map satisfies), through torch's autograd of the returned qpos.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
import torch

import genesis_lite as gs
from conftest import robot_urdf

LINK = "panda_link7"  # the hand is merged into it (fixed joint)


@pytest.fixture(scope="module")
def panda_go2():
    scene = gs.Scene(rigid_options=gs.options.RigidOptions(enable_collision=False))
    panda = scene.add_entity(gs.morphs.URDF(file=str(robot_urdf("panda")), fixed=True), name="panda")
    go2 = scene.add_entity(gs.morphs.URDF(file=str(robot_urdf("go2")), pos=(1.0, 0.0, 0.5)), name="go2")
    scene.build()
    return scene, panda, go2


def _pin_panda():
    model = pin.buildModelFromUrdf(str(robot_urdf("panda")))
    return model, model.createData()


def _random_panda_q(rng, panda):
    lo, hi = (t.numpy() for t in panda.get_dofs_limit())
    return rng.uniform(np.maximum(lo, -2.5), np.minimum(hi, 2.5))


def test_forward_kinematics_and_jacobian_match_the_solver_and_pinocchio(panda_go2):
    scene, panda, go2 = panda_go2
    rng = np.random.default_rng(3)
    q = _random_panda_q(rng, panda)
    panda.set_qpos(q)
    qg = go2.get_qpos().numpy().copy()
    qg[7:] += rng.uniform(-0.5, 0.5, 12)
    quat = rng.normal(size=4)
    qg[3:7] = quat / np.linalg.norm(quat)
    go2.set_qpos(qg)
    for ent in (panda, go2):
        pos, quat = ent.forward_kinematics(ent.get_qpos())
        np.testing.assert_allclose(pos.numpy(), ent.get_links_pos().numpy(), atol=1e-12)
        dq = np.minimum(np.abs(quat.numpy() - ent.get_links_quat().numpy()).max(-1),
                        np.abs(quat.numpy() + ent.get_links_quat().numpy()).max(-1))
        assert dq.max() < 1e-12

    model, data = _pin_panda()
    fid = model.getFrameId(LINK)
    J_pin = pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL_WORLD_ALIGNED)
    J = panda.get_jacobian(panda.get_link(LINK)).numpy()
    np.testing.assert_allclose(J, J_pin, atol=1e-12)
    # a point off the origin: v_p = v_o + w x r
    r_local = np.array([0.02, -0.01, 0.1])
    R = pin.updateFramePlacement(model, data, fid).rotation
    Jp = panda.get_jacobian(panda.get_link(LINK), local_point=r_local).numpy()
    np.testing.assert_allclose(Jp[:3], J_pin[:3] - np.cross(R @ r_local, J_pin[3:].T).T, atol=1e-12)

    # free base: J v is the velocity the solver's kinematics gives the link origin
    v = rng.normal(size=go2.n_dofs)
    go2.set_dofs_velocity(v)
    for li in (0, 5, 12):
        Jg = go2.get_jacobian(go2.links[li]).numpy()
        np.testing.assert_allclose(Jg[:3] @ v, go2.get_links_vel()[li].numpy(), atol=1e-12)
        np.testing.assert_allclose(Jg[3:] @ v, go2.get_links_ang()[li].numpy(), atol=1e-12)


def test_inverse_kinematics_reaches_a_pose_and_its_gradient_is_the_implicit_one(panda_go2):
    scene, panda, go2 = panda_go2
    rng = np.random.default_rng(11)
    link = panda.get_link(LINK)
    q_goal = _random_panda_q(rng, panda)
    p_goal, quat_goal = (t[link.idx_local] for t in panda.forward_kinematics(torch.tensor(q_goal)))
    panda.set_qpos(_random_panda_q(rng, panda))
    q_before = panda.get_qpos().numpy().copy()
    sol, err = panda.inverse_kinematics(link, pos=p_goal, quat=quat_goal, return_error=True)
    np.testing.assert_array_equal(panda.get_qpos().numpy(), q_before)  # the scene's state is left alone
    panda.set_qpos(sol.detach())
    p, quat = panda.get_links_pos()[link.idx_local].numpy(), panda.get_links_quat()[link.idx_local].numpy()
    assert np.linalg.norm(p - p_goal.numpy()) < 5e-4
    assert 2 * np.arccos(min(1.0, abs(float(quat @ quat_goal.numpy())))) < 5e-3
    lo, hi = (t.numpy() for t in panda.get_dofs_limit())
    assert np.all(sol.detach().numpy() >= lo - 1e-12) and np.all(sol.detach().numpy() <= hi + 1e-12)

    # position only: FK(IK(p)) = p for every reachable p, so its Jacobian in p is the identity; the damped
    # step (damping 0.01) leaves an error of order damping^2 / sigma^2
    target = p_goal.clone().requires_grad_(True)
    q_sol = panda.inverse_kinematics(link, pos=target)
    reached = panda.forward_kinematics(q_sol)[0][link.idx_local]
    D = torch.stack([torch.autograd.grad(reached[i], target, retain_graph=True)[0] for i in range(3)])
    np.testing.assert_allclose(D.numpy(), np.eye(3), atol=5e-3)


def test_inverse_kinematics_per_env_targets_and_bad_input():
    scene = gs.Scene(rigid_options=gs.options.RigidOptions(enable_collision=False))
    panda = scene.add_entity(gs.morphs.URDF(file=str(robot_urdf("panda")), fixed=True), name="panda")
    scene.build(n_envs=3)
    rng = np.random.default_rng(5)
    link = panda.get_link(LINK)
    goals = np.stack([_random_panda_q(rng, panda) for _ in range(3)])
    p_goal = panda.forward_kinematics(torch.tensor(goals))[0][:, link.idx_local]
    sol = panda.inverse_kinematics(link, pos=p_goal)
    assert tuple(sol.shape) == (3, panda.n_qs)
    panda.set_qpos(sol.detach())
    assert (panda.get_links_pos()[:, link.idx_local] - p_goal).norm(dim=-1).max() < 5e-4
    with pytest.raises(gs.GenesisException, match="pos and/or quat"):
        panda.inverse_kinematics(link)
    with pytest.raises(gs.GenesisException, match="expected"):
        panda.inverse_kinematics(link, pos=np.zeros((2, 3)))


def test_kept_fixed_link_moves_with_its_parent_and_changes_no_dynamics(panda_go2):
    """Genesis's links_to_keep: panda_hand (fixed to panda_link8, itself fixed to panda_link7) stays a link of
    its own. Its pose is Pinocchio's frame placement; the mass matrix and a 30-step rollout equal those of the
    robot with the hand merged (the same rigid body, described twice)."""
    _, merged, _ = panda_go2
    scene = gs.Scene(rigid_options=gs.options.RigidOptions(enable_collision=False))
    kept = scene.add_entity(gs.morphs.URDF(file=str(robot_urdf("panda")), fixed=True, links_to_keep=["panda_hand"]))
    scene.build()
    names = [l.name for l in kept.links]
    assert "panda_hand" in names and "panda_hand" not in [l.name for l in merged.links]
    assert kept.get_joint("panda_hand_joint").type == "fixed" and kept.n_dofs == merged.n_dofs
    q = _random_panda_q(np.random.default_rng(2), merged)
    for ent in (merged, kept):
        ent.set_qpos(q)
        ent.set_dofs_velocity(np.zeros(ent.n_dofs))
    np.testing.assert_allclose(kept.get_mass_mat().numpy(), merged.get_mass_mat().numpy(), atol=1e-12)
    model, data = _pin_panda()
    pin.framesForwardKinematics(model, data, q)
    hand = kept.get_link("panda_hand")
    np.testing.assert_allclose(kept.get_links_pos()[hand.idx_local].numpy(),
                               data.oMf[model.getFrameId("panda_hand")].translation, atol=1e-12)
    merged._scene.reset()
    merged.set_qpos(q)
    for _ in range(30):
        scene.step()
        merged._scene.step()
    np.testing.assert_allclose(kept.get_qpos().numpy(), merged.get_qpos().numpy(), atol=1e-10)
    with pytest.raises(ValueError, match="links_to_keep"):
        gs.morphs.URDF(file=str(robot_urdf("panda")), links_to_keep="panda_hand")
