"""Cameras: headless rendering and GIF / MP4 recording.

Expected image positions come from a pinhole projection written out here from the camera's
definition (position, look-at point, up vector, vertical field of view), expected depths from
ray-plane intersections; the files are read back with imageio (MP4, through ffmpeg) and Pillow (GIF).
"""
from __future__ import annotations

import os
import warnings

import numpy as np
import pytest
import torch

import genesis_lite as gs
from genesis_lite.errors import GenesisException


# ------------------------------------------------------------------------------------------------
# An independent pinhole model
# ------------------------------------------------------------------------------------------------
def look_frame(pos, lookat, up):
    pos, lookat, up = (np.asarray(v, float) for v in (pos, lookat, up))
    fwd = (lookat - pos) / np.linalg.norm(lookat - pos)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    return fwd, right, np.cross(right, fwd)


def project(points, pos, lookat, up, fov_deg, res):
    """World points (n, 3) -> image column u, row v (pixel (i, j) spans [j, j+1) x [i, i+1)) and depth."""
    W, H = res
    fwd, right, cup = look_frame(pos, lookat, up)
    d = np.asarray(points, float) - np.asarray(pos, float)
    x, y, z = d @ right, d @ cup, d @ fwd
    f = (H / 2) / np.tan(np.radians(fov_deg) / 2)
    return W / 2 + f * x / z, H / 2 - f * y / z, z


def box_corners(center, quat, size):
    w, x, y, z = np.asarray(quat, float) / np.linalg.norm(quat)
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    s = np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)]) * np.asarray(size) / 2
    return np.asarray(center) + s @ R.T


def mask_stats(mask):
    ii, jj = np.nonzero(mask)
    return ii + 0.5, jj + 0.5  # pixel centres: rows, columns


def red_mask(img):
    """Pixels of the red box, lit or in shade (shading scales all three channels alike)."""
    img = img.astype(int)
    return (img[..., 0] > 1.8 * img[..., 1]) & (img[..., 0] > 1.8 * img[..., 2]) & (img[..., 0] > 40)


# ------------------------------------------------------------------------------------------------
# A scene shared by the tests: ground, a red box that falls, a blue box fixed on the ground
# ------------------------------------------------------------------------------------------------
BOX = 0.2
FIXED_BOX = dict(pos=(0.8, 0.6, 0.1), size=(0.4, 0.4, 0.2))


@pytest.fixture(scope="module")
def world():
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
    plane = scene.add_entity(gs.morphs.Plane())
    box = scene.add_entity(gs.morphs.Box(size=(BOX,) * 3, pos=(0.0, 0.0, 1.0)),
                           surface=gs.surfaces.Default(color=(0.9, 0.1, 0.1)))
    fixed = scene.add_entity(gs.morphs.Box(fixed=True, **FIXED_BOX), surface=gs.surfaces.Default(color=(0.1, 0.2, 0.9)))
    early = scene.add_camera(res=(96, 72), pos=(2.0, -2.0, 1.2), lookat=(0.0, 0.0, 0.5), fov=40)
    with pytest.raises(GenesisException, match="build"):
        early.render()  # before build: a clear error
    scene.build()
    return scene, plane, box, fixed, early


def test_camera_added_before_build_renders_after(world):
    scene, plane, box, fixed, early = world
    scene.reset()
    rgb, depth, seg, normal = early.render()
    assert rgb.shape == (72, 96, 3) and rgb.dtype == np.uint8
    assert depth is None and seg is None and normal is None
    assert rgb.reshape(-1, 3).std(0).max() > 10  # not one flat colour


