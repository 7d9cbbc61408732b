"""Issue #3: end-to-end gradients through the rigid solver with ordinary torch autograd.

Every differentiable input and output kind is checked against central finite differences in
float64 (gs.grad.check) on smooth scenes (nothing in contact) built with the default options
(collision and joint limits on): a fixed-base arm, a floating-base body and batched environments.
Tolerance: relative error <= 1e-6, as the issue asks. tests/test_gradient_matrix.py covers contact,
MPM and coupling.
"""
import math

import numpy as np
import pytest
import torch

import genesis_lite as gs
from genesis_lite.errors import GenesisException

from conftest import ASSETS_DIR

ARM = str(ASSETS_DIR / "urdf" / "arm.urdf")
TOL = 1e-6
F64 = dict(dtype=torch.float64)


def make_scene(n_envs=0, integrator=None, substeps=1, checkpoint_every=None, dt=0.01):
    return gs.Scene(  # the default options unless an integrator is given: collision and limits on
        sim_options=gs.options.SimOptions(dt=dt, substeps=substeps, requires_grad=True, checkpoint_every=checkpoint_every),
        rigid_options=gs.options.RigidOptions(**({} if integrator is None else {"integrator": integrator})),
    )


def arm_scene(n_envs=0, **kw):
    scene = make_scene(**kw)
    arm = scene.add_entity(gs.morphs.URDF(file=ARM, fixed=True))
    scene.build(n_envs=n_envs)
    big = torch.full((arm.n_dofs,), 1e6, **F64)
    arm.set_dofs_force_range(-big, big)  # no saturation kinks in the rollouts below
    return scene, arm


def free_scene():
    scene = make_scene()
    box = scene.add_entity(gs.morphs.Box(size=(0.3, 0.2, 0.1), pos=(0.0, 0.0, 1.0)))
    scene.build()
    return scene, box


def assert_ok(report):
    print(report)
    assert report.ok, str(report)


@pytest.fixture(scope="module")
def arm_env():
    return arm_scene()


# ----------------------------------------------------------------------------- initial state
@pytest.mark.parametrize("integrator", [None, gs.integrator.Euler, gs.integrator.implicitfast, gs.integrator.RK4])
def test_initial_state_and_force_controls(integrator):
    scene, arm = arm_scene(integrator=integrator)
    n, T = arm.n_dofs, 12
    rng = np.random.default_rng(0)

    def rollout(q0, v0, forces):
        scene.reset()
        arm.set_dofs_position(q0)
        arm.set_dofs_velocity(v0)
        for t in range(T):
            arm.control_dofs_force(forces[t])
            scene.step()
        return (arm.get_links_pos()[-1] ** 2).sum() + 0.1 * (arm.get_dofs_velocity() ** 2).sum()

    assert_ok(gs.grad.check(rollout, {"q0": torch.tensor(rng.uniform(-1, 1, n)), "v0": torch.tensor(rng.uniform(-1, 1, n)),
                                       "forces": torch.tensor(rng.uniform(-3, 3, (T, n)))}, tol=TOL))


def test_position_and_velocity_controls_and_gains(arm_env):
    scene, arm = arm_env
    n, T = arm.n_dofs, 10
    rng = np.random.default_rng(1)

    def rollout(q_targets, v_targets, kp, kv):
        scene.reset()
        arm.set_dofs_kp(kp)
        arm.set_dofs_kv(kv)
        for t in range(T):
            if t < T // 2:
                arm.control_dofs_position(q_targets[t])
            else:
                arm.control_dofs_velocity(v_targets[t])
            scene.step()
        return (arm.get_links_pos() ** 2).sum() + (arm.get_dofs_position() ** 2).sum()

    assert_ok(gs.grad.check(rollout, {
        "q_targets": torch.tensor(rng.uniform(-1, 1, (T, n))), "v_targets": torch.tensor(rng.uniform(-1, 1, (T, n))),
        "kp": torch.tensor(rng.uniform(20, 60, n)), "kv": torch.tensor(rng.uniform(1, 5, n))}, tol=TOL))


