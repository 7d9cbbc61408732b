"""Issue #8: two-way rigid-MPM coupling, its physics and its gradients in both directions.

Checks: a rigid box resting on an elastic block is held by a reaction equal to its weight; a sphere
dropped into sand stops inside it; an isolated rigid + MPM system keeps its linear momentum through a
collision; gradients of MPM quantities with respect to rigid inputs (a pusher's velocity and mass) and
of rigid quantities with respect to MPM inputs (the block's Young's modulus, the material's initial
velocity) match central finite differences in float64.
"""
from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

import genesis_lite as gs

F64 = dict(dtype=torch.float64)
G = 9.81


def _scene(dt=2e-3, substeps=8, density=32, upper=(0.4, 0.4, 0.4), requires_grad=False, gravity=(0, 0, -G),
           coupler=None):
    return gs.Scene(sim_options=gs.options.SimOptions(dt=dt, substeps=substeps, requires_grad=requires_grad,
                                                      gravity=gravity),
                    mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=upper, grid_density=density),
                    coupler_options=coupler)


def test_box_resting_on_an_elastic_block_feels_its_weight():
    dens = 48
    scene = _scene(density=dens, upper=(0.4, 0.4, 0.3))
    scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 3 / dens + 0.05), size=(0.2, 0.2, 0.1)),
                     material=gs.materials.MPM.Elastic(E=5e4, nu=0.3))
    box = scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 3 / dens + 0.13), size=(0.1, 0.1, 0.05)),
                           material=gs.materials.Rigid(rho=500))
    scene.build()
    weight = box.get_mass() * G
    F, V = [], []
    # 1.4 s: on the default frictionless floor (Genesis's) the block's bounce dies out more slowly than on a
    # floor with friction (at 1 s the box still moved at 9 mm/s, at 1.4 s at 2.4 mm/s)
    for _ in range(700):
        scene.step()
        F.append(box.get_links_mpm_force()[0].numpy())
        V.append(box.get_vel()[2].item())
    F, V = np.array(F), np.array(V)
    assert abs(V[-100:]).max() < 0.005  # at rest on the block
    reaction = F[-100:].mean(0)
    print(f"reaction {reaction} N, weight {weight:.4f} N")
    assert abs(reaction[2] - weight) < 0.02 * weight
    assert np.abs(reaction[:2]).max() < 0.02 * weight
    # it rests on the block's surface (top at 3 cells + 0.1 m), not sunk into it
    assert abs(box.get_pos()[2].item() - (3 / dens + 0.1 + 0.025)) < 1.0 / dens


def test_a_body_beside_an_elastic_block_does_not_push_it_away():
    """No gravity, a fixed plate 11 mm from an elastic block's outermost particles (the block's face, 1 mm
    from the plate): a row of grid nodes lies 0.97 cells inside the plate and holds mass only from particles
    outside it (the quadratic B-spline reaches 1.5 cells). Nothing touches, so nothing may move. Before
    2026-11-29 the coupling pushed such nodes out of a light body as if material had got in (its push
    started 0.5 cells deep): the block drifted 2.6 cm away from the plate in 200 steps, and in Genesis's
    grasp_soft_cube the Panda's fingers pushed the soft cube so and it slid out of them."""
    dens = 32
    scene = _scene(density=dens, upper=(0.4, 0.4, 0.3), gravity=(0.0, 0.0, 0.0))
    block = scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 3 / dens + 0.05), size=(0.1, 0.1, 0.1)),
                             material=gs.materials.MPM.Elastic(E=5e4, nu=0.3))
    plate = scene.add_entity(gs.morphs.Box(pos=(0.301, 0.2, 3 / dens + 0.05), size=(0.1, 0.2, 0.1), fixed=True),
                             material=gs.materials.Rigid(rho=500))
    scene.build()
    x0 = block.get_particles_pos().numpy().copy()
    assert abs(x0[..., 0].max() - 0.24) < 1e-9  # the outermost particles, 11 mm from the plate
    for _ in range(100):
        scene.step()
        assert np.abs(plate.get_links_mpm_force().numpy()).max() < 1e-12
    assert np.abs(block.get_particles_pos().numpy() - x0).max() < 1e-12


