"""Issue #10: one compile serves every robot. A scene takes its Taichi fields from a pool of field sets
of its capacity class (RigidCore, solvers/rigid/core.py) and reads its sizes at run time, so a later
scene of another robot compiles no kernel; cores reused by later scenes, or held by two scenes at
once, must give exactly the results of a fresh core.

Kernel compilations are counted by wrapping Taichi's Kernel.materialize (every kernel Taichi builds,
ours and its own field-copy kernels, goes through it)."""
import gc

import numpy as np
import pytest
import torch

import genesis_lite as gs
from solvers.rigid.pool import POOL

from conftest import ASSETS_DIR

ARM = str(ASSETS_DIR / "urdf" / "arm.urdf")  # 4 dofs
PENDULUM = str(ASSETS_DIR / "urdf" / "double_pendulum.urdf")  # 2 dofs
F64 = dict(dtype=torch.float64)


def _fresh():
    """Forget the pool's free cores: the next scene of every class allocates a new one."""
    gc.collect()
    POOL.clear()


def _scene(urdf, n_envs=0, requires_grad=False, collision=False, plane=False, check_nan=True):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=requires_grad),
                     rigid_options=gs.options.RigidOptions(enable_collision=collision, check_nan=check_nan))
    if plane:
        scene.add_entity(gs.morphs.Plane())
    robot = scene.add_entity(gs.morphs.URDF(file=urdf, fixed=True))
    scene.build(n_envs=n_envs)
    return scene, robot


def _use(scene, robot, steps=20, seed=0):
    """Everything a script does with a scene (setters, gains, PD and force control, getters, the mass
    matrix, energies); returns the trajectory of positions and the last link poses."""
    rng = np.random.default_rng(seed)
    n = robot.n_dofs
    B = (scene.n_envs,) if scene.n_envs else ()
    scene.reset()
    robot.set_dofs_kp(torch.full(B + (n,), 50.0, **F64))
    robot.set_dofs_kv(torch.full(B + (n,), 2.0, **F64))
    robot.set_dofs_damping(torch.full(B + (n,), 0.05, **F64))
    robot.set_dofs_position(torch.tensor(rng.uniform(-0.5, 0.5, B + (n,)), **F64))
    robot.control_dofs_position(torch.tensor(rng.uniform(-0.5, 0.5, B + (n,)), **F64))
    traj = []
    for t in range(steps):
        if t == steps // 2:
            robot.control_dofs_force(torch.tensor(rng.uniform(-1, 1, B + (n,)), **F64))
        scene.step()
        traj.append(robot.get_dofs_position().clone())
    M = robot.get_mass_mat()
    E = robot.get_total_energy()
    return torch.stack(traj), robot.get_links_pos().clone(), M, E


def test_second_robot_compiles_nothing(compiled):
    """A scene of another robot, built after the first one is dropped, takes the first one's core and
    compiles no kernel; its results equal those of the same scene on a fresh core."""
    a = _scene(ARM)
    _use(*a)
    del a
    gc.collect()  # the first scene dies: its core goes back to the pool
    compiled.clear()
    scene, pend = _scene(PENDULUM)
    got = _use(scene, pend)
    assert scene.rigid_solver.reused_core
    assert compiled == [], f"the second robot compiled {compiled}"
    # the same scene on a fresh core: bit-identical results
    _fresh()
    fresh, pend2 = _scene(PENDULUM)
    assert not fresh.rigid_solver.reused_core and fresh.rigid_solver.core is not scene.rigid_solver.core
    ref = _use(fresh, pend2)
    for x, y in zip(got, ref):
        torch.testing.assert_close(x, y, rtol=0, atol=0)


