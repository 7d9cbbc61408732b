"""The user-facing API of genesis_lite and its answers to bad input (issue #2).

What is checked, against references no one here wrote where there is one:
- gs.init / gs.device / tensor creation ops, option validation;
- the Genesis entity API (structure, getters, setters, controls, parameters) on example-robot-data's
  Panda (fixed base), assets/urdf/arm.urdf, and free Box / Sphere bodies; link poses and velocities
  against Pinocchio, energies and the mass matrix against Pinocchio, free fall against the exact
  discrete semi-implicit Euler solution, torque-free spin against the analytic rotation;
- batched scenes (n_envs=4) against the same runs unbatched, reset / get_state round trips,
  determinism, bounded memory without gradients and no solver beyond the rigid one;
- every kind of bad input raises at once with a message that names the thing that is wrong.

Scenes are module-scoped where tests can share them (a scene costs a kernel compile); a test that
changes a parameter of a shared scene puts it back in a `finally`.
"""
from __future__ import annotations

import gc
import math
import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import torch

import genesis_lite as gs
from genesis_lite.errors import GenesisException

ASSETS = Path(__file__).resolve().parents[1] / "assets" / "urdf"
ARM = ASSETS / "arm.urdf"
G = 9.81
DT = 0.01

# Panda: gains of Genesis's Panda example, and a target inside every joint limit
PANDA_KP = [4500.0, 4500.0, 3500.0, 3500.0, 2000.0, 2000.0, 2000.0, 100.0, 100.0]
PANDA_KV = [450.0, 450.0, 350.0, 350.0, 200.0, 200.0, 200.0, 10.0, 10.0]
PANDA_TARGET = [0.3, -0.5, 0.2, -2.0, 0.1, 1.5, 0.5, 0.02, 0.02]


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def make_scene(*morphs, n_envs=0, dt=DT, integrator=None, gravity=(0.0, 0.0, -G), joint_limits=True,
               requires_grad=False, names=None, build=True):
    """A scene holding `morphs` (collisions off: contacts are not what is tested here), with the default
    integrator unless one is given."""
    scene = gs.Scene(
        sim_options=gs.options.SimOptions(dt=dt, gravity=gravity, requires_grad=requires_grad),
        rigid_options=gs.options.RigidOptions(**({} if integrator is None else {"integrator": integrator}),
                                              enable_collision=False, enable_joint_limit=joint_limits),
    )
    ents = [scene.add_entity(m, name=None if names is None else names[i]) for i, m in enumerate(morphs)]
    if build:
        scene.build(n_envs=n_envs)
    return (scene, *ents)