# slow (suite time, ~30 s): the coupled boundary holding a body is checked by default by the box resting
# on an elastic block
@pytest.mark.slow
def test_sphere_dropped_into_sand_comes_to_rest_inside_it():
    dens = 48
    scene = _scene(density=dens, upper=(0.3, 0.3, 0.4), substeps=10)
    sand = scene.add_entity(gs.morphs.Box(pos=(0.15, 0.15, 3 / dens + 0.05), size=(0.3 - 6 / dens - 0.002,) * 2 + (0.1,)),
                            material=gs.materials.MPM.Sand(E=2e5, nu=0.3, friction_angle=35))
    ball = scene.add_entity(gs.morphs.Sphere(pos=(0.15, 0.15, 0.3), radius=0.03), material=gs.materials.Rigid(rho=3000))
    scene.build()
    floor, top = 3 / dens, 3 / dens + 0.1
    zmin = np.inf
    for _ in range(600):
        scene.step()
        zmin = min(zmin, ball.get_pos()[2].item())
    z, v = ball.get_pos()[2].item(), ball.get_vel().norm().item()
    print(f"ball centre {z:.4f} m (sand surface {top:.4f}, floor {floor:.4f}), lowest {zmin:.4f}, speed {v:.2e}")
    assert v < 0.01  # at rest (it creeps on at a few mm/s, decelerating)
    assert floor + 0.03 < z < top + 0.03  # inside the sand, above the floor
    assert zmin > floor + 0.03  # it never went through to the floor


def test_isolated_rigid_and_mpm_system_keeps_its_momentum():
    scene = _scene(gravity=(0, 0, 0), density=32, upper=(0.5, 0.5, 0.5))
    block = scene.add_entity(gs.morphs.Box(pos=(0.3, 0.25, 0.25), size=(0.12, 0.12, 0.12)),
                             material=gs.materials.MPM.Elastic(E=2e4, nu=0.3))
    ball = scene.add_entity(gs.morphs.Sphere(pos=(0.15, 0.25, 0.25), radius=0.04),
                            material=gs.materials.Rigid(rho=500, coup_friction=0.3))
    scene.build()
    ball.set_dofs_velocity(torch.tensor([1.0, 0.0, 0.1, 0.0, 0.0, 0.0], **F64))

    def momentum():
        return (block._masses()[:, None] * block.get_particles_vel()).sum(0) + ball.get_mass() * ball.get_vel()

    p0 = momentum()
    transferred = 0.0
    for _ in range(50):
        scene.step()
        transferred = max(transferred, (block._masses()[:, None] * block.get_particles_vel()).sum(0).norm().item())
    assert transferred > 0.5 * p0.norm().item()  # they collided: most of the momentum changed hands
    assert (momentum() - p0).norm().item() < 1e-9 * p0.norm().item()
    assert block.get_particles_pos()[:, 0].max().item() < 0.5 - 3 / 32  # and never reached a wall


def _fd_check(rollout, inputs, rng, rel=2e-6):
    """Directional derivatives along random directions against central differences. Relative steps
    of 1e-6: the parallel particle-to-grid scatter adds in a varying order, which leaves ~1e-16 relative
    noise in every rollout, and smaller steps would amplify it."""
    leaves = {k: v.clone().requires_grad_(True) for k, v in inputs.items()}
    rollout(**leaves).backward()
    for k, x in inputs.items():
        d = torch.tensor(rng.normal(size=x.shape), **F64)
        h = 1e-6 * max(1.0, x.abs().max().item())
        with torch.no_grad():
            fd = (rollout(**{**inputs, k: x + h * d}).item() - rollout(**{**inputs, k: x - h * d}).item()) / (2 * h)
        ad = (leaves[k].grad * d).sum().item()
        print(f"{k:10s} autograd {ad: .10e} fd {fd: .10e}")
        assert abs(ad) > 1e-8, k  # a gradient that exists
        assert abs(ad - fd) <= rel * abs(fd), (k, ad, fd)


