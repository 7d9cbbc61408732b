"""Genesis's rigid-entity API names that its example scripts use (issue #25), written as a Genesis user
writes them, each checked against what the name means rather than against our own output:
- control_dofs_position_velocity: the PD law with both targets, on a joint whose motion is known in
  closed form (no gravity, one inertia);
- set_mass_shift / set_COM_shift / set_links_inertial_mass: the model's values plus the shift, seen in the
  total mass and in the static torque gravity puts on a joint; a shift below minus the model mass gives
  Genesis's negative mass while the mass matrix stays positive definite (closed form), refused otherwise;
- a URDF with PyBullet's `<?xml version="0.0" ?>` header (Genesis's plane.urdf) loads;
- entity.set_mass / link.set_mass (mass and inertia scaled together, fixed links left alone) and
  rigid_solver.links_info, against the mass matrix's closed form sum(I + m x^2);
- set_friction_ratio: the model's coefficient times the ratio on the named links' geoms only, and a box
  that slides or sticks on a slope as Coulomb's law says for tan(slope) against the new coefficient;
- get_AABB: against the corners of the boxes and spheres it encloses;
- a slice as dofs_idx_local, a boolean envs_idx mask, base_joint, get_dofs_invweight (diag of M^-1);
- entity.uid (Genesis's UID: 32 hex digits, short() the first 7) and scene.get_entity / entity_names;
- RigidJoint.dofs_idx / qs_idx / dof_start / q_start (the scene's numbering) against the scene's state
  vectors, and their _local forms against the entity's own getters, on an entity that is not the first;
- gs.tools.Timer against the wall clock;
- gs.materials.Rigid(coup_softness=0.0), Genesis's hard boundary, in a coupled scene;
- scene.add_emitter / emitter.emit in sand_wheel's loop (tests/test_emitter.py checks emitters in full).
"""
from __future__ import annotations

import os
import re
import tempfile
import time
import uuid
import warnings

import numpy as np
import pytest
import torch

import genesis_lite as gs
from genesis_lite.errors import GenesisWarning

ARM = ('<robot name="arm"><link name="base"/>'
       '<link name="upper"><inertial><origin xyz="0.3 0 0"/><mass value="2.0"/>'
       '<inertia ixx="0.01" iyy="0.05" izz="0.05" ixy="0" ixz="0" iyz="0"/></inertial>'
       '<collision><origin xyz="0.3 0 0"/><geometry><box size="0.6 0.1 0.1"/></geometry></collision></link>'
       '<link name="fore"><inertial><origin xyz="0.2 0 0"/><mass value="1.0"/>'
       '<inertia ixx="0.005" iyy="0.02" izz="0.02" ixy="0" ixz="0" iyz="0"/></inertial>'
       '<collision><origin xyz="0.2 0 0"/><geometry><sphere radius="0.05"/></geometry></collision></link>'
       '<joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/><axis xyz="0 1 0"/>'
       '<limit lower="-3" upper="3" effort="100" velocity="10"/></joint>'
       '<joint name="elbow" type="revolute"><parent link="upper"/><child link="fore"/><origin xyz="0.6 0 0"/>'
       '<axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="100" velocity="10"/></joint></robot>')


@pytest.fixture(scope="module")
def arm_path():
    with tempfile.TemporaryDirectory() as d:
        p = os.path.join(d, "arm.urdf")
        with open(p, "w") as f:
            f.write(ARM)
        yield p


def _arm_scene(path, n_envs=0, gravity=(0, 0, -9.81), dt=1e-3):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, gravity=gravity), show_viewer=False)
    arm = scene.add_entity(gs.morphs.URDF(file=path, fixed=True), name="arm")
    scene.build(n_envs=n_envs)
    return scene, arm


def test_position_velocity_control_follows_the_pd_law(arm_path):
    """Without gravity, kp (q* - q) + kv (v* - v) with a constant v* != 0 comes to rest where the law alone
    says: q = q* + kv v* / kp (the elbow is held at 0 by a stiff PD)."""
    scene, arm = _arm_scene(arm_path, gravity=(0, 0, 0))
    kp, kv, q_t, v_t = 200.0, 40.0, 0.4, 0.5
    arm.set_dofs_kp([kp, 5000.0])
    arm.set_dofs_kv([kv, 200.0])
    arm.control_dofs_position_velocity([q_t, 0.0], [v_t, 0.0])
    for _ in range(3000):
        scene.step()
    q = arm.get_dofs_position().numpy()
    np.testing.assert_allclose(q[0], q_t + kv * v_t / kp, atol=1e-4)
    assert abs(arm.get_dofs_velocity()[0].item()) < 1e-4
    assert abs(q[1]) < 1e-4


