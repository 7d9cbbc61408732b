"""Genesis's option surface (issue #25, "Options surface"): the options Genesis's own scripts pass are accepted,
checked, and, where genesis_lite has the same notion, act as in Genesis.

- ViewerOptions(camera_pos=, camera_lookat=, camera_fov=, max_FPS=, res=), VisOptions(...), Scene(show_FPS=,
  show_viewer=False): accepted (headless: nothing reads them), bad values refused naming the option.
- RigidOptions(dt=, gravity=): Genesis's per-solver copies of SimOptions'. Alone they set the scene's step and
  gravity (checked by a free fall against v = g t, exact for the integrator's velocity update); with a
  SimOptions that disagrees, refused.
- RigidOptions(constraint_solver=, iterations=, tolerance=, max_collision_pairs=, box_box_detection=,
  batch_dofs_info=, batch_links_info=, enable_adjacent_collision=, enable_neutral_collision=), gs.constraint_solver,
  gs.tc_int / tc_bool, gs.init(performance_mode=).
- The file morphs' (Mesh, URDF, MJCF) decimate=, decimate_face_num=, decimate_aggressiveness=,
  batch_fixed_verts= (accepted, checked, change nothing: hulls of whole meshes), file_meshes_are_zup=False (a
  Mesh's or a URDF's y-up files turned as Genesis turns them, against the same mesh turned by trimesh and written
  z-up; an MJCF's meshes as MuJoCo places them, with a warning) and recompute_inertia= (a moving link's mass properties from its collision shapes at the material's density,
  against the analytic box).
"""
from __future__ import annotations

import os

import numpy as np
import pytest
import torch

import genesis_lite as gs
from genesis_lite.errors import GenesisException


def test_viewer_and_vis_options_of_genesis_scripts_are_accepted():
    scene = gs.Scene(
        viewer_options=gs.options.ViewerOptions(camera_pos=(3.5, 0.0, 2.5), camera_lookat=(0.0, 0.0, 0.5),
                                                camera_fov=40, max_FPS=60, res=(1280, 960)),
        vis_options=gs.options.VisOptions(show_world_frame=True, world_frame_size=1.0, show_link_frame=False,
                                          show_cameras=False, plane_reflection=True, ambient_light=(0.1, 0.1, 0.1)),
        show_viewer=False, show_FPS=False)
    assert scene.viewer_options.camera_pos == (3.5, 0.0, 2.5)
    assert scene.viewer_options.res == (1280, 960)
    assert scene.vis_options.show_world_frame is True


@pytest.mark.parametrize("kw, name", [({"camera_fov": 200}, "camera_fov"), ({"camera_pos": (1, 2)}, "camera_pos"),
                                      ({"res": (640,)}, "res"), ({"max_FPS": -1}, "max_FPS")])
def test_bad_viewer_options_are_refused_by_name(kw, name):
    with pytest.raises(ValueError, match=f"ViewerOptions.{name}="):
        gs.options.ViewerOptions(**kw)


def test_vis_options_of_the_wrong_type_are_refused():
    with pytest.raises(TypeError, match="vis_options must be gs.options.VisOptions"):
        gs.Scene(vis_options=gs.options.ViewerOptions())
    with pytest.raises(ValueError, match="segmentation_level"):
        gs.options.VisOptions(segmentation_level="pixel")


def test_constraint_solver_options_are_accepted_and_checked():
    ro = gs.options.RigidOptions(constraint_solver=gs.constraint_solver.Newton, iterations=50, tolerance=1e-6,
                                 max_collision_pairs=100, box_box_detection=True, batch_dofs_info=True,
                                 batch_links_info=True)
    assert ro.constraint_solver == gs.constraint_solver.Newton
    gs.Scene(rigid_options=ro)
    with pytest.raises(ValueError, match="constraint_solver"):
        gs.options.RigidOptions(constraint_solver=7)
    with pytest.raises(ValueError, match="max_collision_pairs"):
        gs.options.RigidOptions(max_collision_pairs=0)
    assert gs.tc_int == torch.int32 and gs.tc_bool == torch.bool
    # Genesis's self-collision switches (their effect: tests/test_mjcf.py::test_self_collision_follows_genesis_s_rules)
    gs.options.RigidOptions(enable_self_collision=True, enable_adjacent_collision=True, enable_neutral_collision=True)
    with pytest.raises(ValueError, match="enable_neutral_collision"):
        gs.options.RigidOptions(enable_neutral_collision="no")


