"""Issue #25: MPM particles attached to a rigid link (MPMEntity.set_particle_constraints, Genesis's API,
as its examples/coupling/rigid_mpm_attachment.py uses it).

Checks against what the spring law says, not against the code: a cube whose particles all hang from a
fixed link settles with each particle m g / k below its anchor (the static balance of the spring and
gravity); particles follow a link that is moved and turned (their link-frame points); per-env masks in
a batched scene; particles that are not attached move exactly as they would in a scene without
attachments; and each bad input's message. The gradients through an attachment are the gradient
matrix's case ball_attached (tests/gradient_cases.py: the ball's velocity and mass, the block's E and
particle velocities, against central differences in float64).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import genesis_lite as gs

F64 = dict(dtype=torch.float64)
G = 9.81


def _scene(gravity=(0, 0, -G), requires_grad=False, substeps=10, couple=True):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=substeps, gravity=gravity,
                                                      requires_grad=requires_grad),
                     mpm_options=gs.options.MPMOptions(lower_bound=(-0.3, -0.3, 0.0), upper_bound=(0.3, 0.3, 0.6),
                                                       grid_density=32))
    scene.add_entity(gs.morphs.Plane(), material=gs.materials.Rigid(needs_coup=couple))
    return scene


def _rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_a_cube_hanging_from_a_link_settles_m_g_over_k_below_its_anchors():
    """Every particle attached: the cube keeps its shape (no stress), and at rest each spring carries its
    particle's weight, k e = m g, whatever the grid and the material do."""
    scene = _scene()
    holder = scene.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 0.45), size=(0.1, 0.1, 0.04), fixed=True))
    cube = scene.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 0.3), size=(0.1, 0.1, 0.1)),
                            material=gs.materials.MPM.Elastic(E=2e4, nu=0.3, rho=1000))
    scene.build()
    x0 = cube.get_particles_pos().clone()
    m = cube.get_mass() / cube.n_particles
    k = 2.0 * m * G / 3e-3  # sag of 1.5 mm
    cube.set_particle_constraints(torch.ones(cube.n_particles, dtype=torch.bool), holder.links[0].idx, k)
    for _ in range(150):  # 0.3 s; the critically damped spring's time scale sqrt(m / k) is 12 ms
        scene.step()
    d = cube.get_particles_pos() - x0
    sag = m * G / k
    np.testing.assert_allclose(d[:, 2].numpy(), -sag, rtol=1e-3)
    assert float(d[:, :2].abs().max()) < 1e-6 * sag
    assert float(cube.get_particles_vel().abs().max()) < 1e-3 * sag


def test_attached_particles_follow_a_link_that_is_moved_and_turned():
    """No gravity: a free box is set to new poses (Genesis's script drives it with set_qpos), and its
    attached particles stay at their link-frame points; the unattached half of the cube is dragged
    along by the material."""
    scene = _scene(gravity=(0, 0, 0))
    box = scene.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 0.4), size=(0.12, 0.12, 0.04)))
    cube = scene.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 0.3), size=(0.1, 0.1, 0.12)),
                            material=gs.materials.MPM.Elastic(E=5e4, nu=0.3, rho=1000))
    scene.build()
    mask = cube.get_particles_in_bbox((-0.06, -0.06, 0.31), (0.06, 0.06, 0.37))
    assert 0 < int(mask.sum()) < cube.n_particles
    x0 = cube.get_particles_pos()[mask].numpy()
    z_rest = float(cube.get_particles_pos()[~mask][:, 2].mean())
    cube.set_particle_constraints(mask, box.links[0].idx, stiffness=1e4)
    n = 60
    for i in range(n):
        a = 0.5 * (i + 1) / n  # up to ~29 degrees about z, and 3 cm up
        q = [math.cos(a / 2), 0.0, 0.0, math.sin(a / 2)]
        box.set_qpos(torch.tensor([0.0, 0.0, 0.4 + 0.03 * (i + 1) / n] + q, **F64))
        scene.step()
    want = (x0 - [0.0, 0.0, 0.4]) @ _rot_z(0.5).T + [0.0, 0.0, 0.43]
    err = np.linalg.norm(cube.get_particles_pos()[mask].numpy() - want, axis=1)
    assert err.max() < 1.5e-3, err.max()  # the link moves 0.5 mm and turns 8 mrad a step
    assert float(cube.get_particles_pos()[~mask][:, 2].mean()) > z_rest + 0.02  # the rest came along


