"""Contact, friction and joint limits (issue #4), at the defaults and dt = 0.01 s unless said.

Physics is checked against analytic results (stopping distance v^2 / (2 mu g), rolling acceleration
5/7 g sin(theta), static equilibria) and for stability (resting, stacking, standing, stress).
Gradients are checked in float64 against central finite differences with gs.grad.check. They are the
exact derivatives of the simulated (smoothed, discretised) model: that is what the finite-difference
checks test, with tight tolerances. Against the idealised physics (hard contact, exact Coulomb friction,
continuous time) they agree only up to the model's smoothing and the time step: the stopping-distance
gradient is compared with d/dmu, d/dv of v^2 / (2 mu g) within a few percent, and the rest-height
gradient with the derivative of the smoothed model's own equilibrium.
"""
from __future__ import annotations

import numpy as np
import pytest
import taichi as ti
import torch

import genesis_lite as gs
from genesis_lite.errors import GenesisException, SimulationNaNError
from solvers.rigid.contact.law import heavy_mass

from conftest import robot_urdf

G = 9.81
# the default contact until 2026-12-05 (1e6 N/m and a fixed damper of 4e4 N s/m per point), kept as an option
FIXED_DAMPER = dict(contact_stiffness=1e6, contact_damping=4e4)
DT = 0.01
F64 = torch.float64


def _t(x):
    return torch.as_tensor(x, dtype=F64)


def _np(x):
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _scene(requires_grad=False, substeps=1, **rigid):
    return gs.Scene(sim_options=gs.options.SimOptions(dt=DT, substeps=substeps, requires_grad=requires_grad),
                    rigid_options=gs.options.RigidOptions(**rigid))


def _roll_body(scene, s0, body, m, mu, dofs_velocity, steps):
    """The finite-difference tests' rollout: from state s0, body's mass, friction and dof velocities set (torch
    tensors, so that gradients reach them), then `steps` steps."""
    scene.reset(s0)
    body.set_links_mass(m.reshape(1))
    body.set_friction(mu)
    body.set_dofs_velocity(dofs_velocity)
    for _ in range(steps):
        scene.step()


def _sink_bound(*stack, i=-1, points=1):
    """How far body i of a resting stack (bodies from the ground up) can have sunk: every interface under it
    pressed by all the weight above that interface, shared by `points` contact points (at least; 4 for a box's
    face on a face) of the default stiffness (N/m per point), load / (points k), summed. Resting heights are
    checked within this of the geometric ones."""
    k = gs.options.RigidOptions().contact_stiffness
    masses = [float(e.get_mass()) for e in stack]
    return sum(sum(masses[j:]) * G / (points * k) for j in range(range(len(masses))[i] + 1))


def _anymal_standing_pose(robot):
    names = [j.name for j in robot.joints if j.n_dofs == 1]
    dofs = [j.dof_start_local for j in robot.joints if j.n_dofs == 1]
    q = [0.0 if "HAA" in n else (0.4 if n[1] == "F" else -0.4) if "HFE" in n else (-0.8 if n[1] == "F" else 0.8)
         for n in names]
    return _t(q), dofs


def _anymal_on_ground(urdf_path, requires_grad=False, z=0.62, kp=300.0, kv=10.0):
    scene = _scene(requires_grad=requires_grad)
    scene.add_entity(gs.morphs.Plane())
    robot = scene.add_entity(gs.morphs.URDF(file=str(urdf_path("anymal")), fixed=False, pos=(0.0, 0.0, z)))
    scene.build()
    q0, dofs = _anymal_standing_pose(robot)
    robot.set_dofs_kp(torch.full((len(dofs),), kp, dtype=F64), dofs)
    robot.set_dofs_kv(torch.full((len(dofs),), kv, dtype=F64), dofs)
    robot.set_dofs_position(q0, dofs)
    robot.control_dofs_position(q0, dofs)
    return scene, robot, q0, dofs


# ------------------------------------------------------------------------------------------------
# Resting, sliding, rolling, stacking, standing
# ------------------------------------------------------------------------------------------------
def test_box_rests_on_plane_10s():
    """A box set down on the ground stays put for 10 s: drift < 1 mm, penetration < 2 mm, no jitter."""
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.3, 0.1), pos=(0.1, -0.2, 0.05)), material=gs.materials.Rigid(rho=1000.0))
    scene.build()
    p0 = _np(box.get_pos()).copy()
    z, vmax_last = [], 0.0
    for i in range(1000):
        scene.step()
        z.append(float(box.get_pos()[2]))
        if i >= 900:
            vmax_last = max(vmax_last, float(box.get_vel().abs().max()), float(box.get_ang().abs().max()))
    p1 = _np(box.get_pos())
    assert np.linalg.norm(p1[:2] - p0[:2]) < 1e-3
    assert abs(p1[2] - 0.05) < 1e-3  # drift in height
    assert 0.05 - min(z) < 2e-3  # penetration, the worst moment included
    assert np.std(z[-100:]) < 1e-7 and vmax_last < 1e-5  # no jitter
    q = _np(box.get_quat())
    assert abs(abs(q[0]) - 1.0) < 1e-6


# the non-default load ("frictionless") is slow: its own scene class, ~18 s of a fresh-cache default suite
@pytest.mark.parametrize("load", ["coulomb", pytest.param("frictionless", marks=pytest.mark.slow)])
@pytest.mark.parametrize("mu,v0", [(0.5, 3.0), (0.3, 2.0)])
def test_sliding_box_stops_after_v2_over_2mug(mu, v0, load):
    """A box launched on a floor stops after v0^2 / (2 mu g), within 5 %, with either friction load
    (RigidOptions.friction_load)."""
    scene = _scene(friction_load=load)
    scene.add_entity(gs.morphs.Plane(), material=gs.materials.Rigid(friction=mu))
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)), material=gs.materials.Rigid(friction=mu))
    scene.build()
    for _ in range(20):
        scene.step()
    x0 = float(box.get_pos()[0])
    box.set_dofs_velocity(_t([v0, 0, 0, 0, 0, 0]))
    for _ in range(int(1.5 * v0 / (mu * G) / DT) + 20):
        scene.step()
    d = float(box.get_pos()[0]) - x0
    ref = v0 ** 2 / (2 * mu * G)
    assert abs(d - ref) / ref < 0.05, (d, ref)
    assert float(box.get_vel().abs().max()) < 1e-3  # it has stopped (no creep)