def test_performance_mode_is_accepted():
    # the session's gs.init was backend=gs.cpu, precision="64" (conftest): the same call with Genesis's flag
    # is the same initialisation (a no-op), not a different one
    gs.init(backend=gs.cpu, precision="64", performance_mode=True)
    with pytest.raises(ValueError, match="performance_mode"):
        gs.init(backend=gs.cpu, precision="64", performance_mode="yes")


def test_rigid_dt_and_gravity_alone_set_the_scenes():
    scene = gs.Scene(rigid_options=gs.options.RigidOptions(dt=0.005, gravity=(0.0, 0.0, -5.0)))
    assert scene.dt == 0.005
    box = scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1), pos=(0.0, 0.0, 1.0)))
    scene.build()
    for _ in range(10):
        scene.step()
    v = box.get_dofs_velocity().numpy()
    # semi-implicit Euler's velocity update is exact for a constant force: v = g t, t = 10 x 0.005 s
    np.testing.assert_allclose(v[:3], [0.0, 0.0, -5.0 * 0.05], rtol=0, atol=1e-12)


def test_rigid_dt_or_gravity_that_disagree_with_sim_options_are_refused():
    with pytest.raises(GenesisException, match=r"RigidOptions\(dt=0.005\) differs from SimOptions\(dt=0.01\)"):
        gs.Scene(sim_options=gs.options.SimOptions(dt=0.01), rigid_options=gs.options.RigidOptions(dt=0.005))
    with pytest.raises(GenesisException, match="RigidOptions.gravity="):
        gs.Scene(sim_options=gs.options.SimOptions(gravity=(0, 0, -9.81)),
                 rigid_options=gs.options.RigidOptions(gravity=(0, 0, -1.0)))
    # the same value in both is fine
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.02), rigid_options=gs.options.RigidOptions(dt=0.02))
    assert scene.dt == 0.02


def test_euler_gives_genesis_orientation():
    """Genesis's `euler` (degrees, roll-pitch-yaw about the fixed axes) against scipy's extrinsic 'xyz'."""
    from scipy.spatial.transform import Rotation

    euler = (30.0, -45.0, 120.0)
    m = gs.morphs.Box(size=(0.1, 0.2, 0.3), euler=euler)
    x, y, z, w = Rotation.from_euler("xyz", euler, degrees=True).as_quat()
    q = np.asarray(m.quat)
    np.testing.assert_allclose(q * np.sign(q[0]), np.array([w, x, y, z]) * np.sign(w), rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match="give one orientation"):
        gs.morphs.Sphere(radius=0.1, quat=(1, 0, 0, 0), euler=(0, 0, 90))


def test_box_from_lower_and_upper_corners():
    m = gs.morphs.Box(lower=(0.1, -0.2, 0.0), upper=(0.3, 0.2, 0.05))
    np.testing.assert_allclose(m.pos, [0.2, 0.0, 0.025], rtol=0, atol=1e-15)
    np.testing.assert_allclose(m.size, [0.2, 0.4, 0.05], rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="do not give those too"):
        gs.morphs.Box(lower=(0, 0, 0), upper=(1, 1, 1), size=(1, 1, 1))
    with pytest.raises(ValueError, match="upper must exceed lower"):
        gs.morphs.Box(lower=(0, 0, 0), upper=(1, 0, 1))
    with pytest.raises(ValueError, match="both lower and upper"):
        gs.morphs.Box(lower=(0, 0, 0))
    # built: the body sits where its corners say, turned as its euler says
    scene = gs.Scene()
    box = scene.add_entity(gs.morphs.Box(lower=(0.1, -0.2, 1.0), upper=(0.3, 0.2, 1.1), euler=(0.0, 0.0, 90.0),
                                         fixed=True))
    scene.build()
    np.testing.assert_allclose(box.get_pos().numpy(), [0.2, 0.0, 1.05], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.abs(box.get_quat().numpy()), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], rtol=0, atol=1e-12)