def _quat_R(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _quat_mul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def _rotvec_quat(r):
    a = np.linalg.norm(r)
    if a < 1e-300:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.concatenate([[np.cos(a / 2)], np.sin(a / 2) * np.asarray(r) / a])


def _same_rotation(q1, q2, atol):
    return np.allclose(_quat_R(q1), _quat_R(q2), rtol=0, atol=atol)


def _resident_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096


class PandaPin:
    """Pinocchio's model of the Panda URDF and the map of our dofs to its q/v indices (by name)."""

    def __init__(self, path, robot):
        self.model = pin.buildModelFromUrdf(str(path))
        self.model.gravity = pin.Motion(np.array([0.0, 0.0, -G]), np.zeros(3))
        self.data = self.model.createData()
        self.jid = {}
        for j in robot.joints:
            if j.n_dofs == 1:
                assert self.model.existJointName(j.name), j.name
                self.jid[j.name] = self.model.getJointId(j.name)
        self.robot = robot

    def q_v(self, q_ours, v_ours):
        q = np.zeros(self.model.nq)
        v = np.zeros(self.model.nv)
        for j in self.robot.joints:
            if j.n_dofs == 1:
                k = self.jid[j.name]
                assert self.model.nqs[k] == 1
                q[self.model.idx_qs[k]] = q_ours[j.dof_idx_local]
                v[self.model.idx_vs[k]] = v_ours[j.dof_idx_local]
        return q, v

    def perm(self):
        """perm[k] = our dof of Pinocchio's velocity index k."""
        p = np.zeros(self.model.nv, dtype=int)
        for j in self.robot.joints:
            if j.n_dofs == 1:
                p[self.model.idx_vs[self.jid[j.name]]] = j.dof_idx_local
        return p


# ----------------------------------------------------------------------------------------------
# shared scenes
# ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def panda_path(urdf_path):
    return urdf_path("panda")


@pytest.fixture(scope="module")
def panda(panda_path):
    scene, robot = make_scene(gs.morphs.URDF(file=str(panda_path), fixed=True), names=["panda"])
    return scene, robot


@pytest.fixture(scope="module")
def arm():
    """arm.urdf, fixed base, implicitfast, unbatched."""
    return make_scene(gs.morphs.URDF(file=str(ARM), fixed=True), names=["arm"])


@pytest.fixture(scope="module")
def arm4():
    """The same scene as `arm`, with 4 environments."""
    return make_scene(gs.morphs.URDF(file=str(ARM), fixed=True), n_envs=4, names=["arm"])


@pytest.fixture(scope="module")
def free():
    """A free box and a free sphere (semi-implicit Euler, no collisions)."""
    return make_scene(gs.morphs.Box(pos=(0.0, 0.0, 1.0), size=(0.1, 0.2, 0.4)),
                      gs.morphs.Sphere(pos=(1.0, 0.0, 2.0), radius=0.1),
                      integrator=gs.integrator.Euler, names=["box", "ball"])


@pytest.fixture
def fresh(request):
    """Reset a shared scene before and after the test that uses it."""
    def _use(scene):
        scene.reset()
        request.addfinalizer(scene.reset)
        return scene
    return _use


# ----------------------------------------------------------------------------------------------
# gs.init, device, tensors, options
# ----------------------------------------------------------------------------------------------
def test_init_again_with_same_arguments_is_a_noop():
    dev = gs.device
    assert gs.init(backend=gs.cpu, precision="64") is None
    assert gs.init(backend=gs.cpu, precision=64) is None  # "64" and 64 are the same request
    assert gs.device == dev and gs.tc_float == torch.float64


@pytest.mark.parametrize("kwargs", [dict(precision="32"), dict(backend=gs.gpu), dict(debug=True)],
                         ids=["precision", "backend", "debug"])
def test_init_again_with_different_arguments_raises(kwargs):
    args = dict(backend=gs.cpu, precision="64")
    args.update(kwargs)
    with pytest.raises(GenesisException, match=r"already") as e:
        gs.init(**args)
    assert "restart" in str(e.value).lower()
    assert gs.tc_float == torch.float64 and gs.device == torch.device("cpu")


def test_device():
    assert isinstance(gs.device, torch.device)
    # no GPU here and conftest initialised on the CPU backend
    assert gs.device.type == "cpu"


@pytest.mark.parametrize("make,shape", [
    (lambda: gs.tensor([1, 2, 3]), (3,)),
    (lambda: gs.tensor(np.eye(2)), (2, 2)),
    (lambda: gs.zeros(2, 3), (2, 3)),
    (lambda: gs.zeros((2, 3)), (2, 3)),
    (lambda: gs.ones(4), (4,)),
    (lambda: gs.rand(5, 2), (5, 2)),
    (lambda: gs.from_torch(torch.ones(3, dtype=torch.float32)), (3,)),
], ids=["tensor", "tensor_np", "zeros", "zeros_tuple", "ones", "rand", "from_torch"])
def test_tensor_creation_dtype_and_device(make, shape):
    t = make()
    assert isinstance(t, torch.Tensor) and isinstance(t, gs.grad.Tensor)
    assert t.dtype == torch.float64 and t.device.type == gs.device.type
    assert tuple(t.shape) == shape
    assert not t.requires_grad


def test_tensor_creation_values_and_grad():
    assert torch.equal(gs.zeros(3), torch.zeros(3, dtype=torch.float64))
    assert torch.equal(gs.ones(2, 2), torch.ones(2, 2, dtype=torch.float64))
    r = gs.rand(1000)
    assert 0.0 <= r.min() and r.max() < 1.0 and 0.4 < r.mean() < 0.6
    assert gs.tensor([1, 2], dtype=torch.int64).dtype == torch.int64
    # tensors created with requires_grad are leaves that receive .grad (what an optimizer updates)
    for x in (gs.zeros(3, requires_grad=True), gs.tensor([1.0, 2.0, 3.0], requires_grad=True),
              gs.rand(3, requires_grad=True), gs.from_torch(torch.ones(3), requires_grad=True)):
        assert x.requires_grad and x.is_leaf
        (x * 3.0).sum().backward()
        assert x.grad is not None and torch.equal(x.grad, torch.full((3,), 3.0, dtype=torch.float64))
    # from_torch keeps the autograd history of its input
    a = torch.ones(3, dtype=torch.float32, requires_grad=True)
    b = gs.from_torch(a * 2.0)
    assert b.dtype == torch.float64 and b.requires_grad
    b.sum().backward()
    assert torch.equal(a.grad, torch.full((3,), 2.0))
    assert not gs.from_torch(torch.ones(2, requires_grad=True), requires_grad=False).requires_grad


@pytest.mark.parametrize("make,pattern", [
    (lambda: gs.options.SimOptions(dt=-0.01), r"SimOptions\.dt=-0\.01.*positive"),
    (lambda: gs.options.SimOptions(dt=0.0), r"SimOptions\.dt=0\.0.*positive"),
    (lambda: gs.options.SimOptions(dt=float("nan")), r"SimOptions\.dt=nan"),
    (lambda: gs.options.SimOptions(dt="0.01"), r"SimOptions\.dt='0\.01'"),
    (lambda: gs.options.SimOptions(substeps=0), r"SimOptions\.substeps=0.*integer >= 1"),
    (lambda: gs.options.SimOptions(substeps=2.5), r"SimOptions\.substeps=2\.5.*integer"),
    (lambda: gs.options.SimOptions(substeps=-3), r"SimOptions\.substeps=-3"),
    (lambda: gs.options.SimOptions(gravity=(0.0, -9.81)), r"SimOptions\.gravity"),
    (lambda: gs.options.RigidOptions(integrator="leapfrog"), r"RigidOptions\.integrator='leapfrog'.*Euler.*RK4"),
    (lambda: gs.options.RigidOptions(integrator=7), r"RigidOptions\.integrator=7.*Euler"),
    (lambda: gs.options.RigidOptions(contact_stiffness=-1.0), r"RigidOptions\.contact_stiffness=-1\.0"),
], ids=["dt_negative", "dt_zero", "dt_nan", "dt_str", "substeps_0", "substeps_float", "substeps_negative",
        "gravity_2d", "integrator_name", "integrator_int", "contact_stiffness"])
def test_options_validation(make, pattern):
    with pytest.raises(ValueError, match=pattern):
        make()


def test_options_accept_valid_values_and_types_are_checked():
    o = gs.options.SimOptions(dt=0.002, substeps=4)
    assert o.substep_dt == pytest.approx(0.0005)
    for i in (gs.integrator.Euler, gs.integrator.implicitfast, gs.integrator.approximate_implicitfast, gs.integrator.RK4):
        assert gs.options.RigidOptions(integrator=i).integrator == i
    with pytest.raises(TypeError, match="SimOptions"):
        gs.Scene(sim_options=gs.options.RigidOptions())
    with pytest.raises(TypeError, match="RigidOptions"):
        gs.Scene(rigid_options=gs.options.SimOptions())


# ----------------------------------------------------------------------------------------------
# entity structure
# ----------------------------------------------------------------------------------------------
def test_panda_structure_matches_pinocchio(panda, panda_path):
    _, robot = panda
    assert (robot.n_dofs, robot.n_qs, robot.n_links) == (9, 9, 10)
    assert len(robot.joints) == len(robot.links) == robot.n_links
    assert robot.joints[0].type == "fixed" and robot.joints[0].dof_idx_local is None
    model = pin.buildModelFromUrdf(str(panda_path))
    for name in [model.names[i] for i in range(1, model.njoints)]:
        j = robot.get_joint(name)
        assert j.name == name
        # same dof numbering as Pinocchio
        assert j.dof_idx_local == model.idx_vs[model.getJointId(name)]
        assert j.dofs_idx_local == [j.dof_idx_local]
    assert robot.get_joint("panda_joint4").dof_idx_local == 3
    assert robot.get_joint("panda_finger_joint2").type == "prismatic"
    for i, link in enumerate(robot.links):
        assert link.idx_local == i and robot.get_link(link.name) is link
        assert link.idx == i  # the panda is the scene's only entity
    assert robot.get_link("panda_link0").idx_local == 0
    assert robot.get_link("panda_link7").idx_local == 7
    assert robot.get_link("panda_leftfinger").parent_idx_local == robot.get_link("panda_link7").idx_local
    with pytest.raises(GenesisException, match=r"no joint 'nope'.*panda_joint1"):
        robot.get_joint("nope")
    # panda_hand hangs from panda_link7 by fixed joints: merged, and the message says so
    with pytest.raises(GenesisException, match=r"no link 'panda_hand'.*merged"):
        robot.get_link("panda_hand")


def test_arm_and_free_body_structure(arm, free):
    _, a = arm
    assert (a.n_dofs, a.n_qs, a.n_links) == (4, 4, 5)
    assert [l.name for l in a.links] == ["base_link", "link1", "link2", "link3", "link4"]  # tool merged
    assert [a.get_joint(n).dof_idx_local for n in ("shoulder_yaw", "shoulder_pitch", "elbow", "wrist_pitch")] == [0, 1, 2, 3]
    assert a.get_link("link4").idx_local == 4
    _, box, ball = free
    for body in (box, ball):
        assert (body.n_dofs, body.n_qs, body.n_links) == (6, 7, 1)
        assert body.joints[0].type == "free"
        assert body.joints[0].dof_idx_local == [0, 1, 2, 3, 4, 5]
    # the second entity's links come after the first's in the scene
    assert box.links[0].idx == 0 and ball.links[0].idx == 1
    # Genesis's default density for objects, 600 kg/m^3
    assert box.get_links_mass().item() == pytest.approx(600.0 * 0.1 * 0.2 * 0.4)
    assert ball.get_links_mass().item() == pytest.approx(600.0 * 4.0 / 3.0 * math.pi * 0.1 ** 3)


# ----------------------------------------------------------------------------------------------
# getters: types, shapes, subsets
# ----------------------------------------------------------------------------------------------
GETTERS = {
    "get_pos": (3,), "get_quat": (4,), "get_vel": (3,), "get_ang": (3,),
    "get_links_pos": ("L", 3), "get_links_quat": ("L", 4), "get_links_vel": ("L", 3), "get_links_ang": ("L", 3),
    "get_qpos": ("Q",), "get_dofs_position": ("D",), "get_dofs_velocity": ("D",), "get_dofs_acc": ("D",),
    "get_dofs_force": ("D",), "get_dofs_control_force": ("D",), "get_mass_mat": ("D", "D"), "get_links_mass": ("L",),
    "get_kinetic_energy": (), "get_potential_energy": (), "get_total_energy": (),
}


def _expected_shape(spec, ent, batch=()):
    sizes = {"L": ent.n_links, "Q": ent.n_qs, "D": ent.n_dofs}
    return tuple(batch) + tuple(sizes.get(s, s) for s in spec)


@pytest.mark.parametrize("which", ["panda", "arm", "box"])
def test_getters_are_float64_torch_on_device(which, panda, arm, free, fresh):
    scene, ent = {"panda": panda, "arm": arm, "box": free[:2]}[which]
    fresh(scene)
    scene.step()
    for name, spec in GETTERS.items():
        out = getattr(ent, name)()
        assert isinstance(out, torch.Tensor), name
        assert out.dtype == torch.float64, f"{name}: {out.dtype}"
        assert out.device.type == gs.device.type, name
        assert tuple(out.shape) == _expected_shape(spec, ent), f"{name}: {tuple(out.shape)}"
        assert torch.isfinite(out).all(), name


def test_getters_with_index_subsets(panda, fresh):
    scene, robot = panda
    fresh(scene)
    rng = np.random.default_rng(1)
    robot.set_dofs_position(rng.uniform(-0.5, 0.5, 9) * np.r_[np.ones(7), 0, 0] + np.r_[np.zeros(7), 0.01, 0.02])
    robot.set_dofs_velocity(rng.normal(size=9))
    dofs = [6, 1, 3]
    for name in ("get_dofs_position", "get_dofs_velocity", "get_dofs_force", "get_dofs_control_force"):
        full = getattr(robot, name)()
        sub = getattr(robot, name)(dofs_idx_local=dofs)
        assert torch.equal(sub, full[dofs]), name
        assert torch.equal(getattr(robot, name)(dofs_idx_local=torch.tensor(dofs)), full[dofs]), name
        assert torch.equal(getattr(robot, name)(dofs_idx_local=np.array(dofs)), full[dofs]), name
    links = [9, 0, 4]
    for name in ("get_links_pos", "get_links_quat", "get_links_vel", "get_links_ang", "get_links_mass"):
        full = getattr(robot, name)()
        assert torch.equal(getattr(robot, name)(links_idx_local=links), full[links]), name
    assert torch.equal(robot.get_qpos(qs_idx_local=[2, 8]), robot.get_qpos()[[2, 8]])
    # the base of a fixed robot is links[0]
    assert torch.equal(robot.get_pos(), robot.get_links_pos()[0])
    assert torch.equal(robot.get_quat(), robot.get_links_quat()[0])


# ----------------------------------------------------------------------------------------------
# setters: round trips, input kinds
# ----------------------------------------------------------------------------------------------
INPUT_KINDS = {
    "torch": lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64)),
    "torch32": lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32)),
    "numpy": lambda a: np.asarray(a, dtype=np.float64),
    "list": lambda a: [float(x) for x in np.asarray(a).reshape(-1)],
}


