"""No silent gradient failure modes.

1. A NaN or inf in any setter's values is refused at the call, with the entity, the quantity and what
   to do, whether or not the tensor requires grad (before, a tensor that required grad skipped the
   check: the error came steps later and blamed divergence, or an inf force was clipped silently).
   Finite values that require grad keep their autograd history.
2. A backward pass that amplifies the gradient of the state by more than
   genesis_lite.grad.growth.GROWTH_WARN_FACTOR (1e6) over a window of steps warns once, naming the
   window: a chaotic double pendulum over 1,000 RK4 steps does; a Panda under PD control and a small
   swing of the same pendulum over 100 steps do not, nor does a loss whose weights fall by orders of
   magnitude over the rollout (the watch measures how the dynamics propagate the gradient, not how
   the loss weights it).
3. A PD target on dofs whose gain is 0 (the default) warns once per entity and set of dofs.
"""
from __future__ import annotations

import math
import re
import warnings

import numpy as np
import pytest
import torch

import genesis_lite as gs
from genesis_lite.errors import GenesisException, GradientGrowthWarning, ZeroGainWarning
from genesis_lite.grad import growth

from conftest import ASSETS_DIR, robot_urdf

F64 = dict(dtype=torch.float64)
ARM = str(ASSETS_DIR / "urdf" / "arm.urdf")
PENDULUM = str(ASSETS_DIR / "urdf" / "double_pendulum.urdf")
NAN, INF = float("nan"), float("inf")


def _grad_scene(**rigid):
    return gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True),
                    rigid_options=gs.options.RigidOptions(**rigid))


def _bad(shape, value, leaf):
    """A tensor that requires grad with one NaN / inf entry: a leaf, or computed from a finite leaf."""
    x = torch.full(shape, 0.5, **F64)
    x.view(-1)[-1] = value
    if leaf:
        return x.requires_grad_()
    w = torch.full(shape, 0.5, **F64, requires_grad=True)
    return w * 0.0 + x  # NaN * 0 stays NaN: the value is bad and it is not a leaf


# --------------------------------------------------------------------------- 1. NaN / inf in setters
@pytest.fixture(scope="module")
def arm_and_box():
    # no collision: a scene with contact kernels alive in the process makes the next ones compile anew
    scene = _grad_scene(enable_collision=False)
    arm = scene.add_entity(gs.morphs.URDF(file=ARM, fixed=True), name="arm")
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(1.0, 0.0, 1.0)), name="box")
    scene.build()
    return scene, arm, box


RIGID_SETTERS = {
    # name: (call(scene, arm, box, values), shape(arm, box), owner, quantity in the message)
    "set_dofs_position": (lambda s, a, b, x: a.set_dofs_position(x), lambda a, b: (a.n_dofs,), "arm", "position"),
    "set_dofs_velocity": (lambda s, a, b, x: a.set_dofs_velocity(x), lambda a, b: (a.n_dofs,), "arm", "velocity"),
    "set_qpos": (lambda s, a, b, x: a.set_qpos(x), lambda a, b: (a.n_qs,), "arm", "qpos"),
    "set_pos": (lambda s, a, b, x: b.set_pos(x), lambda a, b: (3,), "box", "pos"),
    "set_quat": (lambda s, a, b, x: b.set_quat(x), lambda a, b: (4,), "box", "quat"),
    "control_dofs_force": (lambda s, a, b, x: a.control_dofs_force(x), lambda a, b: (a.n_dofs,), "arm", "force"),
    "control_dofs_position": (lambda s, a, b, x: a.control_dofs_position(x), lambda a, b: (a.n_dofs,), "arm",
                              "position target"),
    "control_dofs_velocity": (lambda s, a, b, x: a.control_dofs_velocity(x), lambda a, b: (a.n_dofs,), "arm",
                              "velocity target"),
    "set_dofs_kp": (lambda s, a, b, x: a.set_dofs_kp(x), lambda a, b: (a.n_dofs,), "arm", "kp"),
    "set_dofs_kv": (lambda s, a, b, x: a.set_dofs_kv(x), lambda a, b: (a.n_dofs,), "arm", "kv"),
    "set_dofs_damping": (lambda s, a, b, x: a.set_dofs_damping(x), lambda a, b: (a.n_dofs,), "arm", "damping"),
    "set_dofs_armature": (lambda s, a, b, x: a.set_dofs_armature(x), lambda a, b: (a.n_dofs,), "arm", "armature"),
    "set_dofs_frictionloss": (lambda s, a, b, x: a.set_dofs_frictionloss(x), lambda a, b: (a.n_dofs,), "arm",
                              "frictionloss"),
    "set_dofs_stiffness": (lambda s, a, b, x: a.set_dofs_stiffness(x), lambda a, b: (a.n_dofs,), "arm", "stiffness"),
    "set_links_mass": (lambda s, a, b, x: a.set_links_mass(x), lambda a, b: (a.n_links,), "arm", "mass"),
    "set_links_inertia": (lambda s, a, b, x: a.set_links_inertia(x), lambda a, b: (a.n_links, 3, 3), "arm",
                          "inertia"),
    "set_links_COM": (lambda s, a, b, x: a.set_links_COM(x), lambda a, b: (a.n_links, 3), "arm", "com"),
    "set_friction": (lambda s, a, b, x: b.set_friction(x), lambda a, b: (b.n_geoms,), "box", "friction"),
    "scene.set_gravity": (lambda s, a, b, x: s.set_gravity(x), lambda a, b: (3,), "scene", "gravity"),
}