def test_entities_by_name_and_uid_and_the_control_force():
    scene = gs.Scene(rigid_options=gs.options.RigidOptions(enable_collision=False))
    scene.add_entity(gs.morphs.Plane())
    arm = scene.add_entity(gs.morphs.URDF(file="assets/urdf/arm.urdf", fixed=True), name="arm")
    assert scene.entity_names == ("plane_0", "arm")
    assert scene.get_entity("arm") is arm and scene.get_entity(uid=arm.uid.short()) is arm
    with pytest.raises(GenesisException, match="no entity with name 'hand'"):
        scene.get_entity("hand")
    scene.build()
    # a force control inside the force range is what the actuators apply (Genesis's get_dofs_control_force)
    u = torch.tensor([0.3, -0.2, 0.1, 0.05], dtype=torch.float64)[: arm.n_dofs]
    arm.control_dofs_force(u)
    scene.step()
    np.testing.assert_allclose(arm.get_dofs_control_force().numpy(), u.numpy(), rtol=0, atol=1e-12)


def test_utils_geom_rotations_against_scipy():
    from scipy.spatial.transform import Rotation

    xyz = np.array([[0.3, -1.1, 2.0], [1.5, 0.2, -0.7]])
    for rpy, seq in ((True, "xyz"), (False, "XYZ")):  # scipy: lower case = fixed axes, upper case = moving axes
        q = gs.utils.geom.xyz_to_quat(xyz, rpy=rpy)
        ref = Rotation.from_euler(seq, xyz).as_matrix()
        np.testing.assert_allclose(gs.utils.geom.quat_to_R(q), ref, rtol=0, atol=1e-14)
        qt = gs.utils.geom.xyz_to_quat(torch.tensor(np.rad2deg(xyz)), rpy=rpy, degrees=True)
        np.testing.assert_allclose(gs.utils.geom.quat_to_R(qt).numpy(), ref, rtol=0, atol=1e-13)
        # and back (go2's scripts read the base's roll, pitch, yaw so)
        np.testing.assert_allclose(gs.utils.geom.quat_to_xyz(q, rpy=rpy), Rotation.from_matrix(ref).as_euler(seq),
                                   atol=1e-12)
        np.testing.assert_allclose(gs.utils.geom.quat_to_xyz(qt, rpy=rpy, degrees=True).numpy(),
                                   np.rad2deg(xyz), atol=1e-10)
    geom, rng = gs.utils.geom, np.random.default_rng(1)
    u, w = (Rotation.random(4, random_state=k) for k in (2, 3))
    qu, qw = (np.roll(r.as_quat(), 1, axis=-1) for r in (u, w))  # scipy's (x, y, z, w) -> (w, x, y, z)
    v = rng.normal(size=(4, 3))
    np.testing.assert_allclose(geom.transform_by_quat(v, qu), u.apply(v), atol=1e-12)
    np.testing.assert_allclose(geom.transform_by_quat(torch.tensor(v), torch.tensor(geom.inv_quat(qu))).numpy(),
                               u.inv().apply(v), atol=1e-12)
    np.testing.assert_allclose(geom.quat_to_R(geom.transform_quat_by_quat(qw, qu)), (u * w).as_matrix(), atol=1e-12)