def test_recording_mp4_and_gif_frames_match_projection(world, tmp_path):
    import imageio.v2 as iio
    from PIL import Image

    scene, plane, box, fixed, _ = world
    scene.reset()
    kw = dict(res=(160, 120), pos=(2.0, -2.0, 1.2), lookat=(0.0, 0.0, 0.5), up=(0, 0, 1), fov=40)
    cams = [scene.add_camera(**kw), scene.add_camera(**kw)]
    for c in cams:
        c.start_recording()
    n_frames, boxes, direct = 10, [], []
    for k in range(n_frames):
        for _ in range(3):
            scene.step()
        rgb, _, seg, _ = cams[0].render(segmentation=True)
        cams[1].render()
        boxes.append(box_corners(box.get_pos().numpy(), box.get_quat().numpy(), (BOX,) * 3))
        direct.append((rgb, seg))
    mp4 = cams[0].stop_recording(save_to_filename=tmp_path / "sub" / "fall.mp4", fps=20)
    gif = cams[1].stop_recording(save_to_filename=str(tmp_path / "fall.gif"), fps=20)
    assert os.path.isfile(mp4) and os.path.isfile(gif)
    assert not cams[0].is_recording

    # the box's pixels (segmentation) lie inside the projection of its known corners and fill it
    for corners, (rgb, seg) in zip(boxes, direct):
        u, v, _ = project(corners, kw["pos"], kw["lookat"], kw["up"], kw["fov"], kw["res"])
        rows, cols = mask_stats(seg == box.idx)
        assert rows.size > 20
        assert cols.min() >= u.min() - 1 and cols.max() <= u.max() + 1
        assert rows.min() >= v.min() - 1 and rows.max() <= v.max() + 1
        assert rows.size > 0.4 * (u.max() - u.min()) * (v.max() - v.min())
        assert np.array_equal(red_mask(rgb), seg == box.idx)  # the surface colour is what is drawn

    frames = {"mp4": [f for f in iio.get_reader(mp4, format="FFMPEG")]}
    with Image.open(gif) as im:
        assert im.n_frames == n_frames
        frames["gif"] = []
        for k in range(im.n_frames):
            im.seek(k)
            frames["gif"].append(np.asarray(im.convert("RGB")))
    for kind, fr in frames.items():
        assert len(fr) == n_frames, kind
        centroids = []
        for img, corners in zip(fr, boxes):
            assert img.shape == (120, 160, 3)
            assert img.reshape(-1, 3).std(0).max() > 10, f"{kind}: blank frame"
            u, v, _ = project(corners, kw["pos"], kw["lookat"], kw["up"], kw["fov"], kw["res"])
            rows, cols = mask_stats(red_mask(img))
            assert rows.size > 20, kind
            assert u.min() - 1 <= cols.mean() <= u.max() + 1 and v.min() - 1 <= rows.mean() <= v.max() + 1, kind
            centroids.append(rows.mean())
        # the falling box moves down the image, frame after frame
        assert np.all(np.diff(centroids) > 0), (kind, centroids)


def test_depth_matches_plane_and_box_geometry(world):
    scene, plane, box, fixed, _ = world
    scene.reset()
    res, pos, lookat, up, fov = (120, 90), (0.3, -3.0, 1.5), (0.0, 0.0, 0.8), (0, 0, 1), 50
    cam = scene.add_camera(res=res, pos=pos, lookat=lookat, up=up, fov=fov)
    rgb, depth, seg, normal = cam.render(depth=True, segmentation=True, normal=True)
    assert depth.shape == (90, 120) and depth.dtype == np.float32
    # every ground pixel: intersect the ray through its centre with z = 0
    fwd, right, cup = look_frame(pos, lookat, up)
    f = (res[1] / 2) / np.tan(np.radians(fov) / 2)
    ii, jj = np.nonzero(seg == plane.idx)
    assert ii.size > 0.3 * seg.size
    d = fwd + np.outer((jj + 0.5 - res[0] / 2) / f, right) - np.outer((ii + 0.5 - res[1] / 2) / f, cup)
    t = -pos[2] / d[:, 2]  # d . fwd = 1, so t is the depth along the view axis
    np.testing.assert_allclose(depth[ii, jj], t, rtol=2e-5)
    np.testing.assert_allclose(normal[ii, jj], np.broadcast_to([0.0, 0.0, 1.0], (ii.size, 3)), atol=1e-5)
    seg_rgb = cam.render(rgb=False, segmentation=True, colorize_seg=True)[2]
    assert seg_rgb.shape == (90, 120, 3) and seg_rgb.dtype == np.uint8
    assert len(np.unique(seg_rgb.reshape(-1, 3), axis=0)) == len(np.unique(seg))
    # above the horizon nothing is hit
    sky = (seg == -1)
    assert sky.any() and np.all(np.isinf(depth[sky]))
    assert np.all(d[:, 2] < 0)