def test_physical_parameters(arm_env):
    scene, arm = arm_env
    n, L, T = arm.n_dofs, arm.n_links, 10
    rng = np.random.default_rng(2)
    q0 = torch.tensor(rng.uniform(-1, 1, n))
    mass0 = arm.get_links_mass().detach().clone()
    inertia0 = arm.get_links_inertia().detach().clone()
    com0 = arm.get_links_COM().detach().clone()

    def rollout(mass, inertia, com, damping, armature, gravity):
        scene.reset()
        arm.set_links_mass(mass)
        arm.set_links_inertia(inertia)
        arm.set_links_COM(com)
        arm.set_dofs_damping(damping)
        arm.set_dofs_armature(armature)
        scene.set_gravity(gravity)
        arm.set_dofs_position(q0)
        for _ in range(T):
            scene.step()
        return (arm.get_links_pos() ** 2).sum() + (arm.get_links_vel() ** 2).sum()

    assert_ok(gs.grad.check(rollout, {
        "mass": mass0 * 1.1, "inertia": inertia0 * 1.2, "com": com0 + 0.01,
        "damping": torch.tensor(rng.uniform(0.1, 1.0, n)), "armature": torch.tensor(rng.uniform(0.01, 0.1, n)),
        "gravity": torch.tensor([0.5, -0.3, -9.81], **F64)}, tol=TOL))
    # leave the module scene as it was
    scene.reset()
    arm.set_links_mass(mass0)
    arm.set_links_inertia(inertia0)
    arm.set_links_COM(com0)
    scene.set_gravity(torch.tensor([0.0, 0.0, -9.81]))


def test_friction_loss_gradient_at_zero_and_above(arm_env):
    """The friction loss -fl tanh(v / 0.01) (set_dofs_frictionloss) is differentiable in fl: above 0 against
    central differences, and at fl = 0 (where a loss-free joint starts an identification) against the
    second-order one-sided difference (-3 f(0) + 4 f(h) - f(2h)) / 2h, as a negative friction loss is
    refused. Until 2026-12-01 the gradient path skipped the tanh where fl = 0 and gave 0 there."""
    scene, arm = arm_env
    n, T = arm.n_dofs, 10
    rng = np.random.default_rng(5)
    q0 = torch.tensor(rng.uniform(-1, 1, n))
    v0 = torch.tensor(rng.normal(0, 0.5, n))

    def rollout(frictionloss):
        scene.reset()
        arm.set_dofs_frictionloss(frictionloss)
        arm.set_dofs_position(q0)
        arm.set_dofs_velocity(v0)
        for _ in range(T):
            scene.step()
        return (arm.get_links_pos() ** 2).sum() + (arm.get_links_vel() ** 2).sum()

    try:
        assert_ok(gs.grad.check(rollout, {"frictionloss": torch.tensor(rng.uniform(0.05, 0.3, n))}, tol=TOL))
        zero = torch.zeros(n, **F64, requires_grad=True)
        rollout(zero).backward()
        h = 1e-5
        with torch.no_grad():
            f0 = rollout(torch.zeros(n, **F64)).item()
            for i in range(n):
                e = torch.zeros(n, **F64)
                e[i] = h
                fd = (-3.0 * f0 + 4.0 * rollout(e).item() - rollout(2.0 * e).item()) / (2.0 * h)
                assert abs(fd) > 1e-3, (i, fd)  # the friction loss does act on every joint here
                assert abs(zero.grad[i].item() - fd) <= 1e-6 * abs(fd), (i, zero.grad[i].item(), fd)
    finally:
        scene.reset()
        arm.set_dofs_frictionloss(torch.zeros(n, **F64))


def test_every_output_kind_at_several_steps(arm_env):
    scene, arm = arm_env
    n = arm.n_dofs
    rng = np.random.default_rng(3)
    w = {k: torch.tensor(rng.normal(size=s)) for k, s in [("lp", (arm.n_links, 3)), ("lq", (arm.n_links, 4)),
                                                          ("lv", (arm.n_links, 3)), ("la", (arm.n_links, 3))]}

    def rollout(q0, v0):
        scene.reset()
        arm.set_dofs_position(q0)
        arm.set_dofs_velocity(v0)
        loss = 0.0
        for t in range(9):
            scene.step()
            if t % 3 == 0:
                loss = loss + (w["lp"] * arm.get_links_pos()).sum() + (w["lq"] * arm.get_links_quat()).sum()
                loss = loss + (w["lv"] * arm.get_links_vel()).sum() + (w["la"] * arm.get_links_ang()).sum()
                loss = loss + arm.get_pos().sum() + arm.get_quat()[1:].sum() + arm.get_vel().sum() + arm.get_ang().sum()
                loss = loss + (arm.get_dofs_position() * arm.get_dofs_velocity()).sum() + arm.get_qpos().pow(2).sum()
        return loss

    assert_ok(gs.grad.check(rollout, {"q0": torch.tensor(rng.uniform(-1, 1, n)),
                                       "v0": torch.tensor(rng.uniform(-1, 1, n))}, tol=TOL))


