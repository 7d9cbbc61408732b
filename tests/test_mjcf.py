"""gs.morphs.MJCF against MuJoCo itself, a reference no one here wrote.

The models in assets/mjcf/ (written for these tests) are compiled by MuJoCo; the same file loaded by
genesis_lite must give, at random seeded configurations in float64:
- the joint-space mass matrix of `mujoco.mj_fullM` (armature included on both sides: the reference model
  gets the armature of 0.1 that genesis_lite, as Genesis, adds by default to joints whose element names none);
- MuJoCo's body poses (data.xpos / xquat) and collision geom poses (geom_xpos / geom_xmat). Our link
  frame sits at the joint anchor (jnt_pos) with the body's axes, so a link is compared at
  xpos + xmat @ jnt_pos;
- MuJoCo's gravity-only joint accelerations (data.qacc, zero velocity, damping and friction loss zeroed
  on both sides, contacts off on both).

Convention bridged for the free joint: MuJoCo's qpos is ours ([x, y, z, qw, qx, qy, qz, joints]), its
linear dofs are ours (world velocity of the body origin) but its angular dofs are in the body frame where
ours are in the world: v_ours = T v_mj with T = diag(I, R, I), so M_ours = T M_mj T^T.
"""
from __future__ import annotations

import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

ASSETS = Path(__file__).resolve().parents[1] / "assets" / "mjcf"
GRAVITY = (0.0, 0.0, -9.81)
N_SAMPLES = 3
RTOL_MASS = 1e-10
ATOL_POS = 1e-9  # m
ATOL_ROT = 1e-9
RTOL_ACC = 1e-8


def _gs():
    import genesis_lite as gs

    return gs


def _np(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _t(x):
    import torch

    return torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=torch.float64)


def _rel(a, b) -> float:
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-12))


def _R(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


class Pair:
    """One MJCF file: our scene and entity, MuJoCo's model and data, and the maps between them."""

    def __init__(self, file: str):
        gs = _gs()
        self.path = ASSETS / file
        self.m = mujoco.MjModel.from_xml_path(str(self.path))
        self.m.opt.gravity[:] = GRAVITY
        self.m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        self.m.dof_damping[:] = 0.0
        self.m.dof_frictionloss[:] = 0.0
        # genesis_lite's default, Genesis's: an armature of 0.1 on each of the worldbody's <joint> elements that
        # names none (a default class's value overridden); the reference gets the same, read from the file here
        for e in ET.parse(self.path).getroot().find("worldbody").iter("joint"):
            if "armature" not in e.attrib and e.get("type") != "free":
                j = mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_JOINT, e.get("name"))
                assert j >= 0, f"{file}: name every joint"
                self.m.dof_armature[self.m.jnt_dofadr[j]] = 0.1
        self.d = mujoco.MjData(self.m)
        # contacts off on both sides (the quadruped's feet meet its file's floor at random configurations);
        # semi-implicit Euler, whose step takes the dynamics' own qacc (mj_forward's): the implicit integrators
        # take a free base's gyroscopic moment implicitly (solvers/rigid/bias.py), an O(h) change of the step
        self.scene = gs.Scene(sim_options=gs.options.SimOptions(dt=1e-3, gravity=GRAVITY),
                              rigid_options=gs.options.RigidOptions(enable_collision=False,
                                                                    integrator=gs.integrator.Euler))
        self.robot = self.scene.add_entity(gs.morphs.MJCF(file=str(self.path)))
        self.scene.build()
        zeros = _t(np.zeros(self.robot.n_dofs))
        self.robot.set_dofs_damping(zeros)
        self.robot.set_dofs_frictionloss(zeros)
        self.free = self.m.njnt > 0 and self.m.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE
        self.body = {mujoco.mj_id2name(self.m, mujoco.mjtObj.mjOBJ_BODY, b): b for b in range(self.m.nbody)}

    def sample(self, rng):
        """A random qpos in MuJoCo's (= our) layout: hinge/slide inside their limits (+-pi, +-0.1 m where
        unlimited), a random base pose."""
        q = self.m.qpos0.copy()
        for j in range(self.m.njnt):
            a = self.m.jnt_qposadr[j]
            jt = self.m.jnt_type[j]
            if jt == mujoco.mjtJoint.mjJNT_FREE:
                quat = rng.normal(size=4)
                q[a:a + 7] = np.concatenate([rng.uniform(-1, 1, 3), quat / np.linalg.norm(quat)])
            else:
                lo, hi = self.m.jnt_range[j] if self.m.jnt_limited[j] else (
                    (-np.pi, np.pi) if jt == mujoco.mjtJoint.mjJNT_HINGE else (-0.1, 0.1))
                q[a] = rng.uniform(lo, hi)
        return q

    def set(self, q, v=None):
        """Both sides to qpos q and our dof velocities v (zero when None)."""
        v = np.zeros(self.m.nv) if v is None else v
        self.d.qpos[:] = q
        self.d.qvel[:] = self.T(q).T @ v
        self.d.ctrl[:] = 0.0
        mujoco.mj_forward(self.m, self.d)
        self.robot.set_qpos(_t(q))
        self.robot.set_dofs_velocity(_t(v))

    def T(self, q):
        """v_ours = T v_mj."""
        T = np.eye(self.m.nv)
        if self.free:
            T[3:6, 3:6] = _R(q[3:7])
        return T

    def mass_matrix_ref(self, q):
        M = np.zeros((self.m.nv, self.m.nv))
        if hasattr(self.d, "qM"):  # MuJoCo < 3.4 took the packed matrix itself
            mujoco.mj_fullM(self.m, M, self.d.qM)
        else:
            mujoco.mj_fullM(self.m, self.d, M)
        T = self.T(q)
        return T @ M @ T.T