def test_depth_of_box_top_seen_from_above(world):
    scene, plane, box, fixed, _ = world
    scene.reset()
    top = FIXED_BOX["pos"][2] + FIXED_BOX["size"][2] / 2
    cx, cy = FIXED_BOX["pos"][:2]
    cam = scene.add_camera(res=(64, 64), pos=(cx, cy, 3.0), lookat=(cx, cy, 0.0), up=(0, 1, 0), fov=30)
    _, depth, seg, normal = cam.render(depth=True, segmentation=True, normal=True)
    on_top = seg == fixed.idx
    # the top face is a 0.4 m square seen from 2.8 m: (0.4 / 2.8) * f pixels wide
    f = 32 / np.tan(np.radians(15))
    assert abs(np.sqrt(on_top.sum()) - 0.4 / (3.0 - top) * f) < 1.5
    np.testing.assert_allclose(depth[on_top], 3.0 - top, rtol=2e-5)
    np.testing.assert_allclose(normal[on_top], np.broadcast_to([0, 0, 1.0], (on_top.sum(), 3)), atol=1e-4)
    ground = seg == plane.idx
    np.testing.assert_allclose(depth[ground], 3.0, rtol=2e-5)


def test_camera_matrices_agree_with_projection(world):
    scene = world[0]
    kw = dict(res=(200, 100), pos=(1.0, -2.0, 0.7), lookat=(0.2, 0.3, 0.1), up=(0, 0, 1), fov=35)
    cam = scene.add_camera(**kw)
    pts = np.array([[0.1, 0.2, 0.3], [0.5, -0.4, 0.0], [-0.3, 0.6, 0.9]])
    u, v, z = project(pts, kw["pos"], kw["lookat"], kw["up"], kw["fov"], kw["res"])
    pc = (cam.extrinsics @ np.c_[pts, np.ones(3)].T)[:3]
    uvw = cam.intrinsics @ pc
    np.testing.assert_allclose(uvw[0] / uvw[2], u, atol=1e-9)
    np.testing.assert_allclose(uvw[1] / uvw[2], v, atol=1e-9)
    np.testing.assert_allclose(pc[2], z, atol=1e-12)
    T = cam.transform
    np.testing.assert_allclose(T[:3, 3], kw["pos"])
    np.testing.assert_allclose(np.linalg.inv(T)[:3, :3] @ (np.array(kw["lookat"]) - kw["pos"]),
                               [0, 0, -np.linalg.norm(np.subtract(kw["lookat"], kw["pos"]))], atol=1e-12)
    # set_pose(transform=) round-trips
    cam2 = scene.add_camera(res=(20, 10), pos=(0, -1, 0), lookat=(0, 0, 0))
    cam2.set_pose(transform=T)
    np.testing.assert_allclose(cam2.extrinsics, cam.extrinsics, atol=1e-12)


def test_set_pose_moves_the_image(world):
    scene, plane, box, fixed, _ = world
    scene.reset()
    cam = scene.add_camera(res=(80, 60), pos=(0.8, -1.5, 1.0), lookat=FIXED_BOX["pos"], fov=40)
    seg0 = cam.render(segmentation=True)[2]
    cam.set_pose(lookat=(1.3, 0.6, 0.1))  # look further right: the box moves left in the image
    seg1 = cam.render(segmentation=True)[2]
    c0 = np.nonzero(seg0 == fixed.idx)[1].mean()
    c1 = np.nonzero(seg1 == fixed.idx)[1].mean()
    assert c1 < c0 - 5


