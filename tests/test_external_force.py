"""External link forces and gravity compensation (issue #25), written as a Genesis user writes them:
scene.sim.rigid_solver.apply_links_external_force / _torque and gs.materials.Rigid(gravity_compensation=),
each checked against physics rather than against our own output:
- a free box in zero gravity pushed by F for N steps: v = F t / m, and x the semi-implicit Euler sum
  h^2 F / m N (N + 1) / 2 (= F t^2 / 2m to 1/N); a torque about a principal axis spins it at tau t / I;
- the force lasts one step (Genesis drops it after each step), calls before a step add up, envs_idx picks
  envs, local=True takes the link's axes;
- a force at a point off the centre of mass (ref="link_origin", "link_com", "root_com" on a free
  three-link tree with skewed, offset inertias): one step from rest gives the tree the linear momentum
  F h and the angular momentum about its centre of mass (p - C) x F h, from the links' own velocities;
- gravity_compensation=1 holds a free box and a fixed arm still under gravity, 0.5 halves the fall;
- Genesis's example script (examples/rigid/apply_external_force_torque.py) runs unchanged and spins the
  cube at tau t / I;
- a force on a body coupled to an MPM block adds exactly its impulse to the system's momentum (-m slow);
- bad input (shape, link index, NaN, ref) raises an error naming it;
- gradients of the forces, the gravity compensation and the initial velocity against central finite
  differences in float64 (-m slow: the gradient kernels' first compile).
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

import genesis_lite as gs
from genesis_lite.errors import GenesisException

from conftest import ASSETS_DIR

DT = 0.01
SKEW_ARM = str(ASSETS_DIR / "urdf" / "skew_arm.urdf")
F64 = dict(dtype=torch.float64)


def _scene(gravity=(0.0, 0.0, 0.0), requires_grad=False, substeps=1, checkpoint_every=None):
    # no collisions: the bodies here touch nothing, and a contact solver would add a compile per test
    return gs.Scene(sim_options=gs.options.SimOptions(dt=DT, gravity=gravity, requires_grad=requires_grad,
                                                      substeps=substeps, checkpoint_every=checkpoint_every),
                    rigid_options=gs.options.RigidOptions(enable_collision=False), show_viewer=False)


def _box_scene(n_envs=0, size=(0.2, 0.3, 0.4), quat=(1.0, 0.0, 0.0, 0.0), gravity=(0.0, 0.0, 0.0)):
    scene = _scene(gravity)
    box = scene.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 1.0), size=size, quat=quat))
    scene.build(n_envs=n_envs)
    return scene, box


def _np(x):
    return x.detach().cpu().numpy() if torch.is_tensor(x) else np.asarray(x)


def test_force_on_a_free_box_moves_it_by_F_t2_over_2m_and_lasts_one_step():
    scene, box = _box_scene()
    solver = scene.sim.rigid_solver
    m = float(box.get_mass())
    F = np.array([3.0, -2.0, 1.0])
    N = 20
    x0 = _np(box.get_pos())
    for _ in range(N):
        solver.apply_links_external_force(force=F.reshape(1, 3), links_idx=[box.links[0].idx])
        scene.step()
    t = N * DT
    np.testing.assert_allclose(_np(box.get_vel()), F * t / m, rtol=1e-12, atol=1e-14)
    # semi-implicit Euler's position: sum_k k h^2 a = h^2 a N (N + 1) / 2, the exact F t^2 / 2m to 1/N
    dx = _np(box.get_pos()) - x0
    np.testing.assert_allclose(dx, DT ** 2 * F / m * N * (N + 1) / 2, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(dx, F * t ** 2 / (2 * m), rtol=1.0 / N + 1e-9)
    np.testing.assert_allclose(_np(box.get_ang()), 0.0, atol=1e-14)
    # nothing applied: the velocity stays (the force lasted exactly one step each time)
    for _ in range(3):
        scene.step()
    np.testing.assert_allclose(_np(box.get_vel()), F * t / m, rtol=1e-12, atol=1e-14)
    # two calls before one step add up; a step without a call adds nothing
    scene.reset()
    solver.apply_links_external_force(F / 2, [box.links[0].idx])
    solver.apply_links_external_force(np.tile(F / 2, (1, 1)), box.links[0].idx)
    scene.step()
    np.testing.assert_allclose(_np(box.get_vel()), F * DT / m, rtol=1e-12, atol=1e-14)
    scene.step()
    np.testing.assert_allclose(_np(box.get_vel()), F * DT / m, rtol=1e-12, atol=1e-14)
    # scene.reset() drops a force applied and not yet stepped
    scene.reset()
    solver.apply_links_external_force(F, [box.links[0].idx])
    scene.reset()
    scene.step()
    np.testing.assert_allclose(_np(box.get_vel()), 0.0, atol=1e-14)


def test_torque_spins_a_free_box_at_tau_t_over_I():
    """About the z axis, a principal axis of the box (I_zz = m (a^2 + b^2) / 12): no gyroscopic coupling,
    so omega = tau t / I_zz; a world torque about x on the box turned 90 degrees about z is about its own
    y axis (I_yy)."""
    a, b, c = 0.2, 0.3, 0.4
    scene, box = _box_scene(size=(a, b, c))
    solver = scene.sim.rigid_solver
    m = float(box.get_mass())
    N, tau = 15, 0.05
    for _ in range(N):
        solver.apply_links_external_torque([0.0, 0.0, tau], [box.links[0].idx])
        scene.step()
    w = _np(box.get_ang())
    np.testing.assert_allclose(w, [0.0, 0.0, tau * N * DT / (m * (a * a + b * b) / 12)], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(_np(box.get_vel()), 0.0, atol=1e-14)
    np.testing.assert_allclose(_np(box.get_pos()), [0.0, 0.0, 1.0], atol=1e-14)


def test_local_axes_and_per_env_forces():
    """A box turned 90 degrees about z: a local x force pushes it along world y, a local x torque turns it
    about world y (I of its own x axis). envs_idx picks envs; an (n_envs, links, 3) force gives each
    env its own; a (3,) force is broadcast."""
    s = np.sqrt(0.5)
    scene, box = _box_scene(n_envs=3, quat=(s, 0.0, 0.0, s))
    solver = scene.sim.rigid_solver
    m = float(box.get_mass()[0])
    link = box.links[0].idx
    solver.apply_links_external_force([[[2.0, 0.0, 0.0]]], [link], envs_idx=[1], local=True)
    solver.apply_links_external_torque([[[0.1, 0.0, 0.0]]], [link], envs_idx=[2], ref="link_com", local=True)
    scene.step()
    v, w = _np(box.get_vel()), _np(box.get_ang())
    np.testing.assert_allclose(v[0], 0.0, atol=1e-14)
    np.testing.assert_allclose(v[1], [0.0, 2.0 * DT / m, 0.0], atol=1e-12)
    I_xx = m * (0.3 ** 2 + 0.4 ** 2) / 12
    np.testing.assert_allclose(w[2], [0.0, 0.1 * DT / I_xx, 0.0], atol=1e-12)
    np.testing.assert_allclose(w[:2], 0.0, atol=1e-14)
    # per env, and broadcast
    scene.reset()
    F = np.array([[[1.0, 0.0, 0.0]], [[0.0, 2.0, 0.0]], [[0.0, 0.0, 3.0]]])
    solver.apply_links_external_force(torch.tensor(F, **F64), [link])
    solver.apply_links_external_force([1.0, 1.0, 1.0], [link])
    scene.step()
    np.testing.assert_allclose(_np(box.get_vel()), (F[:, 0] + 1.0) * DT / m, rtol=1e-12, atol=1e-14)


def _tree_momentum(scene, tree):
    """Linear momentum and angular momentum about the tree's centre of mass, from the links' own
    centre-of-mass velocities, angular velocities, masses and inertias (rotated to world)."""
    solver = scene.sim.rigid_solver
    links = [l.idx for l in tree.links]
    m = _np(tree.get_links_mass())
    c = _np(solver.get_links_pos(links, ref="link_com"))
    v = _np(solver.get_links_vel(links, ref="link_com"))
    w = _np(solver.get_links_ang(links))
    R = _np(gs.utils.geom.quat_to_R(solver.get_links_quat(links)))
    I = _np(tree.get_links_inertia())
    C = (m[:, None] * c).sum(0) / m.sum()
    np.testing.assert_allclose(_np(solver.get_links_root_COM(links)), np.tile(C, (len(links), 1)), atol=1e-12)
    P = (m[:, None] * v).sum(0)
    L = sum(m[k] * np.cross(c[k] - C, v[k]) + R[k] @ I[k] @ R[k].T @ w[k] for k in range(len(links)))
    return P, L, C, c


def _after_one_step(scene, tree, state):
    """The tree's momentum with the velocities of one step, at the pose it started from (the step also
    moves the pose by h v1, which turns the momentum's lever arms by O(h |v1|))."""
    scene.step()
    v1 = tree.get_dofs_velocity().detach().clone()
    scene.reset(state)
    tree.set_dofs_velocity(v1)
    P, L, _, _ = _tree_momentum(scene, tree)
    return P, L