@pytest.mark.slow
def test_second_robot_with_gradients_compiles_nothing(compiled):
    """The gradient path too: forward, backward and parameter gradients of a second robot reuse the
    first one's kernels, and its gradients equal those of a fresh core."""

    def grads(scene, robot):
        n = robot.n_dofs
        q0 = torch.linspace(-0.4, 0.3, n, **F64).requires_grad_()
        u = torch.linspace(0.5, -0.5, 8 * n, **F64).reshape(8, n).requires_grad_()
        mass = torch.full((robot.n_links,), 1.3, **F64).requires_grad_()
        scene.reset()
        robot.set_links_mass(mass)
        robot.set_dofs_position(q0)
        for t in range(8):
            robot.control_dofs_force(u[t])
            scene.step()
        loss = (robot.get_links_pos()[-1] ** 2).sum() + (robot.get_dofs_velocity() ** 2).sum()
        loss.backward()
        return loss.detach(), q0.grad, u.grad, mass.grad

    a = _scene(ARM, requires_grad=True)
    grads(*a)
    del a
    gc.collect()  # the first scene dies: its core goes back to the pool
    compiled.clear()
    scene, pend = _scene(PENDULUM, requires_grad=True)
    got = grads(scene, pend)
    assert scene.rigid_solver.reused_core
    # nothing (the Tapes' loss is a torch token, simulator.py tape_loss: no fill kernel, no field per scene)
    assert not compiled, f"the second robot compiled {compiled}"
    _fresh()
    fresh = _scene(PENDULUM, requires_grad=True)
    assert not fresh[0].rigid_solver.reused_core
    ref = grads(*fresh)
    for x, y in zip(got, ref):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
    assert all(torch.isfinite(g).all() and g.abs().sum() > 0 for g in got[1:])


@pytest.mark.slow
def test_other_env_count_of_the_class_compiles_nothing(compiled):
    """Env counts of one capacity class (up to 16 here) share a core: 3 envs after 5."""
    a = _scene(ARM, n_envs=5)
    _use(*a)
    del a
    gc.collect()  # the first scene dies: its core goes back to the pool
    compiled.clear()
    scene, arm = _scene(ARM, n_envs=3)
    traj, pos, M, E = _use(scene, arm)
    assert scene.rigid_solver.reused_core and compiled == [], compiled
    assert traj.shape == (20, 3, arm.n_dofs) and M.shape == (3, arm.n_dofs, arm.n_dofs)
    # the same scene on a fresh core
    _fresh()
    single, arm1 = _scene(ARM, n_envs=3)
    assert not single.rigid_solver.reused_core
    ref = _use(single, arm1)
    for x, y in zip((traj, pos, M, E), ref):
        torch.testing.assert_close(x, y, rtol=0, atol=0)


def test_two_scenes_alive_at_once_are_independent():
    """Two live scenes of one class hold two cores; stepping them interleaved gives each the
    trajectory it has alone."""
    alone_arm = _use(*_scene(ARM), seed=1)
    alone_pend = _use(*_scene(PENDULUM), seed=2)
    gc.collect()  # both back in the pool: the two scenes below take them
    s1, arm = _scene(ARM)
    s2, pend = _scene(PENDULUM)
    assert s1.rigid_solver.core is not s2.rigid_solver.core
    rng1, rng2 = np.random.default_rng(1), np.random.default_rng(2)
    for s, r, rng in ((s1, arm, rng1), (s2, pend, rng2)):
        s.reset()
        n = r.n_dofs
        r.set_dofs_kp(torch.full((n,), 50.0, **F64))
        r.set_dofs_kv(torch.full((n,), 2.0, **F64))
        r.set_dofs_damping(torch.full((n,), 0.05, **F64))
        r.set_dofs_position(torch.tensor(rng.uniform(-0.5, 0.5, n), **F64))
        r.control_dofs_position(torch.tensor(rng.uniform(-0.5, 0.5, n), **F64))
    trajs = {1: [], 2: []}
    for t in range(20):
        for k, s, r, rng in ((1, s1, arm, rng1), (2, s2, pend, rng2)):
            if t == 10:
                r.control_dofs_force(torch.tensor(rng.uniform(-1, 1, r.n_dofs), **F64))
            s.step()
            trajs[k].append(r.get_dofs_position().clone())
    torch.testing.assert_close(torch.stack(trajs[1]), alone_arm[0], rtol=0, atol=0)
    torch.testing.assert_close(torch.stack(trajs[2]), alone_pend[0], rtol=0, atol=0)


