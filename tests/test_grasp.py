"""A Panda (example-robot-data's URDF, its finger pads boxes) grasps a 4 cm cube from the ground and lifts
it, as Genesis's rigid/franka_cube.py does: the arm goes above the cube by inverse kinematics, the fingers
close under PD (kp 100, target 0), the arm lifts. Default options, dt = 10 ms, float64 (conftest).

With the lift's joint targets ramped over 1 s, or changed at once (the script's way: the arm yanks the
hand up 0.165 m), the grasp holds: the pads stay on the cube's faces and the cube rises with the hand.
Before 2026-11-28 the abrupt lift squeezed the pads 6 mm into the cube and left it spinning at 19 rad/s
(a strict xfail): the normal solve's one-shot choice of contacts (contact/__init__.py, step 2b now),
and the second finger, a URDF <mimic> of the first, moved by copying after each step, so that the
contact solve predicted a pad that then went elsewhere (inertia.func_fold_matrix now ties it)."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

import genesis_lite as gs

CUBE = 0.04
KP = np.array([4500, 4500, 3500, 3500, 2000, 2000, 2000, 100, 100], dtype=float)
KV = np.array([450, 450, 350, 350, 200, 200, 200, 10, 10], dtype=float)
Q_START = np.array([-1.0124, 1.5559, 1.3662, -1.6878, -1.5799, 1.7757, 1.4602, 0.04, 0.04])
# the URDF merges panda_hand into panda_link7: the hand is 0.107 m along link 7's z, turned -45 degrees
# about it. Link 7 is aimed so that the hand points down with its fingers closing along the world's y.
TCP = 0.107
Q7 = np.array([0.0, np.cos(np.pi / 8), -np.sin(np.pi / 8), 0.0])


def _np(x):
    return np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x, dtype=float)


def _grasp_and_lift(urdf_path, ramp_steps, lift_steps=150, watch=None, integrator=None, rho=None):
    """The grasp: hold above the cube 1 s, close the fingers 1 s, lift 1.5 s with the arm's joint targets
    moving from the grasp pose to the lift pose over `ramp_steps` steps (1: at once); watch(franka, cube)
    after each lift step if given. Returns the cube's position, its angular speed and the two finger
    joints' positions at the end. integrator: a gs.integrator name instead of the default; rho: the
    cube's density instead of the default."""
    rigid = {} if integrator is None else {
        "rigid_options": gs.options.RigidOptions(integrator=getattr(gs.integrator, integrator))}
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01), **rigid)
    scene.add_entity(gs.morphs.Plane())
    franka = scene.add_entity(gs.morphs.URDF(file=str(urdf_path("panda")), fixed=True))
    material = {} if rho is None else {"material": gs.materials.Rigid(rho=rho)}
    cube = scene.add_entity(gs.morphs.Box(size=(CUBE,) * 3, pos=(0.65, 0.0, CUBE / 2)), **material)
    scene.build()
    arm, fingers = np.arange(7), np.arange(7, 9)
    franka.set_dofs_kp(KP)
    franka.set_dofs_kv(KV)
    franka.set_qpos(Q_START)
    scene.step()
    link7 = franka.get_link("panda_link7")
    q_grasp = _np(franka.inverse_kinematics(link=link7, pos=np.array([0.65, 0.0, 0.135 + TCP]), quat=Q7))
    q_lift = _np(franka.inverse_kinematics(link=link7, pos=np.array([0.65, 0.0, 0.3 + TCP]), quat=Q7))

    def step(q_arm, finger_target):
        franka.control_dofs_position(q_arm, arm)
        franka.control_dofs_position(np.full(2, finger_target), fingers)
        scene.step()

    for _ in range(100):
        step(q_grasp[:7], 0.04)
    for _ in range(100):
        step(q_grasp[:7], 0.0)
    for i in range(lift_steps):
        a = min(1.0, (i + 1) / ramp_steps)
        step((1 - a) * q_grasp[:7] + a * q_lift[:7], 0.0)
        if watch is not None:
            watch(franka, cube)
    return _np(cube.get_pos()), float(np.linalg.norm(_np(cube.get_dofs_velocity())[3:])), \
        _np(franka.get_dofs_position())[7:]


def _check(pos, spin, fingers):
    # the pads on the cube's faces (each finger 0.02 m open), within 1 mm
    assert np.all(np.abs(fingers - CUBE / 2) < 1e-3), fingers
    # lifted with the hand: the fingertips end ~0.12 m under the lift target of the hand (0.3 m)
    assert 0.15 < pos[2] < 0.2 and np.hypot(pos[0] - 0.65, pos[1]) < 0.01, pos
    assert spin < 0.1, spin