def test_rendering_inside_a_gradient_rollout_changes_nothing():
    """Cameras read poses without building graph nodes: gradients are the same with and without them,
    and equal the analytic ones of a box in free fall (x(t) = x0 + v0 t + g t^2 / 2)."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True))
    box = scene.add_entity(gs.morphs.Box(size=(0.2,) * 3, pos=(0.0, 0.0, 2.0)))
    cam = scene.add_camera(res=(48, 32), pos=(3.0, -3.0, 2.0), lookat=(0.0, 0.0, 1.5))
    scene.build()
    grads = []
    for render in (False, True):
        v0 = torch.tensor([0.3, -0.2, 0.5, 0.0, 0.0, 0.0], dtype=torch.float64, requires_grad=True)
        scene.reset()
        box.set_dofs_velocity(v0)
        for _ in range(20):
            scene.step()
            if render:
                cam.render()
        w = torch.tensor([1.0, 2.0, -1.5], dtype=torch.float64)
        (box.get_pos() * w).sum().backward()
        grads.append(v0.grad.clone())
    assert torch.equal(grads[0], grads[1])
    torch.testing.assert_close(grads[0][:3], 0.2 * torch.tensor([1.0, 2.0, -1.5], dtype=torch.float64),
                               rtol=1e-9, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------------
def test_recording_errors(world, tmp_path):
    scene = world[0]
    cam = scene.add_camera(res=(32, 24), pos=(2, -2, 1), lookat=(0, 0, 0.3))
    with pytest.raises(GenesisException, match="without start_recording"):
        cam.stop_recording(save_to_filename=str(tmp_path / "x.mp4"))
    cam.start_recording()
    with pytest.raises(GenesisException, match="already recording"):
        cam.start_recording()
    with pytest.raises(GenesisException, match="no frames"):
        cam.stop_recording(save_to_filename=str(tmp_path / "x.mp4"))
    cam.render()
    cam.render()
    with pytest.raises(GenesisException, match=r"unsupported extension '\.avi'.*\.gif and \.mp4"):
        cam.stop_recording(save_to_filename=str(tmp_path / "x.avi"))
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    bad = blocker / "out" / "x.mp4"
    with pytest.raises(GenesisException, match="cannot write video") as e:
        cam.stop_recording(save_to_filename=str(bad))
    assert str(bad) in str(e.value)
    (tmp_path / "d.mp4").mkdir()
    with pytest.raises(GenesisException, match="existing folder"):
        cam.stop_recording(save_to_filename=str(tmp_path / "d.mp4"))
    with pytest.raises(ValueError, match="fps"):
        cam.stop_recording(save_to_filename=str(tmp_path / "x.gif"), fps=0)
    # the frames survived the failed attempts
    from PIL import Image

    path = cam.stop_recording(save_to_filename=str(tmp_path / "ok.gif"), fps=10)
    with Image.open(path) as im:
        assert im.n_frames >= 1  # two identical frames: Pillow may merge them into one longer frame
    with pytest.raises(GenesisException, match="without start_recording"):
        cam.stop_recording(save_to_filename=str(tmp_path / "x.mp4"))


def test_unwritable_folder_is_named(world, tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root can write into read-only folders; the file-as-folder case is tested above")
    scene = world[0]
    cam = scene.add_camera(res=(16, 16), pos=(2, -2, 1), lookat=(0, 0, 0.3))
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    cam.start_recording()
    cam.render()
    try:
        with pytest.raises(GenesisException, match="not writable") as e:
            cam.stop_recording(save_to_filename=str(ro / "x.mp4"))
        assert str(ro) in str(e.value)
    finally:
        ro.chmod(0o700)


def test_camera_argument_errors(world):
    scene = world[0]
    for kwargs, match in [
        (dict(res=(0, 10)), "res"),
        (dict(res=(10,)), "res"),
        (dict(fov=0), "fov"),
        (dict(fov=180), "fov"),
        (dict(pos=(1, 1, 1), lookat=(1, 1, 1)), "coincide"),
        (dict(pos=(0, 0, 2), lookat=(0, 0, 0), up=(0, 0, 1)), "parallel"),
        (dict(pos=(0, 0, float("nan"))), "pos"),
        (dict(near=1.0, far=0.5), "near"),
        (dict(model="thinlens"), "pinhole"),
    ]:
        with pytest.raises(ValueError, match=match):
            scene.add_camera(**kwargs)
    with pytest.raises(TypeError, match="unexpected"):
        scene.add_camera(resolution=(10, 10))
    with pytest.raises(TypeError):
        scene.add_camera(res=(8, 8)).render(colour=True)
    cam = scene.add_camera(res=(16, 16), env_idx=3)
    with pytest.raises(GenesisException, match="env_idx=3"):
        cam.render()
    with pytest.raises(ValueError, match="color"):
        gs.surfaces.Default(color=(255, 0, 0))
    with pytest.raises(TypeError, match="surface"):
        gs.Scene().add_entity(gs.morphs.Box(), surface="red")


# ------------------------------------------------------------------------------------------------
# Particles (a stand-in for an MPM entity: any entity with get_particles_pos)
# ------------------------------------------------------------------------------------------------
class FakeParticles:
    def __init__(self, pos, color=(0.1, 0.8, 0.2), radius=None):
        self._pos = pos
        self.n_particles = pos.shape[-2]
        self._vis_color = color
        if radius is not None:
            self._vis_radius = radius
        self.name = "fake_particles"

    def get_particles_pos(self):
        return self._pos


def test_sphere_splats_cover_the_projected_disc():
    from genesis_lite.vis.raster import Light, Rasterizer

    rs = Rasterizer(101, 81, f=100.0, near=0.05, far=100.0)
    rs.clear()
    P = np.array([[0.1, -0.05, 2.0]])  # camera frame
    r = 0.06
    rs.draw_spheres(P, r, (1.0, 0.0, 0.0), np.int32(7), Light(np.array([0.0, 0.0, -1.0])))
    u0, v0 = 50.5 + 100 * 0.1 / 2.0, 40.5 + 100 * 0.05 / 2.0
    rp = 100 * r / 2.0
    jj, ii = np.meshgrid(np.arange(101) + 0.5, np.arange(81) + 0.5)
    inside = (jj - u0) ** 2 + (ii - v0) ** 2 <= rp ** 2
    seg = rs.seg()
    assert np.array_equal(seg == 7, inside)
    depth = rs.depth()
    # the disc's depth follows the sphere's near cap
    dist = np.sqrt((jj - u0) ** 2 + (ii - v0) ** 2)[inside] / rp
    np.testing.assert_allclose(depth[inside], 2.0 - r * np.sqrt(1 - dist ** 2), rtol=1e-5)
    # a second sphere behind the first is hidden where they overlap, visible elsewhere
    rs.draw_spheres(np.array([[0.25, -0.05, 2.5]]), r, (0.0, 1.0, 0.0), np.int32(8), Light(np.array([0.0, 0.0, -1.0])))
    seg2 = rs.seg()
    assert np.array_equal(seg2[inside], seg[inside])
    assert (seg2 == 8).sum() > 10


def test_particle_entity_drawn_where_it_is(world):
    scene, plane, box, fixed, _ = world
    scene.reset()
    g = np.stack(np.meshgrid(*[np.linspace(-0.1, 0.1, 8)] * 3, indexing="ij"), -1).reshape(-1, 3)
    P = torch.tensor(g + [0.0, -0.8, 0.4])
    fake = FakeParticles(P, radius=0.012)
    scene.entities.append(fake)  # after build: the solvers never see it, the camera does
    scene.__dict__.pop("_vis_drawables", None)
    try:
        kw = dict(res=(120, 90), pos=(1.5, -2.5, 1.0), lookat=(0.0, -0.8, 0.4), up=(0, 0, 1), fov=40)
        cam = scene.add_camera(**kw)
        rgb, depth, seg, _ = cam.render(depth=True, segmentation=True)
        mine = seg == len(scene.entities) - 1
        u, v, z = project(P.numpy(), kw["pos"], kw["lookat"], kw["up"], kw["fov"], kw["res"])
        rpx = (kw["res"][1] / 2) / np.tan(np.radians(20)) * 0.012 / z.min()
        rows, cols = mask_stats(mine)
        assert rows.size > 200
        assert cols.min() >= u.min() - rpx - 1 and cols.max() <= u.max() + rpx + 1
        assert rows.min() >= v.min() - rpx - 1 and rows.max() <= v.max() + rpx + 1
        assert depth[mine].min() >= z.min() - 0.012 - 1e-4 and depth[mine].max() <= z.max()
        g_ch = rgb[mine].astype(int)
        assert np.all(g_ch[:, 1] > g_ch[:, 0]) and np.all(g_ch[:, 1] > g_ch[:, 2])  # the entity's green
    finally:
        scene.entities.remove(fake)
        scene.__dict__.pop("_vis_drawables", None)


def test_batched_scene_renders_env_idx():
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
    scene.add_entity(gs.morphs.Plane())
    box = scene.add_entity(gs.morphs.Box(size=(0.3,) * 3, pos=(0.0, 0.0, 0.15)))
    kw = dict(res=(80, 60), pos=(0.0, -3.0, 1.5), lookat=(0.0, 0.0, 0.2), up=(0, 0, 1), fov=45)
    cams = [scene.add_camera(**kw), scene.add_camera(env_idx=1, **kw)]
    scene.build(n_envs=2)
    box.set_pos(torch.tensor([[0.8, 0.0, 0.15]], dtype=torch.float64), envs_idx=[1])
    # particles given per environment: env 1's set lies elsewhere
    P = torch.zeros(2, 50, 3, dtype=torch.float64)
    P[0, :, :] = torch.tensor([-0.8, 0.0, 0.5])
    P[1, :, :] = torch.tensor([-0.8, 0.0, 5.0])
    fake = FakeParticles(P + torch.randn(2, 50, 3, dtype=torch.float64) * 0.03, radius=0.02)
    scene.entities.append(fake)
    centres = []
    for cam, x in zip(cams, (0.0, 0.8)):
        seg = cam.render(segmentation=True)[2]
        rows, cols = mask_stats(seg == box.idx)
        u, v, _ = project([[x, 0.0, 0.15]], kw["pos"], kw["lookat"], kw["up"], kw["fov"], kw["res"])
        assert abs(cols.mean() - u[0]) < 1.5
        centres.append(np.nonzero(seg == 2)[1].mean() if (seg == 2).any() else None)
    u_p, _, _ = project([[-0.8, 0.0, 0.5]], kw["pos"], kw["lookat"], kw["up"], kw["fov"], kw["res"])
    assert centres[0] is not None and abs(centres[0] - u_p[0]) < 3
    assert centres[1] is None  # env 1's particles are above the image


# ------------------------------------------------------------------------------------------------
# Visual meshes: loaded at first render, not at build; colours and vis_mode
# ------------------------------------------------------------------------------------------------
def _write_visual_urdf(folder, name, mesh_name):
    (folder / name).write_text(f"""<?xml version="1.0"?>