@pytest.mark.slow
def test_core_of_a_diverged_scene_gives_a_clean_start():
    """A scene whose state became NaN leaves NaN in its core's fields; the next scene of the class
    (here with contacts between moving bodies, whose dense factorisation reads M outside the tree
    pattern) starts clean on that core: the same numbers as on a fresh core."""

    def boxes():
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
        scene.add_entity(gs.morphs.Plane())
        lower = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)))
        top = scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1), pos=(0.03, 0, 0.25), quat=(0.995, 0.0, 0.0, 0.1)))
        scene.build()
        assert scene.rigid_solver.dense_solve
        out = []
        for _ in range(30):
            scene.step()
            out.append(torch.cat([lower.get_qpos(), top.get_qpos()]))
        return scene, torch.stack(out)

    _fresh()
    bad, arm = _scene(ARM, check_nan=False)
    core = bad.rigid_solver.core
    # velocities of 1e200 rad/s: their squares overflow, and NaN reaches the state, M and the forces
    arm.set_dofs_velocity(torch.full((arm.n_dofs,), 1e200, **F64))
    for _ in range(5):
        bad.step()
    assert not torch.isfinite(arm.get_dofs_position()).all()
    key = bad.rigid_solver.core.key
    del bad, arm
    gc.collect()
    assert POOL.free.get(key), "the diverged scene's core went back to the pool"
    reused, traj = boxes()
    assert reused.rigid_solver.core is core
    _fresh()
    fresh, ref = boxes()
    assert not fresh.rigid_solver.reused_core
    assert torch.isfinite(traj).all()
    torch.testing.assert_close(traj, ref, rtol=0, atol=0)


def test_second_robot_over_a_plane_compiles_nothing(compiled):
    """Scenes with collision pairs: the contact kernels are pooled by contact class (capacities and
    flags) and read their sizes at run time, so a different robot over a plane, built after the first
    one is dropped, compiles no kernel; its contacts give the results of a fresh pool."""

    def pendulum():
        scene, robot = _scene(PENDULUM, collision=True, plane=True)
        scene.reset()
        robot.set_dofs_position(torch.tensor([1.2, -0.4], **F64))
        out = []
        for _ in range(60):
            scene.step()
            out.append(robot.get_dofs_position().clone())
        return scene, torch.stack(out)

    def ball():
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
        scene.add_entity(gs.morphs.Plane())
        ball = scene.add_entity(gs.morphs.Sphere(radius=0.1, pos=(0.0, 0.0, 0.3)))
        scene.build()
        ball.set_dofs_velocity(torch.tensor([1.0, 0.5, 0.0, 0.0, 0.0, 2.0], **F64))
        out = []
        for _ in range(60):
            scene.step()
            out.append(ball.get_qpos().clone())
        return scene, torch.stack(out)

    _fresh()
    first, _ = pendulum()
    assert first.rigid_solver.contact is not None
    del first
    gc.collect()  # the first scene dies: its core and contact kernels go back to the pool
    compiled.clear()
    scene, got = ball()
    assert scene.rigid_solver.reused_core
    assert compiled == [], f"the second robot compiled {compiled}"
    z = got[:, 2]
    assert z.min() > 0.09 and abs(float(z[-1]) - 0.1) < 2e-3  # it landed and rests on the plane
    _fresh()
    fresh, ref = ball()
    assert not fresh.rigid_solver.reused_core
    torch.testing.assert_close(got, ref, rtol=0, atol=0)


def _boxes_and_ball_scene(n_envs, specialize):
    """A sphere and a box landing on a plane and a box on the box (pairs plane-sphere, plane-box,
    box-box), with per-env initial velocities: (scene, its three bodies)."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01),
                     rigid_options=gs.options.RigidOptions(specialize_kernels=specialize))
    scene.add_entity(gs.morphs.Plane())
    ball = scene.add_entity(gs.morphs.Sphere(radius=0.1, pos=(0.0, 0.0, 0.3)))
    b1 = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0.6, 0.0, 0.12)))
    b2 = scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1), pos=(0.62, 0.01, 0.3)))
    scene.build(n_envs=n_envs)
    rng = np.random.default_rng(3)
    for e in (ball, b2):
        e.set_dofs_velocity(torch.tensor(rng.uniform(-1, 1, (n_envs, 6)), **F64))
    return scene, (ball, b1, b2)


def _sync_from(src, same, nudged, gen):
    """Entity src's state into `same`, and into `nudged` with its velocities changed by 1e-15 (relative,
    random): the yardstick of rounding amplified by a stiff system."""
    q, v = src.get_qpos(), src.get_dofs_velocity()
    same.set_qpos(q)
    same.set_dofs_velocity(v)
    nudged.set_qpos(q)
    nudged.set_dofs_velocity(v * (1.0 + 1e-15 * torch.randn(v.shape, generator=gen, **F64)))


def _boxes_and_ball(n_envs, specialize):
    """_boxes_and_ball_scene's scene and the trajectory of every env over 50 steps."""
    scene, bodies = _boxes_and_ball_scene(n_envs, specialize)
    out = []
    for _ in range(50):
        scene.step()
        out.append(torch.cat([b.get_qpos() for b in bodies], -1).clone())
    return scene, torch.stack(out)