def _launched_box(dt, mu=0.5, v0=2.0, rho=125.0, **rigid):
    """(scene, box): a 0.2 m box (1 kg at rho = 125) set on a floor of friction mu and launched along +x at v0."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt), rigid_options=gs.options.RigidOptions(**rigid))
    scene.add_entity(gs.morphs.Plane(), material=gs.materials.Rigid(friction=mu))
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)),
                           material=gs.materials.Rigid(friction=mu, rho=rho))
    scene.build()
    box.set_dofs_velocity(_t([v0, 0, 0, 0, 0, 0]))
    return scene, box


def _coulomb_slide(**rigid):
    """A box launched along a floor (0.2 m cube, v0 2 m/s, mu 0.5) against the exact Coulomb slide x(t) =
    v0 t - mu g t^2 / 2, which stops at v0 / (mu g) = 0.41 s, at dt = 10 / 2.5 / 0.625 / 0.3125 ms: per step
    (dt, the error of x at t = 1 s, the friction impulse over mu times the normal impulse while it slides)."""
    mu, v0 = 0.5, 2.0
    t_stop = v0 / (mu * G)
    exact = v0 * t_stop - 0.5 * mu * G * t_stop ** 2
    rows = []
    for dt in (0.01, 0.0025, 0.000625, 0.0003125):
        scene, box = _launched_box(dt, mu, v0, **rigid)
        fn = ft = 0.0
        for k in range(int(round(1.0 / dt))):
            scene.step()
            if (k + 1) * dt < 0.35:  # sliding
                c = box.get_contacts()
                F, n = _np(c["force_a"]), _np(c["normal"])
                normal = (F * n).sum(-1)
                fn += normal.sum()
                ft += np.linalg.norm((F - normal[:, None] * n).sum(0))
        rows.append((dt, float(box.get_pos()[0]) - exact, ft / (mu * fn)))
    return rows


def test_sliding_box_converges_to_coulomb_as_the_step_shrinks():
    """_coulomb_slide with the default options: the error at t = 1 s falls with dt at first order (|error| <=
    1.1 dt m/s, each at most 0.6 of the one before), and over the slide the friction impulse is mu times the
    normal impulse within 1e-3. Measured 2026-12-02: -9.9e-3, -2.5e-3, -6.1e-4, -2.4e-4 m at 10, 2.5, 0.625,
    0.3125 ms, the impulse ratio 0.99998 .. 0.99974.

    A strict xfail until 2026-12-02, when friction's load was the frictionless solve's normal forces (now
    RigidOptions(friction_load="frictionless")): the errors were -9.9e-3, -2.0e-3, +1.2e-3, +3.2e-3 m (they
    changed sign and grew), the ratio 0.9988 / 0.9951 / 0.9908 at 2.5 / 0.625 / 0.3125 ms; the box, pressed
    harder on its front edge by friction's torque, pitched back in the frictionless solve and its f2 summed to
    9.70 N for a 9.81 N box at 0.3125 ms. Friction's load is now the normal force with Coulomb's forces applied
    (contact/__init__.py, step 4)."""
    rows = _coulomb_slide()
    for dt, err, ratio in rows:
        assert abs(err) <= 1.1 * dt, rows
        assert abs(ratio - 1.0) < 1e-3, rows
    errs = [abs(e) for _, e, _ in rows]
    assert all(b < 0.6 * a for a, b in zip(errs, errs[1:])), rows


def test_a_sliding_box_stays_on_its_four_corners():
    """A 0.2 m, 1 kg box launched at 2 m/s along a floor (mu = 0.5, dt = 1 ms) slides to rest on its four bottom
    corners: friction's moment about the leading edge (mu m g h/2) is half gravity's (m g h/2), so a rigid box does
    not tip. In every step of the slide four floor contacts push, and once it has sunk to its rest depth (25 ms,
    the 2.4e-5 m of 1e5 N/m per corner; it starts touching) it stays within 1e-6 m of its rest height and tilts
    less than 1e-3 rad. (MuJoCo 4.0.1's model of the same slide hops, on fewer than four corners in 90 %
    of its steps and rising up to 2.5 mm: benchmarks/step_convergence.py --trace --scene box.) Measured 2026-12-06:
    four in every step, height within 6.4e-7 m of rest after 25 ms, tilt at most 1.2e-4 rad."""
    dt = 1e-3
    scene, box = _launched_box(dt)
    rows = []
    for k in range(int(round(0.5 / dt))):
        scene.step()
        c = box.get_contacts()
        pushing = int(((_np(c["force_a"]) * _np(c["normal"])).sum(-1) > 0).sum())
        q = _np(box.get_quat())
        tilt = 2 * np.arcsin(min(1.0, np.hypot(q[1], q[2])))
        rows.append(((k + 1) * dt, float(box.get_vel()[0]), pushing, float(box.get_pos()[2]), tilt))
    rows = np.array(rows)
    sliding = rows[rows[:, 1] > 0.05]
    assert len(sliding) > 300, len(sliding)  # it slides for v0 / (mu g) = 0.41 s
    assert np.all(sliding[:, 2] == 4), np.unique(sliding[:, 2], return_counts=True)
    settled = sliding[sliding[:, 0] >= 0.025]
    assert np.abs(settled[:, 3] - rows[-1, 3]).max() < 1e-6, np.abs(settled[:, 3] - rows[-1, 3]).max()
    assert sliding[:, 4].max() < 1e-3, sliding[:, 4].max()


# 2026-12-06: friction's load (contact/__init__.py, step 3) is the normal force predicted with Coulomb's forces of the
# frictionless loads f2, one linear response. Where the contacts' depths are within a few contact_smoothing widths
# (5e-6 m) of 0, their slopes differ (front and back of a sliding box), f2 sums to less than the weight (0.936 of it
# for a 100 g box, RK4 at 0.25 ms) and the prediction misses part of the load that friction's torque moves onto the
# leading edge (1.2 % there). With RK4 at 0.25 ms a 1 kg box on the default 1e5 N/m (resting 2.4e-5 m deep) brakes
# 0.005 % short of mu g, a 300 g box 0.33 %, a 100 g box 0.66 %, and a 1 kg box at contact_stiffness=1e6 as the
# 100 g one (the +3.9e-3 m the package docstring notes at 0.3125 ms). The bound rounds (step 5) correct only
# friction above Coulomb's bound.
LIGHT_LOAD_GAP = ("friction's load predicted from the frictionless solve misses part of the load shift where the "
                  "contacts are within a few contact_smoothing widths of zero depth (comment above)")


@pytest.mark.parametrize("rho,rigid", [
    pytest.param(125.0, {}, id="1kg"),
    pytest.param(12.5, {}, id="100g", marks=pytest.mark.xfail(strict=True, reason=LIGHT_LOAD_GAP)),
    pytest.param(125.0, {"contact_stiffness": 1e6}, id="1kg_1e6", marks=pytest.mark.xfail(strict=True,
                                                                                        reason=LIGHT_LOAD_GAP))])
def test_a_sliding_box_brakes_at_mu_g_whatever_its_weight_on_the_contacts(rho, rigid):
    """A 0.2 m box launched at 2 m/s along a floor (mu = 0.5, dt = 1 ms, the default integrator) has lost mu g t
    of its speed after t = 0.3 s of sliding, within 0.1 %, however light it is and however stiff its contacts.
    Measured 2026-12-06: 1 kg -0.005 %; 100 g and 1 kg at 1e6 N/m -0.57 % both (strict xfails: LIGHT_LOAD_GAP)."""
    mu, v0, dt, t = 0.5, 2.0, 1e-3, 0.3
    scene, box = _launched_box(dt, mu, v0, rho, **rigid)
    for _ in range(int(round(t / dt))):
        scene.step()
    lost = v0 - float(box.get_vel()[0])
    assert abs(lost / (mu * G * t) - 1.0) < 1e-3, lost / (mu * G * t) - 1.0


def test_friction_load_refuses_an_unknown_value():
    with pytest.raises(ValueError, match=r"friction_load='normal'.*\"coulomb\" \(the default\) or \"frictionless\""):
        gs.options.RigidOptions(friction_load="normal")


@pytest.mark.parametrize("mu", [1.0, pytest.param(0.05, marks=pytest.mark.slow)])
def test_sphere_on_incline_rolls_or_slides(mu):
    """On a 30 degree incline a solid sphere rolls without slip (a = 5/7 g sin) when mu > 2/7 tan, and
    slides (a = g (sin - mu cos)) otherwise."""
    th = np.deg2rad(30.0)
    n = np.array([np.sin(th), 0.0, np.cos(th)])
    down = np.array([np.cos(th), 0.0, -np.sin(th)])
    r = 0.1
    scene = _scene()
    scene.add_entity(gs.morphs.Plane(normal=tuple(n)), material=gs.materials.Rigid(friction=mu))
    ball = scene.add_entity(gs.morphs.Sphere(radius=r, pos=tuple(n * r)), material=gs.materials.Rigid(friction=mu))
    scene.build()
    s = []
    for _ in range(100):
        scene.step()
        s.append(_np(ball.get_pos()) @ down)
    t = np.arange(100) * DT
    a = 2 * np.polyfit(t, np.array(s), 2)[0]
    v, w = _np(ball.get_vel()), _np(ball.get_ang())
    slip = np.linalg.norm(v + np.cross(w, -n * r))
    if mu > 2.0 / 7.0 * np.tan(th):
        assert abs(a - 5.0 / 7.0 * G * np.sin(th)) / (5.0 / 7.0 * G * np.sin(th)) < 0.01
        assert slip < 0.01 * np.linalg.norm(v)
    else:
        ref = G * (np.sin(th) - mu * np.cos(th))
        assert abs(a - ref) / ref < 0.01
        assert slip > 0.5 * np.linalg.norm(v)


# friction's slip speed fixed at RigidOptions.friction_smoothing (friction_smoothing_accel=None), the default until
# 2026-12-06: a strict xfail where the default's convergence is checked, so that the old law's behaviour stays on
# record and a change to it is seen
FIXED_EPS = {"friction_smoothing_accel": None}


def _fixed_eps_xfail(why):
    return pytest.param(FIXED_EPS, id="fixed_eps", marks=pytest.mark.xfail(strict=True, reason=why))


@pytest.mark.parametrize("rigid", [pytest.param({}, id="default"), _fixed_eps_xfail(
    "a fixed slip speed: the box creeps at (tan / mu) eps whatever the step")])
def test_box_on_incline_below_friction_angle_creeps_less_as_the_step_shrinks(rigid):
    """A box resting on a 15 degree incline with mu = 0.5 (tan 15 = 0.27 < mu): exact Coulomb friction holds it.
    The smoothed law holds a sticking contact with the viscosity mu f / eps (eps the slip speed), so the box
    creeps at (tan / mu) eps. By default eps is RigidOptions.friction_smoothing (1e-3 m/s) at most
    friction_smoothing_accel (0.25 m/s^2) times h, so the creep falls with the step at first order towards
    Coulomb's 0: the speed along the incline after 0.25 s at 1, 0.5, 0.25, 0.125 ms halves with each halving and
    is (tan / mu) min(1e-3, 0.25 h) to 10 %. Measured 2026-12-06: 1.34e-4, 6.7e-5, 3.35e-5, 1.67e-5 m/s. With the
    slip speed fixed (friction_smoothing_accel=None, the default until then; a strict xfail): 5.4e-4, 5.6e-4,
    6.2e-4, 7.0e-4 m/s, the fine steps creeping faster (2026-12-05)."""
    th, mu = np.deg2rad(15.0), 0.5
    n = np.array([np.sin(th), 0.0, np.cos(th)])
    down = np.array([np.cos(th), 0.0, -np.sin(th)])
    opts = gs.options.RigidOptions(**rigid)
    speeds, expect = [], []
    for dt in (1e-3, 5e-4, 2.5e-4, 1.25e-4):
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt), rigid_options=opts)
        scene.add_entity(gs.morphs.Plane(normal=tuple(n)), material=gs.materials.Rigid(friction=mu))
        box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=tuple(0.1 * n),
                                             quat=(np.cos(th / 2), 0.0, np.sin(th / 2), 0.0)),
                               material=gs.materials.Rigid(friction=mu))
        scene.build()
        for _ in range(int(round(0.25 / dt))):
            scene.step()
        speeds.append(float(_np(box.get_vel()) @ down))
        eps = opts.friction_smoothing
        if opts.friction_smoothing_accel is not None:
            eps = min(eps, opts.friction_smoothing_accel * dt)
        expect.append(np.tan(th) / mu * eps)
    assert all(0 < b < 0.6 * a for a, b in zip(speeds, speeds[1:])), speeds
    assert np.allclose(speeds, expect, rtol=0.1), (speeds, expect)


def test_grad_of_a_box_that_slides_and_sticks_on_an_incline_against_finite_differences():
    """The gradient of the default slip speed at a fine step (min(1e-3, 0.25 h), here 5e-4 m/s at dt = 2 ms): a
    box thrown up a 15 degree incline (mu 0.6 against the plane's 0.4: the pair takes the larger) slides, stops
    and sticks within the 60 steps; its final position against its mass, friction and initial velocity, float64
    central differences."""
    th = np.deg2rad(15.0)
    n = np.array([np.sin(th), 0.0, np.cos(th)])
    up = -np.array([np.cos(th), 0.0, -np.sin(th)])
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, requires_grad=True))
    scene.add_entity(gs.morphs.Plane(normal=tuple(n)), material=gs.materials.Rigid(friction=0.4))
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=tuple(0.1 * n),
                                         quat=(np.cos(th / 2), 0.0, np.sin(th / 2), 0.0)),
                           material=gs.materials.Rigid(friction=0.6))
    scene.build()
    s0 = scene.get_state()

    def loss(m, mu, v):
        _roll_body(scene, s0, box, m, mu, torch.cat([v, torch.zeros(3, dtype=F64)]), 60)
        p = box.get_pos()
        return p[0] + 0.3 * p[1] + 2 * p[2]

    v0 = 0.25 * up + np.array([0.0, 0.05, 0.0])
    rep = gs.grad.check(loss, {"mass": _t(8.0), "mu": _t(0.6), "v": _t(v0)}, tol=1e-5)
    assert rep.ok, str(rep)


# long: each contact scene compiles its own contact kernels (~10 s) and these roll out many steps
@pytest.mark.slow
def test_stack_of_five_boxes_stands_10s():
    """Five boxes dropped 5 mm onto each other, slightly offset and turned, stand for 10 s, each at its
    geometric height less at most the contacts' compression under the weight above (_sink_bound: 1.8 mm for
    the top box at the default 1e5 N/m, four points a face; measured 2026-12-05: 1.2 mm)."""
    rng = np.random.default_rng(1)
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    a = 0.2
    boxes = []
    for i in range(5):
        off = rng.uniform(-0.01, 0.01, 2)
        yaw = rng.uniform(-0.05, 0.05)
        boxes.append(scene.add_entity(gs.morphs.Box(size=(a, a, a), pos=(off[0], off[1], a / 2 + i * (a + 0.005)),
                                                    quat=(np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)))))
    scene.build()
    p_start = None
    for i in range(1000):
        scene.step()
        if i == 99:
            p_start = np.array([_np(b.get_pos()) for b in boxes])
    p = np.array([_np(b.get_pos()) for b in boxes])
    v = max(float(b.get_vel().abs().max()) for b in boxes)
    sink = np.array([_sink_bound(*boxes, i=i, points=4) for i in range(5)])
    below = a / 2 + a * np.arange(5) - p[:, 2]
    assert ((below > -1e-4) & (below < sink + 1e-4)).all(), (below, sink)
    assert np.abs(p - p_start).max() < 1e-3  # nothing creeps after settling
    assert v < 1e-4


# slow (suite time, ~16 s): a 10 s stand; the quadruped on its feet is also checked by default
# (trajectory fingerprints, quadruped gradients)
@pytest.mark.slow
def test_quadruped_held_by_pd_stands_10s(urdf_path):
    """ANYmal (fixed=False) dropped onto the ground and held by PD stands for 10 s."""
    scene, robot, q0, dofs = _anymal_on_ground(urdf_path)
    zs = []
    for i in range(1000):
        scene.step()
        if i >= 100:
            zs.append(float(robot.get_pos()[2]))
    quat = _np(robot.get_quat())
    assert min(zs) > 0.45  # the base stays up (standing height ~0.49 m)
    assert max(zs) - min(zs) < 5e-3  # no sinking or bouncing over 9 s
    assert abs(quat[0]) > 0.999  # upright
    assert float(robot.get_dofs_velocity().abs().max()) < 0.01
    np.testing.assert_allclose(_np(robot.get_dofs_position(dofs)), _np(q0), atol=0.05)
    # only the four feet touch the ground
    contacts = robot.get_contacts()
    feet = {robot.get_link(n).idx for n in ("LF_SHANK", "RF_SHANK", "LH_SHANK", "RH_SHANK")}
    assert set(_np(contacts["link_a"]).tolist()) == feet
    total = _np(robot.get_links_net_contact_force()).sum(0)
    np.testing.assert_allclose(total, [0, 0, float(robot.get_mass()) * G], rtol=1e-3, atol=1e-2)


def _anymal_drop_heights(urdf_path, dt, t_end, every, **rigid):
    """Base positions of ANYmal dropped from 0.62 m and held by PD, sampled every `every` s (default
    options but dt and the RigidOptions fields in `rigid`)."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt), rigid_options=gs.options.RigidOptions(**rigid))
    scene.add_entity(gs.morphs.Plane())
    robot = scene.add_entity(gs.morphs.URDF(file=str(urdf_path("anymal")), fixed=False, pos=(0.0, 0.0, 0.62)))
    scene.build()
    q0, dofs = _anymal_standing_pose(robot)
    robot.set_dofs_kp(torch.full((len(dofs),), 100.0, dtype=F64), dofs)
    robot.set_dofs_kv(torch.full((len(dofs),), 5.0, dtype=F64), dofs)
    robot.set_dofs_position(q0, dofs)
    robot.control_dofs_position(q0, dofs)
    n, k = int(round(t_end / dt)), int(round(every / dt))
    out = []
    for i in range(n):
        scene.step()
        if (i + 1) % k == 0:
            out.append(_np(robot.get_pos()).copy())
    return np.array(out)


def _drop_changes(urdf_path, **rigid):
    """The largest change of the base position from t = 0.2 s (the feet landed; before, the fall's own error
    dominates: 7.4e-5, 3.7e-5 m whatever the contact) to 0.6 s as dt halves from 0.2 ms, and the final height."""
    runs = [_anymal_drop_heights(urdf_path, dt, 0.6, 0.05, **rigid)[3:] for dt in (2e-4, 1e-4, 5e-5)]
    return [float(np.linalg.norm(b - a, axis=1).max()) for a, b in zip(runs, runs[1:])], runs[-1][-1][2]


def test_quadruped_drop_converges_as_dt_shrinks(urdf_path):
    """Issue #24: the legged landing converges as the step shrinks, with the default options. ANYmal dropped
    from 0.62 m (impact ~1 m/s, feet sliding as the legs take the load), then standing: the base positions
    from the landing to t = 0.6 s change less and less as dt halves, as a first-order method's should. Measured
    2026-12-05 with the defaults (the contact critically damped, 1e5 N/m; Genesis's armature of 0.1 on every
    joint): 7.3e-6 then 3.5e-6 m. Without the armature (default_armature=None) the fixed damper that was the
    default until then (4e4 N s/m) had changes that grew as dt halved (1.9e-4, 3.3e-4, 6.0e-4 m from 4e-4 s
    down): a light foot's damping time m / c ~ 1e-5 s, which no practical step resolves."""
    changes, z = _drop_changes(urdf_path)
    assert changes[1] < 0.6 * changes[0], changes
    assert changes[1] < 1e-5, changes
    assert 0.45 < z < 0.52  # standing


def test_quadruped_standing_converges_as_dt_shrinks(urdf_path):
    """Issue #24: the standing phase (t = 0.5 .. 1 s) of the same drop converges at practical steps with the
    default options: the base positions, sampled every 50 ms, change less and less as dt halves from 5 ms, at
    first order. Measured 2026-12-05 (the default contact critically damped, 1e5 N/m): 1.23e-4, 5.3e-5, 2.7e-5 m.
    With the fixed damper of before (4e4 N s/m, 1e6 N/m; 2026-12-02): 8.9e-5, 6.0e-5, 4.8e-5 m, barely falling. A
    strict xfail until 2026-12-02, when friction's load was the frictionless solve's normal forces, which miss the
    load friction moves between the feet (now RigidOptions(friction_load="frictionless")): 2.0e-4, 1.2e-4,
    2.5e-4 m."""
    runs = [_anymal_drop_heights(urdf_path, dt, 1.0, 0.05)[9:] for dt in (5e-3, 2.5e-3, 1.25e-3, 6.25e-4)]
    changes = [float(np.linalg.norm(b - a, axis=1).max()) for a, b in zip(runs, runs[1:])]
    assert all(b < 0.6 * a for a, b in zip(changes, changes[1:])), changes
    assert max(changes) < 1.5e-4, changes


