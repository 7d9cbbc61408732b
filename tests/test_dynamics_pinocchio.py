"""Rigid-body dynamics against Pinocchio, a reference no one here wrote (issue #2).

For real robots of example-robot-data (and the URDFs in assets/), at random seeded states in float64:
- the joint-space mass matrix equals `pin.crba` (symmetrised), relative error < 1e-9;
- the acceleration implied by one semi-implicit Euler step, (v1 - v0) / dt, equals
  `pin.aba(model, data, q, v, tau)`, relative error < 1e-8;
- link frame positions equal Pinocchio's forward kinematics.
Damping, armature and friction loss are zeroed on our side, joint limits and collisions are off, gravity
is -9.81 z on both sides.

Conventions bridged here (see DESIGN.md):
- joints are matched by name; Pinocchio's continuous (revolute-unbounded) joints have q = (cos, sin)
  where ours is one angle (`model.nqs[j] == 2`);
- a free base: our qpos is [x, y, z, qw, qx, qy, qz, joints...] and our base dofs are the world-frame
  linear velocity of the base origin and the world-frame angular velocity. Pinocchio's free-flyer has
  q = [x, y, z, qx, qy, qz, qw, ...] and local-frame velocities v_l = R^T pdot, w_l = R^T w. So
  v_ours = T v_pin with T = diag(R, R, I), M_ours = T M_pin T^T, and the accelerations are
  pddot = R (a_l + w_l x v_l) (classical, world) and wdot = R alpha_l.
  `test_free_flyer_conversion` checks these formulas against Pinocchio's own integrator.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
import zlib
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yourdfpy

DT = 0.01
GRAVITY = np.array([0.0, 0.0, -9.81])
N_SAMPLES = 4
RTOL_MASS = 1e-9
RTOL_ACC = 1e-8
ATOL_POS = 1e-10  # m

FIXED_BASE = ["panda", "ur5", "z1", "kinova", "xarm7", "so101", "double_pendulum_continuous", "finger_edu"]
FLOATING_BASE = ["go2", "anymal", "anymal_c"]
LOCAL_ASSETS = ["arm", "double_pendulum", "chain30"]  # assets/urdf/<name>.urdf, fixed base


def _gs():
    """The simulator, imported when a test needs it (its real import error surfaces in that test)."""
    import genesis_lite as gs

    return gs


def _resolve(name, urdf_path, assets_dir) -> Path:
    if name in LOCAL_ASSETS:
        return assets_dir / "urdf" / f"{name}.urdf"
    return urdf_path(name)


def _same_mass_convention(path: Path, tmp_dir: Path) -> Path:
    """The URDF to compare, given our convention for a link without <inertial>.

    genesis_lite (like Genesis) gives such a link the mass of its collision solids at the material's
    density; the URDF spec and Pinocchio give it none. Where that matters (anymal_c's base), compare a
    copy without <collision>/<visual> elements (geometry plays no part here: collisions are off), so
    both sides see the same massless link. Other files are used as they are.
    """
    tree = ET.parse(path)
    links = tree.getroot().findall("link")
    if not any(link.find("inertial") is None and link.find("collision") is not None for link in links):
        return path
    for link in links:
        for tag in ("collision", "visual"):
            for e in link.findall(tag):
                link.remove(e)
    out = tmp_dir / path.name
    tree.write(out, encoding="unicode")
    return out


def _np(x) -> np.ndarray:
    """A tensor (or array) returned by the simulator, as a float64 numpy array."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _t(x):
    import torch

    return torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=torch.float64)


def _rel(a, b, floor=1e-12) -> float:
    """Relative error ||a - b|| / ||b|| (Frobenius / 2-norm)."""
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), floor))


