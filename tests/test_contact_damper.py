"""The mass-relative contact damper (issue #24), the default since 2026-12-05 (RigidOptions(contact_damping_ratio=1)
when no fixed contact_damping is given): critical for the mass each contact moves along its normal.

A contact point's damper is 2 ratio sqrt(k m) with m the effective mass of its two sides along the
contact's normal, each side's through its articulation at the initial configuration, armature included
(contact.law.func_link_invmass, RigidSim.contact_link_weights). Checked against references no one here
wrote: the restitution of a critically damped unilateral spring, exp(-2), for a body hitting the ground
alone, through a joint with rotor inertia and through a joint skewed from the normal; and the weights
against MuJoCo's body_invweight0 (the mean of the same matrix's diagonal) on ANYmal with rotor inertia.
Otherwise default options, float64."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import genesis_lite as gs

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import scenes as S  # noqa: E402

K = gs.options.RigidOptions().contact_stiffness  # the default, N/m per contact point
RADIUS = 0.05

SLIDER = """<?xml version="1.0"?>
<robot name="slider">
  <link name="base"/>
  <link name="ball">
    <inertial><origin xyz="0 0 0"/><mass value="{mass}"/>
      <inertia ixx="1e-3" iyy="1e-3" izz="1e-3" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><geometry><sphere radius="{radius}"/></geometry></collision>
  </link>
  <joint name="slide" type="prismatic">
    <parent link="base"/><child link="ball"/>
    <origin xyz="0 0 {height}"/><axis xyz="{ax} {ay} {az}"/>
    <limit lower="-10" upper="10" effort="0" velocity="100"/>
  </joint>
</robot>
"""


def _rebound(make_body, dt, v_normal=1.0):
    """(restitution, normal mass): a body given by make_body(scene) -> (entity, set_velocity(vn), normal
    velocity(), normal mass) approaches the frictionless ground at v_normal without gravity; the normal
    velocity it leaves with over the one it came with."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, gravity=(0.0, 0.0, 0.0)))
    scene.add_entity(gs.morphs.Plane(), material=gs.materials.Rigid(friction=0.0))
    body, set_vn, get_vn, m = make_body(scene)
    scene.build()
    set_vn(-v_normal)
    # ~1 mm of approach, then the contact: 2 / omega for the critical damper (omega = sqrt(k / m))
    n = int(math.ceil((2e-3 / v_normal + 4.0 * math.sqrt(m / K)) / dt))
    for _ in range(n):
        scene.step()
    return get_vn() / v_normal, m


def _free_ball(scene):
    mass = 2.0
    ball = scene.add_entity(gs.morphs.Sphere(radius=RADIUS, pos=(0.0, 0.0, RADIUS + 1e-3)),
                            material=gs.materials.Rigid(friction=0.0, rho=mass / (4.0 / 3.0 * math.pi * RADIUS ** 3)))

    def set_vn(v):
        ball.set_dofs_velocity(torch.tensor([0.3, 0.0, v, 0.0, 0.0, 0.0], dtype=torch.float64))

    return ball, set_vn, lambda: float(ball.get_vel()[2]), mass


def _slider(tmp_path, tilt_deg, armature):
    """A 1 kg ball on a prismatic joint whose axis leans tilt_deg from the vertical, with rotor inertia
    `armature` (kg): along the ground's normal it moves with (1 + armature) / cos^2(tilt) kg."""
    t = math.radians(tilt_deg)
    axis = (math.sin(t), 0.0, math.cos(t))
    height = RADIUS + 1e-3
    path = tmp_path / f"slider_{tilt_deg}.urdf"
    path.write_text(SLIDER.format(mass=1.0, radius=RADIUS, height=height, ax=axis[0], ay=0.0, az=axis[2]))

    def make(scene):
        ent = scene.add_entity(gs.morphs.URDF(file=str(path), fixed=True, default_armature=armature),
                               material=gs.materials.Rigid(friction=0.0))

        def set_vn(v):
            ent.set_dofs_velocity(torch.tensor([v / axis[2]], dtype=torch.float64))

        return ent, set_vn, lambda: float(ent.get_dofs_velocity()[0]) * axis[2], (1.0 + armature) / axis[2] ** 2

    return make