PAIRS = {}


@pytest.fixture(scope="module")
def pair():
    """Pair objects by file name, built once per module (scene builds dominate this file's time)."""

    def get(file):
        if file not in PAIRS:
            PAIRS[file] = Pair(file)
        return PAIRS[file]

    yield get
    PAIRS.clear()


MODELS = ["skew_arm.xml", "quadruped.xml", "mesh_paddle.xml"]


@pytest.mark.parametrize("file", MODELS)
def test_structure_matches_mujoco(file, pair):
    """Names, dof count and order, total mass: links are MuJoCo's bodies that have a joint or hang from
    the world, joints keep MuJoCo's names and dof addresses."""
    p = pair(file)
    m, robot = p.m, p.robot
    assert robot.n_dofs == m.nv and robot.n_qs == m.nq
    for j in range(m.njnt):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
        joint = robot.get_joint(name)
        assert joint.dofs_idx_local[0] == m.jnt_dofadr[j], name
        assert joint.q_start_local == m.jnt_qposadr[j], name
        b = m.jnt_bodyid[j]
        body = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b)
        last = j == m.body_jntadr[b] + m.body_jntnum[b] - 1  # a body's earlier joints get links of their own
        assert robot.links[joint.link_idx_local].name == (body if last else f"{body}_{name}")
    assert abs(float(_np(robot.get_mass())) - float(m.body_mass.sum())) < 1e-12 * m.body_mass.sum()


@pytest.mark.parametrize("file", MODELS)
def test_mass_matrix_and_poses(file, pair):
    p = pair(file)
    m, d, robot = p.m, p.d, p.robot
    rng = np.random.default_rng(sum(map(ord, file)))
    worst = {"M": 0.0, "pos": 0.0, "rot": 0.0, "geom": 0.0}
    for _ in range(N_SAMPLES):
        q = p.sample(rng)
        p.set(q)
        M, M_ref = _np(robot.get_mass_mat()), p.mass_matrix_ref(q)
        worst["M"] = max(worst["M"], _rel(M, M_ref))

        pos, quat = _np(robot.get_links_pos()), _np(robot.get_links_quat())
        for i, link in enumerate(robot.links):
            if link.name not in p.body:  # the massless link of a body's earlier joint: no MuJoCo body
                assert not robot.model.links[i].geoms and robot.model.links[i].mass == 0.0
                continue
            b = p.body[link.name]
            anchor = np.zeros(3)
            if m.body_jntnum[b] >= 1 and m.jnt_type[m.body_jntadr[b]] != mujoco.mjtJoint.mjJNT_FREE:
                anchor = m.jnt_pos[m.body_jntadr[b] + m.body_jntnum[b] - 1]  # the link sits at the last joint
            R_ref = d.xmat[b].reshape(3, 3)
            worst["pos"] = max(worst["pos"], np.abs(pos[i] - (d.xpos[b] + R_ref @ anchor)).max())
            worst["rot"] = max(worst["rot"], np.abs(_R(quat[i]) - R_ref).max())
            # collision geoms, in MuJoCo's order: every body is a link of its own (jointless ones welded)
            geoms = [g for g in range(m.body_geomadr[b], m.body_geomadr[b] + m.body_geomnum[b])
                     if m.geom_contype[g] or m.geom_conaffinity[g]]
            desc = robot.model.links[i].geoms
            assert len(desc) == len(geoms), f"{file}, link {link.name}: {len(desc)} geoms, MuJoCo {len(geoms)}"
            for gd, g in zip(desc, geoms):
                Rg = _R(quat[i]) @ _R(gd.quat)
                xg = pos[i] + _R(quat[i]) @ gd.pos
                worst["geom"] = max(worst["geom"], np.abs(xg - d.geom_xpos[g]).max(),
                                    np.abs(Rg - d.geom_xmat[g].reshape(3, 3)).max())
    assert worst["M"] < RTOL_MASS, f"{file}: {worst}"
    assert worst["pos"] < ATOL_POS and worst["rot"] < ATOL_ROT and worst["geom"] < ATOL_POS, f"{file}: {worst}"


