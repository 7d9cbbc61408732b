"""Fault injection on the MPM side (issue #21): bad input gets a clear error, never a crash or a silent
wrong result, and scenes built in a loop neither leak nor recompile.

1. A setter that would put particles outside the domain (set_particles_pos, set_position: the rule
   build() applies, within lower + 3 dx .. upper - 3 dx) raises, naming the entity, the particle and
   what to do, and leaves the state as it was; non-finite positions and velocities raise too. A bad
   position written past the setters (straight into the bridge) cannot make a kernel index outside
   the grid: the process survives (a subprocess, as a segfault would take pytest down with it).
2. set_material after build() repeats build()'s time-step check (elastic wave speed against the
   cell and substep) on the values it would set, for E and nu, and so does a new rollout when an
   optimiser has moved a leaf tensor given to set_material.
3. A second scene of the same class takes the solver of a dropped one (no compile) and, run on memory
   a previous, violent scene left behind, a free-falling cube still follows x0 + v0 t - g t^2 / 2 with
   the analytic gradient d(sum z) / d v0_z = n t.
4. (slow) A 4 t or 400 t box on a jelly block over a plane, far heavier than the jelly can bear: it
   sinks to the plane, rests on it within 1 mm, and at rest no particle is inside it (counted with the
   box's exact geometry; before: 22 inside, 4 of them deeper than half a cell).
5. The README's `entity.set_position((x, y, z))` on an unbatched scene moves the centre of mass there
   and keeps the shape.
6. A heavy box on jelly in a scene with no floor for rigid bodies: the domain's walls stop particles,
   not bodies, so it goes through the domain's floor. The scene raises at that step, naming the box,
   the floor and what to do (before: it fell on, out of the domain, without a word).

Every test but the coupled ones uses one scene shape (a small elastic cube with gradients) so its
kernels compile once.
"""
from __future__ import annotations

import gc
import os
import subprocess
import sys
import textwrap
import weakref

import numpy as np
import pytest
import torch

import genesis_lite as gs
from genesis_lite.errors import GenesisException

F64 = dict(dtype=torch.float64)
G = 9.81
DENS = 40  # dx = 0.025 m: particles live in [0.075, 0.225] x [0.075, 0.225] x [0.075, 0.325]
LO, HI = np.array([0.075, 0.075, 0.075]), np.array([0.225, 0.225, 0.325])


def _scene(substeps=4):
    return gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=substeps, requires_grad=True),
                    mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.3, 0.3, 0.4),
                                                      grid_density=DENS))


def _cube(size=0.05, pos=(0.15, 0.15, 0.2), E=2e4, name="jelly"):
    scene = _scene()
    cube = scene.add_entity(gs.morphs.Box(pos=pos, size=(size,) * 3),
                            material=gs.materials.MPM.Elastic(E=E, nu=0.3, rho=1000), name=name)
    scene.build()
    return scene, cube


# ------------------------------------------------------------------------------- 1. outside the domain
def test_positions_outside_the_domain_are_refused_and_the_state_is_kept():
    scene, cube = _cube()
    x0 = cube.get_particles_pos().detach().clone()
    far = x0.clone()
    far[3, 0] = -50.0
    with pytest.raises(GenesisException, match=r"jelly.*set_particles_pos would put particle 3 at \[-50\.0, .*"
                                               r"outside the MPM domain along x.*Move the entity inside"):
        cube.set_particles_pos(far)
    with pytest.raises(GenesisException, match=r"jelly.*set_position.*outside the MPM domain along x"):
        cube.set_position((-3.0, 0.5, 0.5))
    with pytest.raises(GenesisException, match=r"jelly.*outside the MPM domain"):
        cube.set_position((1e6, 1e6, 1e6))
    # just outside (a third of a cell beyond the walls' cells) is outside too, not clamped silently
    with pytest.raises(GenesisException, match=r"jelly.*particle 0 .*along z.*within \[0\.075, 0\.075, 0\.075\] "
                                               r"\.\. \[0\.225, 0\.225, 0\.325\]"):
        cube.set_particles_pos(torch.tensor([[0.15, 0.15, LO[2] - 0.008]], **F64), particles_idx_local=[0])
    # non-finite values are refused as well, naming the quantity
    with pytest.raises(GenesisException, match=r"jelly.*pos contains NaN"):
        cube.set_particles_pos(torch.tensor([[float("nan"), 0.15, 0.15]], **F64), particles_idx_local=[1])
    with pytest.raises(GenesisException, match=r"jelly.*velocity contains NaN or infinite"):
        cube.set_velocity((0.0, float("inf"), 0.0))
    with pytest.raises(GenesisException, match=r"jelly.*vel contains NaN"):
        cube.set_particles_vel(torch.full((cube.n_particles, 3), float("nan"), **F64))
    # nothing of the refused calls got in: the state is the one built, and the scene steps on
    assert torch.equal(cube.get_particles_pos().detach(), x0)
    scene.step()
    assert torch.isfinite(cube.get_particles_pos()).all()
    # the edge of the admitted region is inside
    cube.set_particles_pos(torch.tensor([[*(HI - 1e-9)]], **F64), particles_idx_local=[0])