@pytest.mark.parametrize("kind", list(INPUT_KINDS))
def test_set_qpos_and_dofs_round_trip_on_panda(kind, panda, fresh):
    scene, robot = panda
    fresh(scene)
    conv = INPUT_KINDS[kind]
    tol = 1e-6 if kind == "torch32" else 0.0
    q = np.array([0.1, -0.2, 0.3, -1.5, 0.4, 1.2, -0.6, 0.01, 0.03])
    robot.set_qpos(conv(q))
    assert np.allclose(_np(robot.get_qpos()), q, rtol=0, atol=tol)
    assert np.allclose(_np(robot.get_dofs_position()), q, rtol=0, atol=tol)  # 1-dof joints: same numbers
    v = np.linspace(-1.0, 1.0, 9)
    robot.set_dofs_velocity(conv(v))
    assert np.allclose(_np(robot.get_dofs_velocity()), v, rtol=0, atol=tol)
    # a subset: only those dofs change; setting positions zeroes velocities (Genesis convention)
    robot.set_dofs_position(conv([0.7, -0.7]), dofs_idx_local=[0, 5])
    q2 = q.copy()
    q2[[0, 5]] = [0.7, -0.7]
    assert np.allclose(_np(robot.get_dofs_position()), q2, rtol=0, atol=tol)
    assert np.all(_np(robot.get_dofs_velocity()) == 0.0)
    robot.set_dofs_velocity(conv([0.25]), dofs_idx_local=[4])
    assert _np(robot.get_dofs_velocity())[4] == pytest.approx(0.25, abs=tol)
    assert np.all(np.delete(_np(robot.get_dofs_velocity()), 4) == 0.0)
    robot.set_dofs_position(conv(q), zero_velocity=False)
    assert _np(robot.get_dofs_velocity())[4] == pytest.approx(0.25, abs=tol)


@pytest.mark.parametrize("kind", ["torch", "numpy", "list"])
def test_free_body_pose_round_trip(kind, free, arm, fresh):
    scene, box, ball = free
    fresh(scene)
    conv = INPUT_KINDS[kind]
    pos = np.array([0.3, -0.2, 1.7])
    quat = np.array([0.8, 0.1, -0.3, 0.5])
    quat /= np.linalg.norm(quat)
    box.set_pos(conv(pos))
    box.set_quat(conv(quat))
    assert np.allclose(_np(box.get_pos()), pos, rtol=0, atol=1e-15)
    assert np.allclose(_np(box.get_quat()), quat, rtol=0, atol=1e-15)
    assert np.allclose(_np(box.get_qpos()), np.concatenate([pos, quat]), rtol=0, atol=1e-15)
    # dof positions of a free joint, as Genesis's: xyz and intrinsic x-y-z Euler angles (R = Rx(a) Ry(b) Rz(c),
    # the quaternion qx(a) qy(b) qz(c))
    def euler_quat(e):
        x, y, z = (_rotvec_quat(e[k] * np.eye(3)[k]) for k in range(3))
        return _quat_mul(_quat_mul(x, y), z)

    dp = _np(box.get_dofs_position())
    assert np.allclose(dp[:3], pos, atol=1e-15)
    assert _same_rotation(euler_quat(dp[3:]), quat, 1e-12)
    assert abs(dp[4]) <= np.pi / 2
    e = np.array([0.4, -1.1, 0.7])
    box.set_dofs_position(conv(np.concatenate([pos + 1.0, e])))
    assert np.allclose(_np(box.get_dofs_position()), np.concatenate([pos + 1.0, e]), atol=1e-12)
    assert _same_rotation(_np(box.get_quat()), euler_quat(e), 1e-12)
    vel = np.array([1.0, -2.0, 0.5, 0.3, 0.2, -0.1])
    box.set_dofs_velocity(conv(vel))
    assert np.allclose(_np(box.get_dofs_velocity()), vel, rtol=0, atol=0)
    assert np.allclose(_np(box.get_vel()), vel[:3], atol=1e-14)  # origin = centre of the box
    assert np.allclose(_np(box.get_ang()), vel[3:], atol=1e-14)
    # the other entity is untouched
    assert np.allclose(_np(ball.get_pos()), [1.0, 0.0, 2.0], atol=0)
    assert np.all(_np(ball.get_dofs_velocity()) == 0)
    with pytest.raises(GenesisException, match=r"'arm'.*set_pos.*free base"):
        arm[1].set_pos([0.0, 0.0, 1.0])


