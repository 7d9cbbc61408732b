"""Loaders: URDF / primitive / mesh morphs -> EntityModel, checked against Pinocchio and closed forms."""
import glob
import os
import site
import time
import warnings

import numpy as np
import pytest
import trimesh

from genesis_lite import materials, morphs
from genesis_lite.loaders import load_morph, load_urdf
from genesis_lite.loaders import primitives as prim
from genesis_lite.loaders.primitives import pose_matrix, quat_to_mat

ERD = os.path.join(site.getsitepackages()[0], "cmeel.prefix", "share", "example-robot-data", "robots")
ALL_URDFS = sorted(glob.glob(os.path.join(ERD, "**", "*.urdf"), recursive=True))
RIGID = materials.Rigid(rho=1000.0)


def erd(rel):
    p = os.path.join(ERD, rel)
    if not os.path.isfile(p):
        pytest.skip(f"example-robot-data has no {rel}")
    return p


def urdf(path, **kw):
    return load_urdf(morphs.URDF(file=str(path), **kw), RIGID, "robot")


def write(tmp_path, body, name="robot.urdf"):
    p = tmp_path / name
    p.write_text(f'<?xml version="1.0"?>\n<robot name="t">\n{body}\n</robot>\n')
    return p


def link(name, mass=1.0, extra=""):
    inertial = (
        f'<inertial><origin xyz="0 0 0"/><mass value="{mass}"/>'
        '<inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial>'
        if mass is not None
        else ""
    )
    return f'<link name="{name}">{inertial}{extra}</link>'


def joint(name, parent, child, type="revolute", extra=""):
    lim = '<limit lower="-1" upper="1" effort="10" velocity="2"/>' if type in ("revolute", "prismatic") else ""
    return (f'<joint name="{name}" type="{type}"><parent link="{parent}"/><child link="{child}"/>'
            f'<axis xyz="0 0 1"/>{lim}{extra}</joint>')


# --------------------------------------------------------------------------------------------
# (1) every example-robot-data URDF that yourdfpy can parse loads
# --------------------------------------------------------------------------------------------
def test_all_example_robot_data_urdfs_load():
    import yourdfpy

    if not ALL_URDFS:
        pytest.skip("example-robot-data not installed")
    t0 = time.perf_counter()
    loaded, skipped, failed = [], [], []
    for p in ALL_URDFS:
        rel = os.path.relpath(p, ERD)
        try:
            yourdfpy.URDF.load(p, build_scene_graph=False, load_meshes=False, load_collision_meshes=False)
        except Exception as e:
            skipped.append(f"{rel} ({type(e).__name__}: {e})")
            continue
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                for fixed in (True, False):
                    m = urdf(p, fixed=fixed)
                    m.validate()
                    assert m.links[0].joint_type == ("fixed" if fixed else "free")
        except Exception as e:
            failed.append(f"{rel}: {type(e).__name__}: {e}")
            continue
        loaded.append(rel)
    dt = time.perf_counter() - t0
    print(f"\nloaded {len(loaded)} / {len(ALL_URDFS)} example-robot-data URDFs in {dt:.1f} s; "
          f"yourdfpy cannot parse {len(skipped)}: {skipped}")
    assert not failed, "\n".join(failed)
    assert len(loaded) >= 60


def test_joint_order_matches_pinocchio_for_all_robots():
    pin = pytest.importorskip("pinocchio")
    checked = 0
    for p in ALL_URDFS:
        try:
            pm = pin.buildModelFromUrdf(p)
        except Exception:
            continue
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                m = urdf(p, fixed=True)
        except ValueError:
            continue  # files yourdfpy cannot parse; covered above
        ours = [l.joint_name for l in m.links[1:]]
        theirs = [pm.names[i] for i in range(1, pm.njoints)]
        assert ours == theirs, os.path.relpath(p, ERD)
        checked += 1
    assert checked >= 60