@pytest.mark.parametrize("case", ["free ball", "vertical slider with armature", "skewed slider with armature"])
def test_a_landing_rebounds_as_a_critically_damped_contact(tmp_path, case):
    """A linear spring-damper critically damped for the mass m it stops, x = v0 t exp(-w t), pushes until
    its force k x + c x' = m v0 w exp(-w t) (2 - w t) reaches 0 at w t = 2, and lets go at x' = -v0 exp(-2):
    a restitution of exp(-2) = 0.1353 whatever m. The ball alone (2 kg), a 1 kg ball on a vertical slider
    with a rotor inertia of 3 kg (4 kg along the normal: its own mass alone would make the damper half-critical),
    and on a slider leaning 40 degrees (6.8 kg along the normal) all rebound with it. At dt = 10 us (the
    contact lasts 2 / w = 8.9-16.5 ms at the default 1e5 N/m) and the default contact smoothing (5 um against
    ~1-2 mm of overlap), default options. Measured 2026-12-05: 0.1350, 0.1351, 0.1352 (0.1347, 0.1349, 0.1350 at
    20 us; 0.1352, 0.1352, 0.1353 at 5 us: first order in dt). With the fixed damper that was the default
    until then (4e4 N s/m per point, with 1e6 N/m): 0.0012, 0.0024, 0.0041, over-damped."""
    make = {"free ball": _free_ball, "vertical slider with armature": _slider(tmp_path, 0.0, 3.0),
            "skewed slider with armature": _slider(tmp_path, 40.0, 3.0)}[case]
    e, m = _rebound(make, 1e-5)
    assert abs(e - math.exp(-2.0)) < 0.002, (case, e, m)


def test_the_weights_are_mujocos_body_invweight0(tmp_path):
    """The damper's weight of each link, J (M0 + diag(armature))^-1 J^T at its centre of mass and the initial
    configuration, averaged over its diagonal, is MuJoCo's body_invweight0 (mj_setConst) for the same URDF:
    ANYmal on a free joint, with a rotor inertia of 0.1 on its 12 joints in both. Measured 2026-12-01: within
    1.6e-7 relative on all 13 links (the compilers' inertia conversions). The foot moves 4.6 kg along the
    vertical there, 13 times its own 0.35 kg: the mass the damper is made critical for."""
    import mujoco
    from bench_contact import BASE_Z, mujoco_quadruped

    urdf = S.write_anymal(tmp_path)
    scene = gs.Scene(rigid_options=gs.options.RigidOptions(contact_damping_ratio=1.0))
    scene.add_entity(gs.morphs.Plane())
    robot = scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=False, pos=(0.0, 0.0, BASE_Z), default_armature=0.1))
    scene.build()
    W, own = scene._rigid.contact_link_weights(scene.rigid_entities)
    m, _ = mujoco_quadruped(urdf)
    m.dof_armature[6:] = 0.1
    mujoco.mj_setConst(m, mujoco.MjData(m))
    ours, theirs = [], []
    for i, link in enumerate(robot.links):
        b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, link.name)
        assert b >= 0, link.name
        assert own[robot._link_start + i] == 0  # weighed through the articulation
        ours.append(np.trace(W[robot._link_start + i]) / 3.0)
        theirs.append(m.body_invweight0[b, 0])
    assert len(ours) == 13
    np.testing.assert_allclose(ours, theirs, rtol=1e-6)
    foot = robot._link_start + [l.name for l in robot.links].index("LF_SHANK")
    own_mass = float(robot.links[foot - robot._link_start].get_mass())
    assert 1.0 / W[foot][2, 2] > 10.0 * own_mass


# slow: ~47 s of a fresh-cache default suite (2026-12-03: 1,127 s on 2 cores, over its 15 minutes); the gradient
# matrix's gripper_plane case keeps an articulated link's contact gradient in the default suite
@pytest.mark.slow
def test_grad_through_a_landing_on_an_articulated_link(tmp_path):
    """The damper's weight along a normal that turns: a free ball (its own mass) thrown at the ball of the skewed
    slider with rotor inertia (weighed through its joint, n.W n with n the line between the two centres), the
    two rolling off each other, dt = 1 ms, 60 steps. A loss on both positions against the thrown ball's
    velocity and position and the slider's velocity, autograd against central differences in float64."""
    t = math.radians(40.0)
    path = tmp_path / "slider.urdf"
    path.write_text(SLIDER.format(mass=1.0, radius=RADIUS, height=0.3, ax=math.sin(t), ay=0.0, az=math.cos(t)))
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=1e-3, gravity=(0.0, 0.0, 0.0), requires_grad=True),
                     rigid_options=gs.options.RigidOptions(contact_damping_ratio=1.0))
    slider = scene.add_entity(gs.morphs.URDF(file=str(path), fixed=True, default_armature=3.0))
    ball = scene.add_entity(gs.morphs.Sphere(radius=RADIUS, pos=(0.0, 0.0, 0.45)))
    scene.build()

    def loss(v, p, w):
        scene.reset()
        ball.set_pos(p)
        ball.set_dofs_velocity(torch.cat([v, torch.zeros(3, dtype=torch.float64)]))
        slider.set_dofs_velocity(w.reshape(1))
        for _ in range(60):
            scene.step()
        q = ball.get_pos()
        return q[0] + 0.5 * q[1] + 2.0 * q[2] + slider.get_dofs_position()[0]

    f64 = torch.float64
    rep = gs.grad.check(loss, {"v": torch.tensor([0.2, 0.1, -1.5], dtype=f64),
                               "p": torch.tensor([0.03, 0.01, 0.45], dtype=f64), "w": torch.tensor(0.3, dtype=f64)},
                        tol=1e-5)
    assert rep.ok, str(rep)
    assert all(float(g.norm()) > 1e-3 for g in rep.autograd)
