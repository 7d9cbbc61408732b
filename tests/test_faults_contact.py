"""Fault injection on rigid contact (issue #21, "Faults and bad input"): extreme speeds, spins and masses.

1. Forces from nowhere: a box spinning at 1e3 or 1e6 rad/s, 6 cm above the ground and 1 m from another
   box, touches nothing, so both keep their free-flight momentum (v = v0 + g t, w = w0) exactly. Before,
   its speculative contacts predicted the gap closing along the corners' tangents (h w x r: metres per
   step) and the ground threw it at 28.8 m/s (1e3 rad/s) or 1.25e4 m/s (1e6 rad/s), and the two boxes
   exchanged momentum; the depth prediction now turns each body by exactly h w (contact.func_rot_excess).
2. Tunnelling: a box at 1e6 m/s onto the ground or onto another box (1e4 m per step of 0.01 s) ends the
   step metres deep: the scene warns (ContactPenetrationWarning), naming both bodies, the step and
   what to do (smaller dt / more substeps, or a stiffer contact); once per pair of geoms, so that a
   body placed inside the ground at the start does not hide a later tunnelling elsewhere.
3. Heavy bodies: a 4 t or 400 t box rests on the ground within 0.5 mm (its contacts' stiffness scales
   with its mass above 100 kg); a 400 t box carried by a light box presses that one into the ground (its
   contacts keep its own stiffness): the scene warns, naming RigidOptions.contact_stiffness; with the
   stiffness the message asks for, it rests.
4. A box sliding over the edge of a fixed box (the setup of the known bug): the contact force on it
   stays within Coulomb's cone, |horizontal| <= mu * vertical (its contacts are face contacts).

Default options, float64 (conftest). All default-set scenes share one contact class (ground + two free
boxes, 4 envs), so their kernels compile once.
"""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

import genesis_lite as gs
from solvers.rigid.contact import ContactPenetrationWarning

G = 9.81
DT = 0.01
F64 = torch.float64
N_ENVS = 4


def _t(x):
    return torch.as_tensor(np.asarray(x, dtype=float), dtype=F64)


def _np(x):
    return x.detach().cpu().numpy()