@pytest.mark.parametrize("file", ["skew_arm.xml", "quadruped.xml"])
def test_forward_dynamics(file, pair):
    """One step under gravity from a random state: our dof accelerations are MuJoCo's qacc (mj_forward).
    A free base's are converted: MuJoCo's linear dofs are ours, and d/dt (R w_body) = R d/dt w_body."""
    p = pair(file)
    rng = np.random.default_rng(11)
    for v_scale in (0.0, 1.0):
        q = p.sample(rng)
        v = rng.normal(0.0, v_scale, p.m.nv)
        p.set(q, v)
        p.scene.step()
        acc_ref = p.T(q) @ p.d.qacc
        v1 = _np(p.robot.get_dofs_velocity())
        for acc in (_np(p.robot.get_dofs_acc()), (v1 - v) / 1e-3):
            assert _rel(acc, acc_ref) < RTOL_ACC, f"{file}: ours {acc}\nMuJoCo {acc_ref}"


def test_joint_parameters_from_compiled_model():
    """Limits, damping, armature, friction loss, efforts and friction come from the compiled model, i.e.
    after default classes (from the <include>d file) and degrees -> radians."""
    from genesis_lite import morphs
    from genesis_lite.loaders import load_mjcf

    gs = _gs()
    model = load_mjcf(morphs.MJCF(file=str(ASSETS / "skew_arm.xml"), default_armature=None), gs.materials.Rigid(), "arm")
    L = {l.name: l for l in model.links}
    # with Genesis's default armature (0.1) the default classes' armature gives way on every joint here
    assert {l.armature for l in load_mjcf(morphs.MJCF(file=str(ASSETS / "skew_arm.xml")), gs.materials.Rigid(),
                                          "arm").links if l.joint_type != "fixed"} == {0.1}
    assert [l.name for l in model.links] == ["base", "link1", "link2", "slider", "mount", "link4", "link5",
                                             "pendulum_drop", "pendulum"]
    # a jointless body is a link of its own, welded to its parent (as Genesis keeps it)
    assert L["mount"].joint_type == "fixed" and L["mount"].parent == 3 and L["link4"].parent == 4
    assert L["base"].joint_type == "fixed" and L["pendulum_drop"].parent == -1 and L["pendulum"].parent == 7
    assert L["pendulum_drop"].joint_type == "prismatic" and L["pendulum_drop"].mass == 0.0
    assert L["link1"].limit == (-2.5, 2.5) and L["link2"].limit == (-1.5, 1.8)
    assert L["pendulum"].limit == (-np.inf, np.inf)
    assert L["slider"].joint_type == "prismatic" and L["slider"].limit == (-0.08, 0.12)
    assert (L["link1"].damping, L["link1"].armature, L["link1"].frictionloss) == pytest.approx((0.3, 0.02, 0.05))
    assert (L["slider"].damping, L["slider"].armature, L["slider"].frictionloss) == pytest.approx((2.0, 0.15, 0.0))
    assert L["link1"].effort == pytest.approx(10.0) and L["slider"].effort == pytest.approx(30.0)
    assert np.isinf(L["link2"].effort)
    assert L["slider"].mass == pytest.approx(800 * 4 / 3 * np.pi * 0.03**3) and L["mount"].mass == pytest.approx(0.2)
    assert all(g.friction == pytest.approx(0.45) for l in model.links for g in l.geoms)
    assert [v.type for v in L["link1"].visuals] == ["sphere"] and [v.type for v in L["mount"].visuals] == ["box"]

    quad = load_mjcf(morphs.MJCF(file=str(ASSETS / "quadruped.xml")), gs.materials.Rigid(), "q")
    assert quad.links[-1].name == "world" and quad.links[-1].geoms[0].type == "plane"
    assert quad.links[0].joint_type == "free" and quad.links[0].joint_name == "root"
    assert quad.links[3].name == "fl_shin" and quad.links[3].limit == pytest.approx((np.radians(-140), np.radians(-20)))
    welded = load_mjcf(morphs.MJCF(file=str(ASSETS / "quadruped.xml"), fixed=True), gs.materials.Rigid(), "q")
    assert welded.links[0].joint_type == "fixed" and welded.n_dofs == 9