# slow (suite time, ~60 s): the gradient matrix's ball_in_block case checks the coupling's gradients to a
# rigid body's velocity and mass against finite differences by default
@pytest.mark.slow
def test_gradient_of_soft_body_centre_wrt_rigid_pusher_velocity_and_mass():
    """A rigid box (offset, rotated, spinning) pushes an elastic cube sideways without gravity: the
    cube's final centre of mass against the box's initial linear and angular velocity and its mass."""
    scene = _scene(gravity=(0, 0, 0), requires_grad=True, density=32, upper=(0.5, 0.5, 0.5), substeps=5)
    cube = scene.add_entity(gs.morphs.Box(pos=(0.3, 0.25, 0.25), size=(0.1, 0.1, 0.1)),
                            material=gs.materials.MPM.Elastic(E=2e4, nu=0.3))
    pusher = scene.add_entity(gs.morphs.Box(pos=(0.215, 0.26, 0.24), size=(0.05, 0.12, 0.1), quat=(0.99, 0.05, 0.1, 0.0)),
                              material=gs.materials.Rigid(rho=2000, coup_friction=0.4))
    scene.build()
    w = torch.tensor([1.0, -0.7, 0.4], **F64)

    def rollout(vel, mass):
        scene.reset()
        pusher.set_links_mass(mass)
        pusher.set_dofs_velocity(vel)
        for _ in range(12):
            scene.step()
        return (w * cube.get_pos()).sum()

    rng = np.random.default_rng(1)
    _fd_check(rollout, {"vel": torch.tensor([1.2, 0.1, -0.05, 0.5, -0.3, 1.0], **F64),
                        "mass": torch.tensor([pusher.get_mass()], **F64)}, rng)


# slow (suite time, ~55 s): the gradient matrix's ball_in_block case checks the same scene's gradients
# (E, the ball's velocity and mass, the particles' velocities) by default
@pytest.mark.slow
def test_gradient_of_ball_sink_depth_wrt_block_stiffness_and_material_velocity():
    """A rigid ball dropped on an elastic block: its height after it has pressed in against the block's
    Young's modulus (and Poisson's ratio) and the block's initial particle velocities."""
    dens = 48
    scene = _scene(requires_grad=True, density=dens, upper=(0.3, 0.3, 0.3), substeps=6)
    block = scene.add_entity(gs.morphs.Box(pos=(0.15, 0.15, 3 / dens + 0.04), size=(0.12, 0.12, 0.08)),
                             material=gs.materials.MPM.Elastic(E=1e4, nu=0.3))
    ball = scene.add_entity(gs.morphs.Sphere(pos=(0.155, 0.148, 3 / dens + 0.08 + 0.045), radius=0.04),
                            material=gs.materials.Rigid(rho=800))
    scene.build()
    n = block.n_particles

    def rollout(E, nu, vel):
        scene.reset()
        block.set_material(E=E, nu=nu)
        block.set_particles_vel(vel)
        ball.set_dofs_velocity(torch.tensor([0.0, 0.0, -0.8, 0.0, 0.0, 0.0], **F64))
        for _ in range(15):
            scene.step()
        return ball.get_pos()[2]

    rng = np.random.default_rng(2)
    z = rollout(torch.tensor(1e4, **F64), torch.tensor(0.3, **F64), torch.zeros(n, 3, **F64)).item()
    assert z < 3 / dens + 0.08 + 0.04  # it pressed into the block
    _fd_check(rollout, {"E": torch.tensor(1e4, **F64), "nu": torch.tensor(0.3, **F64),
                        "vel": torch.tensor(rng.normal(0, 0.3, (n, 3)), **F64)}, rng)


def test_one_way_coupling_moves_the_material_but_not_the_body():
    scene = _scene(density=32, upper=(0.4, 0.4, 0.4), coupler=gs.options.CouplerOptions(mpm_reaction=False))
    block = scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 3 / 32 + 0.05), size=(0.15, 0.15, 0.1)),
                             material=gs.materials.MPM.Elastic(E=2e4, nu=0.3))
    ball = scene.add_entity(gs.morphs.Sphere(pos=(0.2, 0.2, 0.25), radius=0.04), material=gs.materials.Rigid(rho=500))
    scene.build()
    z0 = ball.get_pos()[2].item()
    x0 = block.get_particles_pos().numpy().copy()
    for _ in range(60):
        scene.step()
    t = 60 * scene.dt
    assert abs(ball.get_pos()[2].item() - (z0 - 0.5 * G * t * t)) < 0.01  # free fall: it feels nothing
    # it pushed the material under it 3 cm down (the ball's bottom went 4.5 cm into the block), and no
    # particle is inside it by more than half a cell
    x = block.get_particles_pos().numpy()
    under = (np.abs(x0[:, 0] - 0.2) < 0.02) & (np.abs(x0[:, 1] - 0.2) < 0.02)
    assert x0[under, 2].max() - x[under, 2].max() > 0.03
    assert np.linalg.norm(x - ball.get_pos().numpy(), axis=1).min() > 0.04 - 0.5 / 32
    assert np.abs(ball.get_links_mpm_force().numpy()).max() == 0.0


