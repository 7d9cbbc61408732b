"""Gradients of a body that starts in exact contact with the ground (depth exactly 0), the most common
initial state (a box set down on the floor, a robot standing on it).

At depth 0 with no normal velocity the contact law's softplus is evaluated at exactly 0 (both the
current and the predicted depth), where its derivative is 1/2. Spelled max(z, 0) + log(1 + e^-|z|),
Taichi's reverse mode gave 0 there (max's adjoint goes to its second argument at a tie, abs's is
sign(0) = 0), so the first step lost the force's dependence on the depth: a box on the ground pushed
along x had d(x + 2y)/d(vz) = 0.754 by autograd against 0.301 by finite differences (the tracker case,
the first test here).
The forward is smooth there (the one-sided differences agree), so autograd must give its derivative.

Every case checks autograd against finite differences in float64, with the default options, element
by element:
- the central difference is the fourth-order one, (4 D(h) - D(2h)) / 3 of the central differences D(h)
  and D(2h): the contact's curvature is large on the scale of the steps, and this removes their O(h^2)
  error without making them larger. Autograd must match it to 1e-6 relative to the input group's
  gradient scale (max |FD| over the group), so an entry that should be zero is checked as zero;
- the second-order one-sided differences, (-3 f(x) + 4 f(x + h) - f(x + 2h)) / 2h and its mirror, must
  agree with the central one to 1e-4 of the scale: where the loss is smooth they do to O(h^2) (1e-8
  to 1e-5 of the scale here), at a kink they differ by the jump of the slope. That is how the steps are known not to cross
  any threshold of the contact model.

FD steps: the contact force varies over the smoothing width delta = 5e-6 m, so each step moves the
first step's contact depth by ~1e-3 delta or less (velocity 1e-7 m/s over dt = 5e-3 s: 5e-10 m;
position 3e-9 m; quaternion 1e-8 on half sizes of 0.1 m; force 1e-5 N and mass 1e-5 kg a few 1e-10 m
over the rollout): far inside the softplus's smooth region and far from its activation thresholds (the
margin, 20 delta below the surface, and the force-sign tests), while the round-off of the differences
stays ~1e-7 of the scale or less.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import genesis_lite as gs

F64 = torch.float64
DT = 5e-3
STEPS = 40
TOL = 1e-6
KINK_TOL = 1e-4
CTRL_STEPS = (0, 7, 19)
H = {"v0": 1e-7, "pos": 3e-9, "quat": 1e-8, "ctrl": 1e-5, "mass": 1e-5}
STACK_H = {k: 10.0 * h for k, h in H.items()}


def _t(x):
    return torch.as_tensor(x, dtype=F64)


def _scene(morph):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT, requires_grad=True))
    scene.add_entity(gs.morphs.Plane())
    body = scene.add_entity(morph)
    scene.build()
    return scene, body


def _check(fn, inputs):
    """Autograd of the scalar fn(**inputs) against finite differences, element by element (see the
    module docstring); inputs: name -> (value, FD step h; the differences take x +- h and x +- 2h)."""
    leaves = {k: v.detach().clone().requires_grad_(True) for k, (v, _) in inputs.items()}
    ad = dict(zip(leaves, torch.autograd.grad(fn(**leaves), list(leaves.values()))))
    x0 = {k: v.detach().clone() for k, (v, _) in inputs.items()}
    with torch.no_grad():
        f0 = float(fn(**x0))  # the same (untracked) evaluation as the perturbed ones
        for name, (v, h) in inputs.items():
            c, fw, bw = (np.zeros(v.numel()) for _ in range(3))
            for k in range(v.numel()):
                vals = {}
                for step in (h, -h, 2 * h, -2 * h):
                    x = {kk: vv.clone() for kk, vv in x0.items()}
                    x[name].view(-1)[k] += step
                    vals[step] = float(fn(**x))
                d1 = (vals[h] - vals[-h]) / (2 * h)
                d2 = (vals[2 * h] - vals[-2 * h]) / (4 * h)
                c[k] = (4 * d1 - d2) / 3
                # second-order one-sided differences (each side's curvature term taken out)
                fw[k] = (-3 * f0 + 4 * vals[h] - vals[2 * h]) / (2 * h)
                bw[k] = (3 * f0 - 4 * vals[-h] + vals[-2 * h]) / (2 * h)
            a = ad[name].detach().reshape(-1).numpy()
            scale = np.abs(c).max()
            assert scale > 0, f"{name}: zero gradient, nothing checked"
            msg = f"{name}: autograd {a}\n central FD {c}\n forward FD {fw}\n backward FD {bw}"
            assert np.abs(fw - c).max() <= KINK_TOL * scale and np.abs(bw - c).max() <= KINK_TOL * scale, \
                "one-sided differences disagree (a kink at the starting point): " + msg
            err = np.abs(a - c).max() / scale
            kink = max(np.abs(fw - c).max(), np.abs(bw - c).max()) / scale
            print(f"{name:5s} scale {scale:.3e}  autograd - FD {err:.1e}  one-sided - central {kink:.1e}")
            assert err <= TOL, f"relative error {err:.2e} > {TOL:g}: " + msg
    return ad


def _pushed_rollout(scene, body, start_depths):
    """The loss (position and orientation after STEPS steps) of a body pushed by 2 N along x, plus the
    forces ctrl[j] on its first ctrl.shape[1] dofs at step CTRL_STEPS[j], from the initial velocity, pose
    and mass given; the depths of its contacts in the first step are appended to start_depths."""
    push = _t([2.0, 0.0, 0.0, 0.0, 0.0, 0.0])

    def rollout(v0, pos, quat, ctrl, mass):
        scene.reset()
        body.set_links_mass(mass.reshape(1))
        body.set_pos(pos)
        body.set_quat(quat)
        body.set_dofs_velocity(v0)
        for t in range(STEPS):
            f = push
            for j, ts in enumerate(CTRL_STEPS):
                if t == ts:
                    f = push + torch.cat([ctrl[j], torch.zeros(6 - ctrl.shape[1], dtype=F64)])
            body.control_dofs_force(f)
            scene.step()
            if t == 0:
                start_depths.append(body.get_contacts()["penetration"].detach().cpu().numpy().copy())
        p, q = body.get_pos(), body.get_quat()
        return p[0] + 2.0 * p[1] + 0.5 * p[2] + (q * _t([0.1, 0.3, -0.2, 0.4])).sum()

    return rollout


def _inputs(v0, pos, quat, mass, seed, h=None, n_ctrl=6):
    ctrl = np.random.default_rng(seed).uniform(-3.0, 3.0, (len(CTRL_STEPS), n_ctrl))
    vals = {"v0": _t(v0), "pos": _t(pos), "quat": _t(quat), "ctrl": _t(ctrl), "mass": _t(mass)}
    steps = {**H, **(h or {})}
    return {k: (v, steps[k]) for k, v in vals.items()}


def _assert_exact_contact(start_depths):
    """The autograd rollout (the first one) started in contact, every touching point at depth exactly 0
    (get_contacts lists the points that carry a force at the end of the step)."""
    d = start_depths[0]
    assert len(d) >= 1 and np.all(d == 0.0), f"not in exact contact at the start: depths {d}"


def test_box_resting_exactly_on_the_plane_pushed_along_x():
    """The tracker case: a box on the plane (centre at half its height), pushed by 2 N along x, initial
    velocity (1.5, 0.4, vz, 0, 0, 0.3) at vz = 0, loss x + 2y after 40 steps, against the initial velocity."""
    scene, box = _scene(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0.0, 0.0, 0.1)))
    push = _t([2.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    start = []

    def loss(v0):
        scene.reset()
        box.set_dofs_velocity(v0)
        for t in range(STEPS):
            box.control_dofs_force(push)
            scene.step()
            if t == 0:
                start.append(box.get_contacts()["penetration"].detach().cpu().numpy().copy())
        p = box.get_pos()
        return p[0] + 2.0 * p[1]

    _check(loss, {"v0": (_t([1.5, 0.4, 0.0, 0.0, 0.0, 0.3]), H["v0"])})
    _assert_exact_contact(start)


def test_box_turned_about_the_vertical_starting_on_its_face():
    """A box turned 0.2 rad about z, its face exactly on the plane: initial velocity, pose, forces at
    three steps and mass."""
    scene, box = _scene(gs.morphs.Box(size=(0.3, 0.2, 0.1), pos=(0.0, 0.0, 0.05)))
    start = []
    a = 0.2
    _check(_pushed_rollout(scene, box, start),
           _inputs([1.5, 0.4, 0.0, 0.0, 0.0, 0.3], [0.0, 0.0, 0.05], [math.cos(a / 2), 0.0, 0.0, math.sin(a / 2)],
                   2.0, seed=0))
    _assert_exact_contact(start)


def test_tilted_box_starting_on_a_corner():
    """A box tilted a little, its lowest corner exactly on the plane (a centre height and a quaternion
    for which the simulator computes that corner's depth as exactly 0, found by trying neighbouring
    floats), tipping towards its face: initial velocity, pose, forces and mass."""
    half = np.array([0.15, 0.1, 0.05])
    scene, box = _scene(gs.morphs.Box(size=tuple(2 * half), pos=(0.0, 0.0, 0.3)))
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    found = None
    with torch.no_grad():
        for j in range(200):
            q = np.array([0.995, 0.06 + j * 1e-9, -0.04, 0.05])
            q /= np.linalg.norm(q)
            w, x, y, z = q
            Rz = np.array([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)])
            zc0 = -(corners @ Rz).min()
            for k in (0, -1, 1):
                zc = zc0 + k * np.spacing(zc0)
                scene.reset()
                box.set_pos(_t([0.0, 0.0, zc]))
                box.set_quat(_t(q))
                scene.step()
                d = box.get_contacts()["penetration"].cpu().numpy()
                if len(d) == 1 and d[0] == 0.0:
                    found = (zc, q)
                    break
            if found:
                break
    assert found, "no pose with a corner at depth exactly 0 found"
    zc, q = found
    start = []
    _check(_pushed_rollout(scene, box, start), _inputs([0.8, -0.3, 0.0, 0.0, 0.0, 0.2], [0.0, 0.0, zc], q, 2.0, seed=1))
    _assert_exact_contact(start)


def test_rotated_sphere_starting_on_the_plane():
    """A sphere (turned, rolling and spinning) resting exactly on the plane: initial velocity, pose,
    forces at three steps and mass."""
    scene, ball = _scene(gs.morphs.Sphere(radius=0.1, pos=(0.0, 0.0, 0.1)))
    start = []
    q = np.array([0.98, 0.1, -0.15, 0.08])
    _check(_pushed_rollout(scene, ball, start),
           _inputs([1.0, -0.5, 0.0, 0.2, 0.3, 0.0], [0.0, 0.0, 0.1], q / np.linalg.norm(q), 3.0, seed=2))
    _assert_exact_contact(start)


# slow (suite time: its own box-on-box contact class, ~150 s cold with its finite differences); the
# other exact-start cases of this file stay in the default suite
@pytest.mark.slow
def test_box_resting_exactly_on_a_box():
    """A small box turned about z, resting exactly on a larger box that rests exactly on the plane (a
    contact between two moving bodies: the densely factorised solve and the box's SDF), pushed along x:
    the top box's initial velocity, pose, forces and mass. The stack's stiff contacts amplify round-off
    (~1e-14 on the loss, 200 ulps, measured), so the FD steps are 10x those of the other cases (the
    depth still moves < 1e-2 delta). Torque controls are left out: they spin the small top box (inertia
    ~2e-3 kg m^2) into trajectories whose lift-offs (kinks) lie within such steps of the pose, and at
    steps small enough for the torques that round-off is ~1e-6 of the gradient."""
    a = 0.3
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT, requires_grad=True))
    scene.add_entity(gs.morphs.Plane())
    scene.add_entity(gs.morphs.Box(size=(0.4, 0.4, 0.2), pos=(0.0, 0.0, 0.1)))
    top = scene.add_entity(gs.morphs.Box(size=(0.2, 0.1, 0.1), pos=(0.05, 0.0, 0.25)))
    scene.build()
    start = []
    _check(_pushed_rollout(scene, top, start),
           _inputs([0.5, 0.2, 0.0, 0.0, 0.0, 0.4], [0.05, 0.0, 0.25], [math.cos(a / 2), 0.0, 0.0, math.sin(a / 2)],
                   1.0, seed=3, h=STACK_H, n_ctrl=3))
    _assert_exact_contact(start)