def test_a_panda_grasps_a_cube_and_lifts_it(urdf_path):
    """Lift ramped over 1 s; the cube at Genesis's default density for objects, 600 kg/m^3 (38 g). Measured
    (2026-11-28, the defaults: approximate_implicitfast, armature 0.1, the bound rounds' releases): fingers
    0.0200 / 0.0200, cube at (0.652, -0.0004, 0.185). Before, with a 200 kg/m^3 cube: (0.651, -0.0004,
    0.178)."""
    _check(*_grasp_and_lift(urdf_path, ramp_steps=100))


def test_a_panda_lifting_a_cube_at_once_keeps_it_between_its_pads(urdf_path):
    """The lift's targets changed at once, as Genesis's franka_cube.py does. Measured (2026-11-28, the
    defaults, a 38 g cube): it ends at (0.652, -0.0004, 0.185), fingers 0.0200 / 0.0200 (Genesis's own
    franka_cube: 0.652, -0.0004, 0.183). Before the bound rounds released a law that pulls (contact
    package docstring, step 5), the ground's laws, kept because they pushed in the frictionless solve,
    held the cube down with up to 3.6 N against its 0.38 N weight: the 38 g cube stayed at z = 0.020
    while the pads slid up its faces and the fingers closed on nothing (9.6e-10); a 12.8 g cube rose,
    turning between the pads at up to 19 rad/s, and ended at (0.651, -0.0004, 0.165). At 82740ed: 37 kN
    of contact force in the lift's first steps, the pads 1.7 cm deep; it ended with the fingers 5.7 mm
    inside its faces."""
    _check(*_grasp_and_lift(urdf_path, ramp_steps=1))


@pytest.mark.parametrize("rho", [200.0, pytest.param(2000.0, marks=pytest.mark.slow)])
def test_the_abrupt_lift_holds_lighter_and_heavier_cubes(urdf_path, rho):
    """The abrupt lift with a 12.8 g cube (200 kg/m^3, genesis_lite's default density before 2026-11-28)
    and a 128 g one. Measured (2026-11-29, float64): 200: (0.6525, -0.0004, 0.1850), 2000: (0.6517, -0.0004,
    0.1816), fingers 0.0200 / 0.0200 (float32, 2000: (0.6520, -0.0004, 0.1754))."""
    _check(*_grasp_and_lift(urdf_path, ramp_steps=1, rho=rho))


@pytest.mark.xfail(strict=True, reason="the final system lets go of a pad's rows of laws (and the bound rounds' "
                   "releases oscillate): a 192 g cube turns at up to 7.4 rad/s in the abrupt lift's first steps (8.9 "
                   "before friction's load was the law's force with Coulomb's forces applied, 6.5 at 52afb4e)")
def test_the_abrupt_lift_of_a_heavy_cube_does_not_turn_it(urdf_path):
    """A 192 g cube (3,000 kg/m^3; the pads squeeze with ~2 N each) lifted at once: it should rise between
    the pads without turning. Measured (2026-11-29): it ends held at (0.650, -0.0004, 0.175), but turns at up
    to 8.9 rad/s on the way (7.4 rad/s on 2026-12-02, friction's load with Coulomb's forces applied) (6.5 rad/s before the releases, 52afb4e). Traced on Genesis's MJCF Panda (mesh
    pads, ~40 contact points a pad): in the lift's first step the bound rounds release ~10 of a pad's 16
    laws and the ground's four, bring the ground's back at 279-439 N, release them again, and end (8 rounds)
    with a pad held by a few points: the cube tilts at 1.8 rad/s in that step; with the MJCF Panda a 128-192 g
    cube then keeps turning at 2-7 rad/s while held (Genesis 0.4.5: 0.04 rad/s; 52afb4e: 0.01). The rounds
    release every law that pulls at once and bring one back once; choosing the releases by step 2b's exact line
    search instead (a prototype) still turns the cube, so the final system's own solution lets go of the rows.
    Traced further (2026-11-29, MJCF Panda, 192 g, float64): with no limit on returns the releases cycle with a
    period of three rounds; changing only the worst law a round, the viscosities held while the set changes,
    reaches a set exact for its viscosities, and the cube still tilts at 1.3 rad/s: the pads' viscosities
    (secants at intermediate rounds' slips, 0.07-0.19 N s/m against the friction pass's 3-5; bounds from the
    frictionless loads, a quarter apart between the pads) make the tilt, not the set search."""
    spins = []
    _grasp_and_lift(urdf_path, ramp_steps=1, rho=3000.0, lift_steps=60,
                    watch=lambda franka, cube: spins.append(float(np.linalg.norm(_np(cube.get_ang())))))
    assert max(spins) < 1.0, max(spins)