@pytest.mark.parametrize("leaf", [True, False], ids=["leaf", "computed"])
@pytest.mark.parametrize("value", [NAN, INF, -INF], ids=["nan", "inf", "-inf"])
@pytest.mark.parametrize("setter", list(RIGID_SETTERS))
def test_rigid_setters_refuse_nan_and_inf_that_require_grad(arm_and_box, setter, value, leaf):
    scene, arm, box = arm_and_box
    scene.reset()
    call, shape, owner, quantity = RIGID_SETTERS[setter]
    x = _bad(shape(arm, box), value, leaf)
    q_before = arm.get_qpos().detach().clone()
    prefix = "scene" if owner == "scene" else f"entity '{owner}'"
    with pytest.raises(GenesisException) as info:
        call(scene, arm, box, x)
    msg = str(info.value)
    assert msg.startswith(f"{prefix}: {quantity} contains NaN or infinite values"), msg
    assert "Pass finite values" in msg and "requires grad" in msg, msg
    assert torch.equal(arm.get_qpos().detach(), q_before)


MPM_SETTERS = {
    "set_particles_pos": (lambda e, x: e.set_particles_pos(x), lambda e: (e.n_particles, 3), "pos"),
    "set_particles_vel": (lambda e, x: e.set_particles_vel(x), lambda e: (e.n_particles, 3), "vel"),
    "set_position": (lambda e, x: e.set_position(x), lambda e: (3,), "pos"),
    "set_position(all particles)": (lambda e, x: e.set_position(x), lambda e: (e.n_particles, 3), "pos"),
    "set_velocity": (lambda e, x: e.set_velocity(x), lambda e: (3,), "velocity"),
    "set_particles_force": (lambda e, x: e.set_particles_force(x), lambda e: (e.n_particles, 3), "force"),
    "set_material(E)": (lambda e, x: e.set_material(E=x), lambda e: (e.n_particles,), "E"),
    "set_material(nu)": (lambda e, x: e.set_material(nu=x), lambda e: (e.n_particles,), "nu"),
}


@pytest.fixture(scope="module")
def jelly():
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=4, requires_grad=True),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.5, 0.5, 0.5),
                                                       grid_density=16))
    ent = scene.add_entity(gs.morphs.Box(pos=(0.25, 0.25, 0.25), size=(0.1, 0.1, 0.1)),
                           material=gs.materials.MPM.Elastic(E=1e4, nu=0.3), name="jelly")
    scene.build()
    return scene, ent


@pytest.mark.parametrize("value", [NAN, INF], ids=["nan", "inf"])
@pytest.mark.parametrize("setter", list(MPM_SETTERS))
def test_mpm_setters_refuse_nan_and_inf_that_require_grad(jelly, setter, value):
    scene, ent = jelly
    scene.reset()
    call, shape, quantity = MPM_SETTERS[setter]
    x_before = ent.get_particles_pos().detach().clone()
    with pytest.raises(GenesisException) as info:
        call(ent, _bad(shape(ent), value, leaf=True))
    msg = str(info.value)
    assert msg.startswith(f"MPM entity 'jelly': {quantity} contains NaN or infinite values"), msg
    assert "requires grad" in msg, msg
    assert torch.equal(ent.get_particles_pos().detach(), x_before)