def _ground_and_two_boxes(size_a=(0.2, 0.2, 0.2), rho_a=1000.0, **rigid):
    """Ground, box A and box B (0.2 m, free), 4 envs: the shape every default test here uses."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT), rigid_options=gs.options.RigidOptions(**rigid))
    scene.add_entity(gs.morphs.Plane())
    a = scene.add_entity(gs.morphs.Box(size=size_a, pos=(0.0, 0.0, 1.0)), material=gs.materials.Rigid(rho=rho_a))
    b = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0.0, 3.0, 1.0)))
    scene.build(n_envs=N_ENVS)
    return scene, a, b


def _place(body, pos, vel):
    body.set_pos(_t(np.broadcast_to(pos, (N_ENVS, 3)).copy()))
    body.set_dofs_velocity(_t(np.broadcast_to(vel, (N_ENVS, 6)).copy()))


def test_spinning_box_touches_nothing_and_keeps_free_flight():
    """Box A (0.2 m) 6 cm above the ground (its corners sweep down to 1.9 cm above it) and 1 m from box
    B, spinning at 1e3 and 1e6 rad/s about x (corners sweeping towards the ground and B) or z: after 3
    steps both boxes move exactly as in free flight (semi-implicit Euler: v = g n h, w = w0), and
    nothing warns. Before the fix env 0 left at 28.8 m/s."""
    scene, a, b = _ground_and_two_boxes()
    spins = [(1e3, 0.0, 0.0), (1e6, 0.0, 0.0), (0.0, 0.0, 1e3), (0.0, 0.0, 1e6)]
    _place(a, (0.0, 0.0, 0.16), [(0.0, 0.0, 0.0) + w for w in spins])
    _place(b, (0.0, 1.0, 0.16), (0.0,) * 6)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ContactPenetrationWarning)
        for _ in range(3):
            scene.step()
    v_free = np.array([0.0, 0.0, -G * 3 * DT])
    for body, w0 in ((a, np.array(spins)), (b, np.zeros((N_ENVS, 3)))):
        dv = np.abs(_np(body.get_vel()) - v_free).max(1)
        assert (dv < 1e-5).all(), (body.name, dv)  # m/s; the bug: 28.8 and 1.25e4
        dw = np.abs(_np(body.get_ang()) - w0).max(1)
        assert (dw <= 1e-9 * np.maximum(np.abs(w0).max(1), 1.0)).all(), (body.name, dw)
    # and nothing touched: no contact force reported
    for body in (a, b):
        assert float(np.abs(_np(body.get_links_net_contact_force())).max()) < 1e-9


@pytest.mark.parametrize("onto", ["plane", "box"])
def test_box_at_1e6_mps_warns_that_the_step_is_too_long(onto):
    """A box falling at 1e6 m/s (1e4 m per step) onto the ground, or shot along the ground at box B
    resting on it, cannot be stopped by the penalty contact within the step: the first step warns,
    naming the bodies of the deepest contact (the falling box and the ground; B, which A shoves through
    the ground), the step and the remedies (dt / substeps)."""
    scene, a, b = _ground_and_two_boxes()
    if onto == "plane":
        _place(b, (0.0, 3.0, 0.1), (0.0,) * 6)
        _place(a, (0.0, 0.0, 0.5), (0.0, 0.0, -1e6, 0.0, 0.0, 0.0))
        other = "plane"
    else:  # both on the ground, A shot sideways at B
        _place(b, (0.0, 0.0, 0.1), (0.0,) * 6)
        _place(a, (0.0, -0.5, 0.1), (0.0, 1e6, 0.0, 0.0, 0.0, 0.0))
        other = f"entity '{b.name}'"
    with pytest.warns(ContactPenetrationWarning) as rec:
        scene.step()
    msg = str(rec[0].message)
    assert rec[0].filename == __file__  # points at the user's scene.step()
    # onto the box: A shoves B through the ground within the step, and that is the deepest contact
    assert (f"entity '{a.name}'" in msg and other in msg) if onto == "plane" else other in msg, msg
    assert "at step 1 " in msg and "too fast" in msg, msg
    assert "smaller dt" in msg and "substeps" in msg, msg
    # once per pair of geoms: the next steps do not warn about that pair again
    with warnings.catch_warnings(record=True) as later:
        warnings.simplefilter("always", ContactPenetrationWarning)
        scene.step()
        scene.step()
    first = msg.split(": at step")[0]
    assert not any(str(w.message).split(": at step")[0] == first for w in later), [str(w.message) for w in later]


def test_a_later_tunnelling_warns_after_an_early_one():
    """Box B starts 10 cm inside the ground (warned at step 1). Ten steps later box A is shot into the
    ground at 1e6 m/s: a second warning, naming A. Before (2026-11-28) the scene warned once in all, so
    a body set inside another at the start silenced every later warning (a thrown pile whose upright
    cylinder started 15 cm in the ground said nothing of the tangles that blew it up,
    tests/test_many_bodies.py)."""
    scene, a, b = _ground_and_two_boxes()
    _place(b, (0.0, 3.0, 0.0), (0.0,) * 6)
    _place(a, (0.0, 0.0, 0.5), (0.0,) * 6)
    with pytest.warns(ContactPenetrationWarning) as rec:
        scene.step()
    assert f"entity '{b.name}'" in str(rec[0].message) and "at step 1 " in str(rec[0].message)
    for _ in range(9):
        scene.step()
    _place(a, (0.0, 0.0, 0.3), (0.0, 0.0, -1e6, 0.0, 0.0, 0.0))
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always", ContactPenetrationWarning)
        for _ in range(16):
            scene.step()
    msgs = [str(w.message) for w in rec if issubclass(w.category, ContactPenetrationWarning)]
    assert any(f"entity '{a.name}'" in m and "at step 11 " in m and "too fast" in m for m in msgs), msgs


@pytest.mark.parametrize("tonnes", [4, 400])
def test_heavy_box_rests_on_the_ground(tonnes):
    """A 4 t or 400 t box (1 m cube) set on the ground rests on it: its contacts' stiffness and damping
    scale with its mass above k (10 ms)^2, 10 kg at the default 1e5 N/m (solvers/rigid/contact/law.py,
    heavy_mass), as MuJoCo's follow the
    effective mass (MuJoCo: 0.11 mm for a 400 t, 0.2 m box). After 1 s it is within 0.5 mm of resting
    height (measured: 0.25 mm), at rest, and nothing warns. Before: the 400 t box sank 0.76 m (its
    weight on four corners of 1e6 N/m)."""
    scene, a, b = _ground_and_two_boxes(size_a=(1.0, 1.0, 1.0), rho_a=tonnes * 1e3)
    _place(a, (0.0, 0.0, 0.5), (0.0,) * 6)
    _place(b, (0.0, 3.0, 0.1), (0.0,) * 6)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ContactPenetrationWarning)
        for _ in range(100):
            scene.step()
    sink = 0.5 - _np(a.get_pos())[:, 2]
    assert ((sink > 0) & (sink < 5e-4)).all(), sink
    assert float(a.get_vel().norm(dim=-1).max()) < 1e-6


def test_heavy_load_on_a_light_box_warns_about_contact_stiffness():
    """The scaling follows each contact's own pair: a 400 t box resting on a light one (box B, 4.8 kg) presses
    B into the ground with 3.9 MN through contacts of B's own 1e5 N/m, which cannot hold it. Within 32 steps
    the scene warns, naming contact_stiffness and the light body's case."""
    scene, a, b = _ground_and_two_boxes(size_a=(1.0, 1.0, 1.0), rho_a=4e5)
    _place(b, (0.0, 0.0, 0.1), (0.0,) * 6)
    _place(a, (0.0, 0.0, 0.7), (0.0,) * 6)
    with pytest.warns(ContactPenetrationWarning) as rec:
        for _ in range(32):
            scene.step()
    msg = str(rec[0].message)
    assert f"entity '{b.name}'" in msg and "contact_stiffness" in msg and "light body" in msg, msg
    assert float(b.get_pos()[0, 2]) < 0.1 - 0.01  # B did sink (more than 10 % of its size)