# slow: ~96,000 steps a case (the incline test keeps the fine steps' law and the fixed slip speed's creep in the
# default set)
@pytest.mark.slow
@pytest.mark.parametrize("rigid", [pytest.param({}, id="default"), _fixed_eps_xfail(
    "a fixed slip speed: the changes grow below ~50 us")])
def test_quadruped_standing_converges_at_fine_steps(urdf_path, rigid):
    """The same drop's standing phase (t = 0.5 .. 1 s) keeps converging at first order below the practical steps,
    dt = 156, 78, 39, 20 us, each change at most 0.7 of the one before, with the default slip speed (at most 0.25
    h). Measured 2026-12-06: 3.1e-6, 1.6e-6, 9.9e-7 m (each 0.50, 0.63 of the one before; with a cap of 0.1 h:
    3.1e-6, 1.6e-6, 6.1e-7 m). With a fixed slip speed (friction_smoothing_accel=None, the default until then;
    a strict xfail) the changes grow below ~50 us (4.1e-6, 4.6e-6, 2.2e-5 m from 78 us, 2026-12-05): the
    predicted Coulomb impulse h mu f / m against eps decides between the sticking viscosity and the creep below
    eps, so the fine steps leave the model the coarse ones converge to."""
    dts = (1.5625e-4, 7.8125e-5, 3.90625e-5, 1.953125e-5)
    runs = [_anymal_drop_heights(urdf_path, dt, 1.0, 0.1, **rigid)[4:] for dt in dts]
    changes = [float(np.linalg.norm(b - a, axis=1).max()) for a, b in zip(runs, runs[1:])]
    assert all(b < 0.7 * a for a, b in zip(changes, changes[1:])), changes
    assert changes[-1] < 1.5e-6, changes


@pytest.mark.slow
def test_quadruped_drop_converges_as_dt_shrinks_with_the_fixed_damper(urdf_path):
    """The same with the fixed damper that was the default until 2026-12-05 (contact_stiffness 1e6, contact_damping
    4e4 N s/m per point). Measured 2026-12-05: 4.0e-6 then 3.1e-6 m: the changes fall, slower than at first order
    (the default's 7.3e-6 then 3.5e-6 m)."""
    changes, z = _drop_changes(urdf_path, **FIXED_DAMPER)
    assert changes[1] < changes[0], changes
    assert changes[1] < 1e-5, changes
    assert 0.45 < z < 0.52  # standing


def test_joint_driven_past_its_limit_stops_at_the_limit(assets_dir):
    """assets/urdf/arm.urdf: shoulder_pitch has limits [-2, 2] rad; a PD target of 3 rad stops at 2."""
    scene = _scene(enable_collision=False)
    arm = scene.add_entity(gs.morphs.URDF(file=str(assets_dir / "urdf" / "arm.urdf"), fixed=True))
    scene.build()
    j = arm.get_joint("shoulder_pitch").dof_idx_local
    lo, hi = (float(x[0]) for x in arm.get_dofs_limit([j]))
    assert (lo, hi) == (-2.0, 2.0)
    arm.set_dofs_kp(_t([100.0]), [j])
    arm.set_dofs_kv(_t([10.0]), [j])
    for target, limit in ((3.0, hi), (-3.0, lo)):
        arm.control_dofs_position(_t([target]), [j])
        qmax, vmax = -np.inf, 0.0
        for _ in range(300):
            scene.step()
            q = float(arm.get_dofs_position([j])[0])
            qmax = max(qmax, abs(q))
            vmax = max(vmax, abs(float(arm.get_dofs_velocity([j])[0])))
        # at rest at the limit, pushed past it by kp (target - limit) / joint_limit_stiffness
        assert abs(q - limit) < 0.02, (q, limit)
        assert abs(float(arm.get_dofs_velocity([j])[0])) < 1e-3
        # on the way, at most one step's travel past it (the joint arrives at ~20 rad/s: the limit spring
        # acts from the first step that starts beyond the limit)
        assert qmax - abs(limit) < vmax * DT


# ------------------------------------------------------------------------------------------------
# Shapes against each other
# ------------------------------------------------------------------------------------------------
Q_X90 = (np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0)  # axis along y
Q_Y90 = (np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0)  # axis along x


@pytest.fixture(scope="module")
def mesh_files(tmp_path_factory):
    import trimesh

    d = tmp_path_factory.mktemp("meshes")
    trimesh.creation.icosphere(subdivisions=2, radius=0.1).export(d / "ico.stl")
    trimesh.creation.box(extents=(0.3, 0.2, 0.1)).export(d / "box.obj")
    flat = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], faces=[[0, 1, 2], [1, 3, 2]])
    flat.export(d / "flat.stl")
    return d


# long: each contact scene compiles its own contact kernels (~10 s) and these roll out many steps
@pytest.mark.slow
def test_every_supported_pair_comes_to_rest(mesh_files):
    """One scene, cases side by side: each top shape settles on its bottom shape (or the ground) at the
    height the geometry says, within 0.2 mm, and stops."""
    M = gs.morphs
    ico, mbox = str(mesh_files / "ico.stl"), str(mesh_files / "box.obj")
    cases = [  # (bottom or None for the ground, top, expected top height)
        (None, M.Sphere(radius=0.1, pos=(0, 0, 0.2)), 0.1),
        (None, M.Capsule(radius=0.05, height=0.2, pos=(0, 0, 0.2), quat=Q_X90), 0.05),
        (None, M.Capsule(radius=0.05, height=0.2, pos=(0, 0, 0.3)), 0.15),
        (None, M.Cylinder(radius=0.05, height=0.2, pos=(0, 0, 0.2)), 0.1),
        (None, M.Cylinder(radius=0.05, height=0.2, pos=(0, 0, 0.2), quat=Q_X90), 0.05),
        (None, M.Mesh(file=ico, pos=(0, 0, 0.2)), None),
        (None, M.Mesh(file=mbox, pos=(0, 0, 0.2)), 0.05),
        (M.Box(size=(0.4, 0.4, 0.2), pos=(0, 0, 0.1)), M.Sphere(radius=0.1, pos=(0.05, 0, 0.35)), 0.3),
        (M.Box(size=(0.4, 0.4, 0.2), pos=(0, 0, 0.1)), M.Box(size=(0.1, 0.1, 0.1), pos=(0.1, 0.05, 0.3)), 0.25),
        (M.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)), M.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.32),
                                                               quat=(np.cos(np.pi / 8), 0, 0, np.sin(np.pi / 8))), 0.3),
        (M.Box(size=(0.4, 0.4, 0.2), pos=(0, 0, 0.1)), M.Capsule(radius=0.05, height=0.2, pos=(0, 0, 0.3), quat=Q_X90), 0.25),
        (M.Box(size=(0.4, 0.4, 0.2), pos=(0, 0, 0.1)), M.Cylinder(radius=0.05, height=0.2, pos=(0, 0, 0.32)), 0.3),
        (M.Cylinder(radius=0.2, height=0.2, pos=(0, 0, 0.1)), M.Box(size=(0.1, 0.1, 0.1), pos=(0.05, 0, 0.3)), 0.25),
        (M.Cylinder(radius=0.2, height=0.2, pos=(0, 0, 0.1)), M.Sphere(radius=0.05, pos=(0.05, 0, 0.3)), 0.25),
        (M.Capsule(radius=0.05, height=0.3, pos=(0, 0, 0.05), quat=Q_X90),
         M.Capsule(radius=0.05, height=0.3, pos=(0, 0, 0.17), quat=Q_Y90), 0.15),
        (M.Mesh(file=mbox, pos=(0, 0, 0.05)), M.Box(size=(0.1, 0.1, 0.1), pos=(0.05, 0, 0.2)), 0.15),
        (M.Mesh(file=mbox, pos=(0, 0, 0.05)), M.Sphere(radius=0.05, pos=(0.05, 0, 0.2)), 0.15),
        (M.Box(size=(0.4, 0.4, 0.2), pos=(0, 0, 0.1)), M.Mesh(file=ico, pos=(0, 0, 0.35)), None),
    ]
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    tops, bottoms = [], []
    for k, (bottom, top, _) in enumerate(cases):
        shift = np.array([1.0 * k, 0.0, 0.0])
        for m in (bottom, top):
            if m is not None:
                m.pos = np.asarray(m.pos) + shift
        bottoms.append(None if bottom is None else scene.add_entity(bottom))
        tops.append(scene.add_entity(top))
    scene.build()
    assert scene.rigid_solver.dense_solve  # moving bodies touch each other: the coupled solve
    for _ in range(200):
        scene.step()
    # the icosphere's lowest vertex: its hull's extent along -z
    lowest = None
    for (bottom, top, z), ent, under in zip(cases, tops, bottoms):
        got = float(ent.get_pos()[2])
        if z is None:
            lowest = -float(ent.model.links[0].geoms[0].vertices[:, 2].min()) if lowest is None else lowest
            z = lowest + (0.0 if bottom is None else 0.2)
        sink = _sink_bound(*[e for e in (under, ent) if e is not None])
        assert -2e-4 < z - got < sink + 2e-4, (type(bottom).__name__, type(top).__name__, got, z, sink)
        assert float(ent.get_vel().abs().max()) < 2e-3, (type(bottom).__name__, type(top).__name__)


@pytest.mark.slow  # a scene class of its own (cylinder on a plane), two step sizes
@pytest.mark.parametrize("dt", [0.01, 0.002])
def test_a_cylinder_standing_on_its_cap_is_still(dt):
    """A 15 kg cylinder (0.2 m radius and height) set on its cap is still after 3 s: |w| < 1e-4 rad/s, and it
    rests on its cap's four points (three rim samples and the deepest rim point's slot, at the centre when
    level), sunk by its weight on them. Until 2026-12-05 it rocked with a period of two steps, |w| ~0.01 rad/s
    at dt = 10, 5 and 2 ms: that slot jumped to the opposite side of the rim each time the tilt changed sign
    (collision/narrow.py, func_slot_point, now faded towards the centre near level)."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt))
    scene.add_entity(gs.morphs.Plane())
    cyl = scene.add_entity(gs.morphs.Cylinder(radius=0.2, height=0.2, pos=(0, 0, 0.1)))
    scene.build()
    w = []
    n = round(3.0 / dt)
    for i in range(n + 4):
        scene.step()
        if i >= n:
            w.append(float(cyl.get_ang().abs().max()))
    assert max(w) < 1e-4, w
    # 15 kg is above the mass from which the stiffness is scaled (k HEAVY_TIME^2, 10 kg at the default k): each
    # point's k m / heavy_mass, so the four points hold m g at g HEAVY_TIME^2 / 4
    m, k = float(cyl.get_mass()), gs.options.RigidOptions().contact_stiffness
    assert m > heavy_mass(k)
    np.testing.assert_allclose(0.1 - float(cyl.get_pos()[2]), m * G / (4 * k * m / heavy_mass(k)), rtol=0.02)


def test_adjacent_links_never_collide_and_self_collision_is_an_option(assets_dir):
    """chain30 folded onto itself: off by default, non-adjacent links collide with the option on, and
    parent/child links never do."""
    def build(**kw):
        scene = _scene(**kw)
        chain = scene.add_entity(gs.morphs.URDF(file=str(assets_dir / "urdf" / "chain30.urdf"), fixed=True))
        scene.build()
        return scene, chain

    scene, chain = build()
    assert scene.rigid_solver.contact is None  # alone, without self-collision: nothing can touch
    scene, chain = build(enable_self_collision=True)
    c = scene.rigid_solver.contact
    parent = scene.rigid_solver.flat.np_link_parent
    links = {(int(c.geoms.link[a]), int(c.geoms.link[b])) for a, b in c.pairs}
    assert links and all(parent[la] != lb and parent[lb] != la and la != lb for la, lb in links)
    assert (3, 1) in links or (1, 3) in links


def test_collision_off_and_no_pairs_compile_nothing():
    """RigidOptions(enable_collision=False), or a scene where no two geoms can touch, has no contact
    solver and no contact stages in its step."""
    for kw, plane in (({"enable_collision": False}, True), ({}, False)):
        scene = _scene(**kw)
        if plane:
            scene.add_entity(gs.morphs.Plane())
        box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)))
        scene.build()
        s = scene.rigid_solver
        assert s.contact is None and not s.dense_solve
        from solvers.rigid.core import DYNAMICS

        assert s.dynamics_stages == DYNAMICS
        for _ in range(10):
            scene.step()
        assert float(box.get_pos()[2]) < 0.1 - 0.5 * G * 0.1 ** 2 + 1e-3  # falls freely
        assert box.get_contacts()["position"].shape == (0, 3)
        np.testing.assert_allclose(_np(box.get_links_net_contact_force()), 0.0)
        box.set_friction(0.3)
        np.testing.assert_allclose(_np(box.get_friction()), [0.3])


# ------------------------------------------------------------------------------------------------
# Contact readers and friction parameter
# ------------------------------------------------------------------------------------------------
def test_contacts_readable():
    scene = _scene()
    plane = scene.add_entity(gs.morphs.Plane())
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0.3, 0, 0.1)), material=gs.materials.Rigid(rho=500.0))
    ball = scene.add_entity(gs.morphs.Sphere(radius=0.05, pos=(0.3, 0, 0.25)))
    scene.build()
    for _ in range(100):
        scene.step()
    m_box, m_ball = float(box.get_mass()), float(ball.get_mass())
    c = box.get_contacts()
    assert set(c) >= {"link_a", "link_b", "geom_a", "geom_b", "position", "normal", "force_a", "force_b", "penetration"}
    assert (_np(c["link_a"]) == box.base_link.idx).all()  # this entity is side a
    ground = _np(c["link_b"]) == plane.base_link.idx
    assert ground.sum() == 4  # the four bottom corners
    np.testing.assert_allclose(np.abs(_np(c["position"])[ground][:, :2] - [0.3, 0]), 0.1, atol=1e-4)
    np.testing.assert_allclose(_np(c["normal"])[ground], np.tile([0, 0, 1.0], (4, 1)), atol=1e-9)
    np.testing.assert_allclose(_np(c["force_a"])[ground].sum(0), [0, 0, (m_box + m_ball) * G], rtol=1e-4, atol=1e-8)
    np.testing.assert_allclose(_np(c["force_b"]), -_np(c["force_a"]))
    on_ball = box.get_contacts(with_entity=ball)
    assert len(on_ball["position"]) >= 1 and (_np(on_ball["link_b"]) == ball.base_link.idx).all()
    np.testing.assert_allclose(_np(on_ball["force_a"]).sum(0), [0, 0, -m_ball * G], rtol=1e-4, atol=1e-8)
    # the box sinks (m_box + m_ball) g / (4 k) into the ground, the ball m_ball g / k into the box (linear springs
    # of the default k per point); the point reported is midway between the two surfaces
    k = gs.options.RigidOptions().contact_stiffness
    sink_box, sink_ball = (m_box + m_ball) * G / (4 * k), m_ball * G / k
    np.testing.assert_allclose(_np(on_ball["penetration"]), sink_ball, rtol=0.02)
    np.testing.assert_allclose(_np(on_ball["position"])[:, 2], 0.2 - sink_box - 0.5 * sink_ball, atol=2e-6)
    np.testing.assert_allclose(_np(box.get_links_net_contact_force()), [[0, 0, m_box * G]], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(_np(ball.get_links_net_contact_force()), [[0, 0, m_ball * G]], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(_np(plane.get_links_net_contact_force()), [[0, 0, -(m_box + m_ball) * G]], rtol=1e-4,
                               atol=1e-8)


def test_contacts_batched():
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)))
    scene.build(n_envs=3)
    box.set_pos(_t([[0, 0, 0.1], [0, 0, 1.0], [1, 0, 0.1]]))
    scene.step()
    c = box.get_contacts()
    mask = _np(c["valid_mask"])
    assert mask.shape[0] == 3 and c["position"].shape[:2] == mask.shape
    assert mask.sum(1).tolist() == [4, 0, 4]  # env 1 is in the air
    f = _np(box.get_links_net_contact_force())
    assert f.shape == (3, 1, 3) and f[1].max() == 0 and f[0, 0, 2] > 0


def _top_node(field):
    """The node below its tree's root that holds `field`."""
    node = field.snode
    while node.parent().parent() is not None:
        node = node.parent()
    return node._id