def test_utils_geom_as_the_locomotion_envs_use_it():
    """go2_env.py's and hover_env.py's calls, batched torch in and out, against scipy: the projected gravity
    (the world's -z in the base frame), the base's roll / pitch / yaw in degrees relative to its initial
    orientation (quat_to_xyz(transform_quat_by_quat(inv_quat(q0), q), rpy=True, degrees=True)), and the base
    velocity in the base frame. Quaternions of any norm stand for their rotation (as in Genesis); at
    pitch +-90 degrees the angles still give the rotation back."""
    from scipy.spatial.transform import Rotation

    from genesis_lite.utils.geom import inv_quat, quat_to_xyz, transform_by_quat, transform_quat_by_quat, xyz_to_quat

    def wxyz(r):
        return torch.tensor(np.roll(r.as_quat(), 1, axis=-1))

    n = 6
    base, init = Rotation.random(n, random_state=4), Rotation.from_euler("z", 30, degrees=True)
    q, q0 = wxyz(base) * torch.linspace(0.5, 2.0, n)[:, None], wxyz(init)  # (n, 4) of assorted norms, (4,)
    gravity = torch.tensor([0.0, 0.0, -1.0])
    np.testing.assert_allclose(transform_by_quat(gravity.double(), inv_quat(q)).numpy(),
                               base.inv().apply([0.0, 0.0, -1.0]), atol=1e-12)
    rel = transform_quat_by_quat(inv_quat(q0), q)  # (v, u): v then u, R(rel) = R(q) R(q0)^-1
    np.testing.assert_allclose(rel.norm(dim=-1).numpy(), 1.0, atol=1e-12)  # a unit quaternion
    euler = quat_to_xyz(rel, rpy=True, degrees=True)
    assert euler.shape == (n, 3) and euler.dtype == torch.float64
    np.testing.assert_allclose(euler.numpy(), (base * init.inv()).as_euler("xyz", degrees=True), atol=1e-9)
    vel = torch.tensor(np.random.default_rng(5).normal(size=(n, 3)))
    np.testing.assert_allclose(transform_by_quat(vel, inv_quat(q)).numpy(), base.inv().apply(vel.numpy()), atol=1e-12)
    # a (4,) quaternion against (n, 3) vectors, and float32 in gives float32 out
    np.testing.assert_allclose(transform_by_quat(vel, q0).numpy(), init.apply(vel.numpy()), atol=1e-12)
    assert quat_to_xyz(q.float()).dtype == torch.float32

    # gimbal lock: pitch +-90 degrees (scipy warns there and picks its own split of roll and yaw)
    for rpy, seq in ((True, "xyz"), (False, "XYZ")):
        for pitch in (90.0, -90.0):
            r = Rotation.from_euler(seq, [20.0, pitch, -50.0], degrees=True)
            for qq in (wxyz(r), wxyz(r).float()):
                e = quat_to_xyz(qq, rpy=rpy, degrees=True).double()
                assert abs(float(e[1]) - pitch) < 1e-2 and float(e[0]) == 0.0
                back = Rotation.from_euler(seq, e.numpy(), degrees=True).as_matrix()
                np.testing.assert_allclose(back, r.as_matrix(), atol=1e-6 if qq.dtype == torch.float32 else 1e-12)
                np.testing.assert_allclose(
                    Rotation.from_quat(np.roll(xyz_to_quat(e, rpy=rpy, degrees=True).numpy(), -1)).as_matrix(),
                    r.as_matrix(), atol=1e-6 if qq.dtype == torch.float32 else 1e-12)
    # gradients flow (a policy's loss through the observation)
    qg = q.clone().requires_grad_(True)
    quat_to_xyz(transform_quat_by_quat(inv_quat(q0), qg), rpy=True).sum().backward()
    assert torch.isfinite(qg.grad).all() and qg.grad.abs().sum() > 0
    with pytest.raises(TypeError, match="all as numpy arrays, not a mix"):
        transform_by_quat(vel.numpy(), q)
    with pytest.raises(ValueError, match="quat must have 4 components"):
        quat_to_xyz(torch.zeros(3, 3))
    with pytest.raises(TypeError, match="numpy array or a torch tensor"):
        inv_quat([1.0, 0.0, 0.0, 0.0])


def test_batch_info_options_change_nothing():
    """RigidOptions(batch_dofs_info=, batch_links_info=, batch_joints_info=) are Genesis's switch to
    per-environment link / dof parameters. genesis_lite's are per environment always: with the flags off, a
    kp per env still acts per env (the stiffer position servo, 4x the kp, is twice as fast; after 0.1 s from
    rest toward 0.2 rad the joint of env 1 is further on), and with them on the step is the same."""
    finals = []
    for flag in (False, True):
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, gravity=(0, 0, 0)),
                         rigid_options=gs.options.RigidOptions(enable_collision=False, batch_dofs_info=flag,
                                                               batch_links_info=flag, batch_joints_info=flag))
        arm = scene.add_entity(gs.morphs.URDF(file="assets/urdf/arm.urdf", fixed=True))
        scene.build(n_envs=2)
        arm.set_dofs_kp(torch.tensor([[50.0], [200.0]], dtype=torch.float64), dofs_idx_local=[0])
        np.testing.assert_array_equal(arm.get_dofs_kp(dofs_idx_local=[0]).numpy(), [[50.0], [200.0]])
        arm.control_dofs_position(torch.full((2, 1), 0.2, dtype=torch.float64), dofs_idx_local=[0])
        for _ in range(10):
            scene.step()
        finals.append(arm.get_dofs_position().numpy())
    q = finals[0][:, 0]
    assert 0.0 < q[0] < q[1] < 0.25, q
    np.testing.assert_array_equal(finals[0], finals[1])
    for name in ("batch_dofs_info", "batch_links_info", "batch_joints_info"):
        with pytest.raises(ValueError, match=f"RigidOptions.{name}='yes': must be True or False"):
            gs.options.RigidOptions(**{name: "yes"})