@pytest.fixture
def free_tree():
    """skew_arm.urdf on a free base, in zero gravity: three links with offset centres of mass and rotated
    non-diagonal inertias, hinges on skewed axes (a scene per test: a scene kept for the module would
    hold its core, and later tests of its class would compile a core of their own); its joint damping off (implicitfast treats damping
    implicitly, which would take momentum from the step's impulse: the damper acts on the hinges, not
    between the tree and the world, but h D enters the step's solve)."""
    scene = _scene()
    tree = scene.add_entity(gs.morphs.URDF(file=SKEW_ARM, fixed=False, pos=(0.2, -0.1, 1.0)))
    scene.build()
    tree.set_dofs_damping([0.0, 0.0, 0.0], dofs_idx_local=[6, 7, 8])
    tree.set_dofs_position([0.4, -0.7, 0.5], dofs_idx_local=[6, 7, 8])
    return scene, tree, scene.get_state()


@pytest.mark.parametrize("ref", ["link_origin", "link_com", "root_com"])
def test_force_off_the_centre_of_mass_gives_the_torque_r_cross_f(free_tree, ref):
    """One step from rest, a force F on link 2 at the point of `ref` changes the tree's momentum by the
    impulse: linear F h, angular (point - C) x F h about the tree's centre of mass C. No other force acts
    and the tree starts at rest, so the step's velocities v1 = h M^-1 J^T F carry exactly that momentum at
    the starting pose (read there: _after_one_step)."""
    scene, tree, state = free_tree
    scene.reset(state)
    solver = scene.sim.rigid_solver
    link = tree.links[2].idx
    F = np.array([0.7, -1.1, 2.3])
    _, _, C, c = _tree_momentum(scene, tree)
    point = {"link_origin": _np(solver.get_links_pos([link]))[0], "link_com": c[2], "root_com": C}[ref]
    solver.apply_links_external_force(F, [link], ref=ref)
    P, L = _after_one_step(scene, tree, state)
    np.testing.assert_allclose(P, F * DT, rtol=1e-9, atol=1e-13)
    np.testing.assert_allclose(L, np.cross(point - C, F) * DT, rtol=1e-8, atol=1e-13)