def test_mass_and_com_shifts_act_as_in_genesis(arm_path):
    """Held at the horizontal by a known torque: the static torque gravity puts on the shoulder is
    g * sum(m_i x_i) over the links' centres of mass; the shifts change m and x by what they say."""
    scene, arm = _arm_scene(arm_path)
    g = 9.81

    def shoulder_gravity_torque():
        # one step from rest with zero control: the shoulder's acceleration times the mass matrix row gives
        # the generalised gravity force (elbow locked by a stiff PD at 0)
        arm.set_dofs_kp([1e6], dofs_idx_local=[1])
        arm.set_dofs_kv([1e4], dofs_idx_local=[1])
        arm.control_dofs_force([0.0], dofs_idx_local=[0])
        arm.control_dofs_position([0.0], dofs_idx_local=[1])
        arm.set_dofs_position([0.0, 0.0])
        arm.set_dofs_velocity([0.0, 0.0])
        M = arm.get_mass_mat().numpy()
        scene.step()
        a = arm.get_dofs_acc().numpy()
        return float(M[0] @ a)  # the elbow's row carries the PD's reaction, the shoulder's does not

    base = shoulder_gravity_torque()
    # links: upper 2 kg at x = 0.3, fore 1 kg at x = 0.6 + 0.2; y is the axis, -z gravity: torque = +g sum m x
    np.testing.assert_allclose(base, g * (2.0 * 0.3 + 1.0 * 0.8), rtol=2e-3)
    arm.set_mass_shift([0.5, -0.25], links_idx_local=[1, 2])
    np.testing.assert_allclose(arm.get_links_mass([1, 2]).numpy(), [2.5, 0.75], atol=1e-12)
    arm.set_COM_shift([[0.1, 0.0, 0.0]], links_idx_local=[2])
    np.testing.assert_allclose(arm.get_links_COM([2]).numpy(), [[0.3, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(shoulder_gravity_torque(), g * (2.5 * 0.3 + 0.75 * 0.9), rtol=2e-3)
    # a second shift replaces the first (it is relative to the model, not cumulative)
    arm.set_mass_shift([0.0, 0.0], links_idx_local=[1, 2])
    arm.set_links_inertial_mass([3.0], links_idx_local=[1])
    np.testing.assert_allclose(arm.get_links_mass([1, 2]).numpy(), [3.0, 1.0], atol=1e-12)


def test_a_mass_shift_below_the_model_mass_gives_genesis_s_negative_mass_while_the_equations_hold(arm_path):
    """Genesis's set_mass_shift takes any shift (its domain_randomization example draws -0.5 .. 0.5 kg for
    every link of a Go2, whose calves weigh 0.265 kg): the link then has a negative mass. So does ours, with a
    warning, while the joint-space mass matrix (armature included) stays positive definite; where it would
    not, the shift (or a later COM shift) is refused and nothing changes. Checked against the closed form
    at q = 0 (links along x, axes along y): M = [[Iu + mu xu^2 + If + mf xf^2 + a, If + mf 0.2 xf],
    [., If + mf 0.2^2 + a]] (xf = 0.8 the forearm's COM from the shoulder, a = 0.1 Genesis's armature), and
    the first step from rest with no control, M qdd = g [mu xu + mf xf, mf 0.2]."""
    scene, arm = _arm_scene(arm_path)
    g, a = 9.81, 0.1

    def closed_form(mu, mf, x_el=0.2):
        xf = 0.6 + x_el
        M = np.array([[0.05 + mu * 0.3 ** 2 + 0.02 + mf * xf ** 2 + a, 0.02 + mf * x_el * xf],
                      [0.02 + mf * x_el * xf, 0.02 + mf * x_el ** 2 + a]])
        return M, g * np.array([mu * 0.3 + mf * xf, mf * x_el])

    with pytest.warns(GenesisWarning, match=r"link 'fore' has a mass of -0.2 kg after set_mass_shift"):
        arm.set_mass_shift([-1.2], links_idx_local=[2])
    np.testing.assert_allclose(arm.get_links_mass([2]).numpy(), [-0.2], atol=1e-12)
    M, tau = closed_form(2.0, -0.2)
    assert np.linalg.eigvalsh(M).min() > 0
    np.testing.assert_allclose(arm.get_mass_mat().numpy(), M, rtol=1e-9)
    arm.set_dofs_position([0.0, 0.0])
    arm.set_dofs_velocity([0.0, 0.0])
    scene.step()
    np.testing.assert_allclose(arm.get_dofs_acc().numpy(), np.linalg.solve(M, tau), rtol=1e-6)
    assert arm.get_dofs_acc()[1].item() < 0  # the forearm's negative weight turns it up (qdd < 0: +x to +z)

    # -0.5 kg: det M = 0.03 * 0.1 - 0.06^2 < 0, refused, the -0.2 kg kept
    assert np.linalg.eigvalsh(closed_form(2.0, -0.5)[0]).min() < 0
    with pytest.raises(gs.GenesisException, match=r"link 'fore' has a mass of -0.5 kg after set_mass_shift.*"
                                                   r"not positive definite"):
        arm.set_mass_shift([-1.5], links_idx_local=[2])
    np.testing.assert_allclose(arm.get_links_mass([2]).numpy(), [-0.2], atol=1e-12)
    # the forearm's COM moved out to 1 m from the elbow: its M entry 0.02 - 0.2 + 0.1 < 0, refused as well
    assert np.linalg.eigvalsh(closed_form(2.0, -0.2, x_el=1.0)[0]).min() < 0
    with pytest.raises(gs.GenesisException, match=r"after set_COM_shift.*not positive definite"):
        arm.set_COM_shift([[0.8, 0.0, 0.0]], links_idx_local=[2])
    np.testing.assert_allclose(arm.get_mass_mat().numpy(), M, rtol=1e-9)
    # -0.4 kg holds with the elbow's armature (det 0.094 * 0.104 - 0.044^2 > 0), not without it (0.094 * 0.004)
    with pytest.warns(GenesisWarning, match=r"link 'fore' has a mass of -0.4 kg"):
        arm.set_mass_shift([-1.4], links_idx_local=[2])
    with pytest.raises(gs.GenesisException, match=r"after set_dofs_armature.*not positive definite"):
        arm.set_dofs_armature([0.1, 0.0])
    np.testing.assert_allclose(arm.get_mass_mat().numpy(), closed_form(2.0, -0.4)[0], rtol=1e-9)
    # a shift that leaves every mass positive again: no warning, the model's matrix plus the shift
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        arm.set_mass_shift([0.5], links_idx_local=[2])
    np.testing.assert_allclose(arm.get_mass_mat().numpy(), closed_form(2.0, 1.5)[0], rtol=1e-9)


def test_set_mass_scales_links_as_genesis_and_links_info_reads_them(arm_path):
    """Genesis's RigidLink.set_mass scales the link's inertia with its mass (a uniformly denser body) and
    RigidEntity.set_mass scales every link that moves by mass / get_mass(); a link fixed to the world is
    left alone with a warning. Checked on the shoulder's mass-matrix entry at q = 0, which is
    sum(Iyy + m x^2) over the links below it (x: centre of mass from the shoulder axis), and on the elbow's,
    Iyy + m 0.2^2 for the forearm."""
    scene, arm = _arm_scene(arm_path)
    model = {"upper": (2.0, 0.05, 0.3), "fore": (1.0, 0.02, 0.8)}  # mass, Iyy, COM distance from the shoulder

    def shoulder(scale_upper, scale_fore):  # plus the default armature (0.1, Genesis's) on the diagonal
        (mu, iu, xu), (mf, i_f, xf) = model["upper"], model["fore"]
        return scale_upper * (iu + mu * xu ** 2) + scale_fore * (i_f + mf * xf ** 2) + 0.1

    np.testing.assert_allclose(arm.get_mass_mat().numpy()[0, 0], shoulder(1, 1), rtol=1e-9)
    assert arm.links[0].is_fixed and not arm.links[1].is_fixed
    with pytest.warns(GenesisWarning, match="fixed to the world"):
        arm.links[0].set_mass(5.0)
    np.testing.assert_allclose(float(arm.get_mass()), 3.0, rtol=1e-12)  # the base link has no mass
    arm.set_mass(6.0)  # ratio 2 on both moving links, inertia included
    np.testing.assert_allclose(arm.get_links_mass([1, 2]).numpy(), [4.0, 2.0], rtol=1e-12)
    np.testing.assert_allclose(arm.get_mass_mat().numpy()[0, 0], shoulder(2, 2), rtol=1e-9)
    arm.get_link("fore").set_mass(3.0)  # ratio 1.5 on the forearm alone
    M = arm.get_mass_mat().numpy()
    np.testing.assert_allclose(M[0, 0], shoulder(2, 3), rtol=1e-9)
    np.testing.assert_allclose(M[1, 1], 3 * (0.02 + 1.0 * 0.2 ** 2) + 0.1, rtol=1e-9)
    # Genesis's rigid_solver.links_info (solver link order; the arm is the scene's only entity)
    info = scene.sim.rigid_solver.links_info
    np.testing.assert_allclose(info.inertial_mass.to_numpy(), [0.0, 4.0, 3.0], atol=1e-12)
    np.testing.assert_allclose(info.inertial_pos.to_numpy()[2], [0.2, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(info.inertial_i.to_numpy()[2], np.diag([0.015, 0.06, 0.06]), rtol=1e-12)
    with pytest.raises(gs.GenesisException, match="read-only"):
        info.inertial_mass[1] = 1.0
    with pytest.raises(gs.GenesisException, match="not available"):
        info.parent_idx  # noqa: B018


def test_a_link_s_pose_and_velocity_as_genesis_s_rigid_link_gives_them(arm_path):
    """RigidLink.get_pos / get_quat / get_vel / get_ang (grasp_soft_cube reads the hand's pose so): the
    forearm's origin is the elbow, 0.6 m along the upper arm turned by the shoulder angle q1 about y, so at
    (0.6 cos q1, 0, -0.6 sin q1), moving at 0.6 q1' (-sin q1, 0, -cos q1); the forearm is turned by q1 + q2
    about y and spins at q1' + q2'. (3,) per link unbatched, (n_envs, 3) batched, rows by envs_idx."""
    for n_envs in (0, 2):
        scene, arm = _arm_scene(arm_path, n_envs=n_envs)
        q = np.array([[0.3, -0.5], [-1.1, 0.7]])[: max(n_envs, 1)]
        v = np.array([[1.0, 2.0], [-0.5, 0.25]])[: max(n_envs, 1)]
        arm.set_dofs_position(torch.tensor(q if n_envs else q[0], dtype=torch.float64))
        arm.set_dofs_velocity(torch.tensor(v if n_envs else v[0], dtype=torch.float64))
        fore = arm.get_link("fore")
        q1, q12, w1, w12 = q[:, 0], q.sum(1), v[:, 0], v.sum(1)
        zero = np.zeros_like(q1)
        want = {"get_pos": np.stack([0.6 * np.cos(q1), zero, -0.6 * np.sin(q1)], -1),
                "get_quat": np.stack([np.cos(q12 / 2), zero, np.sin(q12 / 2), zero], -1),
                "get_vel": 0.6 * w1[:, None] * np.stack([-np.sin(q1), zero, -np.cos(q1)], -1),
                "get_ang": np.stack([zero, w12, zero], -1)}
        for name, ref in want.items():
            got = getattr(fore, name)()
            d = 4 if name == "get_quat" else 3
            assert tuple(got.shape) == ((n_envs, d) if n_envs else (d,)), (name, got.shape)
            np.testing.assert_allclose(got.numpy(), ref if n_envs else ref[0], atol=1e-12, err_msg=name)
        if n_envs:
            np.testing.assert_allclose(fore.get_pos(envs_idx=[1]).numpy(), want["get_pos"][1:], atol=1e-12)


def test_links_info_layout_follows_batch_links_info(arm_path):
    """(n_links, n_envs) with RigidOptions(batch_links_info=True), as Genesis's fields; without it a per-env
    difference cannot be shown in the (n_links,) layout and is refused with what to do."""
    for batched in (True, False):
        scene = gs.Scene(rigid_options=gs.options.RigidOptions(batch_links_info=batched), show_viewer=False)
        arm = scene.add_entity(gs.morphs.URDF(file=arm_path, fixed=True))
        scene.build(n_envs=2)
        info = scene.sim.rigid_solver.links_info
        assert info.inertial_mass.shape == ((3, 2) if batched else (3,))
        arm.get_link("upper").set_mass([2.5, 3.0])
        if batched:
            np.testing.assert_allclose(info.inertial_mass.to_numpy()[1], [2.5, 3.0], rtol=1e-12)
        else:
            with pytest.raises(gs.GenesisException, match="batch_links_info=True"):
                info.inertial_mass.to_numpy()


def test_urdf_with_pybullet_xml_version_header_loads(tmp_path):
    """Genesis's urdf/plane/plane.urdf (PyBullet's) starts with `<?xml version="0.0" ?>`, which libxml2
    refuses; Genesis loads it (go2_env.py, sand_wheel.py): its ground is a 200 x 200 x 10 m box 5 m below
    the link frame, on a 1 kg link. A file that is really broken still says so."""
    from genesis_lite.loaders import load_morph

    (tmp_path / "plane.urdf").write_text(
        '<?xml version="0.0" ?>\n<robot name="plane"><link name="planeLink"><inertial><mass value="1.0"/>'
        '<inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial><collision>'
        '<origin rpy="0 0 0" xyz="0 0 -5"/><geometry><box size="200 200 10"/></geometry></collision></link></robot>')
    model = load_morph(gs.morphs.URDF(file=str(tmp_path / "plane.urdf"), fixed=True), name="plane")
    (link,) = model.links
    (geom,) = link.geoms
    assert geom.type == "box" and link.mass == 1.0
    np.testing.assert_allclose(np.ravel(geom.size), [100.0, 100.0, 5.0])  # half sizes
    np.testing.assert_allclose(geom.pos, [0.0, 0.0, -5.0])
    (tmp_path / "broken.urdf").write_text('<?xml version="0.0" ?>\n<robot name="b"><link name="l"></robot>')
    with pytest.raises(ValueError, match="broken.urdf.*malformed XML"):
        load_morph(gs.morphs.URDF(file=str(tmp_path / "broken.urdf")), name="broken")


def test_friction_ratio_decides_slide_or_stick_on_a_slope():
    """A box on a plane tilted by 20 degrees (tan = 0.364) slides when its coefficient is below that and
    sticks above: with the model's 0.5 times ratio 0.5 (0.25) it slides, times 1.0 (0.5) it stays."""
    angle = np.deg2rad(20.0)
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3), show_viewer=False)
    tilt = (np.cos(angle / 2), np.sin(angle / 2), 0.0, 0.0)
    # a contact takes the larger coefficient of its two geoms (as MuJoCo and Genesis): the plane's is 0
    scene.add_entity(gs.morphs.Plane(quat=tilt), material=gs.materials.Rigid(friction=0.0))
    normal = np.array([0.0, -np.sin(angle), np.cos(angle)])
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=tuple(0.1 * normal), quat=tilt),
                           material=gs.materials.Rigid(friction=0.5))
    scene.build(n_envs=2)
    box.set_friction_ratio(np.array([[0.5], [1.0]]), links_idx_local=[0])
    np.testing.assert_allclose(box.get_friction().numpy().reshape(2), [0.25, 0.5], atol=1e-12)
    for _ in range(250):
        scene.step()
    speed = box.get_vel().norm(dim=-1).numpy()
    assert speed[0] > 0.3 and speed[1] < 1e-2, speed
    # the slide follows Coulomb: a = g (sin - mu cos) along the slope; after 0.5 s from rest
    expect = 9.81 * (np.sin(angle) - 0.25 * np.cos(angle)) * 0.5
    assert abs(speed[0] - expect) < 0.05 * expect, (speed[0], expect)


def test_aabb_slices_masks_and_small_names(arm_path):
    scene = gs.Scene(show_viewer=False, rigid_options=gs.options.RigidOptions(enable_collision=False))
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.4, 0.6), pos=(1.0, 2.0, 3.0), euler=(0, 0, 90)))
    ball = scene.add_entity(gs.morphs.Sphere(radius=0.25, pos=(-1.0, 0.0, 0.5)))
    arm = scene.add_entity(gs.morphs.URDF(file=arm_path, fixed=True))
    scene.build(n_envs=4)
    # a box turned 90 degrees about z swaps its x and y extents
    np.testing.assert_allclose(box.get_AABB()[0].numpy(), [[0.8, 1.9, 2.7], [1.2, 2.1, 3.3]], atol=1e-12)
    np.testing.assert_allclose(ball.get_AABB(envs_idx=[2]).numpy(), [[[-1.25, -0.25, 0.25], [-0.75, 0.25, 0.75]]],
                               atol=1e-12)
    # the arm straight along x: the box of link 1 spans x 0..0.6, the sphere of link 2 sits at x = 0.8
    np.testing.assert_allclose(arm.get_AABB()[1].numpy(), [[0.0, -0.05, -0.05], [0.85, 0.05, 0.05]], atol=1e-12)

    arm.set_dofs_position(torch.tensor([0.3, -0.2]), dofs_idx_local=slice(0, 2))
    np.testing.assert_allclose(arm.get_dofs_position(dofs_idx_local=slice(1, None))[:, 0].numpy(), -0.2)
    mask = torch.tensor([True, False, True, False])
    arm.set_dofs_position(torch.tensor([0.1, 0.1]), envs_idx=mask)
    np.testing.assert_allclose(arm.get_dofs_position()[:, 0].numpy(), [0.1, 0.3, 0.1, 0.3])
    with pytest.raises(gs.GenesisException, match="boolean envs_idx"):
        arm.set_dofs_position(torch.tensor([0.1, 0.1]), envs_idx=torch.tensor([True, False]))
    assert arm.base_joint is arm.joints[0] and box.base_joint.type == "free"
    # get_dofs_invweight is Genesis's: diag(M^-1) at the initial configuration (joint angles 0 here), whatever
    # the state, and again after set_dofs_armature
    w = arm.get_dofs_invweight()
    arm.set_dofs_position(torch.zeros(4, 2))
    M = arm.get_mass_mat()[0].numpy()
    np.testing.assert_allclose(w[0].numpy(), np.diag(np.linalg.inv(M)), rtol=1e-12)
    arm.set_dofs_armature(torch.tensor([0.5, 0.25]))
    M = arm.get_mass_mat()[0].numpy()
    np.testing.assert_allclose(arm.get_dofs_invweight()[0].numpy(), np.diag(np.linalg.inv(M)), rtol=1e-12)
    assert not np.allclose(w[0].numpy(), arm.get_dofs_invweight()[0].numpy())
    np.testing.assert_allclose(box.get_dofs_invweight()[0, :3].numpy(), 1.0 / box.get_mass()[0].item(), rtol=1e-12)
    assert scene.sim.rigid_solver is scene.rigid_solver and scene.sim.solvers == [scene.rigid_solver]
    assert scene.sim.mpm_solver is None and scene.sim.dt == scene.dt
    mask = scene.rigid_solver.get_error_envs_mask()  # Genesis's spelling of it
    assert tuple(mask.shape) == (4,) and not bool(mask.any())