def test_link_mass_and_set_qpos_skip_forward():
    scene = gs.Scene(rigid_options=gs.options.RigidOptions(enable_collision=False))
    arm = scene.add_entity(gs.morphs.URDF(file="assets/urdf/arm.urdf", fixed=True))
    scene.build()
    link = arm.links[-1]
    link.set_mass(torch.tensor(0.75, dtype=torch.float64))
    assert float(link.get_mass()) == 0.75 == float(arm.get_links_mass()[-1])
    q = torch.tensor([0.2, -0.3, 0.4, 0.1], dtype=torch.float64)[: arm.n_dofs]
    arm.set_qpos(q, skip_forward=True)
    np.testing.assert_array_equal(arm.get_qpos().numpy(), q.numpy())


def _genesis_layout_robot(root):
    """A URDF in Genesis's asset layout (urdf/<robot>/<robot>.urdf) whose mesh is `package://cube.obj`, a
    package-less name some of Genesis's own URDFs use: it is relative to the URDF's folder."""
    import trimesh

    d = root / "urdf" / "cube_bot"
    d.mkdir(parents=True)
    trimesh.creation.box(extents=(0.2, 0.4, 0.6)).export(d / "cube.obj")
    (d / "cube_bot.urdf").write_text(
        '<robot name="cube_bot"><link name="base"><inertial><mass value="2"/>'
        '<inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial>'
        '<collision><geometry><mesh filename="package://cube.obj"/></geometry></collision></link></robot>')
    return "urdf/cube_bot/cube_bot.urdf"


def test_relative_asset_paths_resolve_against_asset_folders(tmp_path, monkeypatch):
    from genesis_lite.loaders import load_morph
    from genesis_lite.loaders import assets

    rel = _genesis_layout_robot(tmp_path / "my_assets")
    monkeypatch.chdir(tmp_path)  # the relative name is not a path from here
    monkeypatch.delenv("GS_ASSETS_DIR", raising=False)
    with pytest.raises(FileNotFoundError, match="GS_ASSETS_DIR"):
        gs.morphs.URDF(file=rel)
    monkeypatch.setenv("GS_ASSETS_DIR", str(tmp_path / "elsewhere") + os.pathsep + str(tmp_path / "my_assets"))
    morph = gs.morphs.URDF(file=rel)
    assert os.path.samefile(morph.file, tmp_path / "my_assets" / rel)
    geom = load_morph(morph, name="cube").links[0].geoms[0]
    np.testing.assert_allclose(np.ptp(geom.vertices, axis=0), [0.2, 0.4, 0.6], atol=1e-12)
    # gs.init(assets_dir=) is the same lookup (assets.set_init_dir is what it calls; a second gs.init with
    # other arguments would raise in this process)
    monkeypatch.delenv("GS_ASSETS_DIR")
    monkeypatch.setattr(assets, "_init_dir", None)
    assets.set_init_dir(tmp_path / "my_assets")
    assert os.path.samefile(gs.morphs.URDF(file=rel).file, tmp_path / "my_assets" / rel)
    with pytest.raises(FileNotFoundError, match="assets_dir"):
        assets.set_init_dir(tmp_path / "missing")