# --------------------------------------------------------------------------------------------
# (2) against Pinocchio: names, order, parents, inertias, joint placements
# --------------------------------------------------------------------------------------------
PIN_CASES = [
    ("panda_description/urdf/panda.urdf", False),
    ("ur_description/urdf/ur5_robot.urdf", False),
    ("z1_description/urdf/z1.urdf", False),
    ("go2_description/urdf/go2.urdf", True),
    ("anymal_b_simple_description/robots/anymal.urdf", True),
    ("go2_description/urdf/go2.urdf", False),
    ("talos_data/robots/talos_full_v2.urdf", True),
]


def compare_with_pinocchio(path, floating, model=None):
    pin = pytest.importorskip("pinocchio")
    pm = pin.buildModelFromUrdf(str(path), pin.JointModelFreeFlyer()) if floating else pin.buildModelFromUrdf(str(path))
    m = model if model is not None else urdf(path, fixed=not floating)
    # pin: joint 0 is the universe; a free base is its joint 1, a fixed base merges into the universe
    ours = m.links if floating else m.links[1:]
    first = 1
    assert len(ours) == pm.njoints - first
    assert [l.joint_name for l in ours if l.parent >= 0] == list(pm.names)[first + floating:]
    T_root = pose_matrix(m.links[0].joint_pos, m.links[0].joint_quat)
    for k, l in enumerate(ours):
        i = k + first
        where = f"{os.path.basename(str(path))} joint {pm.names[i]}"
        # parent: our index -> pin index
        if l.parent >= 0:
            expect_parent = l.parent + (1 if floating else 0)
            assert pm.parents[i] == expect_parent, where
        inert = pm.inertias[i]
        assert abs(inert.mass - l.mass) < 1e-9, where
        np.testing.assert_allclose(l.com, inert.lever, atol=1e-9, rtol=0, err_msg=where)
        np.testing.assert_allclose(l.inertia, inert.inertia, atol=1e-9, rtol=0, err_msg=where)
        if l.parent == -1:
            continue  # pin's free-flyer sits at identity; ours carries the initial placement
        T = pose_matrix(l.joint_pos, l.joint_quat)
        if not floating and l.parent == 0:
            T = T_root @ T  # pin folds the fixed base into the universe
        P = pm.jointPlacements[i]
        np.testing.assert_allclose(T[:3, 3], P.translation, atol=1e-9, rtol=0, err_msg=where)
        np.testing.assert_allclose(T[:3, :3], P.rotation, atol=1e-9, rtol=0, err_msg=where)
        assert pm.joints[i].nv == 1, where
    return pm, m


@pytest.mark.parametrize("rel,floating", PIN_CASES, ids=[f"{r.split('/')[0]}-{'free' if f else 'fixed'}" for r, f in PIN_CASES])
def test_matches_pinocchio(rel, floating):
    pin = pytest.importorskip("pinocchio")
    pm, m = compare_with_pinocchio(erd(rel), floating)
    # joint axes: compare the motion subspace at q = neutral
    data = pm.createData()
    q = pin.neutral(pm)
    pin.computeJointJacobians(pm, data, q)
    ours = m.links if floating else m.links[1:]
    for k, l in enumerate(ours):
        if l.parent == -1:
            continue
        i = k + 1
        S = np.asarray(data.joints[i].S).reshape(6, -1)[:, 0]  # pin: linear part first, then angular
        sub = S[3:] if l.joint_type == "revolute" else S[:3]
        np.testing.assert_allclose(sub, l.joint_axis, atol=1e-9, err_msg=pm.names[i])