<robot name="vis">
  <material name="blue"><color rgba="0.1 0.2 0.9 1"/></material>
  <link name="base">
    <inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><geometry><box size="0.1 0.1 0.1"/></geometry></collision>
    <visual><origin xyz="0.6 0 0"/><geometry><mesh filename="{mesh_name}"/></geometry><material name="blue"/></visual>
  </link>
</robot>
""")
    return folder / name


def test_visual_meshes_load_lazily_and_are_drawn(tmp_path, monkeypatch):
    """A link whose collision shape is a 0.1 m box at its origin and whose visual is a blue ball of
    radius 0.25 m, 0.6 m along x: drawn as the ball, as the box with vis_mode='collision', and as the
    box (with a warning) when the ball's file is missing."""
    import trimesh

    from genesis_lite.vis import geometry

    trimesh.creation.icosphere(subdivisions=3, radius=0.25).export(tmp_path / "ball.stl")
    urdf = _write_visual_urdf(tmp_path, "robot.urdf", "ball.stl")
    broken = _write_visual_urdf(tmp_path, "broken.urdf", "gone.stl")
    calls = []
    real = geometry.load_visual_file
    monkeypatch.setattr(geometry, "load_visual_file", lambda *a, **k: calls.append(a) or real(*a, **k))
    scene = gs.Scene()
    vis = scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=True, pos=(0, 0, 0.5)))
    col = scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=True, pos=(0, 1.0, 0.5)),
                           surface=gs.surfaces.Default(vis_mode="collision"))
    gone = scene.add_entity(gs.morphs.URDF(file=str(broken), fixed=True, pos=(-0.6, 1.0, 0.5)))
    kw = dict(res=(160, 120), pos=(0.3, -3.0, 0.5), lookat=(0.3, 0.5, 0.5), up=(0, 0, 1), fov=40)
    cam = scene.add_camera(**kw)
    scene.build()
    assert calls == []  # nothing read at build
    with pytest.warns(UserWarning, match="gone.stl.*collision"):
        rgb, _, seg, _ = cam.render(segmentation=True)
    assert len(calls) == 1 and calls[0][0].endswith("ball.stl")

    f = 60 / np.tan(np.radians(20))
    u, v, z = project([[0.6, 0.0, 0.5], [0.0, 1.0, 0.5], [-0.6, 1.0, 0.5]], kw["pos"], kw["lookat"], kw["up"],
                      kw["fov"], kw["res"])
    # the blue ball (its collision box is not drawn)
    rows, cols = mask_stats(seg == vis.idx)
    assert abs(cols.mean() - u[0]) < 1.5 and abs(rows.mean() - v[0]) < 1.5
    assert abs(np.sqrt(rows.size / np.pi) - 0.25 * f / z[0]) < 1.5  # a disc of the ball's radius
    px = rgb[seg == vis.idx].astype(int)
    assert np.all(px[:, 2] > px[:, 0])  # the URDF material's blue
    # vis_mode='collision', and a missing visual file: only the 0.1 m box at the link origin
    for ent, k in ((col, 1), (gone, 2)):
        rows, cols = mask_stats(seg == ent.idx)
        assert abs(cols.mean() - u[k]) < 1.5 and abs(rows.mean() - v[k]) < 1.5
        assert cols.max() - cols.min() < 0.12 * f / z[k] + 2