FLOOR_AND_BOXES = """<mujoco model="floor_and_boxes">
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="low" pos="0 0 0.3"><freejoint/><geom type="box" size="0.1 0.1 0.1" mass="1"/></body>
    <body name="high" pos="0.03 0 0.7"><freejoint/><geom type="box" size="0.08 0.08 0.08" mass="0.5"/></body>
    <body name="arm" pos="1 0 0.5">
      <joint name="hinge" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" mass="0.3"/>
      <body name="tip" pos="0.3 0 0"><joint type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" mass="0.2"/></body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.mark.slow  # ~43 s of a fresh-cache default suite (2026-12-04), its scene class compiled for it alone; by
# default stay the rule it rests on, a file's free body a tree of its own (test_adjacency_and_trees_are_genesis_s),
# and links of one file landing on its own table (test_self_collision_follows_genesis_s_rules)
def test_bodies_of_one_file_collide_with_each_other_and_its_floor(tmp_path):
    """An MJCF's bodies that are not one kinematic tree collide, as in MuJoCo and in Genesis (whose "self"
    collision is between links of one root): two free boxes dropped on the file's own floor come to rest
    stacked (z = 0.1 and 0.28 m, the half heights, within the contacts' millimetre), and a pinned two-link
    arm of the same file swings down through the floor's level (it is welded to the world above it) without
    the file's floor or its own links stopping it (its links are one tree: self-collision stays off by
    default). Before 2026-11-29 every pair of one entity was skipped: the boxes fell through the floor."""
    gs = _gs()
    path = tmp_path / "floor_and_boxes.xml"
    path.write_text(FLOOR_AND_BOXES)
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.005))
    ent = scene.add_entity(gs.morphs.MJCF(file=str(path)))
    scene.build()
    names = [link.name for link in ent.links]
    low, high, tip = names.index("low"), names.index("high"), names.index("tip")
    for _ in range(300):
        scene.step()
    pos = ent.get_links_pos().detach().numpy()
    np.testing.assert_allclose(pos[low, 2], 0.1, atol=1e-3)
    np.testing.assert_allclose(pos[high, 2], 0.28, atol=1e-3)
    assert abs(pos[high, 0] - 0.03) < 0.01 and abs(pos[low, 0]) < 0.01
    assert pos[tip, 2] < 0.3  # hanging down from the pivot at 0.5 m: 0.5 - 0.3 at full length


GANTRY = """<mujoco model="gantry">
  <worldbody>
    <body name="table">
      <geom type="box" size="0.5 0.5 0.05"/>
      <body name="carriage" pos="0 0 0.6">
        <joint name="x" type="slide" axis="1 0 0"/>
        <geom type="sphere" size="0.03" mass="0.5"/>
        <body name="drop" pos="0 0 -0.3">
          <joint name="z" type="slide" axis="0 0 1"/>
          <geom type="box" size="0.05 0.05 0.05" pos="0 0 {box_z}" mass="0.2"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("box_z", [0.0, -0.21])