def test_finite_values_that_require_grad_keep_their_gradients():
    """The finite check reads a detached view: a finite input that requires grad still gets its gradient."""
    scene = _grad_scene()
    arm = scene.add_entity(gs.morphs.URDF(file=ARM, fixed=True), name="arm")
    scene.build()
    q0 = torch.tensor([0.1, 0.4, -0.3, 0.2], **F64, requires_grad=True)
    force = torch.tensor([0.5, -0.2, 0.1, 0.0], **F64, requires_grad=True)
    arm.set_dofs_position(q0 * 1.0)
    arm.control_dofs_force(force)
    for _ in range(3):
        scene.step()
    (arm.get_links_pos()[-1] ** 2).sum().backward()
    for x in (q0, force):
        assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


@pytest.mark.parametrize("through", ["step", "getter"])
def test_second_derivatives_are_refused_not_silently_missing(through):
    """create_graph=True asks torch to differentiate the backward again; the step's and the getters' backward
    are Taichi's adjoint kernels, so the second-order part through the scene would be silently missing (the
    first-order gradient came back as a constant). Refused, naming what to do."""
    scene = _grad_scene()
    arm = scene.add_entity(gs.morphs.URDF(file=ARM, fixed=True), name="arm")
    scene.build()
    q0 = torch.tensor([0.1, 0.4, -0.3, 0.2], **F64, requires_grad=True)
    arm.set_dofs_position(q0)
    for _ in range(3 if through == "step" else 0):
        scene.step()
    loss = (arm.get_links_pos()[-1] ** 2).sum()
    with pytest.raises(GenesisException, match="create_graph=True.*first derivatives only"):
        torch.autograd.grad(loss, q0, create_graph=True)
    (g,) = torch.autograd.grad(loss, q0)  # first order as before
    assert float(g.abs().sum()) > 0


def test_a_leaf_that_turned_nan_is_refused_at_reset(arm_and_box):
    """A parameter leaf set once is re-applied at every reset; if an optimiser step made it NaN, the reset
    says which quantity of which entity, not a divergence steps later."""
    scene, arm, _ = arm_and_box
    scene.reset()
    mass0 = arm.get_links_mass().detach().clone()
    leaf = mass0.clone().requires_grad_()
    arm.set_links_mass(leaf)
    try:
        with torch.no_grad():
            leaf[1] = NAN  # what a diverged optimiser step leaves behind
        with pytest.raises(GenesisException, match=r"entity 'arm': mass contains NaN.*mass\[1\] = nan.*requires grad"):
            scene.reset()
    finally:
        arm.set_links_mass(mass0)
        scene.reset()


# --------------------------------------------------------------------------- 2. gradient growth
def _pendulum(**rigid):
    # the URDF's joint limits (+-4 pi) are for analytic checks; large swings run without them, as its header says
    scene = _grad_scene(integrator=gs.integrator.RK4, enable_joint_limit=False, **rigid)
    pend = scene.add_entity(gs.morphs.URDF(file=PENDULUM, fixed=True), name="pendulum")
    scene.build()
    return scene, pend


def _pendulum_rollout(scene, pend, q0, steps):
    scene.reset()
    pend.set_dofs_position(q0)
    for _ in range(steps):
        scene.step()
    return pend.get_dofs_position()


def _growth_warnings(fn):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fn()
    return [w for w in caught if issubclass(w.category, GradientGrowthWarning)]


# A start with both arms high, in the chaotic sea of this double pendulum: over 10 s (1,000 RK4 steps of 0.01 s)
# the backward pass amplifies the gradient ~3e7 times, over 1 s less than 10 times. Not every large-angle start
# is chaotic: on a grid of 12 starts with angles 1.8-3.0 and -1.0-2.0 rad, the 10 s growth ranged from 1e3
# (regular islands) to 3e7, half of them above 1e6.
CHAOTIC_START = (1.8, 2.0)