# ------------------------------------------------------------------------------------------------
# Geometry helpers
# ------------------------------------------------------------------------------------------------
def test_decimation_keeps_the_shape_within_its_budget():
    import trimesh

    from genesis_lite.vis.geometry import corner_normals, decimate

    m = trimesh.creation.icosphere(subdivisions=5, radius=1.0)  # 20480 faces
    colors = np.tile([[0.2, 0.3, 0.4]], (len(m.faces), 1))
    V, F, C = decimate(np.asarray(m.vertices), np.asarray(m.faces), 2000, colors)
    assert 500 < len(F) <= 2000 and C.shape == (len(F), 3)
    r = np.linalg.norm(V, axis=1)
    assert np.all(np.abs(r - 1.0) < 0.08)
    # smooth corner normals of a sphere point along the radius
    N = corner_normals(V, F)
    radial = V[F] / r[F][..., None]
    cos = np.einsum("mkj,mkj->mk", N, radial)
    assert np.median(cos) > 0.995 and cos.min() > 0.9  # no face turned inside out


def test_primitive_silhouettes_and_mesh_morph(tmp_path):
    """Sphere, capsule and cylinder seen side-on: their projected extents match their dimensions. A
    gs.morphs.Mesh is drawn from its file, not from the convex hull that is its collision shape."""
    import trimesh

    # an L-shaped solid in the x-z plane: its hull fills the notch between the bars, the drawing must not
    a = trimesh.creation.box((0.4, 0.1, 0.1), transform=trimesh.transformations.translation_matrix((0.15, 0, 0)))
    b = trimesh.creation.box((0.1, 0.1, 0.4), transform=trimesh.transformations.translation_matrix((0, 0, 0.15)))
    trimesh.util.concatenate([a, b]).export(tmp_path / "ell.stl")
    scene = gs.Scene()
    # (drawn only: its collision shape is beside the point, so it is not split into convex parts)
    with pytest.warns(UserWarning, match="collides as its convex hull"):
        ell = scene.add_entity(gs.morphs.Mesh(file=str(tmp_path / "ell.stl"), fixed=True, pos=(1.3, 0, 0.3),
                                              decompose_nonconvex=False))
    d = 8.0  # camera distance
    # silhouettes of the tangent cones from the camera: a circle of radius r at distance d spans
    # 2 f r / sqrt(d^2 - r^2); a cylinder's rim is nearest at d - r; a capsule's cap adds its angle
    shapes = [
        (gs.morphs.Sphere(radius=0.2, pos=(-0.8, 0, 0.5), fixed=True),
         lambda f: (2 * f * 0.2 / np.sqrt(d * d - 0.04),) * 2),
        (gs.morphs.Capsule(radius=0.1, height=0.3, pos=(0.0, 0, 0.5), fixed=True),
         lambda f: (2 * f * 0.1 / np.sqrt(d * d - 0.01),
                    2 * f * np.tan(np.arctan(0.15 / d) + np.arcsin(0.1 / np.hypot(d, 0.15))))),
        (gs.morphs.Cylinder(radius=0.15, height=0.2, pos=(0.8, 0, 0.5), fixed=True),
         lambda f: (2 * f * 0.15 / np.sqrt(d * d - 0.0225), 2 * f * 0.1 / (d - 0.15))),
    ]
    ents = [scene.add_entity(m) for m, _ in shapes]
    kw = dict(res=(240, 120), pos=(0.0, -d, 0.5), lookat=(0.0, 0.0, 0.5), up=(0, 0, 1), fov=12)
    cam = scene.add_camera(**kw)
    scene.build()
    seg = cam.render(segmentation=True)[2]
    f = 60 / np.tan(np.radians(6))
    for e, (m, extent) in zip(ents, shapes):
        rows, cols = mask_stats(seg == e.idx)
        w, h = extent(f)
        u, v, _ = project([m.pos], kw["pos"], kw["lookat"], kw["up"], kw["fov"], kw["res"])
        assert abs(cols.mean() - u[0]) < 1 and abs(rows.mean() - v[0]) < 1
        # pixel centres inside a span of w pixels: w - 1 < count <= w + 1
        assert abs((cols.max() - cols.min() + 1) - w) < 1.5, (type(m).__name__, cols.max() - cols.min() + 1, w)
        assert abs((rows.max() - rows.min() + 1) - h) < 1.5, (type(m).__name__, rows.max() - rows.min() + 1, h)
    # (0.15, 0.15) in the L's frame is inside its hull (x + z < 0.4) but outside both bars; (0.25, 0) is on one
    (un, ua), (vn, va), _ = project([[1.45, 0.0, 0.45], [1.55, 0.0, 0.3]], kw["pos"], kw["lookat"], kw["up"],
                                    kw["fov"], kw["res"])
    assert seg[int(vn), int(un)] != ell.idx
    assert seg[int(va), int(ua)] == ell.idx