def test_contact_fields_are_placed_env_major():
    """Each env's contact data is one block (FieldTree): the per-env fields of the contact solver and
    those of each force bank hang from one env node per tree. A field per array put one env's contact
    data some sixty arrays apart, at offsets that are multiples of large powers of two (the same cache
    sets): the same ANYmal step, bitwise the same trajectory, ran ~20 % slower."""
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)))
    scene.build(n_envs=3)
    c = scene.rigid_solver.contact
    B = scene.rigid_solver.core.cap_envs
    for owner in (c, c.bank_normal, c.bank_relinearise, c.bank_coulomb, c.bank_friction):
        per_env = [f for f in vars(owner).values() if isinstance(f, ti.Field) and f.shape[0] == B]
        assert len(per_env) >= 3
        assert len({_top_node(f) for f in per_env}) == 1, type(owner).__name__
    # the fields with a leading axis of 1 before the env axis: env-major among themselves
    slots = [c.qacc_candidates, c.qacc_normal, c.dqacc_coulomb, c.solve_tmp]
    assert len({_top_node(f) for f in slots}) == 1


def test_env_axis_is_one_rule_for_placement_and_zeroing():
    """FieldTree places a field env-major, and ZeroPlan zeroes it env by env, by the same rule
    (layout.env_axis): the env axis is the first of length B, or the second after a leading 1. A field
    with neither cannot be zeroed env by env: by_env_axis, which sorts them for ZeroPlan, refuses it by
    its shape rather than zero the wrong cells."""
    from types import SimpleNamespace

    from solvers.rigid.layout import ZeroPlan, by_env_axis, env_axis
    assert env_axis((5, 7, 3), 5) == 0 and env_axis(5, 5) == 0
    assert env_axis((1, 5, 7), 5) == 1
    assert env_axis((2, 5, 7), 5) is None and env_axis((7, 5), 5) is None and env_axis((5, 3), None) is None
    assert env_axis((1, 1, 4), 1) == 0  # one env: the first axis
    f = [SimpleNamespace(shape=s) for s in ((5, 3), (5,), (1, 5, 3), (5, 3))]
    plan = ZeroPlan((), (), 0, *by_env_axis(f, 5))
    assert sorted((axis, rest, len(xs)) for axis, rest, xs in plan.groups) == [(0, (), 1), (0, (3,), 2),
                                                                               (1, (1, 3), 1)]
    with pytest.raises(ValueError, match=r"\(2, 5, 3\).*no env axis"):
        by_env_axis(f + [SimpleNamespace(shape=(2, 5, 3))], 5)


def _mixed_contact_rollout(requires_grad, n_steps=60, **rigid):
    """Three envs: a stack landing (candidate contacts, contacts dropped by pass 1), a box sliding and
    spinning on the ground, and everything starting in the air (no slot on for the first steps); and in
    each two planks crossed at right angles, the upper one landing on the lower one, which touch only
    where the edges of one's face cross the other's rim (the box pairs' face slots, at the choices of their
    pair's separating-axis test: collision.func_box_pair_test, in the broad phase)."""
    scene = _scene(requires_grad=requires_grad, **rigid)
    scene.add_entity(gs.morphs.Plane())
    lower = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.102)))
    upper = scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1), pos=(0.03, 0, 0.26), quat=(0.995, 0.0, 0.0, 0.1)))
    slider = scene.add_entity(gs.morphs.Box(size=(0.2, 0.1, 0.1), pos=(0.8, 0, 0.05), quat=(0.999, 0.02, 0.03, 0.01)))
    plank = scene.add_entity(gs.morphs.Box(size=(1.0, 0.1, 0.05), pos=(3.0, 0.0, 0.025)))
    crossed = scene.add_entity(gs.morphs.Box(size=(1.0, 0.1, 0.05), pos=(3.25, 0.003, 0.0755),
                                             quat=(0.7071, 0.0014, -0.0007, 0.7071)))
    scene.build(n_envs=3)
    lift = _t([[0, 0, 0], [0, 0, 0], [0, 0, 0.3]])
    for b in (lower, upper, slider):
        b.set_pos(b.get_pos() + lift)
    slider.set_dofs_velocity(_t([[0, 0, 0, 0, 0, 0], [2.0, 0.5, 0, 0, 0, 3.0], [1.0, 0, 0, 0, 0, 0]]))
    crossed.set_dofs_velocity(_t([[0.1, -0.05, -0.2, 0, 0, 0.3], [0, 0, -0.2, 0, 0, 0], [-0.1, 0.05, -0.1, 0, 0, -0.3]]))
    bodies = (lower, upper, slider, plank, crossed)
    qs = []
    for _ in range(n_steps):
        scene.step()
        qs.append(np.concatenate([_np(b.get_qpos()) for b in bodies], axis=-1))
    c = lower.get_contacts()
    p = crossed.get_contacts()
    return (np.array(qs), np.concatenate([_np(c["force_a"]), _np(p["force_a"])], axis=1),
            np.concatenate([_np(c["valid_mask"]), _np(p["valid_mask"])], axis=1))


@pytest.mark.slow  # ~70 s of a fresh-cache default suite (2026-12-04): its five-body scene compiled twice, with and
# without gradients, for it alone; the default set keeps the fused step against the op-by-op one on joint limits
# (test_joint_limits.py::test_every_step_path_gives_the_same_limits) and the gradient schedule against FD (the matrix)
@pytest.mark.parametrize("contact", ["fixed damper of before", "default"])
def test_fused_step_without_gradients_matches_the_gradient_schedule(contact):
    """Without gradients the fused step's contact solve skips work (only the slots that are on, no second
    factorisation when pass 1 changes nothing, nothing for an env without contacts); a scene built with
    requires_grad runs the full schedule of the contact passes. Both give the same rollout and contact
    forces (to rounding: the two compile to different code). "fixed damper of before": 1e6 N/m and 4e4 N s/m,
    the default contact until 2026-12-05.
    Until 2026-12-05 (found by the default case) a slot beyond the contact margin could count as acting by the
    sign of rounding noise in its ~0 force: in env 2 the upper box, falling 8 mm above the lower one, kept that
    null law when the ground stopped the lower box, and on the fused path it fell 8.4 mm into it in one step (the
    gradient schedule's noise had the other sign: 4.2e-5 m). Such a slot is now linearised again as a candidate
    whatever its count (passes.func_relinearise_share), and the upper box lands on the lower one on both paths."""
    rigid = {} if contact == "default" else FIXED_DAMPER
    q0, f0, m0 = _mixed_contact_rollout(False, **rigid)
    q1, f1, m1 = _mixed_contact_rollout(True, **rigid)
    assert m0[0].any() and m0[1].any() and (m0 == m1).all()
    assert np.abs(q0[:, 2] - q0[0, 2]).max() > 0.2  # env 2 fell and landed
    # the upper box (0.1 m, turned about the vertical) never sinks 0.1 mm into the lower one (0.2 m): its centre
    # stays 0.15 m above the lower's (columns 9 and 2), to within the 9 points' compression of a 1 kg box
    # landing (4.2e-5 m measured)
    for q in (q0, q1):
        assert (q[:, :, 9] - q[:, :, 2]).min() > 0.15 - 1e-4
    # the crossed plank rests on the lower one in every env (7 qpos a body: the fifth body's z is column 30)
    assert (q0[-1, :, 30] > 0.07).all() and (q0[-1, :, 30] < 0.08).all()
    np.testing.assert_allclose(q0, q1, rtol=0, atol=1e-10)
    np.testing.assert_allclose(f0, f1, rtol=0, atol=1e-7 * max(np.abs(f1).max(), 1.0))


def test_friction_parameter():
    """Friction comes from the material, can be set per entity (a tensor, per geom or per env), and a
    contact uses the larger coefficient of its two geoms."""
    scene = _scene()
    plane = scene.add_entity(gs.morphs.Plane(), material=gs.materials.Rigid(friction=0.1))
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)), material=gs.materials.Rigid(friction=0.4))
    scene.build(n_envs=2)
    np.testing.assert_allclose(_np(plane.get_friction()), [[0.1], [0.1]])
    np.testing.assert_allclose(_np(box.get_friction()), [[0.4], [0.4]])
    box.set_friction(_t([[0.2], [0.6]]))
    np.testing.assert_allclose(_np(box.get_friction()), [[0.2], [0.6]])
    box.set_dofs_velocity(_t([2.0, 0, 0, 0, 0, 0]))
    x0 = _np(box.get_pos())[:, 0].copy()
    for _ in range(150):
        scene.step()
    d = _np(box.get_pos())[:, 0] - x0
    np.testing.assert_allclose(d, [4.0 / (2 * 0.2 * G), 4.0 / (2 * 0.6 * G)], rtol=0.05)
    plane.set_friction(0.5, envs_idx=[0])  # max(0.5, 0.2) in env 0
    np.testing.assert_allclose(_np(plane.get_friction()), [[0.5], [0.1]])


# ------------------------------------------------------------------------------------------------
# Gradients
# ------------------------------------------------------------------------------------------------
# long: each contact scene compiles its own contact kernels (~10 s) and these roll out many steps
@pytest.mark.slow
def _skew_arm_rollout(assets_dir, plane: bool):
    """The skew arm (offset COMs, rotated inertias, skewed axes) 1 m above the ground under PD for 8 steps
    with gradients, over a plane or alone: (link positions, d loss / d start angles, the contact solver)."""
    scene = _scene(requires_grad=True)
    if plane:
        scene.add_entity(gs.morphs.Plane())
    arm = scene.add_entity(gs.morphs.URDF(file=str(assets_dir / "urdf" / "skew_arm.urdf"), fixed=True, pos=(0.0, 0.0, 1.0)))
    scene.build()
    arm.set_dofs_kp(_t([12.0, 8.0, 4.0]))
    arm.set_dofs_kv(_t([0.6, 0.4, 0.2]))
    q0 = _t([0.3, -0.5, 0.8]).requires_grad_(True)
    arm.set_dofs_position(q0)
    arm.control_dofs_position(_t([0.0, 0.2, -0.3]))
    traj = []
    for _ in range(8):
        scene.step()
        traj.append(arm.get_links_pos())
    traj = torch.stack(traj)
    w = torch.as_tensor(np.random.default_rng(5).normal(size=tuple(traj.shape)), dtype=F64)
    (w * traj).sum().backward()
    return traj.detach(), q0.grad, scene.sim.rigid_solver.contact