def test_chaotic_double_pendulum_warns_once_naming_the_window():
    scene, pend = _pendulum()
    q0 = torch.tensor(CHAOTIC_START, **F64, requires_grad=True)
    qT = _pendulum_rollout(scene, pend, q0, 1000)
    caught = _growth_warnings(lambda: qT.sum().backward())
    assert len(caught) == 1, [str(w.message) for w in caught]
    msg = str(caught[0].message)
    print(msg)
    m = re.search(r"amplified the gradient of the state by ([0-9.e+]+) from step (\d+) back to step "
                  r"(\d+) \(backward through steps (\d+)-(\d+)", msg)
    assert m, msg
    factor, late, early = float(m.group(1)), int(m.group(2)), int(m.group(3))
    assert factor > growth.GROWTH_WARN_FACTOR and late - early >= 500, msg
    assert "chaotic or unstable" in msg and "shorten the horizon" in msg
    # the growth is the dynamics', not an artefact of the watch: the gradient and the separation of two
    # trajectories started 1e-9 rad apart (no backward involved) grow as much
    assert q0.grad.norm().item() > 1e5
    with torch.no_grad():
        dq = 1e-9
        a = _pendulum_rollout(scene, pend, torch.tensor(CHAOTIC_START, **F64), 1000)
        b = _pendulum_rollout(scene, pend, torch.tensor(CHAOTIC_START, **F64) + torch.tensor([dq, 0.0], **F64), 1000)
    assert (a - b).abs().max().item() / dq > 1e5


def test_same_pendulum_over_a_short_horizon_does_not_warn():
    scene, pend = _pendulum()
    q0 = torch.tensor(CHAOTIC_START, **F64, requires_grad=True)
    qT = _pendulum_rollout(scene, pend, q0, 100)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        qT.sum().backward()
    assert torch.isfinite(q0.grad).all()


def test_small_swing_with_a_loss_weighted_over_orders_of_magnitude_does_not_warn():
    """A loss over every step whose weights fall from 1 to 1e-12: the gradient that reaches early states is
    ~1e12 times the one the last step receives, but the dynamics amplify nothing (a small, regular swing)."""
    scene, pend = _pendulum()
    q0 = torch.tensor([0.1, -0.05], **F64, requires_grad=True)
    scene.reset()
    pend.set_dofs_position(q0)
    loss, T = 0.0, 100
    for t in range(T):
        scene.step()
        loss = loss + 10.0 ** (-12.0 * t / (T - 1)) * pend.get_dofs_position().sum()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loss.backward()
    assert torch.isfinite(q0.grad).all() and q0.grad.abs().sum() > 0


PANDA_KP = [4500.0, 4500.0, 3500.0, 3500.0, 2000.0, 2000.0, 2000.0, 100.0, 100.0]
PANDA_KV = [450.0, 450.0, 350.0, 350.0, 200.0, 200.0, 200.0, 10.0, 10.0]