def test_per_env_masks_in_a_batched_scene_and_removal():
    """Env 0 holds its cube, env 1 attaches nothing and its cube falls; a reset keeps the attachments;
    removing env 0's attachment lets it fall too."""
    scene = _scene()
    holder = scene.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 0.45), size=(0.1, 0.1, 0.04), fixed=True))
    cube = scene.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 0.35), size=(0.08, 0.08, 0.08)),
                            material=gs.materials.MPM.Elastic(E=5e4, nu=0.3, rho=1000))
    scene.build(n_envs=2)
    top = cube.get_particles_in_bbox((-1, -1, 0.37), (1, 1, 1))  # (2, n)
    assert top.shape == (2, cube.n_particles) and bool(top[0].any())
    mask = top.clone()
    mask[1] = False
    cube.set_particle_constraints(mask, holder.links[0].idx, stiffness=1e4)
    for _ in range(40):
        scene.step()
    z = cube.get_pos()[:, 2]
    assert abs(float(z[0]) - 0.35) < 5e-3  # held (an elastic sag of a few mm)
    assert float(z[1]) < 0.35 - 0.5 * G * 0.08 ** 2 * 0.9  # fell freely for 80 ms
    scene.reset()  # attachments are kept (Genesis's): the same again (up to the order of atomic adds)
    for _ in range(40):
        scene.step()
    assert float((cube.get_pos()[:, 2] - z).abs().max()) < 1e-12
    cube.remove_particle_constraints()
    z0 = float(cube.get_pos()[0, 2])
    for _ in range(20):
        scene.step()
    assert float(cube.get_pos()[0, 2]) < z0 - 0.5 * G * 0.04 ** 2 * 0.8


def _two_cubes(attach):
    scene = _scene()
    holder = scene.add_entity(gs.morphs.Box(pos=(-0.15, 0.0, 0.45), size=(0.08, 0.08, 0.04), fixed=True))
    held = scene.add_entity(gs.morphs.Box(pos=(-0.15, 0.0, 0.37), size=(0.06, 0.06, 0.06)),
                            material=gs.materials.MPM.Elastic(E=5e4, nu=0.3, rho=1000))
    free = scene.add_entity(gs.morphs.Box(pos=(0.15, 0.0, 0.2), size=(0.06, 0.06, 0.06)),
                            material=gs.materials.MPM.Elastic(E=2e4, nu=0.3, rho=1000))
    scene.build()
    if attach:
        held.set_particle_constraints(held.get_particles_in_bbox((-1, -1, 0.39), (1, 1, 1)), holder.links[0].idx, 1e4)
    free.set_particles_vel(torch.tensor([0.3, -0.2, 0.5], **F64).expand(free.n_particles, 3))
    xs = []
    for _ in range(30):
        scene.step()
        xs.append(free.get_particles_pos().clone())
    return torch.stack(xs)


def test_particles_not_attached_move_as_without_attachments():
    """The stage with attachments computes a free particle's grid-to-particle as the plain one does: a
    falling cube far from the attached one moves the same. Equal to 1e-13 m: the two stages are
    separate kernels, which LLVM may contract differently under Taichi's default fast_math. (Elastic, as the
hanging cube's scene: the same solver classes, compiled once.)"""
    a, b = _two_cubes(True), _two_cubes(False)
    assert float((a - b).abs().max()) < 1e-13
    assert float((a[-1] - a[0]).abs().max()) > 1e-2  # it moved


def test_bad_attachments_are_clear_errors():
    scene = _scene()
    box = scene.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 0.45), size=(0.1, 0.1, 0.04), fixed=True))
    cube = scene.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 0.3), size=(0.06, 0.06, 0.06)),
                            material=gs.materials.MPM.Elastic())
    with pytest.raises(gs.GenesisException, match="scene.build"):
        cube.set_particle_constraints(np.ones(cube.n_particles, bool), 1, 1e4)
    scene.build()
    ok = np.ones(cube.n_particles, bool)
    with pytest.raises(gs.GenesisException, match="boolean"):
        cube.set_particle_constraints(np.ones(cube.n_particles), box.links[0].idx, 1e4)
    with pytest.raises(gs.GenesisException, match="shape"):
        cube.set_particle_constraints(ok[:-1], box.links[0].idx, 1e4)
    with pytest.raises(gs.GenesisException, match="stiffness"):
        cube.set_particle_constraints(ok, box.links[0].idx, -1.0)
    with pytest.raises(gs.GenesisException, match="stiffness"):
        cube.set_particle_constraints(ok, box.links[0].idx, float("nan"))
    with pytest.raises(gs.GenesisException, match="link_idx"):
        cube.set_particle_constraints(ok, 7, 1e4)
    with pytest.raises(gs.GenesisException, match="link_idx"):
        cube.set_particle_constraints(ok, 1.0, 1e4)
    # no coupler: no rigid entity couples with the material
    scene2 = _scene(couple=False)
    b2 = scene2.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 0.45), size=(0.1, 0.1, 0.04), fixed=True),
                           material=gs.materials.Rigid(needs_coup=False))
    c2 = scene2.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 0.3), size=(0.06, 0.06, 0.06)), material=gs.materials.MPM.Elastic())
    scene2.build()
    with pytest.raises(gs.GenesisException, match="coupler"):
        c2.set_particle_constraints(np.ones(c2.n_particles, bool), b2.links[0].idx, 1e4)