def test_self_collision_follows_genesis_s_rules(tmp_path, box_z):
    """A box on a vertical slide hangs from a carriage on a horizontal slide over a table, all one tree:
    the box and the table are not adjacent (the carriage's joint is between them), the carriage and the
    table are. Off by default, the box falls through the table; with enable_self_collision it lands on the
    table top (z = 0.05 + 0.05 m within the contacts' millimetre). Started 1 cm into the table (box_z = -0.21: its
    centre at 0.09 m), the pair overlaps with every joint at zero and Genesis's filter leaves it
    out (the box falls through), unless enable_neutral_collision keeps it (the table pushes the box up out of
    it to rest on the top)."""
    gs = _gs()
    path = tmp_path / "gantry.xml"
    path.write_text(GANTRY.format(box_z=box_z))

    def final_box_z(**rigid):
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.005), rigid_options=gs.options.RigidOptions(**rigid))
        ent = scene.add_entity(gs.morphs.MJCF(file=str(path), default_armature=None))
        scene.build()
        ent.set_dofs_damping(np.zeros(2))
        for _ in range(200):
            scene.step()
        drop = [link.name for link in ent.links].index("drop")
        return float(ent.get_links_pos()[drop, 2]) + box_z  # the box's centre (the geom sits at box_z)

    assert final_box_z() < -1.0
    if box_z == 0.0:
        np.testing.assert_allclose(final_box_z(enable_self_collision=True), 0.1, atol=1e-3)
    else:
        assert final_box_z(enable_self_collision=True) < -1.0
        np.testing.assert_allclose(final_box_z(enable_self_collision=True, enable_neutral_collision=True), 0.1,
                                   atol=1e-3)


WELDED_CHAIN = """<mujoco model="welded_chain">
  <worldbody>
    <body name="a" pos="0 0 1"><joint name="ja" type="hinge"/><geom type="sphere" size="0.05"/>
      <body name="b" pos="0.2 0 0"><joint name="jb" type="hinge"/><geom type="sphere" size="0.05"/>
        <body name="c" pos="0.2 0 0"><geom type="sphere" size="0.05"/>
          <body name="d" pos="0.2 0 0"><joint name="jd" type="hinge"/><geom type="sphere" size="0.05"/></body>
        </body>
      </body>
    </body>
    <body name="e" pos="1 0 1"><freejoint/><geom type="sphere" size="0.05"/></body>
  </worldbody>
</mujoco>
"""


def test_adjacency_and_trees_are_genesis_s(tmp_path):
    """Genesis's adjacency (collider.py, v0.4.5): a link is adjacent to its parent and, through links welded by
    fixed joints, to their parents; a jointed child of a welded link is not adjacent to the welded link's
    parent. c is welded to b (a jointless body, kept as a link): (b, c) and (a, c) adjacent, (b, d) not, (c, d)
    adjacent, (a, b) adjacent. e, a free body of the same file, is a tree of its own."""
    from genesis_lite import morphs
    from genesis_lite.loaders import load_mjcf
    from solvers.rigid.collision.geoms import link_roots, links_adjacent
    from solvers.rigid.flatten import FlatModel

    gs = _gs()
    path = tmp_path / "welded_chain.xml"
    path.write_text(WELDED_CHAIN)
    model = load_mjcf(morphs.MJCF(file=str(path)), gs.materials.Rigid(), "w")
    flat = FlatModel([model], use_mimic=True)
    i = {link.name: k for k, link in enumerate(model.links)}
    assert model.links[i["c"]].joint_type == "fixed"
    adjacent = {(x, y): links_adjacent(flat, i[x], i[y]) for x in "abcd" for y in "abcd" if x < y}
    assert adjacent == {("a", "b"): True, ("a", "c"): True, ("a", "d"): False, ("b", "c"): True,
                        ("b", "d"): False, ("c", "d"): True}
    roots = link_roots(flat)
    assert len({roots[i[x]] for x in "abcd"}) == 1 and roots[i["e"]] != roots[i["a"]]