def test_panda_under_pd_control_does_not_warn():
    scene = _grad_scene()
    panda = scene.add_entity(gs.morphs.URDF(file=str(robot_urdf("panda")), fixed=True), name="panda")
    scene.build()
    panda.set_dofs_kp(PANDA_KP)
    panda.set_dofs_kv(PANDA_KV)
    q0 = torch.tensor([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8, 0.02, 0.02], **F64, requires_grad=True)
    target = torch.tensor([0.3, -0.5, 0.2, -2.0, 0.1, 1.5, 0.5, 0.02, 0.02], **F64, requires_grad=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene.reset()
        panda.set_dofs_position(q0)
        panda.control_dofs_position(target)
        for _ in range(100):
            scene.step()
        (panda.get_links_pos()[-1] ** 2).sum().backward()
    assert torch.isfinite(q0.grad).all() and torch.isfinite(target.grad).all()


@pytest.mark.parametrize("loss_at", ["end", "every step"])
def test_worst_window_of_the_recorded_norms(loss_at):
    """The window arithmetic on synthetic norms: per-step amplification 10 for steps 20-29 of a 40-step
    rollout (nodes run from step 39 down to 0), 0.9 elsewhere; with a loss at every step the incoming
    norm jumps at each step, which must not count."""
    steps = list(range(39, -1, -1))
    rows, g = [], 1.0
    for s in steps:
        g_in = g + (5.0 if loss_at == "every step" else 0.0)
        g_out = g_in * (10.0 if 20 <= s < 30 else 0.9)
        rows.append([g_in, g_out])
        g = g_out
    log_factor, (late, _), (early, _) = growth._worst_growth(steps, [1] * len(steps), rows)
    assert math.isclose(log_factor, 10.0) and (late, early) == (30, 20)


# --------------------------------------------------------------------------- 3. PD targets on zero gains
def _arm(n_envs=0):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
    arm = scene.add_entity(gs.morphs.URDF(file=ARM, fixed=True), name="arm")
    scene.build(n_envs=n_envs)
    return scene, arm


def _gain_warnings(fn):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fn()
    return [str(w.message) for w in caught if issubclass(w.category, ZeroGainWarning)]


def test_position_target_on_zero_kp_warns_once_per_set_of_dofs():
    scene, arm = _arm()
    # Genesis's default gains (kp 100, kv 10) drive a target: no warning until kp is set to 0
    assert np.all(arm.get_dofs_kp().numpy() == 100) and np.all(arm.get_dofs_kv().numpy() == 10)
    assert _gain_warnings(lambda: arm.control_dofs_position(np.zeros(4))) == []
    arm.set_dofs_kp([0.0] * 4)
    names = [j.name for j in arm.joints if j.n_dofs]
    msgs = _gain_warnings(lambda: arm.control_dofs_position(np.zeros(4)))
    assert len(msgs) == 1, msgs
    assert msgs[0].startswith("entity 'arm': control_dofs_position on dofs [0, 1, 2, 3] "
                              f"(joints {names}) whose kp is 0, so their targets have no effect"), msgs[0]
    assert "set_dofs_kp(" in msgs[0] and "control_dofs_force" in msgs[0]
    # the same dofs again (a control loop): no new warning; another set of dofs: one more
    assert _gain_warnings(lambda: [arm.control_dofs_position(np.zeros(4)) for _ in range(3)]) == []
    msgs = _gain_warnings(lambda: arm.control_dofs_position([0.1], dofs_idx_local=[2]))
    assert len(msgs) == 1 and "on dofs [2] " in msgs[0] and f"['{names[2]}']" in msgs[0], msgs
    # with kp set on some dofs, only the others are named; with kp everywhere, nothing (kv = 0 is fine:
    # the target still acts through kp)
    arm.set_dofs_kp([100.0, 100.0], dofs_idx_local=[0, 1])
    msgs = _gain_warnings(lambda: arm.control_dofs_position(np.zeros(4)))
    assert len(msgs) == 1 and "on dofs [2, 3] " in msgs[0], msgs
    arm.set_dofs_kp([100.0] * 4)
    assert _gain_warnings(lambda: arm.control_dofs_position(np.full(4, 0.2))) == []
    scene.step()


def test_velocity_target_on_zero_kv_warns():
    scene, arm = _arm()
    arm.set_dofs_kv([0.0] * 4)  # kp (100 by default) does not act on velocity targets
    msgs = _gain_warnings(lambda: arm.control_dofs_velocity(np.ones(4)))
    assert len(msgs) == 1 and "control_dofs_velocity on dofs [0, 1, 2, 3]" in msgs[0] and "kv is 0" in msgs[0]
    assert "set_dofs_kv(" in msgs[0]
    arm.set_dofs_kv([10.0] * 4)
    assert _gain_warnings(lambda: arm.control_dofs_velocity(np.ones(4), dofs_idx_local=[0, 1, 2, 3])) == []
    assert _gain_warnings(lambda: arm.control_dofs_velocity([1.0], dofs_idx_local=[3])) == []


def test_zero_gain_in_some_envs_warns():
    scene, arm = _arm(n_envs=3)
    arm.set_dofs_kp(np.full((3, 4), 100.0))
    arm.set_dofs_kp([0.0], dofs_idx_local=[1], envs_idx=[2])
    assert _gain_warnings(lambda: arm.control_dofs_position(np.zeros(4), envs_idx=[0, 1])) == []
    msgs = _gain_warnings(lambda: arm.control_dofs_position(np.zeros((3, 4))))
    assert len(msgs) == 1 and "on dofs [1] " in msgs[0] and "in some of the envs" in msgs[0], msgs