def test_hard_coupling_boundary_and_state_names():
    assert gs.materials.Rigid(coup_softness=0.0).coup_softness == 0.0  # Genesis's hard boundary
    with pytest.raises(ValueError, match="coup_softness"):
        gs.materials.Rigid(coup_softness=-0.01)
    scene = gs.Scene(show_viewer=False)
    scene.add_entity(gs.morphs.Sphere(radius=0.1, pos=(0, 0, 1)))
    scene.build()
    state = scene.get_state()
    assert len(state.solvers_state) == 1 and state.solvers_state[0] is state.solvers[0]


def test_an_out_of_scope_solver_s_entity_is_left_out_with_a_warning_and_the_rest_runs_unchanged():
    """water_wheel's default path sets up SPH: its options are accepted; an SPH, PBD or FEM entity is left out
    of the simulation with a warning that says what to use, keeps its place in scene.entities (the script's
    indices and names), and raises, naming itself, when read; the rest of the scene steps to the bit as
    without it."""
    def run(with_left_out):
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01),
                         sph_options=gs.options.SPHOptions(lower_bound=(-1, -1, 0), particle_size=0.01),
                         pbd_options=gs.options.PBDOptions(), show_viewer=False)
        scene.add_entity(gs.morphs.Plane())
        left = []
        if with_left_out:
            with pytest.warns(GenesisWarning, match=r"scene.add_entity: gs.materials.SPH.Liquid needs Genesis's SPH "
                                                    r"solver, which is out of genesis_lite's scope.*'water' is left "
                                                    r"out of the simulation.*MPM.Liquid"):
                left.append(scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1), pos=(0.3, 0, 0.2)),
                                             material=gs.materials.SPH.Liquid(rho=1000), name="water"))
            with pytest.warns(GenesisWarning, match=r"gs.materials.FEM.Elastic.*left out"):
                left.append(scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1)), material=gs.materials.FEM.Elastic()))
        box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.5), euler=(10, 20, 30)))
        scene.build(n_envs=2)
        zs = []
        for _ in range(60):
            scene.step()
            zs.append(box.get_qpos().clone())
        return scene, left, box, torch.stack(zs)

    scene, (water, fem), box, zs = run(True)
    assert scene.entities.index(water) == 1 and scene.entities[2] is fem and scene.entities[3] is box
    assert scene.get_entity(name="water") is water and fem.name in scene.entity_names
    with pytest.raises(gs.GenesisException, match=r"entity 'water' \(gs.materials.SPH.Liquid\) has no "
                                                  r"'get_particles_pos': genesis_lite left it out.*MPM.Liquid"):
        water.get_particles_pos()
    assert not hasattr(water, "get_particles_pos")  # an AttributeError too: probes by hasattr say no
    _, _, _, zs0 = run(False)
    assert torch.equal(zs, zs0) and float(zs[-1, 0, 2]) < 0.2  # the box fell onto the plane, as without them
    with pytest.raises(TypeError, match="unexpected arguments"):
        gs.Scene(sph_optoins=1)