def test_mesh_geom_lands_where_mujoco_puts_it():
    """The collision mesh is MuJoCo's compiled (recentred, rotated, scaled) vertex set; the visual keeps
    the OBJ file and a pose that puts the file's vertices (times the mesh scale) at the same place."""
    import trimesh

    from genesis_lite import morphs
    from genesis_lite.loaders import load_mjcf

    gs = _gs()
    path = ASSETS / "mesh_paddle.xml"
    m = mujoco.MjModel.from_xml_path(str(path))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    paddle = load_mjcf(morphs.MJCF(file=str(path)), gs.materials.Rigid(), "p").links[1]
    g, v = paddle.geoms[0], paddle.visuals[0]
    assert g.type == "mesh" and v.type == "mesh" and Path(v.file) == ASSETS / "wedge.obj"
    gid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "wedge_col")
    V_ref = np.asarray(m.mesh_vert, dtype=float)  # one mesh
    assert np.array_equal(g.vertices, V_ref)
    # at q = 0 the link frame is the paddle body frame moved to the anchor
    b = m.geom_bodyid[gid]
    T_link = np.eye(4)
    T_link[:3, :3] = d.xmat[b].reshape(3, 3)
    T_link[:3, 3] = d.xpos[b] + T_link[:3, :3] @ m.jnt_pos[0]
    world_ref = V_ref @ d.geom_xmat[gid].reshape(3, 3).T + d.geom_xpos[gid]
    world_col = (g.vertices @ _R(g.quat).T + g.pos) @ T_link[:3, :3].T + T_link[:3, 3]
    file_V = np.asarray(trimesh.load(v.file, force="mesh", process=False).vertices) * v.scale
    world_vis = (file_V @ _R(v.quat).T + v.pos) @ T_link[:3, :3].T + T_link[:3, 3]
    assert np.abs(world_col - world_ref).max() < 1e-12
    # mesh_vert is float32 in MuJoCo: the file's vertices match it to single precision
    assert np.abs(np.sort(world_vis, 0) - np.sort(world_ref, 0)).max() < 1e-6