def test_pd_gains_default_to_genesis_and_drive_a_target_unset():
    """Genesis's gains where the file sets none: kp 100, kv 10 on revolute and prismatic joints, the URDF's
    <safety_controller k_position k_velocity> where it has one (as Genesis reads it), 0 on a free joint. A
    position target without set_dofs_kp then moves the joint as the PD law says: one revolute joint of
    inertia I about its axis, no gravity, q'' = (kp (q* - q) - kv q') / I, a damped oscillator whose
    solution is known in closed form."""
    import trimesh  # noqa: F401  (the URDF below has primitive geometry only)

    I, kp, kv, target = 0.5, 100.0, 10.0, 0.3
    urdf = ('<robot name="r"><link name="base"/><link name="bar"><inertial><origin xyz="0 0 0"/><mass value="1"/>'
            f'<inertia ixx="{I}" iyy="{I}" izz="{I}" ixy="0" ixz="0" iyz="0"/></inertial></link>'
            '<link name="tip"><inertial><mass value="0.1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" '
            'ixz="0" iyz="0"/></inertial></link>'
            '<joint name="hinge" type="continuous"><parent link="base"/><child link="bar"/><axis xyz="0 0 1"/></joint>'
            '<joint name="slide" type="prismatic"><parent link="bar"/><child link="tip"/><axis xyz="1 0 0"/>'
            '<limit lower="-1" upper="1" effort="50" velocity="2"/>'
            '<safety_controller k_position="42" k_velocity="7" soft_lower_limit="-1" soft_upper_limit="1"/></joint>'
            '</robot>')
    import tempfile

    Iz = I + 0.01 + 0.1  # the hinge carries the bar and the tip (the tip's COM on the axis), and its armature
    # (Genesis's default, 0.1 kg m^2 on every URDF joint)
    wn, zeta = np.sqrt(kp / Iz), kv / (2 * np.sqrt(kp * Iz))
    wd, t = wn * np.sqrt(1 - zeta ** 2), 0.15
    expect = target * (1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta * wn / wd * np.sin(wd * t)))
    errors = []
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "r.urdf")
        with open(path, "w") as f:
            f.write(urdf)
        for dt in (2e-3, 1e-3):
            scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, gravity=(0, 0, 0)), show_viewer=False)
            arm = scene.add_entity(gs.morphs.URDF(file=path, fixed=True))
            box = scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1), pos=(2, 0, 1)))
            scene.build()
            np.testing.assert_array_equal(arm.get_dofs_kp().numpy(), [kp, 42.0])
            np.testing.assert_array_equal(arm.get_dofs_kv().numpy(), [kv, 7.0])
            np.testing.assert_array_equal(box.get_dofs_kp().numpy(), np.zeros(6))
            arm.control_dofs_position([target], dofs_idx_local=[0])
            for _ in range(round(t / dt)):
                scene.step()
            q = float(arm.get_dofs_position()[0])
            errors.append(abs(q - expect))
    # first order in dt (the default integrator treats kv implicitly, kp explicitly), converging to the solution
    assert errors[1] < 0.6 * errors[0] and errors[1] < 5e-3 * target, (errors, expect)
    assert abs(expect - target) > 0.05 * target  # still on its way at t: the check sees the law, not the end point


def test_kernel_cache_cap_fits_the_library(monkeypatch):
    """Taichi's default 100 MB kernel-cache cap is smaller than the library's kernels (the suite's cache
    passes it), so scenes evicted each other and recompiled; gs.init raises it (GS_KERNEL_CACHE_MB)."""
    from solvers import taichi_compat

    assert taichi_compat.config().offline_cache_max_size_of_files >= 1 << 30
    monkeypatch.setenv("GS_KERNEL_CACHE_MB", "2047")
    assert gs.kernel_cache_cap_bytes() == 2047 << 20
    for bad in ("lots", "4096"):  # Taichi holds the cap in a 32-bit int
        monkeypatch.setenv("GS_KERNEL_CACHE_MB", bad)
        with pytest.raises(GenesisException, match="GS_KERNEL_CACHE_MB"):
            gs.kernel_cache_cap_bytes()


BOX_LINK = """<robot name="r"><link name="base"/><joint name="j" type="revolute"><parent link="base"/>
<child link="arm"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
<link name="arm"><inertial><origin xyz="0.3 0 0"/><mass value="10"/><inertia ixx="1" ixy="0" ixz="0" iyy="1"
iyz="0" izz="1"/></inertial><collision><origin xyz="0.1 0.2 0.05" rpy="0 0 0.5"/><geometry>
<box size="0.2 0.1 0.4"/></geometry></collision></link></robot>"""
BOX_MJCF = """<mujoco><compiler angle="radian"/><worldbody><body name="base"><body name="arm"><joint name="j" type="hinge" axis="0 0 1"/>
<inertial pos="0.3 0 0" mass="10" diaginertia="1 1 1"/><geom type="box" size="0.1 0.05 0.2" pos="0.1 0.2 0.05"
euler="0 0 0.5"/></body></body></worldbody></mujoco>"""