def test_local_torque_and_local_force_at_the_centre_of_mass(free_tree):
    """A torque in link 1's axes changes the tree's angular momentum by R1 tau h; a force at link 1's centre
    of mass in its axes by R1 F h, with the torque (c1 - C) x R1 F."""
    scene, tree, state = free_tree
    scene.reset(state)
    solver = scene.sim.rigid_solver
    link = tree.links[1].idx
    tau, F = np.array([0.2, -0.1, 0.3]), np.array([-0.5, 0.4, 0.9])
    R1 = _np(gs.utils.geom.quat_to_R(solver.get_links_quat([link])))[0]
    _, _, C, c = _tree_momentum(scene, tree)
    solver.apply_links_external_torque(tau, [link], local=True)
    solver.apply_links_external_force(F, [link], ref="link_com", local=True)
    P, L = _after_one_step(scene, tree, state)
    np.testing.assert_allclose(P, R1 @ F * DT, rtol=1e-9, atol=1e-13)
    np.testing.assert_allclose(L, (R1 @ tau + np.cross(c[1] - C, R1 @ F)) * DT, rtol=1e-8, atol=1e-13)


def test_gravity_compensation_one_floats_half_halves_the_fall():
    """Genesis's meaning: the entity feels (1 - gc) of gravity. Three free boxes, gc 0, 0.5, 1; and the
    skew arm (fixed base) with gc = 1 stays where it was put, with gc = 0 it falls."""
    g = 9.81
    scene = _scene(gravity=(0.0, 0.0, -g))
    boxes = [scene.add_entity(gs.morphs.Box(pos=(k, 0.0, 1.0), size=(0.1, 0.2, 0.3)),
                              material=gs.materials.Rigid(gravity_compensation=gc)) for k, gc in enumerate((0.0, 0.5, 1.0))]
    held = scene.add_entity(gs.morphs.URDF(file=SKEW_ARM, fixed=True, pos=(0.0, 2.0, 0.0)),
                            material=gs.materials.Rigid(gravity_compensation=1.0))
    free = scene.add_entity(gs.morphs.URDF(file=SKEW_ARM, fixed=True, pos=(0.0, 3.0, 0.0)))
    scene.build()
    assert held.gravity_compensation == 1.0 and float(held.get_gravity_compensation()) == 1.0
    q0 = torch.tensor([0.4, -0.9, 1.2], **F64)
    held.set_dofs_position(q0)
    free.set_dofs_position(q0)
    N = 20
    for _ in range(N):
        scene.step()
    for box, gc in zip(boxes, (0.0, 0.5, 1.0)):
        np.testing.assert_allclose(_np(box.get_vel()), [0.0, 0.0, -(1 - gc) * g * N * DT], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(_np(box.get_pos())[2], 1.0 - (1 - gc) * g * DT ** 2 * N * (N + 1) / 2,
                                   rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(_np(held.get_dofs_position()), _np(q0), atol=1e-12)
    np.testing.assert_allclose(_np(held.get_dofs_velocity()), 0.0, atol=1e-10)
    assert np.abs(_np(free.get_dofs_velocity())).max() > 0.1


def test_gravity_compensation_set_after_build_per_env():
    """entity.set_gravity_compensation after build (an unused scene gains it then), per env: env k falls with
    (1 - gc_k) g."""
    g = 9.81
    scene = _scene(gravity=(0.0, 0.0, -g))
    box = scene.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 1.0), size=(0.1, 0.2, 0.3)))
    scene.build(n_envs=3)
    gc = np.array([0.0, 0.25, 1.0])
    box.set_gravity_compensation(gc)
    np.testing.assert_allclose(_np(box.get_gravity_compensation()), gc)
    for _ in range(5):
        scene.step()
    np.testing.assert_allclose(_np(box.get_vel())[:, 2], -(1 - gc) * g * 5 * DT, rtol=1e-12, atol=1e-12)
    with pytest.raises(GenesisException, match=r"gravity_compensation must lie in \[0, 1\]"):
        box.set_gravity_compensation(1.5)
    with pytest.raises(ValueError, match="gravity_compensation"):
        gs.materials.Rigid(gravity_compensation=-0.1)
    with pytest.raises(ValueError, match="gravity_compensation"):
        gs.materials.Rigid(gravity_compensation=float("nan"))