def test_scale_and_placement():
    """morph.scale multiplies lengths by s, masses by s^3 and inertias by s^5; pos/quat move the whole
    model, worldbody included."""
    from genesis_lite import morphs
    from genesis_lite.loaders import load_mjcf

    gs = _gs()
    f = str(ASSETS / "skew_arm.xml")
    a = load_mjcf(morphs.MJCF(file=f), gs.materials.Rigid(), "a")
    b = load_mjcf(morphs.MJCF(file=f, scale=2.0, pos=(1, 2, 3), euler=(0, 0, 90)), gs.materials.Rigid(), "b")
    for la, lb in zip(a.links, b.links):
        assert lb.mass == pytest.approx(8 * la.mass) and np.allclose(lb.inertia, 32 * la.inertia, atol=1e-15)
        assert np.allclose(lb.com, 2 * la.com)
        if la.parent >= 0:
            assert np.allclose(lb.joint_pos, 2 * la.joint_pos)
    assert b.links[3].limit == pytest.approx((-0.16, 0.24))
    Rz = _R([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    assert np.allclose(b.links[0].joint_pos, [1, 2, 3] + Rz @ (2 * a.links[0].joint_pos))


def _write(tmp_path, body, name="m.xml"):
    p = tmp_path / name
    p.write_text(f"<mujoco><worldbody>{body}</worldbody></mujoco>")
    return str(p)


def test_errors(tmp_path, monkeypatch):
    gs = _gs()
    bad = tmp_path / "bad.xml"
    bad.write_text("<mujoco><worldbody><body><geom size='0.1'/></body></worldbod></mujoco>")
    with pytest.raises(ValueError, match=r"MJCF '.*bad\.xml': MuJoCo could not compile it"):
        _load(str(bad))
    ball = _write(tmp_path, "<body name='b'><freejoint/><geom size='.1'/><body name='arm'>"
                            "<joint name='shoulder' type='ball'/><geom size='.1'/></body></body>")
    with pytest.raises(ValueError, match=r"body 'arm', joint 'shoulder' is a ball joint"):
        _load(ball)
    two = _write(tmp_path, "<body name='b'><joint name='a' type='slide'/><joint name='c' type='ball'/>"
                           "<geom size='.1'/></body>")
    with pytest.raises(ValueError, match=r"body 'b', joint 'c' is a ball joint"):
        _load(two)
    ref = _write(tmp_path, "<body name='b'><joint name='a' ref='30'/><geom size='.1'/></body>")
    with pytest.raises(ValueError, match=r"joint 'a' has ref="):
        _load(ref)
    monkeypatch.setitem(sys.modules, "mujoco", None)
    with pytest.raises(ImportError, match="pip install mujoco"):
        _load(ball)


def _load(path, **kw):
    from genesis_lite import morphs
    from genesis_lite.loaders import load_mjcf

    return load_mjcf(morphs.MJCF(file=path, **kw), _gs().materials.Rigid(), "e")


def test_joint_equality_becomes_mimic(tmp_path):
    f = _write(tmp_path, "<body name='b'><joint name='lead' type='slide'/><geom size='.1'/>"
                         "<body name='c'><joint name='follow' type='slide'/><geom size='.1'/></body></body>")
    p = Path(f)
    p.write_text(p.read_text().replace("</mujoco>", "<equality><joint joint1='follow' joint2='lead' "
                                                    "polycoef='0.01 -1 0 0 0'/></equality></mujoco>"))
    c = _load(f).links[1]
    assert c.mimic.joint == "lead" and c.mimic.multiplier == -1.0 and c.mimic.offset == pytest.approx(0.01)


# --- the same robot from URDF and from MJCF -------------------------------------------------------------


def _mjcf_twin(urdf: Path, out: Path):
    """An MJCF of the URDF written by MuJoCo's own URDF importer (mj_saveLastXML), geometry stripped from
    both (MuJoCo cannot find package:// meshes; masses come from <inertial>). fusestatic="false" keeps the
    root and fixed-joint bodies as bodies, as the URDF's links."""
    import xml.etree.ElementTree as ET

    tree = ET.parse(urdf)
    root = tree.getroot()
    for link in root.findall("link"):
        for tag in ("collision", "visual"):
            for e in link.findall(tag):
                link.remove(e)
    ET.SubElement(ET.SubElement(root, "mujoco"), "compiler", fusestatic="false")
    stripped = out / urdf.name
    tree.write(stripped)
    xml = out / (urdf.stem + ".xml")
    mujoco.mj_saveLastXML(str(xml), mujoco.MjModel.from_xml_path(str(stripped)))
    return stripped, xml


@pytest.mark.parametrize("name", ["panda", "go2"])
def test_urdf_and_mjcf_twins_agree(name, urdf_path, tmp_path):
    """example-robot-data's panda (fixed base, mimic fingers) and go2 (floating base, with fixed=False on
    the MJCF) give the same links, mass matrix and link poses from our URDF loader and our MJCF loader.
    MuJoCo writes the MJCF with 6 significant digits (quaternions like 0.707107), hence the tolerances."""
    gs = _gs()
    u, x = _mjcf_twin(urdf_path(name), tmp_path)
    floating = name == "go2"
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=1e-3))
    # both keep the fixed-joint links (MJCF's jointless bodies are links, as in Genesis)
    a = scene.add_entity(gs.morphs.URDF(file=str(u), fixed=not floating, merge_fixed_links=False))
    b = scene.add_entity(gs.morphs.MJCF(file=str(x), fixed=not floating))
    scene.build()
    # the same links (the loaders order siblings differently: ours by joint name, MuJoCo's importer by file order)
    assert sorted(l.name for l in a.links) == sorted(l.name for l in b.links)
    by_name = [b.get_link(l.name).idx_local for l in a.links]  # b's index of each of a's links
    assert abs(float(_np(a.get_mass())) - float(_np(b.get_mass()))) < 1e-4
    ja = {j.name: j.dof_start_local for j in a.joints if j.n_dofs == 1}
    jb = {j.name: j.dof_start_local for j in b.joints if j.n_dofs == 1}
    assert ja.keys() == jb.keys() and a.n_dofs == b.n_dofs
    perm = np.arange(a.n_dofs)  # perm[dof of b] = dof of a
    for n in ja:
        perm[jb[n]] = ja[n]
    if name == "panda":
        follower = next(l.name for l in a.model.links if l.mimic is not None)
        ma, mb = a.model.links[a.get_link(follower).idx_local].mimic, b.model.links[b.get_link(follower).idx_local].mimic
        assert (ma.joint, ma.multiplier, ma.offset) == (mb.joint, mb.multiplier, mb.offset)
    rng = np.random.default_rng(3)
    worst = {"M": 0.0, "pos": 0.0, "rot": 0.0}
    for _ in range(2):
        qa = rng.uniform(-1.0, 1.0, a.n_dofs)
        if floating:
            quat = rng.normal(size=4)
            base = np.concatenate([rng.uniform(-1, 1, 3), quat / np.linalg.norm(quat)])
            a.set_qpos(_t(np.concatenate([base, qa[6:]])))
            b.set_qpos(_t(np.concatenate([base, qa[perm][6:]])))
        else:
            a.set_dofs_position(_t(qa))
            b.set_dofs_position(_t(qa[perm]))
        Ma, Mb = _np(a.get_mass_mat()), _np(b.get_mass_mat())
        worst["M"] = max(worst["M"], _rel(Mb, Ma[np.ix_(perm, perm)]))
        worst["pos"] = max(worst["pos"], np.abs(_np(a.get_links_pos()) - _np(b.get_links_pos())[by_name]).max())
        Ra = [_R(q) for q in _np(a.get_links_quat())]
        Rb = [_R(q) for q in _np(b.get_links_quat())[by_name]]
        worst["rot"] = max(worst["rot"], max(np.abs(r1 - r2).max() for r1, r2 in zip(Ra, Rb)))
    assert worst["M"] < 1e-5 and worst["pos"] < 1e-5 and worst["rot"] < 1e-5, worst