# ----------------------------------------------------------------------------- floating base
def test_floating_base_pose_setters_and_getters():
    scene, box = free_scene()
    rng = np.random.default_rng(4)

    def rollout(pos, quat, v0):
        scene.reset()
        box.set_pos(pos)
        box.set_quat(quat)
        box.set_dofs_velocity(v0)
        loss = 0.0
        for t in range(8):
            scene.step()
        loss = loss + (box.get_pos() ** 2).sum() + (box.get_quat() * torch.tensor([0.3, -1.0, 0.5, 2.0], **F64)).sum()
        loss = loss + (box.get_vel() ** 2).sum() + (box.get_ang() * torch.tensor([1.0, 2.0, 3.0], **F64)).sum()
        return loss

    q = torch.tensor(rng.normal(size=4))
    assert_ok(gs.grad.check(rollout, {"pos": torch.tensor([0.1, -0.2, 1.0], **F64), "quat": q / q.norm(),
                                       "v0": torch.tensor(rng.uniform(-2, 2, 6))}, tol=TOL))


def test_floating_base_set_qpos_and_force():
    scene, box = free_scene()
    rng = np.random.default_rng(5)

    def rollout(qpos, forces):
        scene.reset()
        box.set_qpos(qpos)
        for t in range(6):
            box.control_dofs_force(forces[t])
            scene.step()
        return (box.get_qpos() ** 2).sum() + (box.get_dofs_velocity() ** 2).sum()

    qpos = torch.tensor([0.0, 0.1, 1.0, 0.9, 0.1, -0.2, 0.3], **F64)
    assert_ok(gs.grad.check(rollout, {"qpos": qpos, "forces": torch.tensor(rng.uniform(-5, 5, (6, 6)))}, tol=TOL))


def test_floating_base_quadruped_free_fall():
    """A real floating-base robot (go2) in free fall, joints under force control."""
    from conftest import robot_urdf

    scene = make_scene()
    go2 = scene.add_entity(gs.morphs.URDF(file=str(robot_urdf("go2")), pos=(0, 0, 1.0)))
    scene.build()
    rng = np.random.default_rng(6)
    n = go2.n_dofs
    joints = list(range(6, n))

    def rollout(q_joints, tau):
        scene.reset()
        go2.set_dofs_position(q_joints, dofs_idx_local=joints)
        for t in range(5):
            go2.control_dofs_force(tau[t], dofs_idx_local=joints)
            scene.step()
        return (go2.get_links_pos() ** 2).sum() + (go2.get_quat() ** 3).sum()

    # eps 1e-4: the torques' gradient is ~3e-3 (the default armature, 0.1, on light legs), and central
    # differences at 1e-6 are round-off bound there (rel. 2.8e-6); at 1e-4 their truncation error is ~1e-8
    assert_ok(gs.grad.check(rollout, {"q_joints": torch.tensor(rng.uniform(-0.5, 0.5, n - 6)),
                                       "tau": torch.tensor(rng.uniform(-2, 2, (5, n - 6)))}, eps=1e-4, tol=TOL))


# ----------------------------------------------------------------------------- batched
def test_batched_environments_each_get_their_own_gradient():
    scene, arm = arm_scene(n_envs=3)
    n = arm.n_dofs
    rng = np.random.default_rng(7)
    weights = torch.tensor([1.0, 2.0, 0.0], **F64)  # env 2 does not enter the loss

    def rollout(q0, forces):
        scene.reset()
        arm.set_dofs_position(q0)
        for t in range(6):
            arm.control_dofs_force(forces[t])
            scene.step()
        return ((arm.get_links_pos()[:, -1] ** 2).sum(-1) * weights).sum()

    q0 = torch.tensor(rng.uniform(-1, 1, (3, n)))
    forces = torch.tensor(rng.uniform(-2, 2, (6, 3, n)))
    r = gs.grad.check(rollout, {"q0": q0, "forces": forces}, tol=TOL)
    assert_ok(r)
    g_q0 = r.autograd[0]
    assert torch.all(g_q0[2] == 0) and g_q0[0].abs().sum() > 0 and g_q0[1].abs().sum() > 0
    # env 1 alone (weight 2 vs weight 1) is not a copy of env 0: independent inputs give independent gradients
    assert not torch.allclose(g_q0[0], g_q0[1] / 2)