def test_tiny_urdf_merging_matches_pinocchio(tmp_path):
    """Fixed joints with rotations, rotated inertials, a joint below a merged link."""
    inertial = ('<inertial><origin xyz="0.1 -0.2 0.05" rpy="0.3 -0.2 0.9"/><mass value="{m}"/>'
                '<inertia ixx="0.3" ixy="0.01" ixz="-0.02" iyy="0.2" iyz="0.03" izz="0.25"/></inertial>')
    body = "\n".join([
        f'<link name="base">{inertial.format(m=2.0)}</link>',
        f'<link name="a">{inertial.format(m=1.5)}</link>',
        f'<link name="f1">{inertial.format(m=0.7)}</link>',
        f'<link name="f2">{inertial.format(m=0.3)}</link>',
        f'<link name="b">{inertial.format(m=0.9)}</link>',
        f'<link name="c">{inertial.format(m=0.4)}</link>',
        '<joint name="j_a" type="revolute"><parent link="base"/><child link="a"/>'
        '<origin xyz="0.1 0.2 0.3" rpy="0.1 0.2 0.3"/><axis xyz="1 1 0"/>'
        '<limit lower="-1" upper="1" effort="5" velocity="3"/></joint>',
        '<joint name="f_1" type="fixed"><parent link="a"/><child link="f1"/><origin xyz="0.0 0.5 0" rpy="1.2 0 0.4"/></joint>',
        '<joint name="f_2" type="fixed"><parent link="f1"/><child link="f2"/><origin xyz="0.3 0 0.1" rpy="0 -0.7 0"/></joint>',
        '<joint name="j_b" type="prismatic"><parent link="f2"/><child link="b"/>'
        '<origin xyz="0 0 0.2" rpy="0.5 0.5 0.5"/><axis xyz="0 0 2"/><limit lower="0" upper="0.1" effort="1" velocity="1"/></joint>',
        '<joint name="i_c" type="continuous"><parent link="a"/><child link="c"/><origin xyz="0.2 0 0"/><axis xyz="0 1 0"/></joint>',
    ])
    p = write(tmp_path, body)
    _, m = compare_with_pinocchio(p, floating=True)
    _, m = compare_with_pinocchio(p, floating=False)
    # children of 'a' in joint-name order: f_1 (leading to j_b) before i_c
    assert [l.joint_name for l in m.links] == ["root_joint", "j_a", "j_b", "i_c"]
    np.testing.assert_allclose(m.links[1].joint_axis, [2 ** -0.5, 2 ** -0.5, 0])
    np.testing.assert_allclose(m.links[2].joint_axis, [0, 0, 1])
    assert m.links[3].limit == (-np.inf, np.inf)
    assert m.links[2].limit == (0.0, 0.1) and m.links[2].joint_type == "prismatic"


# --------------------------------------------------------------------------------------------
# URDF features
# --------------------------------------------------------------------------------------------
def test_panda_loads_with_expected_structure():
    p = erd("panda_description/urdf/panda.urdf")
    urdf(p)  # imports
    prim._MESH_CACHE.clear()
    t = time.perf_counter()
    m = urdf(p, fixed=True)
    dt = time.perf_counter() - t
    print(f"\npanda cold-cache load: {dt * 1000:.1f} ms")  # timed in benchmarks/bench_build.py, not asserted
    assert m.n_dofs == 9 and m.n_qs == 9
    mesh_geoms = [g for l in m.links for g in l.geoms if g.type == "mesh"]
    assert mesh_geoms and all(g.vertices.shape[1] == 3 and g.faces.shape[1] == 3 for g in mesh_geoms)
    fingers = [l for l in m.links if "finger" in l.joint_name]
    assert [l.joint_type for l in fingers] == ["prismatic", "prismatic"]
    assert fingers[1].mimic is not None and fingers[1].mimic.joint == fingers[0].joint_name


def test_scale(tmp_path):
    p = erd("panda_description/urdf/panda.urdf")
    a, b = urdf(p, fixed=True), urdf(p, fixed=True, scale=2.0)
    for la, lb in zip(a.links[1:], b.links[1:]):
        np.testing.assert_allclose(lb.joint_pos, 2 * la.joint_pos, atol=1e-12)
        np.testing.assert_allclose(lb.joint_quat, la.joint_quat, atol=1e-12)
        np.testing.assert_allclose(lb.com, 2 * la.com, atol=1e-12)
        assert lb.mass == pytest.approx(8 * la.mass, rel=1e-12)
        np.testing.assert_allclose(lb.inertia, 32 * la.inertia, atol=1e-12)
        for ga, gb in zip(la.geoms, lb.geoms):
            np.testing.assert_allclose(gb.pos, 2 * ga.pos, atol=1e-12)
            if ga.type == "mesh":
                np.testing.assert_allclose(gb.vertices, 2 * ga.vertices, atol=1e-12)
    fa = [l for l in a.links if l.joint_type == "prismatic"][0]
    fb = [l for l in b.links if l.joint_type == "prismatic"][0]
    assert fb.limit == pytest.approx((2 * fa.limit[0], 2 * fa.limit[1]))