@pytest.mark.slow
def test_panda_visual_meshes(urdf_path):
    scene = gs.Scene()
    scene.add_entity(gs.morphs.Plane())
    arm = scene.add_entity(gs.morphs.URDF(file=str(urdf_path("panda")), fixed=True))
    kw = dict(res=(160, 120), pos=(1.6, 0.9, 1.1), lookat=(0.1, 0.0, 0.4), up=(0, 0, 1), fov=40)
    cam = scene.add_camera(**kw)
    scene.build()
    arm.set_dofs_position(torch.tensor([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8, 0.02, 0.02], dtype=torch.float64))
    rgb, _, seg, _ = cam.render(segmentation=True)
    assert scene._vis_drawables.n_faces < 40_000  # decimated from 134k in the files
    rows, cols = mask_stats(seg == arm.idx)
    u, v, _ = project(arm.get_links_pos().numpy(), kw["pos"], kw["lookat"], kw["up"], kw["fov"], kw["res"])
    # every link origin lies within the arm's silhouette's extent (origins sit inside the links)
    assert cols.min() - 1 <= u.min() and u.max() <= cols.max() + 1
    assert rows.min() - 1 <= v.min() and v.max() <= rows.max() + 1
    # the files' own materials: light grey shell and dark joint covers
    grey = rgb[seg == arm.idx].astype(int).mean(1)
    assert (grey > 170).mean() > 0.3 and (grey < 90).mean() > 0.02


@pytest.mark.slow
def test_example_record_video_quick(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    import imageio.v2 as iio
    from PIL import Image

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root)}
    p = subprocess.run([sys.executable, "examples/record_video.py", "--quick", "--out", str(tmp_path)], cwd=root,
                       env=env, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    frames = [f for f in iio.get_reader(tmp_path / "rollout.mp4", format="FFMPEG")]
    assert len(frames) == 30 and frames[0].shape == (240, 320, 3)
    with Image.open(tmp_path / "rollout.gif") as im:
        assert im.n_frames == 10