EDGE_SPINS = (1.1, 1.2, 1.3, 1.4, 1.5, 1.6, 1.7, 1.8)  # rad/s about z: the reported 1.5 and its neighbours


def _edge_slide_cone_excess(wz):
    """The reported setup (dt = 1e-3): a box (0.12 x 0.1 x 0.08 m, 0.58 kg) sliding and turning (wz rad/s)
    on a fixed box (0.2 x 0.2 x 0.1 m) over its edge, 200 steps. For every step whose contacts are all face
    contacts (vertical normals): how far the contact force on the sliding box (from its momentum change,
    gravity removed) exceeds Coulomb's bound, |horizontal| - (mu * vertical (mu = 1) + 5 % + 0.05 N for the
    smoothing), and whether a contact of that step pulled (its normal force < 0)."""
    dt = 1e-3
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt))
    scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.1), pos=(0.0, 0.0, 0.051), fixed=True))
    q = np.array([0.98, 0.0, 0.0, 0.2])
    up = scene.add_entity(gs.morphs.Box(size=(0.12, 0.1, 0.08), pos=(0.02, -0.01, 0.143), quat=tuple(q / np.linalg.norm(q))))
    scene.build()
    up.set_dofs_velocity(_t([0.8, -0.4, -0.1, 0.0, 0.0, wz]))
    m = float(up.get_mass().reshape(-1)[0])
    v = _np(up.get_vel()).copy()
    rows = []
    for _ in range(200):
        scene.step()
        v1 = _np(up.get_vel()).copy()
        f = m * (v1 - v) / dt - m * np.array([0.0, 0.0, -G])
        v = v1
        c = up.get_contacts()
        n, F = _np(c["normal"]), _np(c["force_a"])
        if len(n) and (np.abs(n[:, 2]) > 0.99).all():
            pull = ((F * n).sum(-1) < -1e-9 * np.abs(F).sum()).any()  # below the rounding of the reported sums
            rows.append((np.linalg.norm(f[:2]) - (1.05 * max(f[2], 0.0) + 0.05), bool(pull)))
    return rows


@pytest.mark.slow
def test_box_sliding_over_an_edge_stays_in_the_friction_cone():
    """Issue #21, item 4 (see _edge_slide_cone_excess for the setup): in every step of face contacts, no
    contact pulls, and the contact force on the sliding box obeys Coulomb, for the reported spin and seven
    around it. Measured 2026-12-02: 190-192 such steps a run, 1,530 in all, none pulling, none over the bound.
    Until that day one step was over (2026-11-28, the 1.2 rad/s run: 0.595 N over a bound of 7.6 N), in which
    the bound rounds released a contact whose law pulled and the others' friction kept its bound mu f2 from
    the frictionless solve, whose loads included the released one's; friction's load is now the law's force
    with Coulomb's forces applied, bounded in the rounds by the law's force at their solution (the package
    docstring's note on friction's load).

    The history: a strict xfail until 2026-11-27. The lower box's top edge, level with the sliding box's
    bottom face (1 um gap), is tested against the sliding box's SDF, whose nearest feature there is its side
    face; the step's linear prediction along that face's normal (the box slides towards the edge at 0.8
    m/s, 0.8 mm per step, against a 0.18 mm gap) closes a gap that never closes, so a horizontal speculative
    force of ~100 N kicks the box, and its sticking friction, unbounded in the final solve, then made the
    box rock: steps later its horizontal force was 1.7-3x its vertical one. The bound rounds
    (contact/__init__.py, step 5) keep that friction within the law. Until 2026-11-28 the steps in which a
    contact of the final system pulled were left out (8 to 190 steps a run were checked), and with them
    included the bound was exceeded in 4 of the 8 runs, by up to 26 N (a strict xfail); the bound rounds
    now also release a law that pulls."""
    checked, over = 0, []
    for wz in EDGE_SPINS:
        rows = _edge_slide_cone_excess(wz)
        assert not any(pull for _, pull in rows), wz
        over += [ex for ex, _ in rows if ex > 0.0]
        checked += len(rows)
    assert checked > 1200, checked
    assert not over, over