# ----------------------------------------------------------------------------- autograd semantics
def test_loss_backward_and_autograd_grad_agree(arm_env):
    scene, arm = arm_env
    n, T = arm.n_dofs, 8
    q0 = torch.linspace(-0.5, 0.5, n, **F64).requires_grad_()
    u = torch.zeros(T, n, **F64, requires_grad=True)

    def run():
        scene.reset()
        arm.set_dofs_position(q0)
        loss = 0.0
        for t in range(T):
            arm.control_dofs_force(u[t])
            scene.step()
            loss = loss + (arm.get_links_pos()[-1] ** 2).sum()  # a loss summed over many steps
        return loss

    loss = run()
    assert isinstance(arm.get_pos(), gs.grad.Tensor)
    loss.backward()
    g1 = (q0.grad.clone(), u.grad.clone())
    q0.grad = None
    u.grad = None
    g2 = torch.autograd.grad(run(), [q0, u])
    assert torch.equal(g1[0], g2[0]) and torch.equal(g1[1], g2[1])
    assert g1[0].abs().sum() > 0 and g1[1].abs().sum() > 0


def test_torch_policy_in_the_loop(arm_env):
    scene, arm = arm_env
    n = arm.n_dofs
    torch.manual_seed(0)
    policy = torch.nn.Sequential(torch.nn.Linear(2 * n, 8), torch.nn.Tanh(), torch.nn.Linear(8, n)).double()
    flat0 = torch.nn.utils.parameters_to_vector(policy.parameters()).detach()
    q0 = torch.linspace(-0.6, 0.6, n, **F64)

    def rollout(flat):
        torch.nn.utils.vector_to_parameters(flat, policy.parameters())
        # rebuild the parameters as functions of `flat` so autograd sees them
        params, i = [], 0
        for p in policy.parameters():
            params.append(flat[i:i + p.numel()].view_as(p))
            i += p.numel()
        scene.reset()
        arm.set_dofs_position(q0)
        for _ in range(8):
            obs = torch.cat([arm.get_dofs_position(), arm.get_dofs_velocity()])
            h = torch.tanh(obs @ params[0].T + params[1])
            arm.control_dofs_force(5.0 * (h @ params[2].T + params[3]))
            scene.step()
        return (arm.get_links_pos()[-1] ** 2).sum()

    assert_ok(gs.grad.check(rollout, {"policy": flat0}, tol=TOL))


def test_checkpointing_gives_identical_gradients_with_bounded_storage():
    results = {}
    for every in (None, 4):
        scene, arm = arm_scene(checkpoint_every=every)
        n, T = arm.n_dofs, 23
        q0 = torch.linspace(-0.5, 0.5, n, **F64).requires_grad_()
        u = torch.linspace(-1, 1, T * n, **F64).reshape(T, n).requires_grad_()
        scene.reset()
        arm.set_dofs_position(q0)
        loss = 0.0
        for t in range(T):
            arm.control_dofs_force(u[t])
            scene.step()
            if t % 5 == 0:
                loss = loss + arm.get_links_pos().pow(2).sum()
        loss.backward()
        results[every] = (q0.grad, u.grad)
        if every:
            buf = scene._simulator.buffer
            assert len(buf.checkpoints) == math.ceil((T + 1) / every)
            assert buf.n_replayed > 0
    assert torch.equal(results[None][0], results[4][0]) and torch.equal(results[None][1], results[4][1])


def test_substeps_and_long_horizon_gradient():
    scene, arm = arm_scene(substeps=3, integrator=gs.integrator.Euler)
    n = arm.n_dofs
    rng = np.random.default_rng(8)

    def rollout(q0):
        scene.reset()
        arm.set_dofs_position(q0)
        for _ in range(40):
            scene.step()
        return arm.get_links_pos()[-1].sum()

    assert_ok(gs.grad.check(rollout, {"q0": torch.tensor(rng.uniform(-1, 1, n))}, tol=TOL))


