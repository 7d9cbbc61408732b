"""Genesis's `align` of file morphs (genesis_lite/loaders/align.py): a free rigid object's pose is its
centre of mass and principal axes, the body itself unchanged."""
import os

import numpy as np
import pytest
import torch

import genesis_lite as gs
from genesis_lite import materials, morphs
from genesis_lite.loaders import load_morph
from genesis_lite.loaders.primitives import quat_to_mat

ASSETS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "assets")
# a skewed triangular prism: centroid off the file's origin, principal axes off its axes
WEDGE = os.path.join(ASSETS, "mjcf", "wedge.obj")
ARM = os.path.join(ASSETS, "urdf", "arm.urdf")


def _np(t):
    return t.detach().cpu().numpy().astype(np.float64)


def test_a_free_mesh_s_pose_is_genesis_s():
    """The wedge at pos (0.1, 0.2, 0.3), euler (10, 20, 30): Genesis 0.4.5 (float64, its own venv,
    2026-11-28) reports the pose below, its centre of mass and principal axes, by default; with align=False
    the file's frame. Both printed by Genesis, to 10 digits."""
    scene = gs.Scene(show_viewer=False)
    a = scene.add_entity(gs.morphs.Mesh(file=WEDGE, pos=(0.1, 0.2, 0.3), euler=(10, 20, 30)))
    b = scene.add_entity(gs.morphs.Mesh(file=WEDGE, pos=(1.1, 0.2, 0.3), euler=(10, 20, 30), align=False))
    scene.build()
    np.testing.assert_allclose(_np(a.get_pos()), [0.215274897, 0.3488687315, 0.3118022318], atol=1e-9)
    np.testing.assert_allclose(_np(a.get_quat()), [0.6796501837, -0.14979541, 0.4528305255, 0.5572983744], atol=1e-9)
    np.testing.assert_allclose(_np(a.get_dofs_position())[3:], [-0.9149814366, 0.4651660594, 1.6057953907], atol=1e-9)
    np.testing.assert_allclose(_np(b.get_pos()), [1.1, 0.2, 0.3], atol=1e-12)
    np.testing.assert_allclose(_np(b.get_quat()), [0.9515485246, 0.0381345765, 0.1893078574, 0.2392983377], atol=1e-9)
    # aligned: the centre of mass at the link's origin, the inertia diagonal in its axes
    np.testing.assert_allclose(_np(a.get_links_COM())[0], 0.0, atol=1e-15)
    I = _np(a.get_links_inertia())[0]
    assert np.abs(I - np.diag(np.diag(I))).max() < 1e-12 * np.abs(I).max()
    # the same body: mass and principal moments as the unaligned one's
    assert _np(a.get_links_mass()) == pytest.approx(_np(b.get_links_mass()), rel=1e-14)
    np.testing.assert_allclose(np.sort(np.diag(I)), np.linalg.eigvalsh(_np(b.get_links_inertia())[0]), rtol=1e-12)


LONE = """<?xml version="1.0"?>
<robot name="lone">
  <link name="body">
    <inertial>
      <origin xyz="0.03 -0.02 0.05" rpy="0.3 -0.2 0.5"/>
      <mass value="1.3"/>
      <inertia ixx="0.011" ixy="0.002" ixz="-0.001" iyy="0.017" iyz="0.0015" izz="0.023"/>
    </inertial>
    <collision>
      <origin xyz="0.03 -0.02 0.05" rpy="0 0 0"/>
      <geometry><box size="0.2 0.15 0.1"/></geometry>
    </collision>
  </link>
</robot>
"""


def test_a_one_body_urdf_s_pose_is_genesis_s(tmp_path):
    """A one-link URDF (a free rigid object) whose <inertial> is offset, turned and not diagonal: Genesis
    0.4.5 aligns it from the file's inertia and reports the pose below (float64, its own venv, 2026-11-28)."""
    f = tmp_path / "lone.urdf"
    f.write_text(LONE)
    scene = gs.Scene(show_viewer=False)
    e = scene.add_entity(gs.morphs.URDF(file=str(f), pos=(0.1, 0.2, 0.3), euler=(10, 20, 30)))
    scene.build()
    np.testing.assert_allclose(_np(e.get_pos()), [0.152159438, 0.1973455225, 0.3327467064], atol=1e-9)
    np.testing.assert_allclose(_np(e.get_quat()), [0.9332253076, 0.1594733368, 0.1140221432, 0.3010942228], atol=1e-9)