def test_particles_in_bbox_and_attachment_needs_a_coupled_link():
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=10),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(1, 1, 1), grid_density=32),
                     show_viewer=False)
    cube = scene.add_entity(gs.morphs.Box(pos=(0.5, 0.5, 0.3), size=(0.2, 0.2, 0.2)), material=gs.materials.MPM.Elastic())
    scene.build()
    x = cube.get_particles_pos().numpy()
    mask = cube.get_particles_in_bbox((0.4, 0.4, 0.35), (0.6, 0.6, 0.45)).numpy()
    # the top half of the cube (z from 0.2 to 0.4): the particles above 0.35
    np.testing.assert_array_equal(mask, x[:, 2] >= 0.35)
    assert 0 < mask.sum() < len(mask)
    assert scene.get_entity(uid=cube.uid.short()) is cube  # an MPM entity has Genesis's uid too
    # no rigid entity: nothing to attach to (tests/test_attach.py: attachments themselves)
    with pytest.raises(gs.GenesisException, match="set_particle_constraints .* coupler"):
        cube.set_particle_constraints(mask, 0, 1e4)


def test_entity_uid_is_genesis_uid_and_names_find_one_entity():
    """Genesis's entity.uid: a random version-4 UUID; str() its 32 hex digits, short() the first 7 (what
    Genesis prints and scene.get_entity(uid=) takes), full() with a dash after the 7th, `<short>` in an
    f-string. No build needed."""
    scene = gs.Scene(show_viewer=False)
    box = scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1)))
    ball = scene.add_entity(gs.morphs.Sphere(radius=0.1, pos=(1.0, 0.0, 0.0)), name="ball")
    for e in (box, ball):
        uid, digits = e.uid, str(e.uid)
        assert re.fullmatch("[0-9a-f]{32}", digits) and uuid.UUID(hex=digits).version == 4
        assert uid.short() == digits[:7] and uid.full() == f"{digits[:7]}-{digits[7:]}"
        assert f"{uid}" == f"<{digits[:7]}>"
        assert uid.match(digits) and uid.match(digits[:7], short_only=True) and not uid.match(digits[:7])
        for key in (uid.short(), digits, uid.full(), uid):
            assert scene.get_entity(uid=key) is e
    assert box.uid != ball.uid and box.uid == box.uid and isinstance(box.uid, gs.UID)
    other = gs.Scene(show_viewer=False).add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1)))
    assert other.uid not in (box.uid, ball.uid)  # ids are not indices: another scene's first entity differs
    assert box.idx == 0 and ball.idx == 1  # (the index in the scene is idx)

    assert scene.entity_names == ("box_0", "ball") and scene.get_entity(name="ball") is ball
    with pytest.raises(TypeError, match=r"uid is a string.*scene.entities\[i\]"):
        scene.get_entity(uid=1)
    with pytest.raises(gs.GenesisException, match="no entity with uid 'abcdefg'.*ball"):
        scene.get_entity(uid="abcdefg")
    with pytest.raises(ValueError, match="one of them"):
        scene.get_entity()
    # a name finds one entity: a second entity of a name is refused (as Genesis), and a made-up name skips
    # the ones the user took
    with pytest.raises(gs.GenesisException, match="already has an entity of that name"):
        scene.add_entity(gs.morphs.Sphere(radius=0.1), name="ball")
    scene.add_entity(gs.morphs.Sphere(radius=0.1, pos=(2.0, 0.0, 0.0)), name="sphere_3")
    assert scene.add_entity(gs.morphs.Sphere(radius=0.1, pos=(3.0, 0.0, 0.0))).name == "sphere_4"
    with pytest.raises(TypeError, match="non-empty string"):
        scene.add_entity(gs.morphs.Sphere(radius=0.1), name=7)