# ----------------------------------------------------------------------------------------------
# kinematics, mass matrix and energies against Pinocchio
# ----------------------------------------------------------------------------------------------
def test_links_pose_and_velocity_match_pinocchio(panda, panda_path, fresh):
    """Our links are the moving links after merging fixed joints; a link's frame is its joint's frame,
    so it is compared with Pinocchio's oMi of the joint with the same name (the root with oMf)."""
    scene, robot = panda
    fresh(scene)
    ref = PandaPin(panda_path, robot)
    model, data = ref.model, ref.data
    lo, hi = model.lowerPositionLimit, model.upperPositionLimit
    rng = np.random.default_rng(2024)
    for sample in range(4):
        q = np.zeros(9)
        for j in robot.joints[1:]:
            k = ref.jid[j.name]
            q[j.dof_idx_local] = rng.uniform(lo[model.idx_qs[k]], hi[model.idx_qs[k]])
        v = rng.normal(0.0, 1.5, 9)
        robot.set_dofs_position(q)
        robot.set_dofs_velocity(v)
        qp, vp = ref.q_v(q, v)
        pin.forwardKinematics(model, data, qp, vp)
        pin.updateFramePlacements(model, data)
        pos, quat = _np(robot.get_links_pos()), _np(robot.get_links_quat())
        lvel, lang = _np(robot.get_links_vel()), _np(robot.get_links_ang())
        for i, link in enumerate(robot.links):
            j = robot.joints[i]
            if j.n_dofs == 0:
                M = data.oMf[model.getFrameId(link.name)]
                vel = pin.Motion.Zero()
            else:
                M = data.oMi[ref.jid[j.name]]
                vel = pin.getVelocity(model, data, ref.jid[j.name], pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
            where = f"sample {sample}, link {link.name}"
            assert np.allclose(pos[i], M.translation, rtol=0, atol=1e-10), f"{where}: pos {pos[i]} vs {M.translation}"
            assert abs(np.linalg.norm(quat[i]) - 1) < 1e-12, where
            assert np.allclose(_quat_R(quat[i]), M.rotation, rtol=0, atol=1e-10), f"{where}: orientation"
            assert np.allclose(lvel[i], vel.linear, rtol=0, atol=1e-10), f"{where}: vel {lvel[i]} vs {vel.linear}"
            assert np.allclose(lang[i], vel.angular, rtol=0, atol=1e-10), f"{where}: ang {lang[i]} vs {vel.angular}"


def test_links_velocity_is_the_derivative_of_links_pose(arm, fresh):
    """Central differences of get_links_pos / get_links_quat along the velocity."""
    scene, a = arm
    fresh(scene)
    q = np.array([0.3, 0.7, -1.1, 0.5])
    v = np.array([0.9, -0.4, 1.3, -2.0])
    a.set_dofs_position(q)
    a.set_dofs_velocity(v)
    lvel, lang = _np(a.get_links_vel()), _np(a.get_links_ang())
    h = 1e-6
    a.set_dofs_position(q + h * v)
    pp, qp = _np(a.get_links_pos()), _np(a.get_links_quat())
    a.set_dofs_position(q - h * v)
    pm, qm = _np(a.get_links_pos()), _np(a.get_links_quat())
    assert np.allclose((pp - pm) / (2 * h), lvel, rtol=0, atol=1e-7)
    for i in range(a.n_links):
        dR = (_quat_R(qp[i]) - _quat_R(qm[i])) / (2 * h)
        a.set_dofs_position(q)
        R = _quat_R(_np(a.get_links_quat())[i])
        W = dR @ R.T  # skew(omega)
        w = np.array([W[2, 1], W[0, 2], W[1, 0]])
        assert np.allclose(w, lang[i], rtol=0, atol=1e-7), f"link {i}: {w} vs {lang[i]}"


def test_mass_matrix_masses_and_energies_match_pinocchio(panda, panda_path, fresh):
    scene, robot = panda
    fresh(scene)
    ref = PandaPin(panda_path, robot)
    model, data = ref.model, ref.data
    perm = ref.perm()
    rng = np.random.default_rng(5)
    # link masses: our links are Pinocchio's joint bodies (fixed children merged on both sides)
    masses = _np(robot.get_links_mass())
    for i, link in enumerate(robot.links[1:], start=1):
        assert masses[i] == pytest.approx(model.inertias[ref.jid[robot.joints[i].name]].mass, rel=1e-12), link.name
    assert masses.sum() == pytest.approx(sum(I.mass for I in model.inertias), rel=1e-12)
    assert torch.equal(robot.get_links_mass(links_idx_local=[3]), robot.get_links_mass()[[3]])
    for sample in range(3):
        q = rng.uniform(-1.0, 1.0, 9) * [1, 1, 1, 0.5, 1, 1, 1, 0, 0] + [0, 0, 0, -1.5, 0, 1.5, 0, 0.01, 0.02]
        v = rng.normal(size=9)
        robot.set_dofs_position(q)
        robot.set_dofs_velocity(v)
        qp, vp = ref.q_v(q, v)
        M = _np(robot.get_mass_mat())
        assert np.array_equal(M, M.T), "mass matrix not symmetric"
        assert np.linalg.eigvalsh(M).min() > 0, "mass matrix not positive definite"
        Mp = pin.crba(model, data, qp)
        Mp = np.triu(Mp) + np.triu(Mp, 1).T
        Mo = np.zeros_like(Mp)
        Mo[np.ix_(perm, perm)] = Mp
        arm_ = _np(robot.get_dofs_armature())
        assert np.allclose(M, Mo + np.diag(arm_), rtol=0, atol=1e-10 * np.abs(Mo).max())
        ke = pin.computeKineticEnergy(model, data, qp, vp)
        # Pinocchio's potential leaves out bodies welded to the world (panda_link0): add it
        pe = pin.computePotentialEnergy(model, data, qp)
        pe += model.inertias[0].mass * G * (data.oMi[0].act(model.inertias[0].lever))[2]
        k_ours, p_ours = robot.get_kinetic_energy().item(), robot.get_potential_energy().item()
        # the rotors' kinetic energy (the default armature, 0.1, on every joint) as Genesis counts it
        assert arm_ == pytest.approx([0.1] * 9) and k_ours == pytest.approx(ke + 0.5 * arm_ @ v**2, rel=1e-10)
        assert p_ours == pytest.approx(pe, rel=1e-10, abs=1e-10)
        assert robot.get_total_energy().item() == pytest.approx(k_ours + p_ours, rel=1e-13)
        assert k_ours == pytest.approx(0.5 * v @ M @ v, rel=1e-12)


# ----------------------------------------------------------------------------------------------
# control and parameters
# ----------------------------------------------------------------------------------------------
def test_position_control_reaches_target_with_gravity(panda, fresh):
    scene, robot = panda
    fresh(scene)
    robot.set_dofs_kp(PANDA_KP)
    robot.set_dofs_kv(PANDA_KV)
    assert np.array_equal(_np(robot.get_dofs_kp()), PANDA_KP)
    assert np.array_equal(_np(robot.get_dofs_kv()), PANDA_KV)
    try:
        target = np.array(PANDA_TARGET)
        robot.control_dofs_position(torch.tensor(target))
        err0 = np.abs(_np(robot.get_dofs_position()) - target).max()
        # 4 s: with the default integrator (Genesis's: kv implicit even while saturated) the force-limited
        # wrist (joint 6, 12 N m) swings saturated for ~3 s before it settles (measured: |v6| 0.043 rad/s at
        # 3 s, 2e-4 at 3.5 s; with implicitfast, which drops a saturated actuator's implicit terms, ~1 s)
        for _ in range(399):
            scene.step()
        q_prev, v_prev = _np(robot.get_dofs_position()), _np(robot.get_dofs_velocity())
        scene.step()
        q, v = _np(robot.get_dofs_position()), _np(robot.get_dofs_velocity())
        assert np.abs(q - target).max() < 0.01, f"|q - target| = {np.abs(q - target)} (started at {err0:.2f})"
        moving = {robot.joints[1 + i].name: float(v[i]) for i in np.flatnonzero(np.abs(v) >= 1e-3)}
        assert not moving, f"still moving after 3 s of PD control (rad/s, m/s): {moving}"
        # at rest the PD force holds gravity: kp (target - q) equals the gravity torque
        lo, hi = (_np(x) for x in robot.get_dofs_force_range())
        f = _np(robot.get_dofs_control_force())
        assert np.all(f >= lo) and np.all(f <= hi)
        # the force of the last step, from the state it started in
        assert np.allclose(f, np.array(PANDA_KP) * (target - q_prev) - np.array(PANDA_KV) * v_prev, rtol=1e-12, atol=1e-9)
        # a subset of dofs can be retargeted alone
        robot.control_dofs_position([0.0], dofs_idx_local=[0])
        for _ in range(200):
            scene.step()
        q2 = _np(robot.get_dofs_position())
        assert abs(q2[0]) < 0.01 and np.abs(q2[1:] - target[1:]).max() < 0.01
    finally:
        robot.set_dofs_kp(np.zeros(9))
        robot.set_dofs_kv(np.zeros(9))


SLIDER_LINK = ('<link name="{n}"><inertial><mass value="{m}"/><inertia ixx="1e-3" iyy="1e-3" izz="1e-3" ixy="0" '
               'ixz="0" iyz="0"/></inertial></link>')
SLIDER_JOINT = ('<joint name="{n}" type="prismatic"><parent link="base"/><child link="{c}"/><axis xyz="1 0 0"/>'
                '<limit lower="-10" upper="10" effort="1000" velocity="100"/>{extra}</joint>')


def test_position_control_of_mimic_coupled_joints(tmp_path):
    """The Panda's fingers are coupled by a URDF <mimic>. A coupling must not resist a motion that
    satisfies it: three identical sliders on a fixed base under the same PD target, s2 mimicking s1,
    s3 free, no gravity. All three must follow the exact discrete recursion of the default integrator
    (approximate_implicitfast, Genesis's: kv implicit, kp explicit), (m + a0 + h kv) a = kp (target - q) - kv v
    with the default armature a0 = 0.1 kg, as s3 alone does."""
    body = "\n".join([SLIDER_LINK.format(n="base", m=1.0)] + [SLIDER_LINK.format(n=f"l{i}", m=0.5) for i in (1, 2, 3)] + [
        SLIDER_JOINT.format(n="s1", c="l1", extra=""),
        SLIDER_JOINT.format(n="s2", c="l2", extra='<mimic joint="s1" multiplier="1" offset="0"/>'),
        SLIDER_JOINT.format(n="s3", c="l3", extra="")])
    path = _urdf(tmp_path, body, "sliders.urdf")
    scene, r = make_scene(gs.morphs.URDF(file=str(path), fixed=True), gravity=(0.0, 0.0, 0.0), names=["sliders"])
    assert [j.name for j in r.joints if j.n_dofs] == ["s1", "s2", "s3"]
    kp, kv, m, target = 100.0, 5.0, 0.5, 0.2
    r.set_dofs_kp([kp] * 3)
    r.set_dofs_kv([kv] * 3)
    r.control_dofs_position([target] * 3)
    q = v = 0.0
    for _ in range(100):
        a = (kp * (target - q) - kv * v) / (m + 0.1 + DT * kv)
        v += DT * a
        q += DT * v
        scene.step()
    qs, vs = _np(r.get_dofs_position()), _np(r.get_dofs_velocity())
    assert qs[2] == pytest.approx(q, rel=1e-12) and vs[2] == pytest.approx(v, rel=1e-9, abs=1e-12), "uncoupled slider"
    assert qs[0] == qs[1], "the mimic pair must move together"
    assert np.allclose(qs[:2], q, rtol=1e-9), f"mimic pair at {qs[:2]}, an uncoupled PD slider at {q}: the coupling resists a motion that satisfies it"
    assert np.allclose(vs[:2], v, rtol=1e-9, atol=1e-12), f"mimic pair moves at {vs[:2]}, expected {v}"


def test_velocity_control_tracks_target(arm, fresh):
    scene, a = arm
    fresh(scene)
    scene.set_gravity((0.0, 0.0, 0.0))
    kv = 200.0
    a.set_dofs_kv([kv] * 4)
    lo0, hi0 = (x.clone() for x in a.get_dofs_force_range())
    # kv (target - v) stays below the (raised) effort limits: a saturated actuator is another test
    a.set_dofs_force_range([-500.0] * 4, [500.0] * 4)
    try:
        a.set_dofs_position([0.0, 0.3, -0.6, 0.2])
        target = np.array([0.5, 0.3, -0.3, 0.2])
        a.control_dofs_velocity(target)
        for _ in range(49):
            scene.step()
        v_prev = _np(a.get_dofs_velocity())
        scene.step()
        v = _np(a.get_dofs_velocity())
        damping = _np(a.get_dofs_damping())
        # steady state of kv (target - v) = damping v, up to the Coriolis forces of the moving arm
        assert np.allclose(v, kv * target / (kv + damping), rtol=0, atol=3e-3), v
        f = _np(a.get_dofs_control_force())
        assert np.allclose(f, kv * (target - v_prev), rtol=1e-12, atol=1e-12)
    finally:
        a.set_dofs_force_range(lo0, hi0)
        a.set_dofs_kv([0.0] * 4)
        scene.set_gravity((0.0, 0.0, -G))


def test_force_control_and_force_range_clipping(arm, fresh):
    """From rest without gravity, one implicitfast step gives (M + h D) a = tau exactly."""
    scene, a = arm
    fresh(scene)
    scene.set_gravity((0.0, 0.0, 0.0))
    lo0, hi0 = (x.clone() for x in a.get_dofs_force_range())
    try:
        q = np.array([0.2, 0.6, -0.9, 0.4])
        tau = np.array([3.0, -5.0, 2.0, 0.5])

        def one_step(force):
            a.set_dofs_position(q)
            M = _np(a.get_mass_mat())
            D = np.diag(_np(a.get_dofs_damping()))
            a.control_dofs_force(force)
            scene.step()
            return M, D, _np(a.get_dofs_acc()), _np(a.get_dofs_velocity()), _np(a.get_dofs_control_force())

        M, D, acc, v1, f = one_step(tau)
        expected = np.linalg.solve(M + DT * D, tau)
        assert np.allclose(acc, expected, rtol=1e-10, atol=1e-12), (acc, expected)
        assert np.allclose(v1, DT * expected, rtol=1e-10, atol=1e-14)
        assert np.array_equal(f, tau)

        a.set_dofs_force_range([-1.0] * 4, [1.0] * 4)
        assert np.array_equal(_np(a.get_dofs_force_range()[1]), [1.0] * 4)
        M, D, acc, _, f = one_step(tau)
        clipped = np.clip(tau, -1.0, 1.0)
        assert np.array_equal(f, clipped), f
        assert np.allclose(acc, np.linalg.solve(M + DT * D, clipped), rtol=1e-10, atol=1e-12)
        # position control saturates too
        a.set_dofs_kp([1e4] * 4)
        a.set_dofs_position(q)
        a.control_dofs_position(q + 1.0)
        scene.step()
        assert np.array_equal(_np(a.get_dofs_control_force()), [1.0] * 4)
        with pytest.raises(GenesisException, match="lower > upper"):
            a.set_dofs_force_range([1.0] * 4, [-1.0] * 4)
    finally:
        a.set_dofs_kp([0.0] * 4)
        a.set_dofs_force_range(lo0, hi0)
        scene.set_gravity((0.0, 0.0, -G))


@pytest.mark.parametrize("integrator", [None, "Euler"])
def test_dofs_force_is_genesis_generalised_force(integrator):
    """get_dofs_force has Genesis's meaning (its dofs_state.force): actuator + joint damping - bias of the
    step's starting state, checked against Pinocchio on the skewed arm (offset centres of mass, rotated
    non-diagonal inertia, skewed axes; default options, collision on with nothing to touch): clip(PD) -
    D v - rnea(q, v, 0). With Euler, M(q) qacc equals it; get_dofs_control_force is the actuator part."""
    path = Path(__file__).resolve().parents[1] / "assets" / "urdf" / "skew_arm.urdf"
    rigid = {} if integrator is None else {"rigid_options": gs.options.RigidOptions(integrator=gs.integrator.Euler)}
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT), **rigid)
    arm = scene.add_entity(gs.morphs.URDF(file=str(path), fixed=True))
    scene.build()
    model = pin.buildModelFromUrdf(str(path))
    model.gravity = pin.Motion(np.array([0.0, 0.0, -G]), np.zeros(3))
    data = model.createData()
    assert [model.names[j] for j in range(1, model.njoints)] == [j.name for j in arm.joints if j.n_dofs]
    q, v = np.array([0.4, -0.7, 1.1]), np.array([0.6, -0.9, 1.3])
    kp, kv, target = np.array([30.0, 20.0, 10.0]), np.array([1.0, 0.8, 0.5]), np.array([0.9, 0.2, 0.5])
    damping = _np(arm.get_dofs_damping())
    assert np.all(damping > 0)
    arm.set_dofs_kp(kp)
    arm.set_dofs_kv(kv)
    arm.set_dofs_force_range([-100.0, -100.0, -2.0], [100.0, 100.0, 2.0])  # the third saturates
    arm.set_dofs_position(q)
    arm.set_dofs_velocity(v)
    M = _np(arm.get_mass_mat())
    arm.control_dofs_position(target)
    scene.step()
    tau = np.clip(kp * (target - q) - kv * v, -np.r_[100.0, 100.0, 2.0], np.r_[100.0, 100.0, 2.0])
    assert abs(tau[2]) == 2.0
    bias = pin.rnea(model, data, q, v, np.zeros(3))
    expected = tau - damping * v - bias
    np.testing.assert_allclose(_np(arm.get_dofs_control_force()), tau, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(_np(arm.get_dofs_force()), expected, rtol=1e-9, atol=1e-9)
    if integrator == "Euler":
        np.testing.assert_allclose(M @ _np(arm.get_dofs_acc()), expected, rtol=1e-9, atol=1e-9)


def _run(scene, a, steps, q0=(0.0, 0.9, -0.6, 0.4), v0=(0.0, 0.0, 0.0, 0.0)):
    scene.reset()
    a.set_dofs_position(q0)
    a.set_dofs_velocity(v0)
    e0 = a.get_total_energy().item()
    for _ in range(steps):
        scene.step()
    return e0, a.get_total_energy().item(), _np(a.get_dofs_position()) - np.array(q0)


def test_damping_armature_frictionloss_change_motion_as_expected(arm, fresh):
    scene, a = arm
    fresh(scene)
    base = {k: _np(getattr(a, f"get_dofs_{k}")()) for k in ("damping", "armature")}
    zeros = np.zeros(4)
    try:
        # damping, without gravity from a spin that stays inside the joint limits: the energy is
        # kinetic only, kept without damping (up to the integrator's O(h) error), lost with it
        scene.set_gravity((0.0, 0.0, 0.0))
        spin = dict(q0=(0.0, 0.2, -0.3, 0.1), v0=(1.0, 0.5, -0.5, 0.8))
        a.set_dofs_damping(zeros)
        e0, e_free, _ = _run(scene, a, 100, **spin)
        assert abs(e_free - e0) < 0.02 * e0, (e0, e_free)
        a.set_dofs_damping([0.05] * 4)
        e0d, e_damped, _ = _run(scene, a, 100, **spin)
        assert e0d == e0
        assert e_damped < 0.9 * e_free, f"damping should dissipate energy: {e_damped} vs {e_free}"
        a.set_dofs_damping(base["damping"])
        scene.set_gravity((0.0, 0.0, -G))

        # from rest under gravity (0.2 s, before any joint limit is reached)
        _, _, dq_free = _run(scene, a, 20)
        assert np.linalg.norm(dq_free) > 0.05, dq_free
        a.set_dofs_armature([0.5] * 4)
        assert np.array_equal(_np(a.get_dofs_armature()), [0.5] * 4)
        _, _, dq_arm = _run(scene, a, 20)
        a.set_dofs_armature(zeros)
        # rotor inertia slows the start of the fall
        assert np.linalg.norm(dq_arm) < 0.5 * np.linalg.norm(dq_free), (dq_arm, dq_free)
        a.set_dofs_frictionloss([30.0] * 4)  # more than gravity's torque on any joint here
        _, _, dq_fric = _run(scene, a, 20)
        assert np.linalg.norm(dq_fric) < 0.1 * np.linalg.norm(dq_free), (dq_fric, dq_free)
    finally:
        scene.set_gravity((0.0, 0.0, -G))
        a.set_dofs_damping(base["damping"])
        a.set_dofs_armature(base["armature"])
        a.set_dofs_frictionloss(zeros)


def test_parameter_setters_validate(arm):
    _, a = arm
    with pytest.raises(GenesisException, match=r"'arm'.*damping must be >= 0"):
        a.set_dofs_damping([-1.0, 0.0, 0.0, 0.0])
    with pytest.raises(GenesisException, match=r"'arm'.*kp must be >= 0"):
        a.set_dofs_kp([-5.0] * 4)
    with pytest.raises(GenesisException, match=r"'arm'.*link masses must be >= 0"):
        a.set_links_mass([-1.0], links_idx_local=[2])


# ----------------------------------------------------------------------------------------------
# free bodies: free fall and spin
# ----------------------------------------------------------------------------------------------
def test_free_fall_follows_semi_implicit_euler_exactly(free, fresh):
    scene, box, ball = free
    fresh(scene)
    z0 = box.get_pos()[2].item()
    n = 120
    for _ in range(n):
        scene.step()
    t = n * DT
    # v_n = -g h n,  z_n = z0 - g h^2 n (n + 1) / 2  (velocity first, then position)
    z_exact = z0 - G * DT * DT * n * (n + 1) / 2
    assert box.get_pos()[2].item() == pytest.approx(z_exact, rel=1e-13)
    assert np.allclose(_np(box.get_vel()), [0.0, 0.0, -G * DT * n], rtol=1e-13, atol=1e-13)
    assert np.allclose(_np(box.get_pos())[:2], 0.0, atol=1e-15)
    assert np.array_equal(_np(box.get_quat()), [1.0, 0.0, 0.0, 0.0])
    assert np.allclose(_np(box.get_ang()), 0.0, atol=1e-15)
    # and the continuous solution within the method's first-order error g h t / 2
    assert box.get_pos()[2].item() == pytest.approx(z0 - G * t * t / 2 - G * DT * t / 2, abs=1e-10)
    assert ball.get_pos()[2].item() == pytest.approx(2.0 - G * DT * DT * n * (n + 1) / 2, rel=1e-13)
    assert np.allclose(_np(box.get_dofs_acc()), [0, 0, -G, 0, 0, 0], atol=1e-12)


def test_free_spin_keeps_orientation_on_the_analytic_rotation(free, fresh):
    """Torque-free rotation: a sphere with any spin and a box spinning about a principal axis keep a
    constant angular velocity, so q(t) = exp(w t / 2) q0 exactly; an asymmetric spin keeps the angular
    momentum and the kinetic energy (to the integrator's order) and a unit quaternion."""
    scene, box, ball = free
    fresh(scene)
    scene.set_gravity((0.0, 0.0, 0.0))
    try:
        q0 = np.array([0.9, 0.1, 0.3, -0.2])
        q0 /= np.linalg.norm(q0)
        w_ball = np.array([0.3, -1.2, 2.0])
        ball.set_quat(q0)
        ball.set_dofs_velocity(np.concatenate([[0.5, 0.0, 0.0], w_ball]))
        # box spinning about its own z axis (a principal axis), expressed in the world
        box.set_quat(q0)
        w_box = _quat_R(q0) @ np.array([0.0, 0.0, 3.0])
        box.set_dofs_velocity(np.concatenate([[0.0, 0.0, 0.0], w_box]))
        n = 100
        for _ in range(n):
            scene.step()
        t = n * DT
        for body, w in ((ball, w_ball), (box, w_box)):
            expected = _quat_mul(_rotvec_quat(w * t), q0)
            got = _np(body.get_quat())
            assert abs(np.linalg.norm(got) - 1) < 1e-13
            assert _same_rotation(got, expected, 1e-11), f"{body.name}: {got} vs {expected}"
            assert np.allclose(_np(body.get_ang()), w, rtol=0, atol=1e-11), body.name
        assert np.allclose(_np(ball.get_pos()), [1.0 + 0.5 * t, 0.0, 2.0], atol=1e-12)

        # asymmetric spin of the box: momentum and energy kept
        scene.reset()
        box.set_quat(q0)
        w = np.array([0.2, 2.0, 0.3])
        box.set_dofs_velocity(np.concatenate([[0.0, 0.0, 0.0], w]))
        I_body = _np(box.get_links_inertia())[0]

        def momentum():
            R = _quat_R(_np(box.get_quat()))
            return R @ I_body @ R.T @ _np(box.get_ang())

        L0, K0 = momentum(), box.get_kinetic_energy().item()
        for _ in range(100):
            scene.step()
        assert abs(np.linalg.norm(_np(box.get_quat())) - 1) < 1e-13
        assert np.linalg.norm(momentum() - L0) < 2e-2 * np.linalg.norm(L0)
        assert box.get_kinetic_energy().item() == pytest.approx(K0, rel=2e-2)
        assert not np.allclose(_np(box.get_ang()), w, atol=1e-3)  # gyroscopic terms at work
    finally:
        scene.set_gravity((0.0, 0.0, -G))


# ----------------------------------------------------------------------------------------------
# batched scenes
# ----------------------------------------------------------------------------------------------
def test_batched_getters_have_a_leading_env_axis(arm4, fresh):
    scene, a = arm4
    fresh(scene)
    scene.step()
    for name, spec in GETTERS.items():
        out = getattr(a, name)()
        assert tuple(out.shape) == _expected_shape(spec, a, (4,)), f"{name}: {tuple(out.shape)}"
        assert out.dtype == torch.float64
        sub = getattr(a, name)(envs_idx=[2, 0])
        assert tuple(sub.shape) == _expected_shape(spec, a, (2,)), name
        assert torch.equal(sub, out[[2, 0]]), name
    assert tuple(a.get_dofs_position(dofs_idx_local=[1, 3], envs_idx=[3]).shape) == (1, 2)


def test_batched_setters_touch_only_their_envs(arm4, fresh):
    scene, a = arm4
    fresh(scene)
    q_all = _np(a.get_dofs_position())
    vals = np.array([[0.1, 0.2, 0.3, 0.4], [-0.4, -0.3, -0.2, -0.1]])
    a.set_dofs_position(vals, envs_idx=[1, 3])
    q = _np(a.get_dofs_position())
    assert np.array_equal(q[[1, 3]], vals)
    assert np.array_equal(q[[0, 2]], q_all[[0, 2]])
    # one row given for several envs is broadcast to them
    a.set_dofs_velocity([1.0, 0.0, 0.0, -1.0], envs_idx=[0, 2])
    v = _np(a.get_dofs_velocity())
    assert np.array_equal(v[[0, 2]], [[1.0, 0.0, 0.0, -1.0]] * 2)
    assert np.all(v[[1, 3]] == 0.0)
    d0 = a.get_dofs_damping(envs_idx=[2]).clone()
    a.set_dofs_damping([5.0] * 4, envs_idx=[2])
    try:
        d = _np(a.get_dofs_damping())
        assert np.all(d[2] == 5.0) and np.array_equal(d[[0, 1, 3]], np.tile(_np(d0), (3, 1)))
    finally:
        a.set_dofs_damping(d0, envs_idx=[2])


def test_control_modes_set_by_slice_and_by_index_agree(arm4, fresh):
    """A control call for every env and a run of dofs switches modes by basic slicing; one for envs listed out of
    order, by an index. Position control of all dofs, then force on dofs 0-1 only (2-3 stay under position
    control): both forms give the same trajectory to 1e-12, and it differs from all-position and all-force runs."""
    scene, a = arm4
    fresh(scene)
    q0 = np.array([0.1, 0.5, -0.4, 0.2])
    target = np.tile([0.5, -0.2, 0.3, 0.1], (4, 1))

    def run(envs, force_dofs):
        scene.reset()
        a.set_dofs_position(q0)
        a.control_dofs_position(target, envs_idx=envs)
        for _ in range(10):
            scene.step()
        if force_dofs:
            a.control_dofs_force(np.tile([1.0, -2.0, 0.5, 0.2], (4, 1))[:, :force_dofs], envs_idx=envs,
                                 dofs_idx_local=list(range(force_dofs)))
        for _ in range(20):
            scene.step()
        return _np(a.get_dofs_position())

    try:
        a.set_dofs_kp([300.0, 300.0, 200.0, 50.0])
        a.set_dofs_kv([20.0, 20.0, 10.0, 2.0])
        by_slice, by_index = run(None, 2), run([3, 2, 1, 0], 2)
        assert np.abs(by_slice - by_index).max() <= 1e-12
        assert np.abs(by_slice - by_slice[0]).max() <= 1e-12  # the same controls in every env
        for other in (run(None, 0), run(None, 4)):
            assert np.abs(by_slice - other).max() > 1e-3
    finally:
        a.set_dofs_kp([0.0] * 4)
        a.set_dofs_kv([0.0] * 4)


def test_batched_run_equals_unbatched_runs(arm, arm4, fresh):
    """Different controls per env give different results; env i of the batched run equals the same
    run unbatched to 1e-12. Env 3 runs position control with its own gains."""
    scene4, a4 = arm4
    scene1, a1 = arm
    fresh(scene4)
    fresh(scene1)
    q0 = np.array([0.1, 0.5, -0.4, 0.2])
    taus = np.array([[0.0, 0.0, 0.0, 0.0], [1.0, -2.0, 1.0, 0.5], [-3.0, 4.0, 0.5, -0.2]])
    target = np.array([0.5, -0.2, 0.3, 0.1])
    kp, kv = [300.0, 300.0, 200.0, 50.0], [20.0, 20.0, 10.0, 2.0]
    steps = 60
    try:
        a4.set_dofs_position(q0)
        a4.control_dofs_force(taus, envs_idx=[0, 1, 2])
        a4.set_dofs_kp(kp, envs_idx=[3])
        a4.set_dofs_kv(kv, envs_idx=[3])
        a4.control_dofs_position(target, envs_idx=[3])
        for _ in range(steps):
            scene4.step()
        qb, vb = _np(a4.get_dofs_position()), _np(a4.get_dofs_velocity())
        pb = _np(a4.get_links_pos())
        for i in range(4):
            scene1.reset()
            a1.set_dofs_position(q0)
            if i < 3:
                a1.control_dofs_force(taus[i])
            else:
                a1.set_dofs_kp(kp)
                a1.set_dofs_kv(kv)
                a1.control_dofs_position(target)
            for _ in range(steps):
                scene1.step()
            assert np.allclose(qb[i], _np(a1.get_dofs_position()), rtol=0, atol=1e-12), f"env {i}"
            assert np.allclose(vb[i], _np(a1.get_dofs_velocity()), rtol=0, atol=1e-12), f"env {i}"
            assert np.allclose(pb[i], _np(a1.get_links_pos()), rtol=0, atol=1e-12), f"env {i}"
        for i in range(4):
            for k in range(i):
                assert np.abs(qb[i] - qb[k]).max() > 1e-3, f"envs {k} and {i} did the same thing"
    finally:
        a4.set_dofs_kp([0.0] * 4, envs_idx=[3])
        a4.set_dofs_kv([0.0] * 4, envs_idx=[3])
        a1.set_dofs_kp([0.0] * 4)
        a1.set_dofs_kv([0.0] * 4)


# ----------------------------------------------------------------------------------------------
# reset, state round trips, determinism
# ----------------------------------------------------------------------------------------------
def test_reset_returns_to_post_build_state(arm4):
    scene, a = arm4
    scene.reset()
    q_build, v_build = _np(a.get_qpos()), _np(a.get_dofs_velocity())
    assert np.all(v_build == 0)
    a.set_dofs_position([0.3, 0.3, 0.3, 0.3])
    a.control_dofs_force([1.0, 1.0, 1.0, 1.0])
    for _ in range(20):
        scene.step()
    assert scene.t == 20
    scene.reset()
    assert scene.t == 0
    assert np.array_equal(_np(a.get_qpos()), q_build)
    assert np.array_equal(_np(a.get_dofs_velocity()), v_build)
    # controls are cleared: the arm now falls from the build pose as on the first run
    for _ in range(10):
        scene.step()
    q_after = _np(a.get_qpos())
    scene.reset()
    for _ in range(10):
        scene.step()
    assert np.array_equal(_np(a.get_qpos()), q_after)
    assert np.array_equal(_np(a.get_dofs_control_force()), np.zeros((4, 4)))
    scene.reset()


def test_get_state_reset_round_trip_and_determinism(arm4, fresh):
    scene, a = arm4
    fresh(scene)
    rng = np.random.default_rng(3)
    tau = rng.normal(size=(4, 4))

    def rollout(n):
        a.control_dofs_force(tau)
        for _ in range(n):
            scene.step()
        return _np(a.get_qpos()), _np(a.get_dofs_velocity())

    a.set_dofs_position(rng.uniform(-0.5, 0.5, (4, 4)))
    rollout(15)
    state = scene.get_state()
    q1, v1 = rollout(25)
    scene.reset(state)
    assert np.array_equal(_np(a.get_qpos()), _np(state.qpos))
    assert np.array_equal(_np(a.get_dofs_velocity()), _np(state.qvel))
    q2, v2 = rollout(25)
    assert np.array_equal(q1, q2) and np.array_equal(v1, v2)
    # the state is a snapshot: stepping does not change it
    assert not np.array_equal(_np(state.qpos), q2)
    # the same rollout from the same start twice: bit for bit the same
    scene.reset(state)
    q3, v3 = rollout(25)
    assert np.array_equal(q1, q3) and np.array_equal(v1, v3)
    with pytest.raises(TypeError, match="get_state"):
        scene.reset({"qpos": state.qpos})


# ----------------------------------------------------------------------------------------------
# skip what a scene does not need
# ----------------------------------------------------------------------------------------------
def _placed_fields():
    import taichi as ti

    out = {}
    for o in gc.get_objects():
        if isinstance(o, ti.Field):
            try:
                placed = o._snode.ptr is not None
            except Exception:
                placed = False
            if placed:
                out[id(o)] = o
    return out


def test_no_solver_or_field_beyond_the_rigid_one():
    """No MPM solver: every Taichi field allocated by building and stepping a rigid-only scene
    (without gradients) is one of the rigid solver's own fields; none is an adjoint. (The scene may
    take its core from the pool, built by an earlier test of the same size class: then it allocates
    few fields or none, and the census is checked on the solver's own fields instead.)"""
    gc.collect()
    before = _placed_fields()
    scene, box = make_scene(gs.morphs.Box(pos=(0.0, 0.0, 1.0)))
    scene.step()
    box.get_links_pos()
    box.get_total_energy()
    gc.collect()
    placed = _placed_fields()
    new = [o for k, o in placed.items() if k not in before]
    solver = scene.rigid_solver
    own = {}

    def collect(obj, depth=0):
        import taichi as ti

        for k, v in vars(obj).items():
            if isinstance(v, ti.Field):
                own[id(v)] = k
            elif depth < 2 and hasattr(v, "__dict__") and type(v).__module__.startswith("solvers."):
                collect(v, depth + 1)

    collect(solver)
    assert own and all(k in placed for k in own), "the census misses the solver's own fields: it is broken"
    foreign = [o for o in new if id(o) not in own]
    assert not foreign, f"{len(foreign)} Taichi fields were allocated outside scene.rigid_solver"
    # no gradient storage without requires_grad
    for name in ("qpos", "qvel", "link_pos", "mass_mat"):
        g = getattr(solver, name).grad
        assert g is None or id(g) not in {id(o) for o in new}, f"{name}.grad was allocated"
    # and no MPM solver on the scene, under any of Genesis's names
    solvers = getattr(scene, "solvers", None)
    if solvers is not None:
        assert all("mpm" not in type(s).__name__.lower() for s in solvers)
    for name in ("mpm_solver", "_mpm", "mpm"):
        assert getattr(scene, name, None) is None, name
    # nothing of the MPM side hangs off the scene (an empty entity list and the default options are
    # not a solver)
    assert scene.mpm_entities == []
    assert not any(type(v).__module__.startswith(("solvers.mpm", "genesis_lite.bridges.mpm")) for v in vars(scene).values())


def test_state_fields_and_memory_do_not_grow_with_steps(arm):
    scene, a = arm
    scene.reset()
    solver = scene.rigid_solver
    shapes = {k: getattr(solver, k).shape for k in ("qpos", "qvel", "qacc")}
    assert shapes["qpos"][0] == 2, "Euler-family integrators keep two state slots (current, next)"
    a.control_dofs_force([0.5, -0.5, 0.2, 0.1])
    for _ in range(500):  # warm up allocators
        scene.step()
    gc.collect()
    rss0 = _resident_bytes()
    for i in range(4000):
        scene.step()
        if i % 500 == 0:
            a.get_qpos()
    gc.collect()
    grown = _resident_bytes() - rss0
    assert {k: getattr(solver, k).shape for k in shapes} == shapes
    assert scene.t == 4500
    assert grown < 4 * 2 ** 20, f"resident memory grew by {grown / 2 ** 20:.1f} MiB over 4000 steps"
    scene.reset()


# ----------------------------------------------------------------------------------------------
# bad input: each raises at once and names the thing
# ----------------------------------------------------------------------------------------------
def _urdf(tmp_path, body, name="robot.urdf"):
    p = tmp_path / name
    p.write_text(f'<?xml version="1.0"?>\n<robot name="r">\n{body}\n</robot>\n')
    return p


LINK = '<link name="{n}"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>{extra}</link>'
JOINT = '<joint name="{n}" type="{t}"><parent link="{p}"/><child link="{c}"/><axis xyz="0 0 1"/></joint>'


def _add_fails(scene, morph_factory, exc, pattern):
    with pytest.raises(exc, match=pattern) as e:
        scene.add_entity(morph_factory())
    assert scene.entities == [], "a failed add_entity must leave the scene as it was"
    return str(e.value)


def test_bad_input_missing_file(tmp_path):
    scene = gs.Scene()
    _add_fails(scene, lambda: gs.morphs.URDF(file=str(tmp_path / "nope.urdf")), FileNotFoundError, r"nope\.urdf")
    _add_fails(scene, lambda: gs.morphs.Mesh(file=str(tmp_path / "gone.stl")), FileNotFoundError, r"gone\.stl")


def test_bad_input_malformed_xml(tmp_path):
    p = tmp_path / "broken.urdf"
    p.write_text('<robot name="x"><link name="a"></robot>')
    _add_fails(gs.Scene(), lambda: gs.morphs.URDF(file=str(p)), ValueError, r"broken\.urdf.*malformed XML")


def test_bad_input_joint_loop(tmp_path):
    body = "\n".join([LINK.format(n="a", extra=""), LINK.format(n="b", extra=""), LINK.format(n="c", extra=""),
                      JOINT.format(n="j1", t="revolute", p="a", c="b"), JOINT.format(n="j2", t="revolute", p="b", c="c"),
                      JOINT.format(n="j3", t="revolute", p="c", c="b")])
    p = _urdf(tmp_path, body, "loop.urdf")
    msg = _add_fails(gs.Scene(), lambda: gs.morphs.URDF(file=str(p)), ValueError, r"loop\.urdf")
    assert "loop" in msg and "'b'" in msg


def test_bad_input_unknown_joint_type(tmp_path):
    body = "\n".join([LINK.format(n="a", extra=""), LINK.format(n="b", extra=""),
                      JOINT.format(n="hinge", t="ball", p="a", c="b")])
    p = _urdf(tmp_path, body, "ball.urdf")
    _add_fails(gs.Scene(), lambda: gs.morphs.URDF(file=str(p)), ValueError,
               r"ball\.urdf.*joint 'hinge' has unknown type 'ball'")


def test_bad_input_mesh_that_fails_to_load(tmp_path):
    junk = tmp_path / "junk.stl"
    junk.write_bytes(b"this is not an stl file at all")
    scene = gs.Scene()
    _add_fails(scene, lambda: gs.morphs.Mesh(file=str(junk)), ValueError, r"junk\.stl")
    p = _urdf(tmp_path, LINK.format(n="base", extra='<collision><geometry><mesh filename="junk.stl"/></geometry></collision>'))
    _add_fails(scene, lambda: gs.morphs.URDF(file=str(p)), ValueError, r"robot\.urdf.*link 'base'.*junk\.stl")
    # the scene is still usable after failed additions
    box = scene.add_entity(gs.morphs.Box())
    assert scene.entities == [box]


def test_bad_input_calls_before_build():
    scene = gs.Scene()
    box = scene.add_entity(gs.morphs.Box())
    for call, what in ((scene.step, "step"), (scene.get_state, "get_state"), (scene.reset, "reset")):
        with pytest.raises(GenesisException, match=rf"scene\.{what}\(\) before scene\.build\(\)"):
            call()
    with pytest.raises(GenesisException, match=r"'box_0'.*scene\.build\(\)"):
        box.get_qpos()
    with pytest.raises(GenesisException, match=r"'box_0'.*scene\.build\(\)"):
        box.set_dofs_velocity(np.zeros(6))


def test_bad_input_add_entity_after_build_and_build_twice(free):
    scene, box, ball = free
    with pytest.raises(GenesisException, match=r"add_entity\(\) after scene\.build\(\)"):
        scene.add_entity(gs.morphs.Sphere())
    assert len(scene.entities) == 2
    with pytest.raises(GenesisException, match=r"build\(\) called twice"):
        scene.build()
    with pytest.raises(ValueError, match="n_envs"):
        gs.Scene().build(n_envs=-1)


def test_bad_input_wrong_length(panda):
    _, robot = panda
    with pytest.raises(GenesisException, match=r"'panda'.*position has shape \(8,\); expected \(9,\)"):
        robot.set_dofs_position(np.zeros(8))
    with pytest.raises(GenesisException, match=r"'panda'.*velocity has shape \(2,\); expected \(3,\)"):
        robot.set_dofs_velocity([0.0, 1.0], dofs_idx_local=[0, 1, 2])
    with pytest.raises(GenesisException, match=r"'panda'.*force has shape \(1, 9\)"):
        robot.control_dofs_force(torch.zeros(1, 9))  # unbatched scene: no env axis


def test_bad_input_wrong_batch_size(arm4):
    _, a = arm4
    with pytest.raises(GenesisException, match=r"'arm'.*position has shape \(3, 4\); expected \(4,\) or \(4, 4\)"):
        a.set_dofs_position(np.zeros((3, 4)))
    with pytest.raises(GenesisException, match=r"'arm'.*force has shape \(4, 4\); expected \(4,\) or \(2, 4\)"):
        a.control_dofs_force(np.zeros((4, 4)), envs_idx=[0, 1])


def test_bad_input_dof_index_out_of_range(panda):
    _, robot = panda
    with pytest.raises(GenesisException, match=r"'panda'.*dofs_idx_local \[9\] out of range.*0\.\.8"):
        robot.get_dofs_position(dofs_idx_local=[9])
    with pytest.raises(GenesisException, match=r"dofs_idx_local \[-1\] out of range"):
        robot.set_dofs_position([0.0], dofs_idx_local=[-1])
    with pytest.raises(GenesisException, match=r"links_idx_local \[10\] out of range"):
        robot.get_links_pos(links_idx_local=[10])
    with pytest.raises(GenesisException, match=r"dofs_idx_local must be integers"):
        robot.get_dofs_velocity(dofs_idx_local=[0.5])


def test_bad_input_env_index_out_of_range(arm4):
    _, a = arm4
    with pytest.raises(GenesisException, match=r"'arm'.*envs_idx \[4\] out of range.*0\.\.3"):
        a.get_qpos(envs_idx=[4])
    with pytest.raises(GenesisException, match=r"envs_idx \[0, 7\] out of range"):
        a.set_dofs_velocity(np.zeros(4), envs_idx=[0, 7])


def test_bad_input_envs_idx_on_unbatched_scene(arm):
    _, a = arm
    with pytest.raises(GenesisException, match=r"'arm'.*envs_idx given but the scene was built without n_envs"):
        a.get_dofs_position(envs_idx=[0])
    with pytest.raises(GenesisException, match=r"envs_idx given"):
        a.control_dofs_force(np.zeros(4), envs_idx=[0])


def test_bad_input_nan_set_into_the_state_raises_at_once(arm, fresh):
    scene, a = arm
    fresh(scene)
    q_before = _np(a.get_qpos())
    with pytest.raises(GenesisException, match=r"'arm'.*position contains NaN"):
        a.set_dofs_position([0.0, float("nan"), 0.0, 0.0])
    with pytest.raises(GenesisException, match=r"'arm'.*velocity contains NaN or infinite"):
        a.set_dofs_velocity(torch.tensor([0.0, 0.0, float("inf"), 0.0]))
    with pytest.raises(GenesisException, match=r"'arm'.*force contains NaN"):
        a.control_dofs_force(np.array([np.nan] * 4))
    with pytest.raises(GenesisException, match=r"'arm'.*damping contains NaN"):
        a.set_dofs_damping([np.nan] * 4)
    assert np.array_equal(_np(a.get_qpos()), q_before)
    scene.step()
    assert torch.isfinite(a.get_qpos()).all()


def test_bad_input_divergence_names_entity_quantity_and_step(arm, fresh):
    """A torque far beyond anything the light wrist can take overflows the state within a few steps.
    The error must name the entity, the quantity and the step at which the state became non-finite
    (or a range of steps holding it), say what to do, and come soon after (the scene may check the
    state every few steps rather than every step)."""
    scene, a = arm
    fresh(scene)
    lo0, hi0 = (x.clone() for x in a.get_dofs_force_range())
    try:
        a.set_dofs_force_range([-1e308] * 4, [1e308] * 4)
        a.control_dofs_force([0.0, 0.0, 0.0, 1e300])
        first_bad = None
        with pytest.raises(gs.errors.SimulationNaNError) as e:
            for step in range(1, 200):
                scene.step()  # raises at some point
                finite = bool(torch.isfinite(a.get_qpos()).all() and torch.isfinite(a.get_dofs_velocity()).all())
                if not finite and first_bad is None:
                    first_bad = step
        msg = str(e.value)
        raised_at = scene.t
        if first_bad is None:  # the check ran in the very step that broke the state
            first_bad = raised_at
        assert 0 <= raised_at - first_bad < 16, f"non-finite since step {first_bad}, reported at step {raised_at}"
        assert "'arm'" in msg and re.search(r"\bq(pos|vel)\[\d\]", msg), msg
        span = re.search(r"between steps? (\d+) and (\d+)|steps (\d+)\s*(?:-|\.\.|to)\s*(\d+)", msg)
        if span:
            lo, hi = [int(x) for x in span.groups() if x is not None]
            assert lo <= first_bad <= hi, f"message gives steps {lo}..{hi}; it became non-finite at {first_bad}: {msg}"
        else:
            m = re.search(r"step (\d+)", msg)
            assert m, msg
            assert int(m.group(1)) == first_bad, (
                f"message names step {m.group(1)}; the state became non-finite at step {first_bad}: {msg}")
        assert re.search(r"dt|substeps", msg)  # says what to do
    finally:
        a.set_dofs_force_range(lo0, hi0)
        scene.reset()
    assert torch.isfinite(a.get_qpos()).all()  # reset recovers the scene


def test_bad_input_non_float_dtype(arm):
    _, a = arm
    with pytest.raises(GenesisException, match=r"'arm'.*position has dtype torch\.bool"):
        a.set_dofs_position(torch.tensor([True, False, True, False]))
    with pytest.raises(GenesisException, match=r"'arm'.*velocity has dtype torch\.complex128"):
        a.set_dofs_velocity(torch.zeros(4, dtype=torch.complex128))
    with pytest.raises(GenesisException, match=r"'arm'.*force must be numbers"):
        a.control_dofs_force(np.array(["a", "b", "c", "d"]))


def test_bad_input_grad_tensor_without_requires_grad(arm):
    _, a = arm
    x = torch.zeros(4, dtype=torch.float64, requires_grad=True)
    for call in (a.set_dofs_position, a.control_dofs_force, a.set_dofs_kp):
        with pytest.raises(GenesisException, match=r"'arm'.*requires grad.*SimOptions\(requires_grad=True\)"):
            call(x)