def test_bad_input_raises_naming_it():
    scene, box = _box_scene(n_envs=2)
    solver = scene.sim.rigid_solver
    link = box.links[0].idx
    with pytest.raises(GenesisException, match=r"force has shape \(2, 2, 3\); expected \(2, 1, 3\)"):
        solver.apply_links_external_force(np.zeros((2, 2, 3)), [link])
    with pytest.raises(GenesisException, match=r"torque has shape \(4,\)"):
        solver.apply_links_external_torque([1.0, 2.0, 3.0, 4.0], [link])
    with pytest.raises(GenesisException, match=r"links_idx \[7\] out of range; the scene's rigid solver has 1 links"):
        solver.apply_links_external_force([0.0, 0.0, 1.0], [7])
    with pytest.raises(GenesisException, match=r"links_idx must be integer"):
        solver.apply_links_external_force([0.0, 0.0, 1.0], [0.5])
    with pytest.raises(GenesisException, match=r"envs_idx \[5\] out of range"):
        solver.apply_links_external_force([0.0, 0.0, 1.0], [link], envs_idx=[5])
    with pytest.raises(GenesisException, match=r"force contains NaN or infinite values"):
        solver.apply_links_external_force([[[0.0, float("nan"), 1.0]], [[0.0, 0.0, 1.0]]], [link])
    with pytest.raises(GenesisException, match=r"ref='com'"):
        solver.apply_links_external_force([0.0, 0.0, 1.0], [link], ref="com")
    with pytest.raises(ValueError, match=r"local=True is not compatible with ref='root_com'"):
        solver.apply_links_external_torque([0.0, 0.0, 1.0], [link], ref="root_com", local=True)
    with pytest.raises(GenesisException, match=r"requires grad but the scene was built without gradients"):
        solver.apply_links_external_force(torch.zeros(3, **F64, requires_grad=True), [link])
    # nothing of the refused calls was applied
    scene.step()
    np.testing.assert_allclose(_np(box.get_vel()), 0.0, atol=1e-14)