def test_root_placement_and_world_link(tmp_path):
    body = "\n".join([
        '<link name="world"/>',
        link("base"), link("arm"),
        '<joint name="weld" type="fixed"><parent link="world"/><child link="base"/><origin xyz="0 0 1" rpy="0 0 1.5707963267948966"/></joint>',
        joint("j1", "base", "arm"),
    ])
    p = write(tmp_path, body)
    q = np.array([np.cos(0.25), 0, np.sin(0.25), 0])  # 0.5 rad about y
    for fixed in (True, False):
        m = load_urdf(morphs.URDF(file=str(p), pos=(1, 2, 3), quat=q, fixed=fixed), RIGID, "r")
        assert [l.name for l in m.links] == ["base", "arm"]
        assert m.links[0].joint_type == ("fixed" if fixed else "free")
        assert m.links[0].joint_name == "weld"
        T = pose_matrix((1, 2, 3), q) @ pose_matrix((0, 0, 1), [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
        np.testing.assert_allclose(pose_matrix(m.links[0].joint_pos, m.links[0].joint_quat), T, atol=1e-12)
    # floating joint from a placeholder root is the free base, not an error
    body = body.replace('type="fixed"', 'type="floating"').replace('name="world"', 'name="odom"').replace('link="world"', 'link="odom"')
    m = urdf(write(tmp_path, body, "f.urdf"))
    assert m.links[0].joint_type == "free" and m.links[0].name == "base"


def test_link_without_inertial_gets_geometry_mass(tmp_path):
    geom = ('<collision><origin xyz="0.5 0 0" rpy="0 1.5707963267948966 0"/><geometry><box size="0.2 0.4 0.6"/></geometry></collision>'
            '<collision><origin xyz="0 0 0"/><geometry><sphere radius="0.1"/></geometry></collision>')
    body = "\n".join([link("base"), link("a", mass=None, extra=geom), link("b", mass=None), joint("j1", "base", "a"),
                      joint("j2", "a", "b")])
    m = urdf(write(tmp_path, body))
    a, b = m.links[1], m.links[2]
    mb, ms = 1000 * 0.2 * 0.4 * 0.6, 1000 * 4 / 3 * np.pi * 0.1 ** 3
    assert a.mass == pytest.approx(mb + ms, rel=1e-12)
    np.testing.assert_allclose(a.com, [0.5 * mb / (mb + ms), 0, 0], atol=1e-12)
    # box rotated 90 deg about y: its local x (0.2) lies along z
    Ibox = mb / 12 * np.diag([0.4 ** 2 + 0.6 ** 2, 0.2 ** 2 + 0.6 ** 2, 0.2 ** 2 + 0.4 ** 2])
    R = quat_to_mat([np.cos(np.pi / 4), 0, np.sin(np.pi / 4), 0])
    d1, d2 = np.array([0.5, 0, 0]) - a.com, -a.com
    pa = lambda m_, d: m_ * (d @ d * np.eye(3) - np.outer(d, d))  # noqa: E731
    expect = R @ Ibox @ R.T + pa(mb, d1) + 0.4 * ms * 0.01 * np.eye(3) + pa(ms, d2)
    np.testing.assert_allclose(a.inertia, expect, atol=1e-12)
    assert b.mass == 0.0 and not b.geoms


def test_default_densities_are_genesis_s(tmp_path):
    """Rigid() (rho=None) fills shapes that have no mass of their own at Genesis 0.4.5's densities: 1,500 kg/m^3
    for the links of an articulated robot, 600 for an object (a primitive, a mesh, a URDF with no hinge or slide);
    Genesis gives these masses for the same files and shapes (a 0.2 x 0.4 x 0.6 m box: 72 kg as a robot's link,
    28.8 kg as an object). An explicit rho is used for both."""
    box = '<collision><geometry><box size="0.2 0.4 0.6"/></geometry></collision>'
    vol = 0.2 * 0.4 * 0.6
    arm = write(tmp_path, "\n".join([link("base", mass=None, extra=box), link("a", mass=None, extra=box),
                                      joint("j1", "base", "a")]), "arm.urdf")
    lone = write(tmp_path, link("base", mass=None, extra=box), "lone.urdf")
    arm_m = load_urdf(morphs.URDF(file=str(arm)), materials.Rigid(), "arm")
    assert [l.mass for l in arm_m.links] == pytest.approx([1500.0 * vol] * 2, rel=1e-12)
    lone_m = load_urdf(morphs.URDF(file=str(lone)), materials.Rigid(), "lone")
    assert lone_m.links[0].mass == pytest.approx(600.0 * vol, rel=1e-12)
    b = load_morph(morphs.Box(size=(0.2, 0.4, 0.6)), materials.Rigid(), "box").links[0]
    assert b.mass == pytest.approx(600.0 * vol, rel=1e-12)
    f = tmp_path / "cube.stl"
    trimesh.creation.box(extents=(0.2, 0.4, 0.6)).export(f)
    assert load_morph(morphs.Mesh(file=str(f)), materials.Rigid(), "m").links[0].mass == pytest.approx(600.0 * vol)
    # an explicit density is the density, robot or not
    assert load_urdf(morphs.URDF(file=str(arm)), materials.Rigid(rho=300.0), "arm").links[1].mass == \
        pytest.approx(300.0 * vol, rel=1e-12)
    with pytest.raises(ValueError, match="rho"):
        materials.Rigid(rho=-1.0)


def test_collision_shapes_and_mesh_paths(tmp_path):
    pkg = tmp_path / "ws" / "my_pkg"
    (pkg / "meshes").mkdir(parents=True)
    (pkg / "urdf").mkdir()
    trimesh.creation.box(extents=(1, 2, 3)).export(pkg / "meshes" / "box.stl")
    trimesh.creation.icosphere(subdivisions=1, radius=0.5).export(pkg / "meshes" / "ball.obj")
    col = lambda g, o="": f'<collision>{o}<geometry>{g}</geometry></collision>'  # noqa: E731
    abs_ball = pkg / "meshes" / "ball.obj"
    geoms = "".join([
        col('<box size="0.2 0.4 0.6"/>', '<origin xyz="1 2 3" rpy="0 0 0"/>'),
        col('<sphere radius="0.3"/>'),
        col('<cylinder radius="0.1" length="0.8"/>'),
        col('<capsule radius="0.05" length="0.4"/>'),
        col('<mesh filename="package://my_pkg/meshes/box.stl" scale="2 1 1"/>'),
        col('<mesh filename="../meshes/ball.obj"/>'),
        col(f'<mesh filename="file://{abs_ball}"/>'),
    ])
    body = link("base", extra=geoms + '<visual><geometry><mesh filename="nowhere/visual.dae"/></geometry></visual>')
    p = pkg / "urdf" / "r.urdf"
    p.write_text(f'<robot name="r">{body}</robot>')
    m = urdf(p)
    gs_ = m.links[0].geoms
    assert [g.type for g in gs_] == ["box", "sphere", "cylinder", "capsule", "mesh", "mesh", "mesh"]
    assert gs_[0].size == pytest.approx((0.1, 0.2, 0.3)) and np.allclose(gs_[0].pos, [1, 2, 3])
    assert gs_[2].size == pytest.approx((0.1, 0.4)) and gs_[3].size == pytest.approx((0.05, 0.2))
    np.testing.assert_allclose(np.ptp(gs_[4].vertices, axis=0), [2, 2, 3], atol=1e-9)
    assert len(gs_[5].vertices) == len(gs_[6].vertices) > 0


def test_joint_properties(tmp_path):
    body = "\n".join([
        link("base"), link("a"), link("b"),
        joint("j1", "base", "a", extra='<dynamics damping="0.5" friction="0.25"/>'),
        '<joint name="j2" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 3 4"/>'
        '<limit lower="-0.5" upper="0.7" effort="3" velocity="4"/><mimic joint="j1" multiplier="-2" offset="0.1"/></joint>',
    ])
    m = urdf(write(tmp_path, body))
    a, b = m.links[1], m.links[2]
    assert (a.damping, a.frictionloss, a.armature) == (0.5, 0.25, 0.0)
    assert (a.limit, a.effort, a.velocity) == ((-1.0, 1.0), 10.0, 2.0)
    np.testing.assert_allclose(b.joint_axis, [0, 0.6, 0.8])
    assert (b.mimic.joint, b.mimic.multiplier, b.mimic.offset) == ("j1", -2.0, 0.1)


def test_merge_fixed_links_false_keeps_welded_links(tmp_path):
    p = write(tmp_path, "\n".join([link("base"), link("a"), joint("weld", "base", "a", type="fixed")]))
    m = urdf(p, merge_fixed_links=False)
    assert [(l.name, l.joint_name, l.joint_type, l.parent) for l in m.links] == [
        ("base", m.links[0].joint_name, "free", -1), ("a", "weld", "fixed", 0)]
    with pytest.raises(ValueError, match="links_to_keep names \\['nope'\\]"):
        urdf(p, links_to_keep=["nope"])


# --------------------------------------------------------------------------------------------
# (3) primitives against closed forms
# --------------------------------------------------------------------------------------------
def test_box():
    m = load_morph(morphs.Box(size=(0.2, 0.4, 0.6), pos=(1, 2, 3)), RIGID, "box")
    (l,) = m.links
    mass = 1000 * 0.2 * 0.4 * 0.6
    assert l.name == "box" and l.joint_type == "free" and np.allclose(l.joint_pos, [1, 2, 3])
    assert l.mass == pytest.approx(mass)
    np.testing.assert_allclose(l.inertia, mass / 12 * np.diag([0.16 + 0.36, 0.04 + 0.36, 0.04 + 0.16]), atol=1e-14)
    assert l.geoms[0].type == "box" and l.geoms[0].size == pytest.approx((0.1, 0.2, 0.3))


def test_sphere_cylinder():
    m = load_morph(morphs.Sphere(radius=0.3, fixed=True), RIGID, "s").links[0]
    mass = 1000 * 4 / 3 * np.pi * 0.027
    assert m.joint_type == "fixed" and m.mass == pytest.approx(mass)
    np.testing.assert_allclose(m.inertia, 0.4 * mass * 0.09 * np.eye(3), atol=1e-14)
    c = load_morph(morphs.Cylinder(radius=0.1, height=0.5), RIGID, "c").links[0]
    mass = 1000 * np.pi * 0.01 * 0.5
    assert c.mass == pytest.approx(mass)
    ixx = mass * (3 * 0.01 + 0.25) / 12
    np.testing.assert_allclose(c.inertia, np.diag([ixx, ixx, mass * 0.01 / 2]), atol=1e-14)
    assert c.geoms[0].size == pytest.approx((0.1, 0.25))


def test_capsule_against_fine_mesh():
    r, h = 0.1, 0.5
    c = load_morph(morphs.Capsule(radius=r, height=h), RIGID, "cap").links[0]
    assert c.mass == pytest.approx(1000 * (np.pi * r * r * h + 4 / 3 * np.pi * r ** 3))
    assert c.geoms[0].type == "capsule" and c.geoms[0].size == pytest.approx((r, h / 2))
    mesh = trimesh.creation.capsule(height=h, radius=r, count=[128, 128])
    mesh.density = 1000.0
    assert c.mass == pytest.approx(mesh.mass, rel=2e-3)
    np.testing.assert_allclose(c.inertia, mesh.moment_inertia, rtol=3e-3, atol=1e-9)


def test_mesh_morph(tmp_path):
    f = tmp_path / "cube.stl"
    cube = trimesh.creation.box(extents=(1, 1, 1))
    cube.apply_translation((0.5, 0, 0))
    cube.export(f)
    m = load_morph(morphs.Mesh(file=str(f), scale=2.0, fixed=True), RIGID, "cube").links[0]
    assert m.mass == pytest.approx(8000.0)
    np.testing.assert_allclose(m.com, [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(m.inertia, 8000 / 6 * 4 * np.eye(3), atol=1e-9)
    assert m.geoms[0].type == "mesh" and len(m.geoms[0].vertices) == 8


def test_plane():
    n = np.array([0.0, 1.0, 1.0]) / np.sqrt(2)
    p = load_morph(morphs.Plane(pos=(0, 0, -1), normal=n), RIGID, "ground")
    (l,) = p.links
    assert l.joint_type == "fixed" and l.mass == 0.0 and l.geoms[0].type == "plane"
    np.testing.assert_allclose(quat_to_mat(l.joint_quat) @ [0, 0, 1], n, atol=1e-12)
    flipped = load_morph(morphs.Plane(normal=(0, 0, -1)), RIGID, "g").links[0]
    np.testing.assert_allclose(quat_to_mat(flipped.joint_quat) @ [0, 0, 1], [0, 0, -1], atol=1e-12)


def test_load_morph_rejects_unknown_type():
    with pytest.raises(TypeError, match="str"):
        load_morph("box.urdf", RIGID, "x")


# --------------------------------------------------------------------------------------------
# (4) bad input
# --------------------------------------------------------------------------------------------
def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.urdf"):
        morphs.URDF(file=str(tmp_path / "nope.urdf"))
    p = write(tmp_path, link("base"))
    morph = morphs.URDF(file=str(p))
    p.unlink()
    with pytest.raises(FileNotFoundError, match="robot.urdf"):
        load_urdf(morph, RIGID, "r")


def test_malformed_xml(tmp_path):
    p = tmp_path / "bad.urdf"
    p.write_text('<robot name="x"><link name="a"></robot>')
    with pytest.raises(ValueError, match=r"bad\.urdf.*malformed XML"):
        urdf(p)


@pytest.mark.parametrize("case,body,pattern", [
    ("two_parents", [link("a"), link("b"), link("c"), joint("j1", "a", "c"), joint("j2", "b", "c")],
     r"'c' is the child of two joints, 'j1' and 'j2'"),
    ("cycle", [link("a"), link("b"), joint("j1", "a", "b"), joint("j2", "b", "a")], r"no root link.*loop"),
    ("detached_cycle", [link("r"), link("a"), link("b"), link("c"), joint("j0", "r", "a"), joint("j1", "b", "c"),
                        joint("j2", "c", "b")], r"'j1', 'j2'|'j2', 'j1'"),
    ("unknown_type", [link("a"), link("b"), joint("hinge", "a", "b", type="ball")], r"joint 'hinge' has unknown type 'ball'"),
    ("floating_inside", [link("a"), link("b"), link("c"), joint("j1", "a", "b"), joint("free6", "b", "c", type="floating")],
     r"joint 'free6' has type 'floating', which is not supported"),
    ("planar", [link("a"), link("b"), joint("pl", "a", "b", type="planar")], r"joint 'pl' has type 'planar'"),
    ("missing_link", [link("a"), joint("j1", "a", "ghost")], r"joint 'j1' names child link 'ghost'"),
    ("two_roots", [link("a"), link("b")], r"2 root links \('a', 'b'\)"),
    ("empty_geometry", [link("a", extra="<collision><geometry></geometry></collision>")],
     r"link 'a', <collision> number 1.*exactly one"),
    ("no_type", [link("a"), link("b"), '<joint name="j"><parent link="a"/><child link="b"/></joint>'], r"joint 'j' has no 'type'"),
])
def test_bad_structure(tmp_path, case, body, pattern):
    p = write(tmp_path, "\n".join(body), name=f"{case}.urdf")
    with pytest.raises(ValueError, match=pattern) as e:
        urdf(p)
    assert f"{case}.urdf" in str(e.value)


def test_bad_meshes(tmp_path):
    (tmp_path / "junk.stl").write_bytes(b"this is not an stl file at all")
    p = write(tmp_path, link("base", extra='<collision><geometry><mesh filename="junk.stl"/></geometry></collision>'))
    with pytest.raises(ValueError, match=r"robot\.urdf.*link 'base'.*junk\.stl"):
        urdf(p)
    p = write(tmp_path, link("base", extra='<collision><geometry><mesh filename="package://pkg/m/gone.stl"/></geometry></collision>'),
              name="missing_mesh.urdf")
    with pytest.raises(FileNotFoundError, match=r"missing_mesh\.urdf.*link 'base'.*gone\.stl.*tried") as e:
        urdf(p)
    assert os.path.join("pkg", "m", "gone.stl") in str(e.value)


def test_dangling_mimic_warns(tmp_path):
    body = "\n".join([link("a"), link("b"), joint("j1", "a", "b", extra='<mimic joint="nobody"/>')])
    with pytest.warns(UserWarning, match="j1.*nobody"):
        m = urdf(write(tmp_path, body))
    assert m.links[1].mimic is None


def test_default_armature_is_genesis_s(tmp_path):
    """URDF / MJCF(default_armature=a), Genesis's morph option with its default 0.1: every hinge and slide joint
    of a URDF gets armature a, a free or fixed joint none; in an MJCF every <joint> element of the worldbody
    that names no armature gets a, a default class's value overridden (what Genesis 0.4.5 loads from its
    ant.xml: 0.1 where the class says 1), an element's own value is kept, and joints of an included file keep
    theirs. None leaves the files' values. A bad value is refused."""
    from conftest import robot_urdf

    urdf = str(robot_urdf("anymal"))
    arm = load_morph(morphs.URDF(file=urdf))
    assert [l.armature for l in arm.links if l.joint_type in ("revolute", "prismatic")] == [0.1] * 12
    assert all(l.armature == 0.0 for l in arm.links if l.joint_type in ("free", "fixed"))
    assert all(l.armature == 0.0 for l in load_morph(morphs.URDF(file=urdf, default_armature=None)).links)
    # the loaded model is not changed for later loads (the model cache's)
    assert [l.armature for l in load_morph(morphs.URDF(file=urdf, default_armature=0.02)).links
            if l.joint_type == "revolute"] == [0.02] * 12
    assert all(l.armature == 0.0 for l in load_morph(morphs.URDF(file=urdf, default_armature=None)).links)
    (tmp_path / "hand.xml").write_text("""<mujoco><body name="d" pos="0 0 0.3"><joint name="j4" type="hinge"/>
      <geom type="box" size="0.1 0.1 0.1" mass="1"/></body></mujoco>""")
    body = """<body name="a" pos="0 0 1"><freejoint/><geom type="box" size="0.1 0.1 0.1" mass="1"/>
      <body name="b" pos="0 0 0.3"><joint name="j1" type="hinge" armature="0.3"/><geom type="box" size="0.1 0.1 0.1" mass="1"/>
      <body name="c" pos="0 0 0.3"><joint name="j2" type="slide"/><joint name="j3" axis="1 0 0"/>
      <geom type="box" size="0.1 0.1 0.1" mass="1"/>{}</body></body></body>"""
    for include in (False, True):
        xml = tmp_path / f"tree{int(include)}.xml"
        xml.write_text(f"""<mujoco><default><joint armature="0.7"/></default><worldbody>
          {body.format('<include file="hand.xml"/>' if include else '')}</worldbody></mujoco>""")
        got = {l.joint_name: l.armature for l in load_morph(morphs.MJCF(file=str(xml), default_armature=0.05)).links
               if l.joint_type in ("revolute", "prismatic")}
        assert got == {"j1": 0.3, "j2": 0.05, "j3": 0.05, **({"j4": 0.7} if include else {})}
        assert {l.joint_name: l.armature for l in load_morph(morphs.MJCF(file=str(xml))).links
                if l.joint_type in ("revolute", "prismatic")} == {k: (0.1 if v == 0.05 else v) for k, v in got.items()}
        assert {l.joint_name: l.armature for l in load_morph(morphs.MJCF(file=str(xml), default_armature=None)).links
                if l.joint_type in ("revolute", "prismatic")} == {"j1": 0.3, "j2": 0.7, "j3": 0.7,
                                                                  **({"j4": 0.7} if include else {})}
    for bad in (-0.1, float("nan"), "0.1", True):
        with pytest.raises(ValueError, match="default_armature"):
            morphs.URDF(file=urdf, default_armature=bad)