def test_an_arm_over_a_plane_it_never_reaches_runs_no_contact_kernel_and_gives_the_arm_alone_s_numbers(assets_dir):
    """Contacts only when some pair can touch (RigidSolver._evaluation_unit): over a plane it never comes
    near, the arm's evaluations run the kernels of the arm alone (no contact report ever ran: its evaluation
    count stays 0), and its trajectory and gradient are those of the arm without the plane, bit for bit."""
    q_plane, g_plane, contact = _skew_arm_rollout(assets_dir, True)
    q_alone, g_alone, none = _skew_arm_rollout(assets_dir, False)
    assert none is None and contact is not None
    assert int(contact.eval_count.to_numpy().sum()) == 0
    assert torch.equal(q_plane, q_alone) and torch.equal(g_plane, g_alone)
    assert g_alone.abs().min() > 1e-3  # (every start angle moves the links)


@pytest.mark.slow  # ~69 s of a fresh-cache default suite (2026-12-04): a Panda over a plane compiled sparse and dense
# for it alone; the default set keeps 'skipping changes no number' for contacts on the skew arm over a plane
# (the test above) and for emitters (test_emitter.py)
def test_a_box_the_arm_never_touches_leaves_the_arm_s_numbers_to_the_bit():
    """A free box beside a Panda makes the contact system a dense one (a pair of moving links could couple:
    mass_cross and the envelope factorisation). Without gradients an evaluation in which no listed slot
    couples two moving links factors and solves M's tree instead (contact/linalg.py func_tree_env): the
    box lands and rests 2 m away, and the arm's trajectory under its PD is the arm's alone, bit for bit
    (before 2026-12-02 the dense factorisation moved it by 8e-16)."""
    q = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8, 0.02, 0.02])
    out = {}
    for box in (False, True):
        scene = gs.Scene()
        scene.add_entity(gs.morphs.Plane())
        arm = scene.add_entity(gs.morphs.URDF(file=str(robot_urdf("panda")), fixed=True))
        if box:
            cube = scene.add_entity(gs.morphs.Box(size=(0.05, 0.05, 0.05), pos=(1.5, 1.5, 0.1)))
        scene.build()
        assert scene.sim.rigid_solver.contact.dense == box
        arm.set_dofs_position(q)
        arm.set_dofs_kp(np.full(9, 100.0))
        arm.set_dofs_kv(np.full(9, 10.0))
        arm.control_dofs_position(q + 0.3)
        traj = []
        for _ in range(150):
            scene.step()
            traj.append(np.concatenate([arm.get_dofs_position().numpy(), arm.get_dofs_velocity().numpy()]))
        out[box] = np.asarray(traj)
        if box:  # it landed and rests on the ground
            assert abs(float(cube.get_pos()[2]) - 0.025) < 1e-3
    assert np.abs(out[True][-1] - out[True][0]).max() > 0.1  # the arm moved
    np.testing.assert_array_equal(out[True], out[False])


def test_grad_of_a_ball_that_starts_out_of_reach_and_lands():
    """A ball 5 cm above the ground, thrown down and sideways with spin: its first evaluations find no pair
    that can touch and run without the contact kernels, its last ones land, roll and slide with them. The
    gradient of where it ends up with respect to its start velocity, through that switch, against
    float64 central finite differences."""
    scene = _scene(requires_grad=True)
    scene.add_entity(gs.morphs.Plane())
    ball = scene.add_entity(gs.morphs.Sphere(radius=0.05, pos=(0.0, 0.0, 0.1)))
    scene.build()
    contact = scene.sim.rigid_solver.contact
    T = 14
    evals = []

    def where(v):
        scene.reset()
        contact.eval_count.fill(0)
        ball.set_dofs_velocity(v)
        for _ in range(T):
            scene.step()
        evals.append(int(contact.eval_count.to_numpy()[0]))
        p = ball.get_pos()
        return p[0] + 2.0 * p[2]

    rep = gs.grad.check(where, {"v": _t([0.8, 0.3, -0.2, 1.0, -2.0, 0.5])}, tol=1e-6)
    assert rep.ok, str(rep)
    # the contact kernels ran in some evaluations of the rollout, not in all: it switched on the way down
    assert 0 < evals[0] < T, evals
    g = rep.autograd[0]
    # in free flight d/dvx = T dt and d/dvz = 2 T dt: friction after landing and the ground changed them
    assert float(g[0]) < 0.95 * T * DT and float(g[2]) < 0.5 * 2 * T * DT, g


def test_grad_stopping_distance_wrt_mu_and_v():
    """Exact against finite differences; within 3 % of d/dmu, d/dv of v^2 / (2 mu g) (the model's
    friction is smoothed below 1 mm/s and integrated at dt = 0.01 s)."""
    scene = _scene(requires_grad=True)
    plane = scene.add_entity(gs.morphs.Plane())
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)))
    scene.build()
    for _ in range(20):
        scene.step()
    s0 = scene.get_state()
    x0 = float(box.get_pos()[0])

    def distance(mu, v):
        scene.reset(s0)
        plane.set_friction(mu)
        box.set_friction(mu)
        box.set_dofs_velocity(torch.cat([v.reshape(1), torch.zeros(5, dtype=F64)]))
        for _ in range(70):
            scene.step()
        return box.get_pos()[0] - x0

    mu, v = 0.5, 2.0
    rep = gs.grad.check(distance, {"mu": _t(mu), "v": _t(v)}, tol=1e-6)
    assert rep.ok, str(rep)
    g_mu, g_v = (float(g) for g in rep.autograd)
    assert abs(g_mu / (-v ** 2 / (2 * mu ** 2 * G)) - 1) < 0.03
    assert abs(g_v / (v / (mu * G)) - 1) < 0.03


@pytest.mark.slow
def test_grad_rest_height_wrt_mass():
    """A dropped box's rest height against its mass: exact against finite differences and equal to the
    derivative of the smoothed model's equilibrium, 4 k delta softplus(depth / delta) = m g."""
    scene = _scene(requires_grad=True)
    scene.add_entity(gs.morphs.Plane())
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.15)))
    scene.build()

    def rest_height(m):
        scene.reset()
        box.set_links_mass(m.reshape(1))
        for _ in range(150):
            scene.step()
        return box.get_pos()[2]

    m = 1.6
    rep = gs.grad.check(rest_height, {"mass": _t(m)}, tol=1e-6)
    assert rep.ok, str(rep)
    opt = scene.rigid_options
    k, dl = opt.contact_stiffness, opt.contact_smoothing
    y = m * G / (4 * k * dl)
    z = np.log(np.expm1(y))  # depth / delta at equilibrium
    analytic = -G / (4 * k / (1 + np.exp(-z)))
    assert abs(float(rep.autograd[0]) / analytic - 1) < 1e-6


# long: each contact scene compiles its own contact kernels (~10 s) and these roll out many steps
@pytest.mark.slow
def test_grad_quadruped_base_position_wrt_pd_targets(urdf_path):
    """ANYmal standing on the ground, PD targets held for 50 steps: the final base position against the
    12 targets, exact against finite differences."""
    scene, robot, q0, dofs = _anymal_on_ground(urdf_path, requires_grad=True)
    with torch.no_grad():
        for _ in range(100):
            scene.step()
    s0 = scene.get_state()
    w = _t([1.0, 0.5, 2.0])

    def base(target):
        scene.reset(s0)
        robot.control_dofs_position(target, dofs)
        for _ in range(50):
            scene.step()
        return (robot.get_pos() * w).sum()

    target = q0 + 0.1 * torch.sin(torch.arange(12, dtype=F64))
    rep = gs.grad.check(base, {"targets": target}, tol=1e-5)
    assert rep.ok, str(rep)
    assert float(rep.autograd[0].norm()) > 1e-2


# long: each contact scene compiles its own contact kernels (~10 s) and these roll out many steps
@pytest.mark.slow
def test_grad_through_contact_between_moving_bodies():
    """A box sliding to rest on another one (the coupled, densely factorised solve): exact against
    finite differences in its mass, its friction and its initial velocity. The difference step is 1e-7:
    friction's load (the share r of Coulomb's force that acts, contact/__init__.py) has a kink where a
    contact's predicted slip crosses 0, within 1e-6 of this input along v_z: the central differences of
    d/dv_z at 1e-5, 1e-6, 1e-7 are 0.620, 0.645765, 0.645758 against autograd's 0.6457579 (2026-12-02)."""
    scene = _scene(requires_grad=True)
    scene.add_entity(gs.morphs.Plane(), material=gs.materials.Rigid(friction=0.2))
    lower = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)),
                             material=gs.materials.Rigid(friction=0.2, rho=200.0))  # 1.6 kg: it moves too
    top = scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1), pos=(0.03, 0, 0.25), quat=(0.995, 0.0, 0.0, 0.1)))
    scene.build()
    assert scene.rigid_solver.dense_solve
    with torch.no_grad():
        for _ in range(30):
            scene.step()
    s0 = scene.get_state()

    def loss(m, mu, v):
        _roll_body(scene, s0, top, m, mu, torch.cat([v, torch.zeros(3, dtype=F64)]), 40)
        p, q = top.get_pos(), lower.get_pos()
        return p[0] + 0.3 * p[1] + 2 * p[2] + q[0]

    rep = gs.grad.check(loss, {"mass": _t(0.5), "mu": _t(0.8), "v": _t([0.5, 0.2, 0.0])}, eps=1e-7, tol=1e-5)
    assert rep.ok, str(rep)
    assert all(float(g.norm()) > 1e-4 for g in rep.autograd), str(rep)


# ------------------------------------------------------------------------------------------------
# Stress
# ------------------------------------------------------------------------------------------------
def _quadruped_random_targets(urdf_path, n_steps):
    """Targets jump by up to 0.5 rad every 0.5 s: the robot stumbles and may fall over (PD target jumps
    alone swing the light shanks at ~80 rad/s, in the air too). Sane: finite, the base never below the
    ground nor flying off, links never deep in the ground, joint speeds bounded."""
    scene, robot, q0, dofs = _anymal_on_ground(urdf_path)
    rng = np.random.default_rng(0)
    zmin, zmax, vmax, lowest = np.inf, -np.inf, 0.0, np.inf
    for i in range(n_steps):
        if i % 50 == 0:
            robot.control_dofs_position(q0 + _t(rng.uniform(-0.5, 0.5, len(dofs))), dofs)
        scene.step()
        if i % 10 == 0:
            z = float(robot.get_pos()[2])
            zmin, zmax = min(zmin, z), max(zmax, z)
            vmax = max(vmax, float(robot.get_dofs_velocity().abs().max()))
            lowest = min(lowest, float(robot.get_links_pos()[:, 2].min()))
    assert torch.isfinite(robot.get_qpos()).all()
    assert zmin > 0.05 and zmax < 1.0 and vmax < 200.0
    assert lowest > -0.02  # link origins (joint axes) never sink into the ground


@pytest.mark.slow  # a stress run, for the default suite's margin under 15 minutes; by default the quadruped
# stands and converges (test_quadruped_standing_converges_as_dt_shrinks)
def test_stress_quadruped_random_pd_targets_10000_steps(urdf_path):
    _quadruped_random_targets(urdf_path, 10000)  # ~8 s


# long: each contact scene compiles its own contact kernels (~10 s) and these roll out many steps
@pytest.mark.slow
def test_stress_heavy_box_on_light_box():
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    light = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)), material=gs.materials.Rigid(rho=125.0))
    heavy = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.305)), material=gs.materials.Rigid(rho=125000.0))
    scene.build()
    assert abs(float(light.get_mass()) - 1.0) < 1e-9 and abs(float(heavy.get_mass()) - 1000.0) < 1e-6
    for _ in range(500):
        scene.step()
    zl, zh = float(light.get_pos()[2]), float(heavy.get_pos()[2])
    # a light body keeps its own contact stiffness whatever it carries (contact/law.py, heavy_mass): the light box
    # is pressed into the ground by 10 kN on its four corners, 24.5 mm at the default 1e5 N/m (2.5 mm at 1e6, the
    # default until 2026-12-05), and the heavy one into it by less than 10 kN on four points
    k = gs.options.RigidOptions().contact_stiffness
    np.testing.assert_allclose(0.1 - zl, 1001.0 * G / (4 * k), rtol=0.02)
    assert 0 < 0.2 - (zh - zl) < 1000.0 * G / (4 * k)
    assert max(float(light.get_vel().abs().max()), float(heavy.get_vel().abs().max())) < 1e-5
    np.testing.assert_allclose(_np(heavy.get_links_net_contact_force()), [[0, 0, 1000 * G]], rtol=1e-4, atol=1e-6)