def test_joint_indices_number_the_scene_and_the_entity(arm_path):
    """Genesis's numbering: the scene's rigid solver lists every rigid entity's links (one joint each),
    position coordinates q and dofs in the order of add_entity. Two free bodies come first (7 q, 6 dofs
    each), then the arm (a fixed base link and two revolute joints): its shoulder is dof 12 and q 14 of the
    scene, dof 0 and q 0 of the arm. The scene's state vectors (get_state().qpos / qvel) are indexed by the
    global names; the entity's getters by the _local ones. (The scene of test_aabb_slices_masks_and_small_names:
    its kernels are compiled already.)"""
    scene = gs.Scene(show_viewer=False, rigid_options=gs.options.RigidOptions(enable_collision=False))
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.4, 0.6), pos=(1.0, 2.0, 3.0), euler=(0, 0, 90)))
    ball = scene.add_entity(gs.morphs.Sphere(radius=0.25, pos=(-1.0, 0.0, 0.5)))
    arm = scene.add_entity(gs.morphs.URDF(file=arm_path, fixed=True))
    base, shoulder, elbow = arm.joints
    expect = [  # joint: idx, dof_start, dofs_idx, dofs_idx_local, q_start, qs_idx, qs_idx_local
        (box.base_joint, (0, 0, list(range(0, 6)), list(range(6)), 0, list(range(0, 7)), list(range(7)))),
        (ball.base_joint, (1, 6, list(range(6, 12)), list(range(6)), 7, list(range(7, 14)), list(range(7)))),
        (base, (2, 12, [], [], 14, [], [])),
        (shoulder, (3, 12, [12], [0], 14, [14], [0])),
        (elbow, (4, 13, [13], [1], 15, [15], [1])),
    ]

    def check():
        for j, (idx, d0, d, dl, q0, q, ql) in expect:
            got = (j.idx, j.dof_start, j.dofs_idx, j.dofs_idx_local, j.q_start, j.qs_idx, j.qs_idx_local)
            assert got == (idx, d0, d, dl, q0, q, ql), (j.name, got)
            assert (j.dof_end, j.q_end) == (d0 + len(d), q0 + len(q))
        # Genesis's older singular names: an int for one index, None for none, the list otherwise
        assert (elbow.dof_idx, elbow.dof_idx_local, elbow.q_idx, elbow.q_idx_local) == (13, 1, 15, 1)
        assert base.dof_idx is None and base.q_idx_local is None and ball.base_joint.dof_idx == list(range(6, 12))
        assert (arm.link_start, arm.joint_start, arm.dof_start, arm.q_start) == (2, 2, 12, 14)
        assert (arm.link_end, arm.dof_end, arm.q_end) == (5, 14, 16) and elbow.link is arm.links[2]

    check()  # known from add_entity on, as in Genesis
    scene.build(n_envs=4)
    check()
    arm.set_dofs_position(torch.tensor([0.3, -0.2]))
    arm.set_dofs_velocity(torch.tensor([0.5, -0.7]))
    ball.set_pos(torch.tensor([-1.0, 0.25, 0.75]))
    state = scene.get_state()
    np.testing.assert_allclose(state.qpos[:, elbow.qs_idx].numpy(), -0.2)
    np.testing.assert_allclose(state.qvel[:, shoulder.dofs_idx + elbow.dofs_idx].numpy(), [[0.5, -0.7]] * 4)
    np.testing.assert_allclose(state.qpos[:, ball.base_joint.qs_idx[:3]].numpy(), [[-1.0, 0.25, 0.75]] * 4)
    np.testing.assert_allclose(arm.get_dofs_position(dofs_idx_local=elbow.dofs_idx_local).numpy(), [[-0.2]] * 4)
    np.testing.assert_allclose(arm.get_qpos(qs_idx_local=shoulder.qs_idx_local).numpy(), [[0.3]] * 4)
    np.testing.assert_allclose(ball.get_dofs_velocity(dofs_idx_local=ball.base_joint.dofs_idx_local).numpy(),
                               state.qvel[:, ball.base_joint.dofs_idx].numpy())