def test_a_position_written_past_the_setters_cannot_crash_the_kernels():
    # straight into the bridge (what a bug or a diverged state could leave there): the kernels must stay
    # on the grid; before, p2g wrote outside the grid's memory and the process died with SIGSEGV
    code = textwrap.dedent(f"""
        import torch, genesis_lite as gs
        from genesis_lite.errors import SimulationNaNError
        gs.init(backend=gs.cpu, precision="64", logging_level="warning")
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=4, requires_grad=True),
                         mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.3, 0.3, 0.4),
                                                           grid_density={DENS}))
        cube = scene.add_entity(gs.morphs.Box(pos=(0.15, 0.15, 0.2), size=(0.05,) * 3),
                                material=gs.materials.MPM.Elastic(E=2e4, nu=0.3, rho=1000))
        scene.build()
        for bad in (-50.0, 1e6, -1e30, float("nan")):
            scene.reset()
            x, v, C, F = (t.clone() for t in scene._mpm.state())
            x[0, 0, 0] = bad
            scene._mpm.set_state(x, v, C, F)
            try:
                scene.step()
                scene.step()
            except SimulationNaNError:
                pass
        print("survived")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600,
                         cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert out.returncode == 0 and "survived" in out.stdout, (out.returncode, out.stderr[-3000:])


# ------------------------------------------------------------------------------- 2. time step after build
def test_set_material_that_breaks_the_time_step_is_refused():
    scene, cube = _cube()
    E0 = cube.get_material("E").detach().clone()
    with pytest.raises(GenesisException, match=r"jelly.*substep dt / substeps = 0\.0005 s is too long.*"
                                               r"E=1e\+12 Pa.*SimOptions\(substeps=\d+\).*E <= .* Pa.*"
                                               r"set_material\(E=\.\.\.\)"):
        cube.set_material(E=1e12)
    # nu near 1/2 stiffens the pressure waves by (1 - nu) / ((1 + nu)(1 - 2 nu)): caught as well
    with pytest.raises(GenesisException, match=r"jelly.*too long.*nu=0\.4999.*set_material\(nu=\.\.\.\)"):
        cube.set_material(nu=0.4999)
    # one particle is enough
    E1 = E0.clone()
    E1[5] = 1e10
    with pytest.raises(GenesisException, match=r"jelly.*too long.*particle 5\b"):
        cube.set_material(E=E1)
    assert torch.equal(cube.get_material("E").detach(), E0)  # nothing was stored
    # the bound the message gives is the CFL bound: c h / dx <= 0.9
    import re

    with pytest.raises(GenesisException) as e:
        cube.set_material(E=1e12)
    e_max = float(re.search(r"E <= ([0-9.e+]+) Pa", str(e.value)).group(1))
    nu, h, dx = 0.3, 2e-3 / 4, 1 / DENS
    c = lambda E: np.sqrt(E * (1 - nu) / ((1 + nu) * (1 - 2 * nu)) / 1000.0)  # noqa: E731
    assert c(e_max) * h / dx == pytest.approx(0.9, rel=1e-2)
    cube.set_material(E=0.98 * e_max)  # below the bound: accepted
    # a leaf an optimiser moves in place is checked when the next rollout rebuilds the parameters
    E = torch.tensor(2e4, **F64, requires_grad=True)
    cube.set_material(E=E)
    with torch.no_grad():
        E.fill_(1e12)
    with pytest.raises(GenesisException, match=r"jelly.*too long.*E=1e\+12"):
        scene.reset()


# ------------------------------------------------------------------------------- 3. pooled solvers
def _violent_scene():
    """A cube thrown into a corner for a few steps with a backward pass: it leaves its own values
    all over the solver's memory. Returns a weak reference to its bridge and its solver."""
    scene, cube = _cube(pos=(0.11, 0.18, 0.11), name="thrown")
    v = torch.tensor([-2.0, 2.0, -3.0], **F64, requires_grad=True)
    cube.set_velocity(v)
    for _ in range(4):
        scene.step()
    cube.get_particles_pos()[:, 2].sum().backward()
    assert torch.isfinite(v.grad).all()
    return weakref.ref(scene._mpm), scene._mpm.solver


def test_a_dropped_scene_gives_its_solver_to_the_next_one_of_its_class():
    from solvers.mpm.solver import POOL

    bridge, solver = _violent_scene()
    gc.collect()
    assert bridge() is None, "the dropped scene's MPM bridge is still alive"
    assert solver in POOL.free[solver.key]
    # a cube of the same class elsewhere: the same solver, nothing to compile
    scene, cube = _cube(pos=(0.15, 0.15, 0.2))
    assert scene._mpm.solver is solver and scene._mpm.reused_solver
    err, gerr, gxy = _free_fall(scene, cube, [0.2, -0.1, -0.5])
    assert err < 1e-12 and gerr < 1e-10 and gxy < 1e-10, (err, gerr, gxy)


def _free_fall(scene, cube, v0, T=3):
    """The cube thrown at v0 in free flight for T steps (4 substeps each) and a backward pass of sum z:
    (the largest error against x_n = x0 + n h v0 - g h^2 n (n + 1) / 2, symplectic Euler on a uniform
    velocity field; the relative error of d(sum z) / d v0_z against P n h; |d(sum z) / d v0_xy| over P n h)."""
    x0 = cube.get_particles_pos().detach().clone()
    v0 = torch.tensor(v0, **F64, requires_grad=True)
    cube.set_velocity(v0)
    h = 2e-3 / 4
    for _ in range(T):
        scene.step()
    n = 4 * T
    x = cube.get_particles_pos()
    expect = x0 + n * h * v0.detach() - torch.tensor([0, 0, G * h * h * n * (n + 1) / 2], **F64)
    err = (x.detach() - expect).abs().max().item()
    x[:, 2].sum().backward()
    scale = cube.n_particles * n * h
    return err, abs(v0.grad[2].item() - scale) / scale, v0.grad[:2].abs().max().item() / scale


def test_a_scene_of_another_particle_count_in_the_class_compiles_nothing(compiled):
    """MPM solvers are pooled by a particle capacity (512, 768, 1024, 1536, ...: solvers/mpm/solver.py
    cap_particles), the count read at run time, as rigid scenes share by size class: a sweep over a
    body's size reuses the compiled kernels. A cube of another size (another particle count, the same
    capacity) after a dropped one compiles nothing, and both fall as x0 + v0 t - g t^2 / 2 with the
    gradient d(sum z) / d v0_z = n t."""
    from solvers.mpm.solver import cap_particles

    errors, counts = [], []
    for size in (0.05, 0.075):
        gc.collect()  # the first cube's scene dies: its solver goes back to the pool
        compiled.clear()
        scene, cube = _cube(size=size, pos=(0.15, 0.15, 0.2))
        errors.append(_free_fall(scene, cube, [0.1, 0.2, -0.4]))
        counts.append(cube.n_particles)
        del scene, cube
    assert counts[0] != counts[1] and cap_particles(counts[0]) == cap_particles(counts[1]), counts
    assert not compiled, f"a cube of another size in the class compiled {compiled}"
    for err, gerr, gxy in errors:
        assert err < 1e-12 and gerr < 1e-10 and gxy < 1e-10, errors


# ------------------------------------------------------------------------------- 5. README set_position
def test_readme_set_position_moves_the_centre_of_mass_of_an_unbatched_entity():
    scene, cube = _cube()
    x0 = cube.get_particles_pos().detach().clone()
    target = (0.12, 0.17, 0.25)
    cube.set_position(target)
    x = cube.get_particles_pos().detach()
    assert torch.allclose(cube.get_pos().detach(), torch.tensor(target, **F64), atol=1e-14, rtol=0)
    assert torch.allclose(x - x.mean(0), x0 - x0.mean(0), atol=1e-14, rtol=0)  # same shape
    scene.step()
    assert torch.isfinite(cube.get_particles_pos()).all()


# ------------------------------------------------------------------------------- 4. heavy body on jelly
def _inside_box(x, pos, quat, size):
    """Depth (m, > 0 inside) of each point x (n, 3) in the box of centre pos, quaternion quat (w, x, y, z)
    and full size `size`: its exact geometry, not the simulator's."""
    w, a, b, c = quat
    R = np.array([[1 - 2 * (b * b + c * c), 2 * (a * b - c * w), 2 * (a * c + b * w)],
                  [2 * (a * b + c * w), 1 - 2 * (a * a + c * c), 2 * (b * c - a * w)],
                  [2 * (a * c - b * w), 2 * (b * c + a * w), 1 - 2 * (a * a + b * b)]])
    local = (x - pos) @ R
    return (np.asarray(size) / 2 - np.abs(local)).min(1)


@pytest.mark.slow
@pytest.mark.parametrize("tonnes", [4, 400])
def test_no_particle_stays_inside_a_heavy_box_resting_on_jelly(tonnes):
    # a 4 t (400 t) box (0.1 x 0.1 x 0.05 m) on a 0.2 x 0.2 x 0.1 m jelly block (E = 5e4 Pa) over a plane: far
    # more than the jelly can bear (4e6 Pa on it), so it sinks through the jelly to the plane. Before, material
    # the box struck stayed inside it: 22 particles at rest (4 deeper than half a cell), then 20 within a few
    # mm of its top edges once the mass-scaled ground contact held the box (the expel push, capped at 0.002
    # cells per substep, lost against the jelly pressing back in); the 400 t box went through the plane
    dens = 40
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=8),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, -0.1), upper_bound=(0.4, 0.4, 0.4),
                                                       grid_density=dens))
    scene.add_entity(gs.morphs.Plane())
    jelly = scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 0.05), size=(0.2, 0.2, 0.1)),
                             material=gs.materials.MPM.Elastic(E=5e4, nu=0.3), name="jelly")
    size = np.array([0.1, 0.1, 0.05])
    box = scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 0.1 + size[2] / 2 + 0.002), size=tuple(size)),
                           material=gs.materials.Rigid(rho=tonnes * 1e3 / size.prod()), name="box")
    scene.build()
    for _ in range(300):
        scene.step()
    assert box.get_vel().norm().item() < 1e-3  # at rest
    depth = _inside_box(jelly.get_particles_pos().numpy(), box.get_pos().numpy(), box.get_quat().numpy(), size)
    print(f"box centre z {box.get_pos()[2].item():.5f} m; particles inside {(depth > 0).sum()}, deepest {depth.max():.4f} m")
    assert (depth > 0).sum() == 0
    # the body rests on the plane within 1 mm (its mass-scaled contact: ~0.25 mm), not in it or through it
    assert abs(box.get_pos()[2].item() - size[2] / 2) < 1e-3