def test_genesis_example_apply_external_force_torque():
    """examples/rigid/apply_external_force_torque.py of Genesis, its loop as written (shorter): a spring
    force towards (0, 0, 1) on the cube's origin and a torque of 5 N m about z, reversed every 100
    steps. The force acts at the centre of mass (a cube's origin), so the spin is tau t / I_zz exactly,
    and the cube stays in the air for the 50 steps run here. With Genesis's default density for objects
    (600 kg/m^3: 4.8 kg, ours since 2026-11-28) its height follows Genesis 0.4.5's, printed by the same loop
    in Genesis's venv (0.808517 m after 20 steps, 0.213480 m after 50; by step 60 it meets the ground,
    where the two contact models differ)."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01), show_viewer=False, show_FPS=False)
    scene.add_entity(gs.morphs.Plane())
    cube = scene.add_entity(gs.morphs.Box(pos=(0, 0, 1.0), size=(0.2, 0.2, 0.2)))
    scene.build(n_envs=1)
    link_idx = [1]
    assert cube.links[0].idx == 1
    rotation_direction = 1
    N, z_genesis = 50, {20: 0.808517, 50: 0.213480}
    for i in range(N):
        cube_pos = scene.sim.rigid_solver.get_links_pos(link_idx)
        cube_pos[:, :, 2] -= 1
        force = -100 * cube_pos
        scene.sim.rigid_solver.apply_links_external_force(force=force, links_idx=link_idx)
        torque = [[[0, 0, rotation_direction * 5]]]
        scene.sim.rigid_solver.apply_links_external_torque(torque=torque, links_idx=link_idx)
        scene.step()
        if (i + 50) % 100 == 0:
            rotation_direction *= -1
        if i + 1 in z_genesis:
            assert float(cube.get_pos()[0, 2]) == pytest.approx(z_genesis[i + 1], abs=2e-6)
    m = float(cube.get_mass()[0])
    assert m == pytest.approx(600.0 * 0.2 ** 3)
    I_zz = m * (0.2 ** 2 + 0.2 ** 2) / 12
    spin = 5 * N * 0.01 / I_zz  # +5 N m in every step run (the sign flips after step 50)
    np.testing.assert_allclose(_np(cube.get_ang())[0], [0.0, 0.0, spin], rtol=1e-9, atol=1e-9)
    # the spring (100 N/m) holds it near 1 - m g / k with no damping: it oscillates about there
    z = float(cube.get_pos()[0, 2])
    assert abs(z - (1.0 - m * 9.81 / 100.0)) <= m * 9.81 / 100.0 + 1e-6


@pytest.mark.slow  # an MPM scene coupled to a rigid body: ~25 s of compiles on 2 cores
def test_force_on_a_body_coupled_to_mpm_adds_its_impulse_to_the_whole_system():
    """A ball pushed by F through an elastic block (two-way coupling, zero gravity, 8 substeps a step):
    the momentum of ball + material grows by exactly F t (the coupling exchanges momentum within the
    system; the force acts during every substep of its step)."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=8, gravity=(0, 0, 0)),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.5, 0.5, 0.5),
                                                       grid_density=32))
    block = scene.add_entity(gs.morphs.Box(pos=(0.3, 0.25, 0.25), size=(0.12, 0.12, 0.12)),
                             material=gs.materials.MPM.Elastic(E=2e4, nu=0.3))
    ball = scene.add_entity(gs.morphs.Sphere(pos=(0.2, 0.25, 0.25), radius=0.04),
                            material=gs.materials.Rigid(rho=500, coup_friction=0.3))
    scene.build()
    ball.set_dofs_velocity(torch.tensor([0.5, 0.0, 0.0, 0.0, 0.0, 0.0], **F64))

    def momentum():
        return _np((block._masses()[:, None] * block.get_particles_vel()).sum(0) + ball.get_mass() * ball.get_vel())

    p0 = momentum()
    F, N = np.array([2.0, 0.5, -0.3]), 40
    for _ in range(N):
        scene.sim.rigid_solver.apply_links_external_force(F, [ball.links[0].idx])
        scene.step()
    assert np.abs(_np((block._masses()[:, None] * block.get_particles_vel()).sum(0))).max() > 0.1 * np.abs(p0).max()
    np.testing.assert_allclose(momentum() - p0, F * N * 2e-3, rtol=1e-9, atol=1e-12)