FREE_MJCF = """<mujoco model="free">
  <worldbody>
    <body name="thing" pos="0.1 0.2 0.3" euler="10 20 30">
      <freejoint/>
      <inertial pos="0.03 -0.02 0.05" quat="0.9 0.1 -0.2 0.3" mass="1.3" diaginertia="0.011 0.017 0.023"/>
      <geom type="box" size="0.1 0.07 0.05" pos="0.03 -0.02 0.05"/>
    </body>
  </worldbody>
</mujoco>
"""


def test_a_free_mjcf_body_s_pose_is_genesis_s(tmp_path):
    """An MJCF body on a <freejoint/> with a turned, offset <inertial>, the model placed at (0.5, 0, 0):
    Genesis 0.4.5's pose (float64, its own venv, 2026-11-29), to 10 digits."""
    f = tmp_path / "free.xml"
    f.write_text(FREE_MJCF)
    scene = gs.Scene(show_viewer=False)
    e = scene.add_entity(gs.morphs.MJCF(file=str(f), pos=(0.5, 0.0, 0.0)))
    scene.build()
    np.testing.assert_allclose(_np(e.get_pos()), [0.6509118638, 0.1916928898, 0.3337486895], atol=1e-9)
    np.testing.assert_allclose(_np(e.get_quat()), [0.8053826049, 0.3144146931, -0.0716161719, 0.4973664488], atol=1e-9)