def test_timer_stamps_the_wall_clock(capsys):
    """gs.tools.Timer (Genesis's): stamp(msg) prints and keeps the ms since the previous stamp and since
    reset; skip=True prints nothing."""
    timer = gs.tools.Timer()
    time.sleep(0.05)
    timer.stamp("first")
    time.sleep(0.02)
    timer.stamp("first")
    count, step_sum, accu_sum = timer.accu_log["first"]
    assert count == 2 and 70.0 <= step_sum < 70.0 + 500.0 and accu_sum >= 50.0 + 70.0
    out = capsys.readouterr().out
    steps = [float(x) for x in re.findall(r"\[first\] step: ([0-9.]+)ms", out)]
    assert len(steps) == 2 and steps[0] >= 50.0 and steps[1] >= 20.0
    quiet = gs.tools.Timer(skip=True)
    quiet.stamp("x")
    assert capsys.readouterr().out == "" and quiet.accu_log == {}
    with pytest.raises(ValueError, match="level"):
        gs.tools.Timer(level=-1)


# slow (suite time: its coupler compiles the softness in, ~28 s on an empty kernel cache)
@pytest.mark.slow
def test_hard_coupling_boundary_holds_a_box_on_an_elastic_block():
    """sand_wheel's gs.materials.Rigid(coup_softness=0.0), Genesis's hard boundary, in a coupled scene (the
    shape of test_coupling.py's box on an elastic block): a box dropped 5 mm onto the block is stopped by
    the material at its surface within 0.1 s (free fall would take it 5 cm down), and no particle gets
    into it."""
    dens, g = 48, 9.81
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=8, gravity=(0, 0, -g)),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.4, 0.4, 0.3),
                                                       grid_density=dens), show_viewer=False)
    block = scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 3 / dens + 0.05), size=(0.2, 0.2, 0.1)),
                             material=gs.materials.MPM.Elastic(E=5e4, nu=0.3))
    box = scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 3 / dens + 0.13), size=(0.1, 0.1, 0.05)),
                           material=gs.materials.Rigid(rho=500, coup_softness=0.0))
    scene.build()
    for _ in range(50):
        scene.step()
    z = box.get_pos()[2].item()
    # on the block's top face (3 cells + 0.1 m) with its half height 0.025 m below its centre, within half a cell
    assert abs(z - (3 / dens + 0.1 + 0.025)) < 0.5 / dens, (z - (3 / dens + 0.125)) * dens
    x = block.get_particles_pos().numpy()
    under = (np.abs(x[:, 0] - 0.2) < 0.05) & (np.abs(x[:, 1] - 0.2) < 0.05)
    assert under.sum() > 100 and x[under, 2].max() < z - 0.025  # none inside the box