def test_ellipsoid_collides_as_polytope_and_warns(tmp_path):
    f = _write(tmp_path, "<body name='egg'><freejoint/><geom type='ellipsoid' size='0.1 0.05 0.03' pos='0.2 0 0'/>"
                         "</body>")
    with pytest.warns(UserWarning, match="ellipsoids"):
        g = _load(f).links[0].geoms[0]
    assert g.type == "mesh" and np.allclose(g.pos, [0.2, 0, 0])
    assert np.allclose(np.abs(g.vertices).max(0), [0.1, 0.05, 0.03])
    assert np.all(((g.vertices / [0.1, 0.05, 0.03]) ** 2).sum(1) < 1 + 1e-9)


def test_position_actuators_give_the_pd_gains(tmp_path):
    """Genesis reads an MJCF's position actuators as the joints' PD gains and leaves unactuated joints at 0.
    Reference: MuJoCo's own actuator force, whose slopes in q and qdot are the joint-space kp and kv
    (gear included): kp = -d qfrc_actuator / dq, kv = -d qfrc_actuator / dqdot."""
    xml = tmp_path / "act.xml"
    xml.write_text("""<mujoco><worldbody><body name="a"><joint name="h1" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
      <body name="b" pos="0.3 0 0"><joint name="h2" type="hinge" axis="0 0 1"/>
        <geom type="sphere" size="0.05"/>
        <body name="c" pos="0.1 0 0"><joint name="s3" type="slide" axis="1 0 0"/><geom type="box" size="0.02 0.02 0.02"/>
        </body></body></body></worldbody>
      <actuator><position joint="h1" kp="300" kv="20" gear="2"/><motor joint="h2"/>
        <general joint="s3" gainprm="50" biastype="affine" biasprm="0 -50 -4"/></actuator></mujoco>""")
    gs = _gs()
    m = mujoco.MjModel.from_xml_path(str(xml))
    d = mujoco.MjData(m)

    def qfrc(q, v):
        d.qpos[:], d.qvel[:], d.ctrl[:] = q, v, 0.0
        mujoco.mj_forward(m, d)
        return d.qfrc_actuator.copy()

    z = np.zeros(m.nv)
    kp_ref = np.array([-(qfrc(np.eye(m.nq)[i], z) - qfrc(z, z))[i] for i in range(m.nv)])
    kv_ref = np.array([-(qfrc(z, np.eye(m.nv)[i]) - qfrc(z, z))[i] for i in range(m.nv)])
    np.testing.assert_allclose(kp_ref, [1200.0, 0.0, 50.0])  # the reference itself: gear^2 kp, motor 0
    scene = gs.Scene()
    robot = scene.add_entity(gs.morphs.MJCF(file=str(xml)))
    scene.build()
    np.testing.assert_allclose(robot.get_dofs_kp().numpy(), kp_ref, rtol=1e-12)
    np.testing.assert_allclose(robot.get_dofs_kv().numpy(), kv_ref, rtol=1e-12)