def _pair(dt, plane_z, z=0.2):
    """Two wedges 1 m apart at height z, the second unaligned, over a plane at height plane_z (the spinning
    pair's is 100 m below them, out of reach: the same contact classes as the dropped pair's, so one set
    of kernels serves both scenes)."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt), show_viewer=False)
    scene.add_entity(gs.morphs.Plane(pos=(0.0, 0.0, plane_z)))
    a = scene.add_entity(gs.morphs.Mesh(file=WEDGE, pos=(0.0, 0.0, z), euler=(10, 20, 30)))
    b = scene.add_entity(gs.morphs.Mesh(file=WEDGE, pos=(1.0, 0.0, z), euler=(10, 20, 30), align=False))
    scene.build()
    com_b = _np(b.get_links_COM())[0]
    turn = quat_to_mat(_np(b.get_quat())).T @ quat_to_mat(_np(a.get_quat()))  # principal axes in b's link frame

    def gap():
        """b's centre of mass less a's (less the 1 m between them), and the angle between their principal frames."""
        Ra, Rb = quat_to_mat(_np(a.get_quat())), quat_to_mat(_np(b.get_quat()))
        d = _np(b.get_pos()) + Rb @ com_b - _np(a.get_pos()) - [1.0, 0.0, 0.0]
        c = np.clip((np.trace((Rb @ turn).T @ Ra) - 1.0) / 2.0, -1.0, 1.0)
        return np.abs(d).max(), float(np.arccos(c))

    return scene, a, b, com_b, gap


@pytest.mark.slow  # an unaligned body is an option (align=False); its scene class is compiled for this
# test alone (~80 s). The default run checks aligned bodies' poses against Genesis's above
def test_aligned_and_unaligned_bodies_move_alike():
    """An aligned wedge (the default) and an unaligned one are the same body: thrown spinning, their centres
    of mass and principal frames part only by the integrator's error, which halves with the step (the
    reference point of a free joint's velocity is where the step's linearisation differs); dropped without
    spin onto a plane they fall alike to round-off and come to rest on the same face."""
    w, v = np.array([1.5, -2.0, 3.0]), np.array([0.3, 0.1, 1.0])
    gaps = []
    for dt in (0.004, 0.002):
        scene, a, b, com_b, gap = _pair(dt, plane_z=-100.0)
        r = quat_to_mat(_np(b.get_quat())) @ com_b
        a.set_dofs_velocity(torch.tensor(np.r_[v, w], dtype=torch.float64))
        b.set_dofs_velocity(torch.tensor(np.r_[v - np.cross(w, r), w], dtype=torch.float64))
        for _ in range(int(round(0.2 / dt))):
            scene.step()
        gaps.append(gap())
    (p1, t1), (p2, t2) = gaps
    assert p2 < 2e-3 and t2 < 1e-2, gaps
    assert p1 / p2 > 1.7, gaps  # first order in dt
    scene, a, b, com_b, gap = _pair(0.01, plane_z=0.0)
    turn = quat_to_mat(_np(b.get_quat())).T @ quat_to_mat(_np(a.get_quat()))
    for step in range(150):
        scene.step()
        if _np(a.get_pos())[2] > 0.12:  # in the air: the same fall
            p, t = gap()
            assert p < 1e-12 and t < 1e-9, (step, p, t)
    # at rest on the same face at the same height (where on the plane, and turned how far about the
    # vertical, the impact's slide decides: 0.36 mm and 0.45 degrees apart, measured)
    Ra, Rb = quat_to_mat(_np(a.get_quat())), quat_to_mat(_np(b.get_quat())) @ turn
    zb = _np(b.get_pos())[2] + (quat_to_mat(_np(b.get_quat())) @ com_b)[2]
    assert abs(zb - _np(a.get_pos())[2]) < 1e-6
    np.testing.assert_allclose(Rb[2], Ra[2], atol=1e-5)  # the world's vertical in their principal frames
    assert abs(_np(a.get_vel())).max() < 1e-3 and abs(_np(b.get_vel())).max() < 1e-3  # at rest


def test_which_roots_align(tmp_path):
    """None (Genesis's default): a free root with nothing below it on a hinge or slide is aligned; an
    articulated free robot is not. True aligns that robot's root too, its links' world poses unchanged.
    A fixed root never moves."""
    rigid = materials.Rigid()
    one = load_morph(morphs.Mesh(file=WEDGE), rigid, "w").links[0]
    np.testing.assert_allclose(one.com, 0.0, atol=1e-15)
    assert not np.allclose(one.joint_pos, 0.0)
    fixed = load_morph(morphs.Mesh(file=WEDGE, fixed=True), rigid, "w").links[0]
    np.testing.assert_allclose(fixed.joint_pos, 0.0, atol=0)
    arm = load_morph(morphs.URDF(file=ARM), rigid, "arm")
    assert not np.allclose(arm.links[0].com, 0.0), "the case needs a root whose COM is off its origin"
    # with None the articulated arm keeps its frame; with True its root moves, and forward kinematics of
    # every link (in the world, at the initial pose) is the same
    scene = gs.Scene(show_viewer=False)
    e0 = scene.add_entity(gs.morphs.URDF(file=ARM))
    e1 = scene.add_entity(gs.morphs.URDF(file=ARM, align=True))
    scene.build()
    q = torch.tensor([0.3, -0.7, 1.1, 0.4], dtype=torch.float64)
    for e in (e0, e1):
        e.set_dofs_position(q, dofs_idx_local=list(range(6, e.n_dofs)))
    np.testing.assert_allclose(_np(e0.get_pos()), 0.0, atol=0)
    assert np.abs(_np(e1.get_pos())).max() > 1e-3
    np.testing.assert_allclose(_np(e1.get_links_pos())[1:], _np(e0.get_links_pos())[1:], atol=1e-12)
    com0 = _np(e0.get_links_pos())[0] + quat_to_mat(_np(e0.get_links_quat())[0]) @ _np(e0.get_links_COM())[0]
    np.testing.assert_allclose(_np(e1.get_links_pos())[0], com0, atol=1e-12)


def test_bad_align_is_refused():
    with pytest.raises(ValueError, match="align"):
        gs.morphs.Mesh(file=WEDGE, align="yes")