def test_sand_wheel_style_emitter_script():
    """Genesis's examples/coupling/sand_wheel.py as its users write it (wheels left out, domain and
    particle size made small for the suite): a sand stream from scene.add_emitter whose nozzle sways
    with sin(i / 10). Each emit sends round(a / p) particles per side of the 3 x 5 cm rectangle times
    round(speed dt / p) layers (Genesis's regular lattice) at 8 m/s along the normalised direction; the
    stream falls onto the floor and stays in the domain."""
    scene = gs.Scene(
        sim_options=gs.options.SimOptions(dt=3e-3, substeps=10),
        mpm_options=gs.options.MPMOptions(lower_bound=(0.0, -0.3, -0.1), upper_bound=(0.57, 0.3, 1.0),
                                          grid_density=32, particle_size=0.01),
        viewer_options=gs.options.ViewerOptions(camera_pos=(4.5, 0.0, 1.42), camera_lookat=(1.0, 0.0, 1.0),
                                                camera_fov=30, max_FPS=120),
        vis_options=gs.options.VisOptions(visualize_mpm_boundary=True, rendered_envs_idx=[0]),
        show_viewer=False,
    )
    emitter = scene.add_emitter(
        material=gs.materials.MPM.Sand(),
        max_particles=4000,
        surface=gs.surfaces.Rough(color=(1.0, 0.9, 0.6, 1.0)),
    )
    # water_wheel.py's emitter (material and surface as it writes them), left silent here
    water = scene.add_emitter(
        material=gs.materials.MPM.Liquid(sampler="regular"),
        max_particles=1000,
        surface=gs.surfaces.Glass(color=(0.7, 0.85, 1.0, 0.7), vis_mode="particle"),
    )
    scene.build(n_envs=0)
    per_emit = round(0.03 / 0.01) * round(0.05 / 0.01) * round(8.0 * 3e-3 / 0.01)
    horizon = 40
    for i in range(horizon):
        direction = np.array([0.0, np.sin(i / 10) * 0.35, -1.0])
        emitter.emit(pos=np.array([0.3, 0.0, 0.8]), direction=direction, speed=8.0, droplet_shape="rectangle",
                     droplet_size=[0.03, 0.05])
        n = emitter.entity.get_particles_vel()[(i * per_emit) % 4000].numpy()
        assert np.allclose(n, 8.0 * direction / np.linalg.norm(direction), rtol=0, atol=1e-12)
        scene.step()
    assert per_emit == 30 and emitter.next_particle == horizon * per_emit  # 1200 of 4000: no recycling yet
    x = emitter.entity.get_particles_pos()[:horizon * per_emit].numpy()
    floor = -0.1 + 3 / 32  # the floor's wall: 3 grid cells above lower_bound
    assert -0.1 < x[:, 2].min() < floor + 0.05  # it reached the floor and stayed in the domain
    assert x[:, 1].max() > 0.02  # the nozzle swayed towards +y
    assert np.isfinite(x).all()
    assert water.entity.get_mass() == 0.0 and water.next_particle == 0