def test_the_reported_contact_forces_add_up_to_what_the_cube_felt(urdf_path):
    """In the abrupt lift's first 20 steps, the forces get_contacts() lists on the cube, and
    get_links_net_contact_force(), add up to the cube's momentum change less its weight, to the rounding
    of their sums, and no listed contact pulls (to its rounding). Before (2026-11-28) both left out the
    contacts whose linearised normal law pulled (they were listed by fn > 0): the listed forces summed to
    up to 245 kN while the cube felt 1-2 N; listed, such contacts then pulled: the ground's held the cube
    down (up to 3.6 N on a 0.38 N cube) and points of the pads' faces pulled up to 2.5 N, until the
    bound rounds released a law that pulls (contact package docstring, step 5)."""
    rows, pulls = [], []
    state = {}

    def watch(franka, cube):
        m = float(_np(cube.get_mass()).reshape(-1)[0])
        v = _np(cube.get_vel()).reshape(-1)
        if "v" in state:
            felt = m * (v - state["v"]) / 0.01 - m * np.array([0.0, 0.0, -9.81])
            ct = cube.get_contacts()
            f, n = _np(ct["force_a"]).reshape(-1, 3), _np(ct["normal"]).reshape(-1, 3)
            net = _np(cube.get_links_net_contact_force()).reshape(-1)
            rows.append((felt, f.sum(0), net, np.abs(f).sum()))
            pulls.extend(zip((f * n).sum(-1), np.abs(f).sum(-1)))
        state["v"] = v

    _grasp_and_lift(urdf_path, ramp_steps=1, lift_steps=20, watch=watch)
    assert all(fn >= -1e-9 * scale - 1e-12 for fn, scale in pulls), min(pulls)
    for felt, listed, net, scale in rows:
        tol = 1e-9 * scale + 1e-6
        assert np.abs(listed - felt).max() <= tol and np.abs(net - felt).max() <= tol, (felt, listed, net, scale)


def _grasp_in_float32(ramp_steps, integrator=None):
    """The grasp and lift in a fresh float32 process (tests/workers/grasp_precision.py)."""
    worker = os.path.join(os.path.dirname(os.path.abspath(__file__)), "workers", "grasp_precision.py")
    out = subprocess.run([sys.executable, worker, "32", str(ramp_steps)] + ([integrator] if integrator else []),
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-4000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    return np.array(r["pos"]), r["spin"], np.array(r["fingers"])


@pytest.mark.slow
def test_a_panda_grasps_a_cube_and_lifts_it_in_float32():
    """The ramped lift in float32, Genesis's default precision, with the defaults (approximate_implicitfast,
    armature 0.1, a 38 g cube). Measured (2026-11-28, after the bound rounds' releases): fingers 0.0200 /
    0.0200, cube at (0.652, -0.0004, 0.185), as in float64 within 0.2 mm. Before (at b4ebdfe, a 12.8 g cube)
    it was thrown to (0.79, 0.98, 2.03), spinning at 403 rad/s: blamed then on float32's resolution of the
    pads' forces, it was the ground's laws gluing the cube (the float64 run held it by a narrower
    margin)."""
    _check(*_grasp_in_float32(ramp_steps=100))


@pytest.mark.slow
def test_a_panda_grasps_a_cube_in_float32_with_implicitfast():
    """The ramped lift in float32 with implicitfast (kp and kv implicit while not saturated). Measured
    (2026-11-28, after the bound rounds' releases, a 38 g cube): fingers 0.0200 / 0.0200, cube at (0.652,
    -0.0004, 0.185) (at b4ebdfe, a 12.8 g cube: 0.652, -0.0004, 0.178)."""
    _check(*_grasp_in_float32(ramp_steps=100, integrator="implicitfast"))


@pytest.mark.slow
def test_a_panda_lifting_a_cube_at_once_in_float32():
    """The abrupt lift in float32 with the defaults. Measured (2026-11-28, after the bound rounds'
    releases, a 38 g cube): fingers 0.0200 / 0.0200, cube at (0.652, -0.0004, 0.185). Before (at b4ebdfe,
    a 12.8 g cube) the fingers closed through the cube (1e-9), which stayed on the ground at (0.654,
    -0.007, 0.020); with implicitfast it was thrown to (-4.1, -3.1, 0.033) spinning at 667 rad/s."""
    _check(*_grasp_in_float32(ramp_steps=1))