# long: each contact scene compiles its own contact kernels (~10 s) and these roll out many steps
@pytest.mark.slow
@pytest.mark.parametrize("z0", [3.15, 3.2, 3.25])
def test_stress_chain30_falls_on_the_ground(assets_dir, z0):
    """The 30-link chain (0.1 kg links, no joint damping) dropped onto the ground from several heights. Its free
    swing alone diverges at dt = 0.01 s with one substep (in MuJoCo too), and at 4 substeps once it whips fast
    (released from angles spread over [-1, 1] rad without any contact; and the contact model before speculative
    contacts, stable dropped from 3.2 m, diverged dropped from 3.25 m). At 8 substeps (h = 1.25 ms) too, by the
    start height (2026-12-06): with the fixed slip speed it diverged from 3.22 and 3.25 m, with the default cap
    from 3.2 and 3.21 m, and from the capped run's states the energy grew in steps without any contact (the
    chain alone in the air from its state at step 162 gained 120 J in 10 ms, 1.1 J at h / 64; the contact's
    share of a step's energy change was at most 0 in all but two steps): the first-order integrators' error at
    joint speeds of ~100 rad/s. At 16 substeps no run from seven heights in 3.15-3.25 m gained energy, with
    either slip speed (benchmarks/chain_drop.py; MuJoCo's Euler and implicitfast at h = 1.25 ms diverged from 6
    of the 7, at 0.3125 ms from 2). Energy never grows, the chain comes to rest on the ground. The links' own
    inertia, without the default armature (0.1 kg m^2 a joint, ~1,000x a link's): with it the chain lands on its
    end and stays standing for the 4 s checked."""
    scene = _scene(substeps=16)
    scene.add_entity(gs.morphs.Plane())
    chain = scene.add_entity(gs.morphs.URDF(file=str(assets_dir / "urdf" / "chain30.urdf"), fixed=False, pos=(0, 0, z0),
                                            default_armature=None))
    scene.build()
    e0 = float(chain.get_total_energy())
    emax = e0
    for _ in range(400):
        scene.step()
        emax = max(emax, float(chain.get_total_energy()))
    assert emax <= e0 + 1e-6
    z = _np(chain.get_links_pos())[:, 2]
    assert z.min() > 0.0 and z.max() < 0.2  # lying on the ground
    assert float(chain.get_dofs_velocity().abs().max()) < 0.1


@pytest.mark.parametrize("z0", [0.39, 0.5])
def test_stress_sphere_hits_ground_at_20mps(z0):
    """No tunnelling (a plane is a half-space: a centre below it is still pushed out), no explosion."""
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    ball = scene.add_entity(gs.morphs.Sphere(radius=0.1, pos=(0, 0, z0)))
    scene.build()
    ball.set_dofs_velocity(_t([0, 0, -20.0, 0, 0, 0]))
    zmin, up = np.inf, 0.0
    for _ in range(200):
        scene.step()
        zmin, up = min(zmin, float(ball.get_pos()[2])), max(up, float(ball.get_vel()[2]))
    assert zmin > -0.1  # never fully through
    assert up < 5.0  # at most a modest rebound, no energy gain
    assert abs(float(ball.get_pos()[2]) - 0.1) < 1e-3


def test_exploding_state_names_step_entity_and_quantity():
    scene = _scene(contact_stiffness=1e14, contact_damping=0.0)
    scene.add_entity(gs.morphs.Plane())
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)), name="crate")
    scene.build()
    box.set_dofs_velocity(_t([0, 0, 0, 1e300, 1e300, 1e300]))
    with pytest.raises(SimulationNaNError, match=r"crate.*(qpos|qvel).*step \d+"):
        for _ in range(64):
            scene.step()


# ------------------------------------------------------------------------------------------------
# Fast impacts, friction at impacts, box edges (issue #10). Penetration is measured from the bodies'
# poses with the shapes' exact geometry (not from the contact model's depths); friction against
# Coulomb's law with the impulses the simulation's own momenta show.
# ------------------------------------------------------------------------------------------------
def _rot(q):
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _box_overlap(pa, Ra, ha, pb, Rb, hb):
    """Penetration depth of two boxes (centres, rotations, half sizes): the least overlap of their
    projections over the 15 separating-axis candidates (the exact depth for convex polyhedra); <= 0
    when they are apart."""
    T = pb - pa
    axes = [Ra[:, i] for i in range(3)] + [Rb[:, j] for j in range(3)]
    for i in range(3):
        for j in range(3):
            c = np.cross(Ra[:, i], Rb[:, j])
            if np.linalg.norm(c) > 1e-9:
                axes.append(c / np.linalg.norm(c))
    return min(np.abs(Ra.T @ L) @ ha + np.abs(Rb.T @ L) @ hb - abs(T @ L) for L in axes)


def _box_below_ground(p, R, h):
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * h
    return -(p[2] + (corners @ R.T)[:, 2]).min()


def _segment_distance(p1, q1, p2, q2):
    """Distance between segments p1q1 and p2q2 (closest points by clamped alternation, exact for
    non-parallel segments after a few rounds)."""
    d1, d2 = q1 - p1, q2 - p2
    s = t = 0.5
    for _ in range(50):
        s = np.clip((p2 + t * d2 - p1) @ d1 / (d1 @ d1), 0, 1)
        t = np.clip((p1 + s * d1 - p2) @ d2 / (d2 @ d2), 0, 1)
    return np.linalg.norm(p1 + s * d1 - p2 - t * d2)


def _capsule_axis(p, R, hl):
    return p - hl * R[:, 2], p + hl * R[:, 2]


def _overlap(kind, top, bottom):
    """Deepest overlap (m) of the top body with the bottom one (None: the ground plane), from their
    poses ((n_envs, 3) positions, (n_envs, 4) quaternions): per env."""
    out = []
    for k in range(top[0].shape[0]):
        pt, Rt = top[0][k], _rot(top[1][k])
        if kind == "sphere":
            d = 0.1 - pt[2] if bottom is None else 0.2 - np.linalg.norm(pt - bottom[0][k])
        elif kind == "box":
            h = np.full(3, 0.1)
            d = _box_below_ground(pt, Rt, h) if bottom is None else _box_overlap(pt, Rt, h, bottom[0][k], _rot(bottom[1][k]), h)
        else:
            a, b = _capsule_axis(pt, Rt, 0.1)
            if bottom is None:
                d = 0.1 - min(a[2], b[2])
            else:
                c, e = _capsule_axis(bottom[0][k], _rot(bottom[1][k]), 0.1)
                d = 0.2 - _segment_distance(a, b, c, e)
        out.append(d)
    return np.array(out)


def _morph(kind, pos, quat=(1.0, 0.0, 0.0, 0.0)):
    if kind == "sphere":
        return gs.morphs.Sphere(radius=0.1, pos=pos, quat=quat)
    if kind == "box":
        return gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=pos, quat=quat)
    return gs.morphs.Capsule(radius=0.1, height=0.2, pos=pos, quat=quat)


# box onto box: its own scene class (~37 s of compiling), under -m slow with the other kinds
@pytest.mark.parametrize("kind,onto", [("box", "plane"), pytest.param("box", "same", marks=pytest.mark.slow),
                                       pytest.param("sphere", "plane", marks=pytest.mark.slow),
                                       pytest.param("sphere", "same", marks=pytest.mark.slow),
                                       pytest.param("capsule", "plane", marks=pytest.mark.slow),
                                       pytest.param("capsule", "same", marks=pytest.mark.slow)])
def test_fast_impact_stops_at_the_surface(kind, onto):
    """A body hitting the ground, or a body of its own kind resting on the ground, at 20 m/s (20 cm per
    step at dt = 0.01 s): the deepest overlap over the impact, from the poses, stays below 25 % of its
    radius (0.1 m) whatever part of the step the surfaces meet in (4 envs, 5 cm apart in start height):
    stopped at the surface, not tunnelling. Capsules lie horizontally, crossed at right angles on each other.
    With the default contact since 2026-12-05 (1e5 N/m, critically damped) a 6.3 kg capsule's 1.3 kJ go 12 mm
    into the plane and 22 mm into the capsule below (measured that day); with the contact of before (1e6 N/m,
    4e4 N s/m) every case stayed below 10 %, this test's bound until then."""
    lying = (np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0)  # capsule axis along y
    crossed = (0.5, 0.5, 0.5, 0.5)  # capsule axis along x (z -> x)
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    bottom = None
    if onto == "same":
        bottom = scene.add_entity(_morph(kind, (0.0, 0.0, 0.1), lying if kind == "capsule" else (1.0, 0.0, 0.0, 0.0)))
    base = 0.1 if onto == "plane" else 0.3
    top = scene.add_entity(_morph(kind, (0.0, 0.0, base + 0.3), crossed if kind == "capsule" else (1.0, 0.0, 0.0, 0.0)))
    scene.build(n_envs=4)
    z0 = base + 0.3 + 0.05 * np.arange(4)
    top.set_pos(_t(np.stack([np.zeros(4), np.zeros(4), z0], 1)))
    top.set_dofs_velocity(_t(np.tile([0.0, 0.0, -20.0, 0.0, 0.0, 0.0], (4, 1))))
    worst = np.zeros(4)
    for _ in range(60):
        scene.step()
        pose = lambda e: (_np(e.get_pos()), _np(e.get_quat()))  # noqa: E731
        worst = np.maximum(worst, _overlap(kind, pose(top), None if bottom is None else pose(bottom)))
        if bottom is not None:
            worst = np.maximum(worst, _overlap(kind, pose(bottom), None))
    assert (worst < 0.25 * 0.1).all(), worst
    assert torch.isfinite(top.get_pos()).all() and float(top.get_vel().abs().max()) < 20.0


def _landing(kind, cases, n_steps=40):
    """Bodies (one per env) launched at (height above the ground m, horizontal speed m/s, mu): per env
    the per-step horizontal impulse along the motion, normal impulse (vertical momentum change minus
    gravity's) and contact-point slip speed after the step."""
    scene = _scene()
    plane = scene.add_entity(gs.morphs.Plane())
    body = scene.add_entity(gs.morphs.Box(size=(0.3, 0.2, 0.1), pos=(0, 0, 0.5)) if kind == "box"
                            else gs.morphs.Sphere(radius=0.1, pos=(0, 0, 0.5)))
    B = len(cases)
    scene.build(n_envs=B)
    half = 0.05 if kind == "box" else 0.1
    plane.set_friction(0.0)  # a contact takes the larger coefficient: the body's
    body.set_friction(_t([[c[2]] for c in cases]))
    body.set_pos(_t([[0.0, 0.0, half + c[0]] for c in cases]))
    body.set_dofs_velocity(_t([[c[1], 0.0, 0.0, 0.0, 0.0, 0.0] for c in cases]))
    m = _np(body.get_mass())
    m = float(m.reshape(-1)[0])
    v = _np(body.get_vel()).copy()
    imp_t, imp_n, slip = [], [], []
    for _ in range(n_steps):
        scene.step()
        v1, w1 = _np(body.get_vel()), _np(body.get_ang())
        imp_t.append(-m * (v1[:, 0] - v[:, 0]))
        imp_n.append(m * (v1[:, 2] - v[:, 2]) + m * G * DT)
        foot = v1 + np.cross(w1, np.array([0.0, 0.0, -half]))
        slip.append(np.linalg.norm(foot[:, :2], axis=1))
        v = v1.copy()
    return m, np.array(imp_t).T, np.array(imp_n).T, np.array(slip).T


LANDINGS = [(0.25, 3.0, 0.3), (0.05, 1.0, 0.3), (0.5, 3.0, 0.6), (0.5, 2.0, 0.1), (0.1, 4.0, 0.8)]


@pytest.mark.parametrize("kind", ["box", "sphere"])
def test_friction_at_landing_follows_coulomb(kind):
    """A box (0.3 x 0.2 x 0.1 m) or a ball dropped while moving sideways, for several heights, speeds
    and mu: over the steps the contact slides through (from the first contact impulse until the body
    has stopped falling), the friction impulse is mu times the normal impulse within 5 % (Coulomb's
    law), and the body keeps sliding. (Before issue #10 the box lost all its speed in the landing step,
    2.9 times mu times the normal impulse.)"""
    cases = LANDINGS if kind == "box" else [c for c in LANDINGS if c[2] <= 0.3 or c[1] > 3.5]
    m, it, ino, slip = _landing(kind, cases)
    for k, (h, v0, mu) in enumerate(cases):
        first = int(np.argmax(ino[k] > 1e-6))
        last = first + 5  # the landing transient (the body has stopped falling after 2-3 steps)
        steps = [i for i in range(first, last) if slip[k, i] > 0.05]  # still sliding after the step
        assert steps and steps[0] == first, (h, v0, mu, slip[k, first:last])
        ratio = it[k, steps].sum() / (mu * ino[k, steps].sum())
        assert 0.95 < ratio < 1.05, (kind, h, v0, mu, ratio, it[k, steps] / (mu * ino[k, steps]))
        assert ino[k, first:last].sum() > 0.9 * m * np.sqrt(2 * G * h)  # it stopped falling in the window
        assert kind != "box" or slip[k, last - 1] > 0.05  # and the box slides on


def _run_boxes(scene, boxes, n_steps, ground=True):
    """Deepest overlap (m) between consecutive boxes and of each box with the ground, over the rollout."""
    worst = 0.0
    for _ in range(n_steps):
        scene.step()
        poses = [(_np(b.get_pos()), _rot(_np(b.get_quat())), np.asarray(b.morph.size) / 2) for b in boxes]
        for (pa, Ra, ha), (pb, Rb, hb) in zip(poses[:-1], poses[1:]):
            worst = max(worst, _box_overlap(pa, Ra, ha, pb, Rb, hb))
        if ground:
            worst = max(worst, max(_box_below_ground(p, R, h) for p, R, h in poses))
    return worst


def _crossed_edges(requires_grad=False):
    s2 = np.sqrt(2.0)
    scene = _scene(requires_grad=requires_grad)
    scene.add_entity(gs.morphs.Plane())
    lower = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1 * s2), fixed=True,
                                           quat=(np.cos(np.pi / 8), np.sin(np.pi / 8), 0, 0)))
    upper = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.3 * s2 + 1e-3),
                                           quat=(np.cos(np.pi / 8), 0, np.sin(np.pi / 8), 0)))
    scene.build()
    return scene, lower, upper