def test_add_entity_takes_genesis_vis_mode():
    """differentiable_push passes vis_mode="particle" to add_entity: accepted, kept for the cameras (which draw
    a rigid entity's collision shapes for "collision"); a non-string is refused."""
    scene = gs.Scene(show_viewer=False)
    box = scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1)), vis_mode="collision")
    assert box.vis_mode == "collision"
    assert scene.add_entity(gs.morphs.Sphere(radius=0.1, pos=(1.0, 0.0, 0.0))).vis_mode is None
    with pytest.raises(TypeError, match="vis_mode"):
        scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1)), vis_mode=3)


def test_a_shift_from_a_leaf_keeps_its_gradient_over_new_rollouts():
    """set_mass_shift / set_COM_shift given a leaf once: every rollout after scene.reset() gives the leaf the
    same gradient as the first (the shifted value is made again from the leaf, as a setter's own value is;
    before, a reset left the shift without history and backward found nothing that required grad)."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True), show_viewer=False)
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 1)))
    scene.build()
    mass = torch.tensor([0.3], dtype=torch.float64, requires_grad=True)
    com = torch.tensor([[0.01, 0.02, 0.0]], dtype=torch.float64, requires_grad=True)
    box.set_mass_shift(mass)
    box.set_COM_shift(com)
    grads = []
    for _ in range(3):
        scene.reset()
        box.control_dofs_force(torch.tensor([1.0, 0, 0, 0, 0.5, 0], dtype=torch.float64))
        for _ in range(5):
            scene.step()
        mass.grad = com.grad = None
        (box.get_pos()[0] + box.get_quat()[1]).backward()
        grads.append(torch.cat([mass.grad.reshape(-1), com.grad.reshape(-1)]))
    assert bool((grads[0].abs() > 1e-6).sum() >= 3)
    for g in grads[1:]:
        torch.testing.assert_close(g, grads[0], rtol=1e-12, atol=0)


PUSH = (140.0, 30.0, 0.0, 0.2, 0.1, 0.5)  # N and N m on the free box's six dofs: it slides and turns


@pytest.mark.parametrize("setter", ["set_friction", "set_friction_ratio", "entity.set_mass", "link.set_mass"])
def test_a_setter_s_derived_value_keeps_a_leaf_s_gradient_in_every_rollout(setter):
    """A setter that computes its value from the user's leaf (a scalar friction broadcast to every geom, a ratio
    times the model's friction, the entity's mass shared out over its links, a link's mass with its inertia
    scaled along) given the leaf once, before scene.reset(): each of three rollouts gives the leaf the central
    finite difference of the loss (float64). Before grad/remake.py only a leaf passed straight to a setter was
    made again at a reset, and these four gave no gradient at all (backward found nothing that required grad)."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True), show_viewer=False)
    scene.add_entity(gs.morphs.Plane())  # friction 1.0: a contact takes the larger of its geoms' coefficients
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.3, 0.1), pos=(0, 0, 0.05)))
    scene.build()
    x0 = {"set_friction": 1.5, "set_friction_ratio": 1.5, "entity.set_mass": 2.0, "link.set_mass": 2.0}[setter]
    apply = {"set_friction": lambda x: box.set_friction(x),
             "set_friction_ratio": lambda x: box.set_friction_ratio(x if x.dim() == 1 else x.reshape(1)),
             "entity.set_mass": lambda x: box.set_mass(x),
             "link.set_mass": lambda x: box.links[0].set_mass(x)}[setter]

    def rollout():
        scene.reset()
        box.control_dofs_force(torch.tensor(PUSH, dtype=torch.float64))
        for _ in range(8):
            scene.step()
        pos = box.get_pos()
        return pos[0] + pos[1] + box.get_quat()[3]

    def loss_at(x):
        with torch.no_grad():
            apply(torch.tensor(x, dtype=torch.float64))
            return rollout().item()

    h = 1e-6 * x0
    fd = (loss_at(x0 + h) - loss_at(x0 - h)) / (2 * h)
    assert abs(fd) > 1e-3  # the setter moves the loss: the check can fail
    leaf = torch.tensor([x0] if setter == "set_friction_ratio" else x0, dtype=torch.float64, requires_grad=True)
    apply(leaf)
    for _ in range(3):
        leaf.grad = None
        rollout().backward()
        assert leaf.grad is not None
        assert abs(leaf.grad.item() - fd) <= 1e-6 * abs(fd) + 1e-9, (leaf.grad.item(), fd)


def test_a_value_computed_from_a_leaf_by_the_user_warns_at_the_reset_that_drops_its_gradient():
    """A setter given the user's own expression of a leaf (leaf * 2) before scene.reset(): the reset cannot make
    it again (only a leaf, or a setter's own derived value, carries a recipe), so it keeps the number and says,
    naming the parameter and the user's line, that the leaf gets no gradient through it from then on."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True), show_viewer=False)
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.3, 0.1), pos=(0, 0, 1.0)))
    scene.build()
    leaf = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    box.set_links_mass((leaf * 2).reshape(1))
    with pytest.warns(GenesisWarning, match="setter of 'mass'.*no gradient") as rec:
        scene.reset()
    assert any(w.filename == __file__ for w in rec)
    assert box.get_mass().item() == 2.0
    with warnings.catch_warnings():
        warnings.simplefilter("error", GenesisWarning)
        scene.reset()  # once: the number is kept from the first reset on
    box.set_links_mass(leaf.reshape(1) * 3)  # after the reset, in the rollout: the gradient is there
    box.control_dofs_force(torch.tensor([1.0, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64))
    for _ in range(3):
        scene.step()
    box.get_pos()[0].backward()
    assert leaf.grad is not None and leaf.grad.item() != 0.0