@pytest.mark.parametrize("kind", ["URDF", "MJCF"])
def test_recompute_inertia_fills_the_collision_shapes(tmp_path, kind):
    """Genesis's recompute_inertia=True: the arm link's file inertia (10 kg at x = 0.3 m) is replaced by that of
    its box (0.2 x 0.1 x 0.4 m, turned 0.5 rad about z, at (0.1, 0.2, 0.05)) filled at the material's density:
    the analytic box, m = rho a b c, I = m / 12 diag(b^2 + c^2, a^2 + c^2, a^2 + b^2) turned."""
    from genesis_lite.loaders import load_morph

    path = tmp_path / ("r.urdf" if kind == "URDF" else "r.xml")
    path.write_text(BOX_LINK if kind == "URDF" else BOX_MJCF)
    morph = getattr(gs.morphs, kind)
    arm = lambda **kw: next(l for l in load_morph(morph(file=str(path), fixed=True, **kw),  # noqa: E731
                                                   gs.materials.Rigid(rho=500.0), name="r").links if l.name == "arm")
    kept = arm()
    assert kept.mass == pytest.approx(10.0) and np.allclose(kept.com, [0.3, 0.0, 0.0])
    new = arm(recompute_inertia=True)
    a, b, c = 0.2, 0.1, 0.4
    m = 500.0 * a * b * c
    c5, s5 = np.cos(0.5), np.sin(0.5)
    R = np.array([[c5, -s5, 0.0], [s5, c5, 0.0], [0.0, 0.0, 1.0]])
    I = R @ np.diag([b * b + c * c, a * a + c * c, a * a + b * b]) @ R.T * m / 12.0
    assert new.mass == pytest.approx(m, rel=1e-12)
    np.testing.assert_allclose(new.com, [0.1, 0.2, 0.05], atol=1e-12)
    np.testing.assert_allclose(new.inertia, I, atol=1e-12 * m)


def test_genesis_s_file_morph_options_are_accepted_and_checked(tmp_path):
    """decimate / decimate_face_num / decimate_aggressiveness / batch_fixed_verts change nothing (genesis_lite
    takes the hull of the whole mesh, Genesis's decimate=False); bad values are refused by name."""
    from genesis_lite.loaders import load_morph

    path = tmp_path / "r.urdf"
    path.write_text(BOX_LINK)
    plank = os.path.join(os.path.dirname(__file__), os.pardir, "assets", "meshes", "plank.obj")
    opts = dict(decimate=False, decimate_face_num=100, decimate_aggressiveness=5, batch_fixed_verts=True)
    for morph in (lambda **kw: gs.morphs.URDF(file=str(path), **kw), lambda **kw: gs.morphs.Mesh(file=plank, **kw)):
        base, other = (load_morph(morph(**kw), name="e") for kw in ({}, opts))
        for la, lb in zip(base.links, other.links):
            assert la.mass == lb.mass and all(np.array_equal(ga.vertices, gb.vertices)
                                              for ga, gb in zip(la.geoms, lb.geoms))
        for bad, name in ((dict(decimate=1), "decimate"), (dict(decimate_face_num=0), "decimate_face_num"),
                          (dict(decimate_aggressiveness=9), "decimate_aggressiveness"),
                          (dict(recompute_inertia="yes"), "recompute_inertia"),
                          (dict(file_meshes_are_zup=None), "file_meshes_are_zup"),
                          (dict(convexify=None), "convexify")):
            with pytest.raises(ValueError, match=name):
                morph(**bad)


YUP_URDF = """<robot name="y"><link name="base"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1"
iyz="0" izz="1"/></inertial><collision><origin xyz="0.1 0 0" rpy="0.3 0 0"/><geometry><mesh filename="{f}"
scale="1 2 3"/></geometry></collision><visual><origin xyz="0.1 0 0" rpy="0.3 0 0"/><geometry><mesh filename="{f}"
scale="1 2 3"/></geometry></visual></link></robot>"""