def test_boxes_crossed_edge_on_edge_rest():
    """Two boxes standing on an edge, the edges crossed at right angles (the lower one welded: balanced
    on a point, the pair is an unstable equilibrium): over 0.5 s they overlap by less than 2 mm, and the
    upper one rests at the height the geometry says (before issue #10: 5.4 mm deep in 0.5 s)."""
    scene, lower, upper = _crossed_edges()
    worst = _run_boxes(scene, [lower, upper], 50, ground=False)
    assert worst < 2e-3, worst
    assert abs(float(upper.get_pos()[2]) - 0.3 * np.sqrt(2.0)) < 2e-3
    assert float(upper.get_vel().abs().max()) < 1e-2


@pytest.mark.slow  # ~38 s of a fresh-cache default suite (2026-12-03); edge on edge: test_boxes_crossed_edge_on_edge_rest
def test_box_tipped_onto_another_box_edge_rests():
    """A plank (0.6 x 0.15 x 0.05 m) leaning at 30 degrees with its lower edge on the ground and its face
    on the top edge of a box, off the box's middle (so the contact line is the part of the box's edge
    under the plank): it rests, overlapping the box and the ground by less than 2 mm."""
    th = np.deg2rad(30.0)
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    box = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0, 0, 0.1)))
    # the plank's bottom face passes through the box's top edge (x = -0.1, z = 0.2), 0.4 m from its lower end
    n = np.array([-np.sin(th), 0.0, np.cos(th)])  # the plank's top face normal (rotated -30 deg about y)
    along = np.array([-np.cos(th), 0.0, -np.sin(th)])  # down the plank, away from the box
    centre = np.array([-0.1, 0.03, 0.2]) + 0.1 * along + 0.025 * n + 1e-3 * n
    plank = scene.add_entity(gs.morphs.Box(size=(0.6, 0.15, 0.05), pos=tuple(centre),
                                           quat=(np.cos(-th / 2), 0.0, np.sin(-th / 2), 0.0)))
    scene.build()
    worst = _run_boxes(scene, [box, plank], 150)
    assert worst < 2e-3, worst
    assert float(plank.get_vel().abs().max()) < 1e-2 and float(box.get_vel().abs().max()) < 1e-2


# slow (suite time, ~30 s): box-box edge crossings also rest in the default boxes_crossed_edge_on_edge and
# plank tests
@pytest.mark.slow
def test_stack_of_boxes_turned_45_degrees_rests():
    """Four boxes of decreasing size, each turned 45 degrees about the vertical to the one below (so every
    interface is edges crossing edges), released 2 mm apart: they land together and rest at the heights
    the geometry says, overlapping each other and the ground by less than 2 mm throughout. (The landing
    needs the candidate contacts of contact.py: linearised only at the start-of-step velocity, the top
    pair, both still falling, did not act in the step in which the box below was stopped: 3.7 mm. And a slot
    acting at the start but predicted far out needs the same: on 2026-12-05, the first box caught by the
    second, the third fell 2.9 mm into it, its law's slope there ~1e-8 of the full one; with
    passes.func_relinearise_share the worst is 4.0e-4 m, the ground's compression under the stack.)"""
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    sizes = [0.3, 0.25, 0.2, 0.15]
    boxes, z = [], 0.0
    for i, a in enumerate(sizes):
        yaw = np.pi / 4 * (i % 2)
        boxes.append(scene.add_entity(gs.morphs.Box(size=(a, a, a), pos=(0, 0, z + a / 2 + 2e-3),
                                                    quat=(np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)))))
        z += a + 2e-3
    scene.build()
    worst = _run_boxes(scene, boxes, 200)
    assert worst < 2e-3, worst
    heights = np.cumsum(sizes) - np.array(sizes) / 2
    np.testing.assert_allclose([float(b.get_pos()[2]) for b in boxes], heights, atol=1e-3)
    assert max(float(b.get_vel().abs().max()) for b in boxes) < 1e-3



PLANK = (1.0, 0.1, 0.05)  # length, width, thickness (m)


def _yaw(deg, pitch_deg=0.0):
    """Quaternion of a pitch about the box's own y axis (its width, for a plank) followed by a yaw about z
    (degrees)."""
    a, b = np.deg2rad(deg) / 2, np.deg2rad(pitch_deg) / 2
    # (cos a, 0, 0, sin a) * (cos b, 0, sin b, 0)
    return (np.cos(a) * np.cos(b), -np.sin(a) * np.sin(b), np.cos(a) * np.sin(b), np.sin(a) * np.cos(b))


def _tilt(b):
    """Angle (rad) between the box's z axis and the vertical."""
    return float(np.arccos(np.clip(_rot(_np(b.get_quat()))[2, 2], -1.0, 1.0)))


@pytest.mark.slow  # its three-plank class compiled for it alone (~40 s); by default the box-face slots
# hold the crossed plank of test_fused_step_without_gradients_matches_the_gradient_schedule and test_narrow_phase
def test_plank_across_two_planks_rests():
    """A plank (1.0 x 0.1 x 0.05 m) dropped 3 mm across two others lying on the ground 0.8 m apart, at right
    angles and 0.3 m from their middles: it rests on the two 0.1 x 0.1 m squares where it overlaps them, flat,
    at the height stacking gives (0.075 m). No corner and no edge midpoint of any plank lies in those squares;
    their vertices are where the edges of one plank's face cross the rim of the other's (the box-box face
    slots, collision/narrow.func_box_face_contact). Before them the plank fell through both onto the ground."""
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    L, W, H = PLANK
    left = scene.add_entity(gs.morphs.Box(size=PLANK, pos=(-0.4, 0.3, H / 2), quat=_yaw(90.0)))
    right = scene.add_entity(gs.morphs.Box(size=PLANK, pos=(0.4, 0.3, H / 2), quat=_yaw(90.0)))
    top = scene.add_entity(gs.morphs.Box(size=PLANK, pos=(0.0, 0.0, 1.5 * H + 3e-3)))
    scene.build()
    worst = _run_boxes(scene, [left, top, right], 100)  # overlaps of left-top, top-right and with the ground
    assert worst < 2e-3, worst
    assert abs(float(top.get_pos()[2]) - 1.5 * H) < 2e-3, float(top.get_pos()[2])
    assert max(_tilt(b) for b in (left, right, top)) < 2e-3
    assert max(float(b.get_vel().abs().max()) for b in (left, right, top)) < 1e-2


def test_crossed_planks_tilted_settle_flat():
    """Two planks crossed at right angles, the upper one 0.25 m from the lower one's middle and pitched 1 degree
    along its length, its low side touching: it rocks on the square where they overlap (a seesaw: the plank's
    inertia keeps most of its turn at each landing) and settles on it, flat, at the height stacking gives
    (0.075 m), overlapping the lower plank by less than 2 mm throughout. The square's vertices are face-slot
    crossings (see above); before them the plank touched only at its two long-edge midpoints, on a line
    through its centre, and tipped about it (2.5 mm deep, 3 degrees)."""
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    L, W, H = PLANK
    lower = scene.add_entity(gs.morphs.Box(size=PLANK, pos=(0.0, 0.0, H / 2)))
    z = 1.5 * H + W / 2 * np.sin(np.deg2rad(1.0))  # the low long edge on the lower plank's face
    upper = scene.add_entity(gs.morphs.Box(size=PLANK, pos=(0.25, 0.0, z), quat=_yaw(90.0, 1.0)))
    scene.build()
    worst = _run_boxes(scene, [lower, upper], 100)
    assert worst < 2e-3, worst
    assert abs(float(upper.get_pos()[2]) - 1.5 * H) < 2e-3, float(upper.get_pos()[2])
    assert abs(float(lower.get_pos()[2]) - 0.5 * H) < 1e-3
    assert _tilt(upper) < 2e-3 and _tilt(lower) < 2e-3, (_tilt(upper), _tilt(lower))
    assert max(float(b.get_vel().abs().max()) for b in (lower, upper)) < 1e-2


# slow (suite time, ~24 s): face-slot contact of crossed planks is checked by default on two planks
# (plank across two planks, tilted crossed planks)
@pytest.mark.slow
def test_crossed_plank_tower_stands():
    """A log-cabin tower as Genesis's tower example builds it (its 100 boxes fell through each other here):
    two planks on the ground at x = -+0.4 m along y, two across them at y = -+0.4 m along x, one on those along
    y at x = 0.1 m, each course dropped 2 mm: every crossing is off both planks' middles, so only the face
    slots carry them. They stand, at the heights stacking gives, flat and at rest after 1 s."""
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    L, W, H = PLANK
    layout = [(-0.4, 0.0, 90.0), (0.4, 0.0, 90.0), (0.0, -0.4, 0.0), (0.0, 0.4, 0.0), (0.1, 0.0, 90.0)]
    course = [0, 0, 1, 1, 2]
    planks = [scene.add_entity(gs.morphs.Box(size=PLANK, pos=(x, y, (k + 0.5) * H + k * 2e-3), quat=_yaw(yaw)))
              for (x, y, yaw), k in zip(layout, course)]
    scene.build()
    for _ in range(100):
        scene.step()
    z = np.array([float(p.get_pos()[2]) for p in planks])
    np.testing.assert_allclose(z, (np.array(course) + 0.5) * H, atol=2e-3)
    xy = np.array([_np(p.get_pos())[:2] for p in planks])
    np.testing.assert_allclose(xy, np.array(layout)[:, :2], atol=2e-3)
    assert max(_tilt(p) for p in planks) < 2e-3
    assert max(float(p.get_vel().abs().max()) for p in planks) < 1e-2


# long: each contact scene compiles its own contact kernels (~10 s) and these roll out many steps
@pytest.mark.slow
def test_grad_crossed_edges_rest_height_wrt_mass():
    """The upper box of test_boxes_crossed_edge_on_edge_rest, its height after 0.4 s against its mass
    (the edge-edge contact carries it): exact against finite differences."""
    scene, lower, upper = _crossed_edges(requires_grad=True)

    def height(m):
        scene.reset()
        upper.set_links_mass(m.reshape(1))
        for _ in range(40):
            scene.step()
        return upper.get_pos()[2]

    # the gradient is ~1e-5 m/kg (a stiff contact gives way little): central differences of a 0.42 m
    # height with eps = 1e-6 carry ~1e-11 m of rounding per evaluation, a few 1e-6 of the gradient
    rep = gs.grad.check(height, {"mass": _t(1.6)}, tol=1e-5)
    assert rep.ok, str(rep)
    assert float(rep.autograd[0]) < 0


def _landing_loss(scene, box, steps):
    """A loss on the box's position `steps` steps after it is placed at height z with velocity v and
    friction mu (and link mass m, when given first): its sliding landing on the frictionless plane."""

    def loss(*args):
        *m, mu, v, z = args
        scene.reset()
        if m:
            box.set_links_mass(m[0].reshape(1))
        box.set_friction(mu)
        box.set_pos(torch.cat([torch.zeros(2, dtype=F64), z.reshape(1)]))
        box.set_dofs_velocity(torch.cat([v, torch.zeros(3, dtype=F64)]))
        for _ in range(steps):
            scene.step()
        p = box.get_pos()
        return p[0] + 0.5 * p[1] + 2.0 * p[2]

    return loss


# slow (suite time, ~70 s): the gradient matrix's slide_land cases check a sliding landing's gradients by default
@pytest.mark.slow
def test_grad_through_a_sliding_landing():
    """A box dropped while sliding (the friction passes of the solve at work): its position 0.3 s later
    against mu, the initial velocity and the drop height, exact against finite differences."""
    scene = _scene(requires_grad=True)
    scene.add_entity(gs.morphs.Plane(), material=gs.materials.Rigid(friction=0.0))
    box = scene.add_entity(gs.morphs.Box(size=(0.3, 0.2, 0.1), pos=(0, 0, 0.2), quat=(0.999, 0.02, 0.03, 0.01)))
    scene.build()
    rep = gs.grad.check(_landing_loss(scene, box, 30), {"mu": _t(0.3), "v": _t([2.0, 0.5, -1.0]), "z": _t(0.2)},
                        tol=1e-5)
    assert rep.ok, str(rep)
    assert all(float(g.norm()) > 1e-3 for g in rep.autograd)