# ----------------------------------------------------------------------------------------- gradients
def _fd_check(f, x, h, n_dirs=3, seed=0, rtol=1e-6):
    """autograd's d f / d x against central differences along random directions (float64), to rtol of
    the directional derivative's scale |g| |d| (a direction may nearly cancel it)."""
    x = x.detach().clone().requires_grad_(True)
    y = f(x)
    (g,) = torch.autograd.grad(y, x)
    rng = np.random.default_rng(seed)
    for _ in range(n_dirs):
        d = torch.tensor(rng.normal(size=tuple(x.shape)), **F64)
        with torch.no_grad():
            fd = (f(x.detach() + h * d) - f(x.detach() - h * d)) / (2 * h)
        ad = float((g * d).sum())
        scale = max(abs(float(fd)), float(g.norm() * d.norm()))
        assert abs(ad - float(fd)) <= rtol * scale, (ad, float(fd), scale)
    return g


SEQ = np.random.default_rng(3)
T_GRAD = 5
FORCES = torch.tensor(SEQ.normal(size=(T_GRAD, 3)), **F64)
TORQUES = torch.tensor(0.1 * SEQ.normal(size=(T_GRAD, 3)), **F64)
V0 = torch.tensor([0.2, -0.1, 0.3, 0.5, -0.4, 0.8, 1.0, -0.5, 0.7], **F64)
WQ = torch.tensor(SEQ.normal(size=16), **F64)


def _check_applied_gradients():
    """Forces, torques, gravity compensation (its material's tensor) and the initial velocity."""
    scene = _scene(gravity=(0.0, 0.0, -9.81), requires_grad=True)
    gc0 = torch.tensor(0.3, **F64, requires_grad=True)
    tree = scene.add_entity(gs.morphs.URDF(file=SKEW_ARM, fixed=False, pos=(0.2, -0.1, 1.0)),
                            material=gs.materials.Rigid(gravity_compensation=gc0))
    scene.build()
    solver = scene.sim.rigid_solver
    l1, l2 = tree.links[1].idx, tree.links[2].idx

    def rollout(forces=FORCES, torques=TORQUES, gc=None, v=V0):
        scene.reset()
        if gc is not None:
            tree.set_gravity_compensation(gc)
        tree.set_dofs_velocity(v)
        for t in range(T_GRAD):
            solver.apply_links_external_force(forces[t], [l2], ref="link_com", local=True)
            solver.apply_links_external_torque(torques[t], [l1])
            scene.step()
        return (WQ[:10] * tree.get_qpos()).sum() + (WQ[10:] * tree.get_dofs_velocity()[:6]).sum()

    # the material's tensor: its gradient reaches the leaf, rollout after rollout (checked against finite
    # differences below, through the setter)
    grads = []
    for _ in range(2):
        gc0.grad = None
        rollout().backward()
        grads.append(float(gc0.grad))
    assert grads[0] == grads[1] != 0.0
    _fd_check(lambda x: rollout(forces=x), FORCES, 1e-6)
    _fd_check(lambda x: rollout(torques=x), TORQUES, 1e-6)
    _fd_check(lambda x: rollout(v=x), V0, 1e-6)
    g = _fd_check(lambda x: rollout(gc=x), gc0, 1e-6, n_dirs=1)
    np.testing.assert_allclose(float(g), grads[0], rtol=1e-10)


def _check_late_force_gradient():
    """Forces from step 2 on, in a scene that had no applied wrench until then: its first two steps were
    recorded without them; with checkpoints every 2 steps (backward replays steps from their inputs)."""
    scene = _scene(gravity=(0.0, 0.0, -9.81), requires_grad=True, checkpoint_every=2)
    tree = scene.add_entity(gs.morphs.URDF(file=SKEW_ARM, fixed=False, pos=(0.2, -0.1, 1.0)))
    scene.build()
    solver = scene.sim.rigid_solver

    def late(x):
        scene.reset()
        tree.set_dofs_velocity(V0)
        for t in range(T_GRAD):
            if t >= 2:
                solver.apply_links_external_force(x[t], [tree.links[2].idx])
            scene.step()
        return (WQ[:10] * tree.get_qpos()).sum()

    _fd_check(late, FORCES, 1e-6)


@pytest.mark.slow  # compiles the free tree's gradient kernels: ~18 s cold on 2 cores
def test_gradients_of_forces_gravity_compensation_and_velocity_match_finite_differences():
    """The skew arm on a free base under gravity, 5 steps: a force at link 2's centre of mass in its own axes
    (so the lever and the axes depend on the state) and a world torque on link 1 each step, tensors that
    require grad; gravity compensation a tensor that requires grad (its material's); the loss reads the
    final state. Each against central differences in float64. Then a scene whose first force comes at
    step 2 (steps recorded before the solver had applied wrenches) on the first one's core."""
    _check_applied_gradients()
    _check_late_force_gradient()