@pytest.mark.slow  # an option (specialize_kernels=True) whose own compile is ~2 minutes, for the default
# suite's margin under 15 minutes; by default test_joint_limits steps a specialised core with and
# without a plane against the shared kernels
def test_specialized_kernels_give_the_shared_kernels_results():
    """RigidOptions(specialize_kernels=True) compiles the contact sizes in as constants (fields of
    exact sizes, not pooled by class) and keeps gs.init's optimisation for the fused step: the same
    model, so the same trajectory to rounding. (An env whose slots couple the two boxes factors the dense
    envelope on both; one whose slots do not factors the tree, unrolled over it in the specialised core,
    on fields in the shared one: linalg.func_tree_env. Same operations, compiled differently.) Each step is
    taken from the shared scene's state; the stiff contacts amplify rounding, so the yardstick is a third
    scene on the shared kernels whose velocities are changed by 1e-15 (relative) before each step. A
    second scene of the same sizes reuses the specialised kernels, to the bit; one of other sizes does
    not fit them."""
    _fresh()
    shared, b_shared = _boxes_and_ball_scene(3, False)
    assert not shared.rigid_solver.specialized and not shared.rigid_solver.contact.static_sizes
    spec, b_spec = _boxes_and_ball_scene(3, True)
    c = spec.rigid_solver.contact
    assert spec.rigid_solver.specialized and c.static_sizes and c.caps[2] == c.n_slots and c.dense
    nudged, b_nudged = _boxes_and_ball_scene(3, False)
    gen = torch.Generator().manual_seed(0)
    err, ref = [], []

    def gap(bodies):
        return max(max(float((x.get_qpos() - y.get_qpos()).abs().max()),
                       float((x.get_dofs_velocity() - y.get_dofs_velocity()).abs().max()))
                   for x, y in zip(bodies, b_shared))

    for _ in range(50):
        for x, y, z in zip(b_shared, b_spec, b_nudged):
            _sync_from(x, y, z, gen)
        for scene in (shared, spec, nudged):
            scene.step()
        err.append(gap(b_spec))
        ref.append(gap(b_nudged))
    assert float(b_shared[0].get_qpos()[:, 2].min()) > 0.05  # the ball rests on the plane, not below it
    # the small box rests on the big one in env 0 (its slots couple them: the dense factor) and falls off it
    # onto the plane in the others (the tree's)
    z2 = b_shared[2].get_qpos()[:, 2]
    assert float(z2[0]) > 0.2 and float(z2[1:].max()) < 0.1, z2
    # measured 2026-12-02: the specialised scene up to 1.0e-11 away (median 4e-24), the nudged one 8.0e-11
    # (median 1.7e-12)
    assert max(ref) > 1e-13, max(ref)
    assert max(err) < 10.0 * max(ref), (max(err), max(ref))
    assert np.median(err) < 10.0 * np.median(ref) + 1e-13, (np.median(err), np.median(ref))
    del spec, b_spec
    gc.collect()
    first, got = _boxes_and_ball(3, True)
    del first
    gc.collect()
    again, got2 = _boxes_and_ball(3, True)
    assert again.rigid_solver.reused_core
    torch.testing.assert_close(got2, got, rtol=0, atol=0)
    # other sizes (one box fewer): the specialised SceneCore above does not fit, a new one is made
    scene = gs.Scene(rigid_options=gs.options.RigidOptions(specialize_kernels=True))
    scene.add_entity(gs.morphs.Plane())
    scene.add_entity(gs.morphs.Sphere(radius=0.1, pos=(0.0, 0.0, 0.3)))
    scene.build(n_envs=3)
    assert scene.rigid_solver.contact is not c