# ------------------------------------------------------------------------------- 6. through the domain's floor
def test_a_body_going_through_the_domain_floor_is_an_error_naming_it():
    scene = _scene()  # the class of _cube's scenes (its MPM kernels are shared), with a box coupled to it
    scene.add_entity(gs.morphs.Box(pos=(0.15, 0.15, 0.1), size=(0.05,) * 3),
                     material=gs.materials.MPM.Elastic(E=2e4, nu=0.3, rho=1000), name="jelly")
    box = scene.add_entity(gs.morphs.Box(pos=(0.15, 0.15, 0.16), size=(0.04,) * 3),
                           material=gs.materials.Rigid(rho=4e5 / 0.04 ** 3), name="anvil")
    scene.build()
    with pytest.raises(GenesisException, match=r"'anvil' went through the floor of the MPM domain \(z = 0 m\)") as e:
        for _ in range(400):
            scene.step()
    msg = str(e.value)
    assert "gs.morphs.Plane()" in msg and "at step" in msg, msg
    step = int(msg.split("at step ")[1].split(":")[0])
    # it raised at the step the box's centre crossed z = 0 (the coupler sees it at the next substep's start)
    z = float(box.get_pos()[2])
    assert z < 0.0 and z > -0.05, z
    assert step == scene._simulator.step_count