def _quat_wxyz_to_R(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _joint_dofs(joint) -> list[int]:
    """Local dof indices of one of our joints, whatever the form (int, list, range, None)."""
    d = getattr(joint, "dof_idx_local", None)
    if d is None:
        d = getattr(joint, "dofs_idx_local", None)
    if d is None:
        return []
    if isinstance(d, (int, np.integer)):
        return [int(d)]
    return [int(i) for i in d]


class PinReference:
    """Pinocchio's model of a URDF and the maps between its coordinates and ours."""

    def __init__(self, path: Path, floating: bool):
        self.floating = floating
        if floating:
            self.model = pin.buildModelFromUrdf(str(path), pin.JointModelFreeFlyer())
        else:
            self.model = pin.buildModelFromUrdf(str(path))
        self.model.gravity = pin.Motion(GRAVITY, np.zeros(3))
        self.data = self.model.createData()
        first = 2 if floating else 1  # joint 0 is the universe, joint 1 the free flyer if any
        self.joints = [(self.model.names[j], j) for j in range(first, self.model.njoints)]
        self.nb = 6 if floating else 0  # base dofs

    def match(self, robot):
        """Our dof index of every Pinocchio joint (matched by name), as a permutation of the joints."""
        ours = {}
        for joint in robot.joints:
            dofs = _joint_dofs(joint)
            if len(dofs) == 1:
                ours[joint.name] = dofs[0]
        pin_names = [n for n, _ in self.joints]
        missing = sorted(set(pin_names) - set(ours))
        extra = sorted(set(ours) - set(pin_names))
        assert not missing and not extra, (
            f"joints differ from Pinocchio's: missing in ours {missing}, not in Pinocchio {extra}")
        assert robot.n_dofs == self.model.nv, f"n_dofs {robot.n_dofs} != Pinocchio nv {self.model.nv}"
        if self.floating:
            assert sorted(ours.values()) == list(range(6, robot.n_dofs)), "joint dofs must follow the 6 base dofs"
        self.dof = {name: ours[name] for name in pin_names}
        # perm[k] = our dof index of Pinocchio's velocity index k
        self.perm = np.arange(self.model.nv)
        for name, j in self.joints:
            self.perm[self.model.idx_vs[j]] = self.dof[name]

    def sample(self, rng: np.random.Generator):
        """A random state in our coordinates: joint angles (within finite limits), base pose, velocities."""
        n = self.model.nv
        angles = np.zeros(n)
        for name, j in self.joints:
            iq, nq = self.model.idx_qs[j], self.model.nqs[j]
            lo, hi = -np.pi, np.pi
            if nq == 1:
                l, h = self.model.lowerPositionLimit[iq], self.model.upperPositionLimit[iq]
                if np.isfinite(l) and np.isfinite(h) and h > l and h - l < 1e3:
                    lo, hi = l, h
            angles[self.dof[name]] = rng.uniform(lo, hi)
        v = rng.normal(0.0, 1.0, n)
        base_pos = rng.uniform(-1.0, 1.0, 3)
        quat = rng.normal(size=4)
        quat /= np.linalg.norm(quat)
        return angles, v, base_pos, quat

    def to_pin(self, angles, v_ours, base_pos=None, quat_wxyz=None):
        """Our state -> Pinocchio's (q, v)."""
        q = np.zeros(self.model.nq)
        v = np.zeros(self.model.nv)
        for name, j in self.joints:
            iq, iv, d = self.model.idx_qs[j], self.model.idx_vs[j], self.dof[name]
            if self.model.nqs[j] == 2:
                q[iq], q[iq + 1] = np.cos(angles[d]), np.sin(angles[d])
            else:
                assert self.model.nqs[j] == 1, f"joint {name}: unexpected nq {self.model.nqs[j]}"
                q[iq] = angles[d]
            v[iv] = v_ours[d]
        if self.floating:
            w, x, y, z = quat_wxyz
            q[0:3] = base_pos
            q[3:7] = [x, y, z, w]
            R = _quat_wxyz_to_R(quat_wxyz)
            v[0:3] = R.T @ v_ours[0:3]
            v[3:6] = R.T @ v_ours[3:6]
        return q, v

    def tau_to_pin(self, tau_ours):
        tau = np.zeros(self.model.nv)
        for name, j in self.joints:
            tau[self.model.idx_vs[j]] = tau_ours[self.dof[name]]
        return tau  # base wrench stays 0: only joints are actuated

    def mass_matrix_ours(self, q, quat_wxyz=None):
        """pin.crba (symmetrised) in our dof order and base velocity convention."""
        M = pin.crba(self.model, self.data, q)
        M = np.triu(M) + np.triu(M, 1).T
        if self.floating:
            T = np.eye(self.model.nv)
            R = _quat_wxyz_to_R(quat_wxyz)
            T[0:3, 0:3] = R
            T[3:6, 3:6] = R
            M = T @ M @ T.T
        out = np.zeros_like(M)
        out[np.ix_(self.perm, self.perm)] = M
        return out

    def acc_ours(self, q, v, tau, quat_wxyz=None):
        """pin.aba in our dof order; a free base's part as world-frame classical accelerations."""
        a = pin.aba(self.model, self.data, q, v, tau).copy()
        if self.floating:
            R = _quat_wxyz_to_R(quat_wxyz)
            a_lin = R @ (a[0:3] + np.cross(v[3:6], v[0:3]))
            a_ang = R @ a[3:6]
            a[0:3], a[3:6] = a_lin, a_ang
        out = np.zeros_like(a)
        out[self.perm] = a
        return out


def _build(path: Path, fixed: bool):
    gs = _gs()
    scene = gs.Scene(
        sim_options=gs.options.SimOptions(dt=DT, substeps=1, gravity=tuple(GRAVITY), requires_grad=False),
        rigid_options=gs.options.RigidOptions(
            # Pinocchio treats <mimic> joints as independent: so do we here
            integrator=gs.integrator.Euler, enable_collision=False, enable_joint_limit=False, enable_mimic=False),
    )
    robot = scene.add_entity(gs.morphs.URDF(file=str(path), fixed=fixed))
    scene.build()
    zeros = _t(np.zeros(robot.n_dofs))
    robot.set_dofs_damping(zeros)
    robot.set_dofs_armature(zeros)
    robot.set_dofs_frictionloss(zeros)
    return scene, robot


def _set_state(robot, ref: PinReference, angles, v, base_pos, quat):
    if ref.floating:
        # qpos: base pose then one entry per joint dof, in dof order (no continuous joints here)
        qpos = np.concatenate([base_pos, quat, angles[6:]])
        assert robot.n_qs == qpos.size, f"n_qs {robot.n_qs} != {qpos.size}"
        robot.set_qpos(_t(qpos))
    else:
        robot.set_dofs_position(_t(angles))
    robot.set_dofs_velocity(_t(v))


def _random_tau(ref: PinReference, q_pin, v_pin, rng) -> np.ndarray:
    """Joint torques of a realistic size: those that would give a random N(0,1) joint acceleration,
    clipped to the URDF's effort limits (the simulator, like Genesis, clips control forces to them;
    effort 0 means no limit)."""
    a = rng.normal(0.0, 1.0, ref.model.nv)
    tau_pin = pin.rnea(ref.model, ref.data, q_pin, v_pin, a).copy()
    limit = np.asarray(ref.model.effortLimit, dtype=float).copy()
    limit[~(np.isfinite(limit) & (limit > 0))] = np.inf
    tau_pin = np.clip(tau_pin, -limit, limit)
    tau_pin[: ref.nb] = 0.0
    tau = np.zeros(ref.model.nv)
    tau[ref.perm] = tau_pin
    return tau


def _check_dynamics(path: Path, floating: bool, seed: int):
    scene, robot = _build(path, fixed=not floating)
    ref = PinReference(path, floating)
    ref.match(robot)
    rng = np.random.default_rng(seed)
    for sample in range(N_SAMPLES):
        angles, v0, base_pos, quat = ref.sample(rng)
        q_pin, v_pin = ref.to_pin(angles, v0, base_pos, quat)
        tau = _random_tau(ref, q_pin, v_pin, rng) if sample < N_SAMPLES - 1 else np.zeros(robot.n_dofs)
        tau_pin = ref.tau_to_pin(tau)
        _set_state(robot, ref, angles, v0, base_pos, quat)

        M = _np(robot.get_mass_mat())
        M_ref = ref.mass_matrix_ours(q_pin, quat)
        err = _rel(M, M_ref)
        assert err < RTOL_MASS, f"{path.name} sample {sample}: mass matrix rel. error {err:.3e}"

        robot.control_dofs_force(_t(tau))
        scene.step()
        v1 = _np(robot.get_dofs_velocity())
        acc = (v1 - v0) / DT
        acc_ref = ref.acc_ours(q_pin, v_pin, tau_pin, quat)
        if floating:
            parts = {"base linear": slice(0, 3), "base angular": slice(3, 6), "joints": slice(6, None)}
        else:
            parts = {"joints": slice(None)}
        for what, s in parts.items():
            err = _rel(acc[s], acc_ref[s])
            assert err < RTOL_ACC, (
                f"{path.name} sample {sample}: {what} acceleration rel. error {err:.3e}\n"
                f"ours {acc[s]}\npin  {acc_ref[s]}")
        err = _rel(_np(robot.get_dofs_acc()), acc_ref)
        assert err < RTOL_ACC, f"{path.name} sample {sample}: get_dofs_acc() rel. error {err:.3e}"


@pytest.mark.parametrize("name", FIXED_BASE + LOCAL_ASSETS)
def test_fixed_base_dynamics(name, urdf_path, assets_dir, tmp_path):
    path = _same_mass_convention(_resolve(name, urdf_path, assets_dir), tmp_path)
    _check_dynamics(path, floating=False, seed=zlib.crc32(name.encode()))


@pytest.mark.parametrize("name", FLOATING_BASE)
def test_floating_base_free_fall(name, urdf_path, assets_dir, tmp_path):
    path = _same_mass_convention(_resolve(name, urdf_path, assets_dir), tmp_path)
    _check_dynamics(path, floating=True, seed=zlib.crc32(name.encode()))


@pytest.mark.parametrize("name", ["panda", "kinova", "go2"])
def test_forward_kinematics(name, urdf_path, assets_dir):
    """Link frame origins equal Pinocchio's frame placements (links matched by name)."""
    floating = name in FLOATING_BASE
    path = _resolve(name, urdf_path, assets_dir)  # meshes included: FK does not depend on masses
    scene, robot = _build(path, fixed=not floating)
    ref = PinReference(path, floating)
    ref.match(robot)
    angles, v, base_pos, quat = ref.sample(np.random.default_rng(7))
    _set_state(robot, ref, angles, np.zeros_like(v), base_pos, quat)
    q_pin, _ = ref.to_pin(angles, np.zeros_like(v), base_pos, quat)
    pin.framesForwardKinematics(ref.model, ref.data, q_pin)
    pos = _np(robot.get_links_pos())
    assert pos.shape == (len(robot.links), 3)
    for i, link in enumerate(robot.links):
        assert ref.model.existFrame(link.name), f"{name}: link {link.name} is no frame of Pinocchio's model"
        expected = ref.data.oMf[ref.model.getFrameId(link.name)].translation
        assert np.allclose(pos[i], expected, rtol=0, atol=ATOL_POS), f"{name}: link {link.name} at {pos[i]}, pin {expected}"


# --- checks of the references themselves (no simulator needed) -------------------------------------


@pytest.mark.parametrize("name", FIXED_BASE + FLOATING_BASE + LOCAL_ASSETS)
def test_urdf_parses(name, urdf_path, assets_dir):
    """yourdfpy (our loader's parser) and Pinocchio read the same moving joints from each URDF."""
    path = _resolve(name, urdf_path, assets_dir)
    assert path.is_file(), path
    urdf = yourdfpy.URDF.load(str(path), load_meshes=False, build_scene_graph=False, load_collision_meshes=False)
    moving = {j.name for j in urdf.robot.joints if j.type != "fixed"}
    model = pin.buildModelFromUrdf(str(path))
    assert moving == {model.names[j] for j in range(1, model.njoints)}
    if name in ("kinova", "double_pendulum_continuous", "arm"):
        assert any(model.nqs[j] == 2 for j in range(1, model.njoints)), f"{name} should have a continuous joint"


def test_free_flyer_conversion():
    """The world-frame accelerations used above are the time derivatives of the world-frame velocities
    along Pinocchio's own trajectory (central differences of pin.integrate)."""
    model = pin.buildModelFromUrdf(str(Path(__file__).resolve().parents[1] / "assets" / "urdf" / "arm.urdf"),
                                   pin.JointModelFreeFlyer())
    data = model.createData()
    rng = np.random.default_rng(0)
    q = pin.randomConfiguration(model, -np.ones(model.nq), np.ones(model.nq))
    v = rng.normal(size=model.nv)
    tau = np.concatenate([np.zeros(6), rng.normal(size=model.nv - 6)])

    def world_vel(q, v):
        R = pin.Quaternion(q[6], q[3], q[4], q[5]).toRotationMatrix()  # (w, x, y, z)
        return np.concatenate([R @ v[0:3], R @ v[3:6]])

    def flow(q, v, h):
        # one step of the exact flow to second order: q(h), v(h) with a = aba at the start
        a = pin.aba(model, data, q, v, tau)
        return pin.integrate(model, q, v * h + 0.5 * a * h * h), v + a * h

    h = 1e-5
    qp, vp = flow(q, v, h)
    qm, vm = flow(q, v, -h)
    fd = (world_vel(qp, vp) - world_vel(qm, vm)) / (2 * h)
    a = pin.aba(model, data, q, v, tau)
    R = pin.Quaternion(q[6], q[3], q[4], q[5]).toRotationMatrix()
    assert np.allclose(R, _quat_wxyz_to_R([q[6], q[3], q[4], q[5]]), atol=1e-14)
    expected = np.concatenate([R @ (a[0:3] + np.cross(v[3:6], v[0:3])), R @ a[3:6]])
    assert np.allclose(fd, expected, rtol=1e-6, atol=1e-6), (fd, expected)
    # and the kinetic energy is the same in both velocity conventions with M_ours = T M_pin T^T
    M = pin.crba(model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    T = np.eye(model.nv)
    T[0:3, 0:3] = T[3:6, 3:6] = R
    v_ours = T @ v
    assert np.isclose(v_ours @ (T @ M @ T.T) @ v_ours, v @ M @ v, rtol=1e-12)