def _quadruped(urdf, n_envs, specialize):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01),
                     rigid_options=gs.options.RigidOptions(specialize_kernels=specialize))
    scene.add_entity(gs.morphs.Plane())
    robot = scene.add_entity(gs.morphs.URDF(file=urdf, fixed=False, pos=(0.0, 0.0, 0.62)))
    scene.build(n_envs=n_envs)
    dofs = [j.dof_start_local for j in robot.joints if j.n_dofs == 1]
    robot.set_dofs_kp(torch.full((len(dofs),), 300.0, **F64), dofs)
    robot.set_dofs_kv(torch.full((len(dofs),), 10.0, **F64), dofs)
    return scene, robot, dofs


# slow (suite time, ~40 s: a specialised compile of its own); test_specialized_kernels_give_the_shared_kernels_results
# keeps the specialised path in the default suite
@pytest.mark.slow
def test_specialized_tree_factorisation_gives_the_shared_kernels_results(urdf_path):
    """A specialised scene without gradients unrolls the factorisations and solves of its contact solve
    over its dof tree (inertia.TreeSchedule, contact.func_contact_rounds); the shared kernels loop
    over the tree on fields. Same operations in the same order, compiled differently, so the same
    results to rounding. ANYmal dropped onto the ground, its PD targets jumping by up to 0.5 rad every
    0.3 s per env (feet land, slide and lift off: every round of the contact solve runs), each step
    taken from the shared scene's state. The stiff contact system amplifies rounding, so the yardstick is a third scene on the shared kernels whose
    velocities are changed by 1e-15 (relative) before each step: the specialised scene must stay as
    close to the shared one as that, where a wrong factorisation or round order is off by far more."""
    _fresh()
    urdf = str(urdf_path("anymal"))
    shared, r_shared, dofs = _quadruped(urdf, 3, False)
    spec, r_spec, _ = _quadruped(urdf, 3, True)
    nudged, r_nudged, _ = _quadruped(urdf, 3, False)
    assert not shared.rigid_solver.step_core.unrolled
    assert spec.rigid_solver.step_core.unrolled and not spec.rigid_solver.contact.dense
    rng = np.random.default_rng(5)
    gen = torch.Generator().manual_seed(0)
    err, ref, q_first = [], [], r_shared.get_qpos().clone()

    def gap(r):
        return max(float((r.get_qpos() - r_shared.get_qpos()).abs().max()),
                   float((r.get_dofs_velocity() - r_shared.get_dofs_velocity()).abs().max()))

    for i in range(150):
        if i % 30 == 0:
            target = torch.tensor(rng.uniform(-0.5, 0.5, (3, len(dofs))), **F64)
            for r in (r_shared, r_spec, r_nudged):
                r.control_dofs_position(target, dofs)
        _sync_from(r_shared, r_spec, r_nudged, gen)
        for scene in (shared, spec, nudged):
            scene.step()
        err.append(gap(r_spec))
        ref.append(gap(r_nudged))
    q = r_shared.get_qpos()
    assert torch.isfinite(q).all() and float(q[:, 2].min()) > 0.1  # it stands, stumbling
    assert float((q - q_first).abs().max()) > 0.05  # and moves
    # the yardstick: rounding is amplified on this rollout (measured 2026-11-28 with the default
    # approximate_implicitfast: the nudged scene up to 8.2e-12 away, the specialised one 1.8e-11; medians
    # 2.3e-13 / 2.0e-13)
    assert max(ref) > 1e-12
    assert max(err) < 10.0 * max(ref), (max(err), max(ref))
    assert np.median(err) < 10.0 * np.median(ref) + 1e-13, (np.median(err), np.median(ref))


def test_batched_scenes_specialize_by_default():
    """The default (None) specialises from SPECIALIZE_MIN_ENVS envs on, where the step's run time
    outweighs the compile; smaller scenes share kernels."""
    from solvers.rigid.solver import SPECIALIZE_MIN_ENVS

    for n_envs, want in ((0, False), (4, False), (SPECIALIZE_MIN_ENVS, True)):
        scene = gs.Scene(rigid_options=gs.options.RigidOptions(enable_collision=False))
        scene.add_entity(gs.morphs.URDF(file=PENDULUM, fixed=True))
        scene.build(n_envs=n_envs)
        assert scene.rigid_solver.specialized == want, n_envs


def test_specialize_kernels_rejects_other_values():
    with pytest.raises(ValueError, match="specialize_kernels"):
        gs.options.RigidOptions(specialize_kernels="yes")