def _corner_landing_scene(requires_grad, **rigid):
    """A 6 kg box (0.3 x 0.2 x 0.1 m, tilted a little) 1 cm above a frictionless plane at dt = 1 ms, to land on
    a corner: (scene, box)."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=1e-3, requires_grad=requires_grad),
                     rigid_options=gs.options.RigidOptions(**rigid))
    scene.add_entity(gs.morphs.Plane(), material=gs.materials.Rigid(friction=0.0))
    box = scene.add_entity(gs.morphs.Box(size=(0.3, 0.2, 0.1), pos=(0, 0, 0.06), quat=(0.999, 0.02, 0.03, 0.01)),
                           material=gs.materials.Rigid(rho=1000.0))
    scene.build()
    return scene, box


def test_a_law_that_friction_loads_comes_back_into_the_final_system():
    """A law left out of the frictionless solve (its force ~0 there) can push once friction moves load onto
    it; the bound rounds bring it back (passes.func_release_slot). Before 2026-12-05 only laws they had
    released came back: a 6 kg box landing on a corner with the fixed damper (1e6 N/m, 4e4 N s/m) at 1 ms,
    dropped from heights 1e-6 m apart, had that corner's law in (pushing 8.3 N) or out (none) at step 24, and
    its state jumped by 1.5e-5 m against 3.2e-7 m between the next two heights. The state 25 steps after the
    drop is now as continuous in the height on both sides (measured 3.8e-7 and 3.2e-7 m)."""
    scene, box = _corner_landing_scene(False, **FIXED_DAMPER)
    q = []
    for z in (0.06 - 1e-6, 0.06, 0.06 + 1e-6):
        scene.reset()
        box.set_friction(_t(0.3))
        box.set_pos(_t([0.0, 0.0, z]))
        box.set_dofs_velocity(_t([1.0, 0.3, -0.5, 0.0, 0.0, 0.0]))
        for _ in range(25):
            scene.step()
        q.append(_np(box.get_qpos()))
    below, above = np.abs(q[1] - q[0]).max(), np.abs(q[2] - q[1]).max()
    assert 1e-7 < below < 3 * above and above < 3 * below, (below, above)


# slow: ~37 s of compiling each at 1 ms; the default damper's landing gradients run in the default suite in the
# gradient matrix (slide_land, heavy_land: the mass among their inputs) and above, and on an articulated link
# in test_contact_damper
@pytest.mark.slow
@pytest.mark.parametrize("damper", ["critical (default)", pytest.param("fixed", marks=pytest.mark.xfail(
    strict=True, reason="found 2026-12-05: with the fixed damper the drop height's gradient is off central "
    "differences at 1e-6 (104 %, then 224 %; mass, mu and velocity within 2e-7). Traced the same day: the loss is "
    "kinked at the 1e-6 scale of the height (one-sided differences at 1e-5: -2.53 and +3.28; at 1e-7 and 1e-8: "
    "-1.255, -1.200, -1.230, -1.225, converging on autograd's -1.227): the 120 steps of a box rocking on its "
    "corners on an overdamped stiff contact change their sets of laws many times. A jump among them (a law "
    "friction loaded, left out) is fixed: test_a_law_that_friction_loads_comes_back_into_the_final_system"))])
def test_grad_through_a_landing_with_mass_relative_damping(damper):
    """The default contact damper (contact_damping_ratio = 1) is critical per pair, 2 sqrt(k m_eff), where that
    exceeds its floor 4 k h: at dt = 1 ms for this 6 kg box. Its landing, sliding and turning after a drop, then
    depends on the mass through the damper as well as through the dynamics: the position 0.12 s later against
    mass, mu, velocity and height, against central differences in float64. "fixed": the same with the fixed
    damper that was the default until 2026-12-05 (contact_stiffness 1e6, contact_damping 4e4), whose gradient
    the default suite no longer runs."""
    rigid = {} if damper.startswith("critical") else FIXED_DAMPER
    scene, box = _corner_landing_scene(True, **rigid)
    m0 = float(box.get_mass())
    k = gs.options.RigidOptions(**rigid).contact_stiffness
    assert 2 * np.sqrt(k * m0) > 4 * k * 1e-3  # the critical branch, not the floor
    rep = gs.grad.check(_landing_loss(scene, box, 120),
                        {"mass": _t(m0), "mu": _t(0.3), "v": _t([1.0, 0.3, -0.5]), "z": _t(0.06)}, tol=1e-5)
    assert rep.ok, str(rep)
    assert all(float(g.norm()) > 1e-6 for g in rep.autograd)


# ------------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------------
def test_negative_friction_is_an_error():
    with pytest.raises(ValueError, match="friction"):
        gs.materials.Rigid(friction=-0.1)
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    box = scene.add_entity(gs.morphs.Box(pos=(0, 0, 0.5)))
    scene.build()
    with pytest.raises(GenesisException, match="friction"):
        box.set_friction(-0.5)
    with pytest.raises(GenesisException, match="friction"):
        box.set_friction(float("nan"))


@pytest.mark.parametrize("name,value", [("contact_stiffness", -1.0), ("contact_damping", -1.0),
                                        ("contact_smoothing", 0.0), ("friction_smoothing", -1e-3),
                                        ("max_mesh_contact_points", 2), ("contact_stiffness", float("inf")),
                                        ("contact_damping_ratio", 0.0), ("contact_damping_ratio", float("nan")),
                                        ("friction_smoothing_accel", 0.0), ("friction_smoothing_accel", -1.0)])
def test_bad_contact_options_are_errors(name, value):
    with pytest.raises(ValueError, match=name):
        gs.options.RigidOptions(**{name: value})


def test_a_fixed_damper_and_a_damping_ratio_together_are_an_error():
    """Two dampers cannot both act: giving contact_damping and contact_damping_ratio is refused, naming both."""
    with pytest.raises(ValueError, match=r"contact_damping=4000.0: and contact_damping_ratio=0.5 both given: give one"):
        gs.options.RigidOptions(contact_damping=4e3, contact_damping_ratio=0.5)
    assert gs.options.RigidOptions(contact_damping=4e3).contact_damping_ratio is None


def test_unsupported_pair_is_an_error():
    """A plane on a moving link against another geom is refused with the pair and the way out named, and
    ignore_unsupported_pairs drops the pair. (No loader makes such a plane today: gs.morphs.Plane is
    static and MuJoCo refuses a plane in a moving body; the check guards the contact model's assumption
    that the SDF side of a plane pair does not move, so it is tested on the pair filter directly.)"""
    from types import SimpleNamespace

    from solvers.rigid.collision import GEOM_PLANE, GEOM_SPHERE, candidate_pairs

    geoms = SimpleNamespace(n=2, type=np.array([GEOM_PLANE, GEOM_SPHERE]), link=np.array([0, 1]),
                            entity=np.array([0, 1]), names=["entity 'floater', plane geom", "entity 'ball', sphere geom"])
    flat = SimpleNamespace(n_links=2, np_link_parent=np.array([-1, -1]), np_link_ndof=np.array([6, 6]))
    with pytest.raises(ValueError, match="plane on a moving link.*'floater'.*ignore_unsupported_pairs"):
        candidate_pairs(geoms, flat, False, False)
    assert candidate_pairs(geoms, flat, False, True) == []
    flat.np_link_ndof = np.array([0, 6])  # the plane's link does not move: an ordinary pair
    assert candidate_pairs(geoms, flat, False, False) == [(1, 0)]


@pytest.mark.slow  # ~38 s of compiling for its mesh classes; by default mesh against mesh runs in
# test_grad_through_mesh_against_mesh_contact (a mesh box landing on a mesh slab: gradients and motion)
def test_meshes_collide_with_meshes(mesh_files):
    """Convex meshes against convex meshes (each hull's points against the other's k-DOP, both ways), on a
    fixed mesh slab: a mesh cube slides v^2 / (2 mu g) and stops, an icosphere rests on its lowest vertex,
    and a mesh box carrying a smaller mesh cube (two moving meshes: the coupled solve) rest at the heights
    the geometry says."""
    import trimesh

    slab, cube, small = mesh_files / "slab.obj", mesh_files / "cube.obj", mesh_files / "small.obj"
    trimesh.creation.box(extents=(4.0, 2.0, 0.1)).export(slab)
    trimesh.creation.box(extents=(0.2, 0.2, 0.2)).export(cube)
    trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(small)
    ico, mbox = str(mesh_files / "ico.stl"), str(mesh_files / "box.obj")
    r_ico = -float(trimesh.load(ico).vertices[:, 2].min())
    mu, v0 = 0.5, 3.0
    rigid = gs.materials.Rigid(friction=mu)
    scene = _scene()
    scene.add_entity(gs.morphs.Mesh(file=str(slab), pos=(0.0, 0.0, 0.05), fixed=True), material=rigid)
    slider = scene.add_entity(gs.morphs.Mesh(file=str(cube), pos=(-1.5, 0.0, 0.21)), material=rigid)
    resting = scene.add_entity(gs.morphs.Mesh(file=ico, pos=(1.0, 0.5, 0.1 + r_ico + 0.01)))
    lower = scene.add_entity(gs.morphs.Mesh(file=mbox, pos=(1.0, -0.5, 0.16)))
    upper = scene.add_entity(gs.morphs.Mesh(file=str(small), pos=(1.03, -0.5, 0.26)))
    scene.build()
    assert scene.rigid_solver.dense_solve  # the two moving meshes touch each other
    for _ in range(30):
        scene.step()
    x0 = float(slider.get_pos()[0])
    slider.set_dofs_velocity(_t([v0, 0, 0, 0, 0, 0]))
    for _ in range(int(1.5 * v0 / (mu * G) / DT) + 20):
        scene.step()
    d, ref = float(slider.get_pos()[0]) - x0, v0 ** 2 / (2 * mu * G)
    assert abs(d - ref) / ref < 0.05, (d, ref)
    for what, ent, z, sink in (("slider", slider, 0.2, _sink_bound(slider)), ("icosphere", resting, 0.1 + r_ico,
                               _sink_bound(resting)), ("lower", lower, 0.15, _sink_bound(lower, upper, i=0)),
                               ("upper", upper, 0.25, _sink_bound(lower, upper))):
        assert -2e-4 < z - float(ent.get_pos()[2]) < sink + 2e-4, (what, float(ent.get_pos()[2]), z, sink)
        assert float(ent.get_vel().abs().max()) < 2e-3, what


# slow: ~83 s (a fixed slab) and ~60 s (moving: the coupled, densely factorised solve) of a fresh-cache default
# suite with their compiles (2026-12-03: 1,127 s on 2 cores, over its 15 minutes); the default suite keeps a mesh
# on mesh gradient in the gradient matrix's raft case (tests/gradient_cases.py, hull-edge slots)
@pytest.mark.slow
@pytest.mark.parametrize("moving", [False, True])
def test_grad_through_mesh_against_mesh_contact(mesh_files, moving):
    """A mesh box, turned about z and tilted (its corners land one after another), dropped sliding onto a
    fixed mesh slab, or onto a moving mesh box lying on it: exact against finite differences in its mass,
    its friction and its initial velocity."""
    import trimesh

    slab = mesh_files / "slab_g.obj"
    trimesh.creation.box(extents=(2.0, 2.0, 0.1)).export(slab)
    mbox = str(mesh_files / "box.obj")
    scene = _scene(requires_grad=True)
    scene.add_entity(gs.morphs.Mesh(file=str(slab), pos=(0.0, 0.0, -0.05), fixed=True),
                     material=gs.materials.Rigid(friction=0.3))
    lower = scene.add_entity(gs.morphs.Mesh(file=mbox, pos=(0.0, 0.0, 0.05)),
                             material=gs.materials.Rigid(rho=200.0, friction=0.4)) if moving else None  # light: it moves
    top = scene.add_entity(gs.morphs.Mesh(file=mbox, pos=(0.04, 0.01, 0.17 if moving else 0.07),
                                          quat=tuple(np.array([0.99, 0.03, -0.02, 0.15]) / np.linalg.norm([0.99, 0.03, -0.02, 0.15]))))
    scene.build()
    assert scene.rigid_solver.dense_solve == moving
    s0 = scene.get_state()

    def loss(m, mu, v):
        _roll_body(scene, s0, top, m, mu, torch.cat([v, _t([0.3, -0.5, 0.8])]), 25)
        p = top.get_pos()
        out = p[0] + 0.3 * p[1] + 2 * p[2]
        return out + lower.get_pos()[0] - 0.5 * lower.get_pos()[1] if moving else out

    # with the moving box, some steps run bound rounds (contact/__init__.py, step 5), whose tolerance band
    # is piecewise linear: the mass's differences need steps of 1e-5 (over 1e-6 they were off by ~1e-5
    # relative, round-off), the velocity's 1e-6 (over 1e-5 its second component is off by 2.9e-4
    # relative, converging on autograd's as the step shrinks: -0.0090891, -0.0090917, -0.00909176)
    m, mu, v = _t(0.7), _t(0.6), _t([0.4, 0.2, -0.5])
    # (2026-12-03, with the meshes' face slots: the mass's differences at 1e-5 are 1.75e-5 off autograd's by the
    # loss's curvature, at 3e-6 1.5e-6, at 1e-6 6e-8; a WIP note, see the branch's last commit)
    for fn, inputs, eps in ((lambda a, b: loss(a, b, v), {"mass": m, "mu": mu}, 1e-6),
                            (lambda x: loss(m, mu, x), {"v": v}, 1e-6)):
        rep = gs.grad.check(fn, inputs, eps=eps, tol=1e-5)
        assert rep.ok, str(rep)
        # none trivially zero (measured 2026-11-28, moving: |d/d mu| 6.9e-5, agreeing with the differences to
        # 1e-7; 1.9e-2 for the mass)
        assert all(float(g.norm()) > 1e-5 for g in rep.autograd), str(rep)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # trimesh dividing by the flat mesh's zero volume
def test_mesh_without_volume_is_an_error(mesh_files, tmp_path):
    flat = str(mesh_files / "flat.stl")
    scene = _scene()
    with pytest.raises(ValueError, match="volume"):
        scene.add_entity(gs.morphs.Mesh(file=flat))
    # a URDF link with an explicit inertial (so loading succeeds) and a flat collision mesh
    urdf = tmp_path / "flat.urdf"
    urdf.write_text(f"""<robot name="flat"><link name="base">
      <inertial><mass value="1"/><inertia ixx="1e-2" iyy="1e-2" izz="1e-2" ixy="0" ixz="0" iyz="0"/></inertial>
      <collision><geometry><mesh filename="{flat}"/></geometry></collision></link></robot>""")
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    # (an object's mesh, by Genesis's rules, is measured against its hull when it is loaded: the error comes from
    # add_entity; a robot's from build)
    with pytest.raises(ValueError, match="no volume"):
        scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=False, pos=(0, 0, 1)))
        scene.build()