def test_y_up_mesh_files_are_turned_before_the_scale_as_genesis_turns_them(tmp_path):
    """Genesis's file_meshes_are_zup=False: a y-up file's vertices are turned (x, y, z) -> (x, -z, y) (+90 degrees
    about x), then scaled per axis. A lopsided solid (a box with a wedge on it: no symmetry) written y-up and
    loaded so must give what the same solid turned by trimesh and written z-up gives with the default: the
    collision vertices, mass, centre of mass and inertia of a gs.morphs.Mesh and of a URDF mesh (its <mesh
    scale="1 2 3"> and a turned origin: the file's y extent ends along z, times 3), the URDF's drawn
    visual, and an MPM entity's particles. An MJCF's meshes are placed by MuJoCo's compiler (Genesis ignores the
    option there too): a warning says so."""
    import trimesh
    from trimesh.transformations import quaternion_matrix, rotation_matrix

    from genesis_lite.loaders import load_morph
    from genesis_lite.loaders.particles import sample_particles
    from genesis_lite.vis.geometry import load_visual_file

    box = trimesh.creation.box((0.1, 0.4, 0.2))
    wedge = trimesh.Trimesh([[0.05, 0.2, 0.1], [-0.05, 0.2, 0.1], [0.05, -0.2, 0.1], [0.05, 0.2, 0.25]],
                            [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    solid = trimesh.util.concatenate([box, wedge]).convex_hull  # closed, lopsided
    solid.apply_translation((0.02, 0.03, -0.01))
    solid.export(tmp_path / "yup.obj")
    turned = solid.copy()
    turned.apply_transform(rotation_matrix(np.pi / 2, [1, 0, 0]))
    turned.export(tmp_path / "zup.obj")

    def same(a, b):
        for la, lb in zip(a.links, b.links):
            assert la.mass == pytest.approx(lb.mass, rel=1e-12)
            np.testing.assert_allclose(la.com, lb.com, atol=1e-12)
            np.testing.assert_allclose(la.inertia, lb.inertia, atol=1e-12)
            for ga, gb in zip(la.geoms, lb.geoms):
                np.testing.assert_allclose(np.asarray(ga.pos), np.asarray(gb.pos), atol=1e-12)
                np.testing.assert_allclose(np.asarray(ga.quat), np.asarray(gb.quat), atol=1e-12)
                np.testing.assert_allclose(np.sort(ga.vertices, axis=0), np.sort(gb.vertices, axis=0), atol=1e-12)

    ex, ey, ez = solid.extents
    mesh = lambda f, **kw: load_morph(gs.morphs.Mesh(file=str(tmp_path / f), scale=1.5, align=False, **kw),  # noqa: E731
                                      gs.materials.Rigid(rho=500.0), name="m")
    y, z = mesh("yup.obj", file_meshes_are_zup=False), mesh("zup.obj")
    same(y, z)
    V = y.links[0].geoms[0].vertices
    np.testing.assert_allclose(V.max(0) - V.min(0), [1.5 * ex, 1.5 * ez, 1.5 * ey], atol=1e-12)

    for f in ("yup.obj", "zup.obj"):
        (tmp_path / f"{f}.urdf").write_text(YUP_URDF.format(f=f))
    urdf = lambda f, **kw: load_morph(gs.morphs.URDF(file=str(tmp_path / f"{f}.urdf"), fixed=True, **kw),  # noqa: E731
                                      gs.materials.Rigid(rho=500.0), name="u")
    y, z = urdf("yup.obj", file_meshes_are_zup=False), urdf("zup.obj")
    same(y, z)
    V = y.links[0].geoms[0].vertices  # the <mesh scale="1 2 3"> after the turn: the file's z times 2, its y times 3
    np.testing.assert_allclose(V.max(0) - V.min(0), [ex, 2 * ez, 3 * ey], atol=1e-12)

    def drawn(v):
        V = load_visual_file(v.file, v.scale)[0]
        return np.sort(V @ quaternion_matrix(v.quat)[:3, :3].T + v.pos, axis=0)

    np.testing.assert_allclose(drawn(y.links[0].visuals[0]), drawn(z.links[0].visuals[0]), atol=1e-6)

    pts = [sample_particles(gs.morphs.Mesh(file=str(tmp_path / f), **kw), 0.02, "p")[0]
           for f, kw in (("yup.obj", dict(file_meshes_are_zup=False)), ("zup.obj", {}))]
    np.testing.assert_allclose(np.sort(pts[0], axis=0), np.sort(pts[1], axis=0), atol=1e-9)

    (tmp_path / "m.xml").write_text(f"""<mujoco><compiler meshdir="{tmp_path}"/><asset><mesh file="yup.obj"/></asset>
<worldbody><body name="b"><joint type="hinge"/><geom type="mesh" mesh="yup"/></body></worldbody></mujoco>""")
    mjcf = lambda **kw: load_morph(gs.morphs.MJCF(file=str(tmp_path / "m.xml"), fixed=True, **kw),  # noqa: E731
                                   gs.materials.Rigid(), name="x")
    with pytest.warns(UserWarning, match="file_meshes_are_zup=False.*changes nothing"):
        y = mjcf(file_meshes_are_zup=False)
    same(y, mjcf())