def test_coupling_exists_only_where_both_kinds_do(caplog):
    rigid_only = gs.Scene()
    rigid_only.add_entity(gs.morphs.Sphere(pos=(0, 0, 1), radius=0.1))
    rigid_only.build()
    assert not rigid_only.rigid_solver.external and rigid_only._coupler is None
    mpm_only = _scene()
    mpm_only.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 0.2), size=(0.05,) * 3), material=gs.materials.MPM.Elastic())
    mpm_only.build()
    assert mpm_only.rigid_solver is None and mpm_only._coupler is None
    off = _scene(coupler=gs.options.CouplerOptions(rigid_mpm=False))
    off.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 0.2), size=(0.05,) * 3), material=gs.materials.MPM.Elastic())
    off.add_entity(gs.morphs.Sphere(pos=(0.2, 0.2, 0.3), radius=0.02))
    with caplog.at_level(logging.INFO, logger="genesis_lite"):
        off.build()
    assert off._coupler is None and "do not interact" in caplog.text


def test_rigid_entity_without_collision_geometry_is_logged_not_coupled(tmp_path, caplog):
    urdf = tmp_path / "ghost.urdf"
    urdf.write_text("""<robot name="ghost"><link name="base"><inertial><mass value="1"/><origin xyz="0 0 0"/>
        <inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link></robot>""")
    scene = _scene()
    scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 0.2), size=(0.05,) * 3), material=gs.materials.MPM.Elastic())
    scene.add_entity(gs.morphs.URDF(file=str(urdf), pos=(0.2, 0.2, 0.3)))
    with caplog.at_level(logging.INFO, logger="genesis_lite"):
        scene.build()
    assert "ghost" in caplog.text and "no collision geometry" in caplog.text
    scene.step()  # runs


def test_bad_coupler_options_are_errors():
    with pytest.raises(ValueError, match="rigid_mpm"):
        gs.options.CouplerOptions(rigid_mpm="yes")
    with pytest.raises(ValueError, match="coup_friction"):
        gs.materials.Rigid(coup_friction=-1.0)
    with pytest.raises(TypeError, match="coupler_options"):
        gs.Scene(coupler_options=dict(rigid_mpm=True))


def _pushed_jelly(vel):
    """A coupled scene with gradients (a box pushing a jelly cube): positions and gradients after 3 steps."""
    scene = _scene(density=24, upper=(0.5, 0.5, 0.5), substeps=4, requires_grad=True)
    cube = scene.add_entity(gs.morphs.Box(pos=(0.3, 0.25, 0.25), size=(0.1, 0.1, 0.1)),
                            material=gs.materials.MPM.Elastic(E=2e4, nu=0.3))
    pusher = scene.add_entity(gs.morphs.Box(pos=(0.21, 0.26, 0.24), size=(0.05, 0.12, 0.1)),
                              material=gs.materials.Rigid(rho=2000, coup_friction=0.3))
    scene.build()
    v = torch.tensor(vel, **F64, requires_grad=True)
    pusher.set_dofs_velocity(v)
    for _ in range(3):
        scene.step()
    x, q = cube.get_particles_pos(), pusher.get_qpos()
    ((x[:, 0] ** 2).sum() + q[:3].sum()).backward()
    reused = (scene._coupler.reused, scene.rigid_solver.reused_core, scene._mpm.reused_solver)
    return (x.detach(), q.detach(), v.grad), reused


# slow (suite time, ~37 s: a coupled gradient class of its own): pooling is checked by default for the MPM solver
# (test_faults_mpm.py, a dropped scene gives its solver to the next) and the rigid one (test_build.py)
@pytest.mark.slow
def test_a_second_coupled_scene_of_its_class_compiles_nothing_and_gives_the_same_numbers(compiled):
    import gc

    first, _ = _pushed_jelly([0.8, 0.0, 0.1, 0.0, 0.3, 0.0])
    gc.collect()  # the first scene dies: its MPM solver, rigid scene core and coupler go back to their pools
    compiled.clear()
    again, reused = _pushed_jelly([0.8, 0.0, 0.1, 0.0, 0.3, 0.0])
    assert reused == (True, True, True)
    # nothing at all (the Tapes' loss is a torch token, simulator.py tape_loss: a loss field per scene
    # compiled its fill kernel again each time)
    assert not compiled, f"the second coupled scene compiled {compiled}"
    for a, b in zip(first, again):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert again[2].abs().sum() > 0