def test_chain_longer_than_taichis_default_autodiff_stack(tmp_path):
    """A 40-link chain, longer than the 32 entries Taichi gives an autodiff stack by default (it checks
    the stack in no mode; this gradient was once NaN). Initial positions and velocities, joint
    torques, eight steps."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_chain", ASSETS_DIR / "make_chain.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    urdf = tmp_path / "chain40.urdf"
    urdf.write_text(mod.make_chain(40))
    scene = make_scene(integrator=gs.integrator.Euler, dt=0.002)
    chain = scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=True))
    scene.build()
    assert chain.n_dofs == 40
    rng = np.random.default_rng(40)
    w = torch.tensor([1.0, -0.5, 2.0], **F64)

    def rollout(q0, v0, f):
        scene.reset()
        chain.set_dofs_position(q0)
        chain.set_dofs_velocity(v0)
        for _ in range(8):
            chain.control_dofs_force(f)
            scene.step()
        return (chain.get_links_pos()[-1] * w).sum() + chain.get_links_pos()[20, 0]

    inputs = {"q0": torch.tensor(rng.uniform(-0.3, 0.3, 40)), "v0": torch.tensor(rng.uniform(-1, 1, 40)),
              "force": torch.tensor(rng.uniform(-0.05, 0.05, 40))}
    # eps 1e-4: with the default armature (0.1 on every joint) the torques' gradient is ~1e-3 of q0's, and
    # central differences at 1e-6 are round-off bound there (rel. 1.1e-5; at 1e-4: 1.4e-7, 1e-3: 1.3e-8)
    assert_ok(gs.grad.check(rollout, inputs, eps=1e-4, tol=TOL))


def test_no_grad_reads_are_not_tracked(arm_env):
    scene, arm = arm_env
    q0 = torch.zeros(arm.n_dofs, **F64, requires_grad=True)
    scene.reset()
    arm.set_dofs_position(q0)
    scene.step()
    with torch.no_grad():
        p = arm.get_links_pos()
    assert not p.requires_grad
    assert arm.get_links_pos().requires_grad


# ----------------------------------------------------------------------------- bad input
def test_requires_grad_input_to_a_non_grad_scene_raises():
    scene = gs.Scene(sim_options=gs.options.SimOptions(requires_grad=False))
    arm = scene.add_entity(gs.morphs.URDF(file=ARM, fixed=True))
    scene.build()
    with pytest.raises(GenesisException, match="requires_grad=True"):
        arm.set_dofs_position(torch.zeros(arm.n_dofs, **F64, requires_grad=True))
    with pytest.raises(GenesisException, match="requires_grad=True"):
        arm.control_dofs_force(torch.zeros(arm.n_dofs, **F64, requires_grad=True))


def test_control_of_wrong_shape_raises(arm_env):
    scene, arm = arm_env
    scene.reset()
    with pytest.raises(GenesisException, match="shape"):
        arm.control_dofs_force(torch.zeros(arm.n_dofs + 1, **F64, requires_grad=True))
    with pytest.raises(GenesisException, match="shape"):
        arm.control_dofs_force(torch.zeros(2, arm.n_dofs, **F64))


def test_backward_after_reset_raises(arm_env):
    scene, arm = arm_env
    q0 = torch.zeros(arm.n_dofs, **F64, requires_grad=True)
    scene.reset()
    arm.set_dofs_position(q0)
    scene.step()
    loss = arm.get_links_pos().sum()
    scene.reset()
    with pytest.raises(GenesisException, match="reset"):
        loss.backward()


def test_second_backward_and_step_after_backward_raise(arm_env):
    scene, arm = arm_env
    q0 = torch.zeros(arm.n_dofs, **F64, requires_grad=True)
    scene.reset()
    arm.set_dofs_position(q0)
    scene.step()
    loss = arm.get_links_pos().sum()
    loss.backward()
    with pytest.raises(RuntimeError, match="second time"):
        loss.backward()
    with pytest.raises(GenesisException, match="scene.reset"):
        scene.step()
    scene.reset()
    scene.step()  # a new rollout is fine


def test_parameter_on_wrong_device_or_dtype_raises(arm_env):
    scene, arm = arm_env
    scene.reset()
    with pytest.raises(GenesisException, match="device"):
        arm.set_dofs_kp(torch.ones(arm.n_dofs, device="meta"))
    with pytest.raises(GenesisException, match="dtype"):
        arm.set_dofs_kp(torch.ones(arm.n_dofs, dtype=torch.bool))
    with pytest.raises(GenesisException, match="dtype"):
        arm.set_links_mass(torch.ones(arm.n_links, dtype=torch.complex128))


def test_nan_gradient_raises(arm_env):
    scene, arm = arm_env
    q0 = torch.zeros(arm.n_dofs, **F64, requires_grad=True)
    scene.reset()
    arm.set_dofs_position(q0)
    scene.step()
    # d sqrt(x)/dx at x = 0 is infinite: the NaN/inf enters the simulation's backward pass
    loss = torch.sqrt(arm.get_dofs_velocity()[0] * 0.0)
    with pytest.raises(GenesisException, match="NaN or infinite"):
        loss.backward()


def test_parameters_across_rollouts(arm_env):
    """A leaf parameter set once keeps receiving gradients rollout after rollout; a parameter
    computed anew each rollout (e.g. exp of a log-parameter) works too."""
    scene, arm = arm_env
    mass0 = arm.get_links_mass().detach().clone()
    leaf = (mass0 * 1.1).requires_grad_()
    log_damping = torch.zeros(arm.n_dofs, **F64, requires_grad=True)
    arm.set_links_mass(leaf)
    grads = []
    for _ in range(3):
        scene.reset()
        arm.set_dofs_damping(log_damping.exp())
        arm.set_dofs_position(torch.full((arm.n_dofs,), 0.3, **F64))
        for _ in range(5):
            scene.step()
        loss = arm.get_links_pos().pow(2).sum()
        leaf.grad = None
        log_damping.grad = None
        loss.backward()
        grads.append((leaf.grad.clone(), log_damping.grad.clone()))
    for g_leaf, g_damp in grads[1:]:
        assert torch.equal(g_leaf, grads[0][0]) and torch.equal(g_damp, grads[0][1])
    assert grads[0][0][1:].abs().sum() > 0 and grads[0][1].abs().sum() > 0
    scene.reset()
    arm.set_links_mass(mass0)
    arm.set_dofs_damping(torch.zeros(arm.n_dofs, **F64))


# ----------------------------------------------------------------------------- clearing the adjoints
@pytest.mark.parametrize("integrator", [None, gs.integrator.RK4])
def test_clearing_only_the_inputs_adjoints_gives_the_full_clears_gradients(integrator):
    """RigidSolver.clear_grads zeroes the per-evaluation scratch's adjoints only when they may not be zero already:
    after a backward every one of them is exactly zero (the written-out adjoints zero what they read, after the
    contact stages' adjoints added to them), and a rollout's gradients with the light clear are those with every
    clear full, to the bit. The skewed arm on a free base, its base 4 mm into a plane and moving down (contacts at
    every step), 3 envs, PD control towards targets, gradients to the start velocities, the targets and the gains, a loss
    on the links' poses and velocities at every step."""
    from gradient_cases import URDF_DIR
    scene = make_scene(integrator=integrator)
    scene.add_entity(gs.morphs.Plane())
    arm = scene.add_entity(gs.morphs.URDF(file=str(URDF_DIR / "skew_arm.urdf"), fixed=False, pos=(0.0, 0.0, -0.004)))
    scene.build(n_envs=3)
    solver = scene.rigid_solver
    rng = np.random.default_rng(11)
    v0 = torch.tensor(rng.uniform(-1.0, 1.0, (3, arm.n_dofs)), **F64)
    v0[:, 2] = -0.3
    target = torch.tensor(rng.uniform(-0.5, 0.5, (3, arm.n_dofs - 6)), **F64)
    kp = torch.tensor(rng.uniform(20.0, 80.0, (3, arm.n_dofs - 6)), **F64)
    hinges = list(range(6, arm.n_dofs))
    clears = []
    kernel = solver.step_core.kernel_clear_grads
    solver.step_core.kernel_clear_grads = lambda scratch: (clears.append(scratch), kernel(scratch))[1]

    def gradients(light):
        solver.light_clear = light
        leaves = [x.clone().requires_grad_() for x in (v0, target, kp)]
        scene.reset()
        arm.set_dofs_velocity(leaves[0])
        arm.set_dofs_kp(leaves[2], dofs_idx_local=hinges)
        arm.control_dofs_position(leaves[1], dofs_idx_local=hinges)
        loss = 0.0
        for _ in range(4):
            scene.step()
            loss = loss + (arm.get_links_pos() ** 2).sum() + 0.1 * (arm.get_links_vel() ** 2).sum()
            assert (arm.get_links_pos()[:, 0, 2] > -0.006).all()  # held up by the plane (falling: below -0.0079)
        del clears[:]
        loss.backward()
        for g in solver.core.scratch_grads:
            assert np.all(g.to_numpy() == 0.0), g  # nothing left for the next backward to find
        return [x.grad for x in leaves], list(clears)

    full, full_clears = gradients(False)
    light, light_clears = gradients(True)
    assert solver.contact is not None and all(full_clears) and not any(light_clears)
    for a, b in zip(full, light):
        assert a.abs().max() > 0 and torch.equal(a, b)
