"""Genesis's MPM emitters (issue #25): scene.add_emitter, emitter.emit / emit_omni.

Checked against references outside the code under test: a droplet's particle count is its volume over
the particle volume (exact for boxes that hold whole particles, within the lattice's edge error for
cylinders and balls); emitted particles lie inside the droplet's shape around the nozzle's axis and move
at speed * direction; a stream falls as g t^2 / 2 with its momentum growing by m g per second exactly
(nothing else acts on it); the grid carries exactly the mass of the entities plus the emitted particles;
an emitter that has not emitted changes no bit of the other entities' trajectories; bad input raises an
exception that names the problem.
"""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

import genesis_lite as gs
from genesis_lite.errors import GenesisException, GenesisWarning

G = 9.81
NOWHERE = torch.tensor([2333333.0, 6666666.0, 5201314.0], dtype=torch.float64)  # Genesis's gu.nowhere()


def _scene(upper=(0.5, 0.5, 0.6), particle_size=None, n_emitters=1, cube=True, max_particles=2000,
           requires_grad=False, material=None):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=10, gravity=(0, 0, -G),
                                                       requires_grad=requires_grad),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=upper, grid_density=32,
                                                       particle_size=particle_size))
    c = None
    if cube:
        c = scene.add_entity(gs.morphs.Box(pos=(0.25, 0.25, 0.2), size=(0.1, 0.1, 0.1)),
                             material=gs.materials.MPM.Elastic(E=1e5, nu=0.3))
    ems = [scene.add_emitter(material=material or gs.materials.MPM.Liquid(), max_particles=max_particles)
           for _ in range(n_emitters)]
    return scene, c, ems


def _grid_mass(scene):
    """Total mass on the grid after the last substep (the block of nodes the particles touched)."""
    s = scene.mpm_solver
    lo, n = s.active_lo.to_numpy(), s.active_n.to_numpy()
    m = s.grid_m.to_numpy()[0]
    return float(m[lo[0]:lo[0] + n[0], lo[1]:lo[1] + n[1], lo[2]:lo[2] + n[2]].sum())


# ------------------------------------------------------------------------------------ a silent emitter
SILENT = textwrap.dedent("""
    import torch
    import sys
    import genesis_lite as gs
    # "exact": Taichi's fast_math off, so that kernels compiled for another capacity class (the emitters'
    # particles make the class larger) round alike
    gs.init(backend=gs.cpu, precision="64", **({"fast_math": False} if sys.argv[1] == "exact" else {}))
    sys.path.insert(0, "tests")
    from test_emitter import _scene, NOWHERE
    runs = []
    for n_em in (0, 1, 2):
        scene, cube, ems = _scene(n_emitters=n_em)
        scene.build()
        for _ in range(15):
            scene.step()
        runs.append((cube.get_particles_pos().clone(), cube.get_particles_vel().clone()))
        for em in ems:
            x = em.entity.get_particles_pos()
            assert x.shape == (2000, 3) and torch.equal(x, NOWHERE.to(x).expand(2000, 3))
            assert torch.count_nonzero(em.entity.get_particles_vel()) == 0 and em.entity.get_mass() == 0.0
    assert runs[0][0][:, 2].min() < 0.157  # its lowest particles (at 0.16 m) fell g t^2 / 2 = 4 mm: not trivial
    for x, v in runs[1:]:
        print("bitwise", torch.equal(x, runs[0][0]) and torch.equal(v, runs[0][1]),
              max((x - runs[0][0]).abs().max().item(), (v - runs[0][1]).abs().max().item()))
""")


def test_an_emitter_that_has_not_emitted_changes_no_bit_of_the_scene():
    """The same elastic cube dropped on the floor, without an emitter, with one and with two: the same
    positions and velocities to the last bit with Taichi's fast_math off; the emitter's particles read as
    Genesis reports unemitted ones (at gu.nowhere(), at rest) and weigh nothing. With the default
    fast_math, the scenes with emitters run kernels compiled for a larger capacity class, which LLVM may
    round differently (measured: 8e-17 m after 15 steps): within 1e-14. In a process of one thread: with
    many threads per env, particle-to-grid adds atomically, in an order that varies from run to run."""
    env = dict(os.environ, GS_NUM_THREADS="1")
    for mode in ("exact", "default"):
        out = subprocess.run([sys.executable, "-c", SILENT, mode], capture_output=True, text=True, timeout=900,
                             env=env, cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        assert out.returncode == 0, out.stderr[-3000:]
        lines = [ln.split() for ln in out.stdout.splitlines() if ln.startswith("bitwise")]
        assert len(lines) == 2, out.stdout[-2000:]
        if mode == "exact":
            assert all(ln[1] == "True" for ln in lines), out.stdout[-2000:]
        else:
            assert all(float(ln[2]) < 1e-14 for ln in lines), out.stdout[-2000:]


# ------------------------------------------------------------------------------------ droplet shapes
@pytest.mark.parametrize("shape,size,length,expected,rtol", [
    ("square", 0.1, 0.04, 0.1 * 0.1 * 0.04, 0.0),       # 10 x 10 x 4 particles of 1 cm exactly
    ("rectangle", (0.06, 0.1), 0.03, 0.06 * 0.1 * 0.03, 0.0),
    ("circle", 0.2, 0.02, np.pi * 0.1 ** 2 * 0.02, 0.03),
    ("sphere", 0.2, 0.05, 4 / 3 * np.pi * 0.1 ** 3, 0.03),  # a sphere ignores droplet_length
])
def test_droplet_count_is_its_volume_over_the_particle_volume(shape, size, length, expected, rtol):
    p = 0.01
    scene, _, (em,) = _scene(particle_size=p, cube=False, max_particles=6000)
    scene.build()
    pos, d, speed = np.array([0.25, 0.25, 0.3]), np.array([1.0, 0.0, -1.0]), 1.5
    em.emit(droplet_shape=shape, droplet_size=size, droplet_length=length, pos=pos, direction=d, theta=0.3,
            speed=speed)
    n = em.high_water  # (next_particle may have been recycled to 0 already: Genesis's rule)
    assert abs(n - expected / p ** 3) <= rtol * expected / p ** 3 + 1e-9, (n, expected / p ** 3)
    # a particle weighs rho p^3, as in Genesis
    assert em.entity.get_mass() == pytest.approx(1000.0 * p ** 3 * n, rel=1e-12)
    x = em.entity.get_particles_pos()[:n].numpy() - pos
    u = d / np.linalg.norm(d)
    axial = x @ u
    radial = np.linalg.norm(x - axial[:, None] * u, axis=1)
    tol = 1e-12
    if shape == "sphere":
        assert np.linalg.norm(x, axis=1).max() <= size / 2 + tol
    else:
        assert np.abs(axial).max() <= length / 2 + tol  # centred at the nozzle, along the direction
        r = size / 2 if shape == "circle" else np.hypot(*np.broadcast_to(size, 2)) / 2
        assert radial.max() <= r + tol
    v = em.entity.get_particles_vel()[:n].numpy()
    assert np.abs(v - speed * u).max() < 1e-12
    # the rest still waits at nowhere
    assert torch.equal(em.entity.get_particles_pos()[n:], NOWHERE.expand(6000 - n, 3))


def test_rectangle_sides_follow_theta():
    """A thin rectangle droplet pointing down, turned by theta about its axis: its long side lies along
    (cos theta, sin theta) rotated from the nozzle frame's x axis, which Genesis makes horizontal."""
    scene, _, (em,) = _scene(particle_size=0.01, cube=False)
    scene.build()
    em.emit(droplet_shape="rectangle", droplet_size=(0.2, 0.02), droplet_length=0.01, pos=(0.25, 0.25, 0.3),
            direction=(0, 0, -1), theta=np.pi / 2)
    x = em.entity.get_particles_pos()[:em.next_particle].numpy()
    spread = x.max(0) - x.min(0)
    # 20 x 2 x 1 particles; turned a quarter turn, the 0.2 m side is along world x or y, not both
    assert em.next_particle == 40
    assert sorted(np.round(spread[:2], 6).tolist()) == [0.01, 0.19] and spread[2] < 1e-12


def test_emit_omni_sends_a_shell_outwards():
    scene, _, (em,) = _scene(particle_size=0.01, cube=False, max_particles=6000)
    scene.build()
    c = np.array([0.25, 0.25, 0.3])
    em.emit_omni(source_radius=0.1, pos=c, speed=2.0)
    n = em.high_water
    assert abs(n - 4 / 3 * np.pi * (0.1 ** 3 - 0.04 ** 3) / 1e-6) < 0.03 * n  # shell 0.4 r .. r
    x = em.entity.get_particles_pos()[:n].numpy() - c
    v = em.entity.get_particles_vel()[:n].numpy()
    r = np.linalg.norm(x, axis=1)
    assert r.min() >= 0.04 - 1e-12 and r.max() <= 0.1 + 1e-12
    assert np.abs(v - 2.0 * x / r[:, None]).max() < 1e-12


# ------------------------------------------------------------------------------------ physics
def test_a_stream_and_a_droplet_fall_freely():
    """A stream from a nozzle pointing down at v0 = 2 m/s, droplet_length from the speed (4 mm a step: one
    2 cm layer every 5 steps), and beside it a single ball-shaped droplet thrown down at v0 by a second
    emitter. Gravity is the only external force (the liquid's pressure is internal, nothing is touched).
    The stream's centre of mass moves as each layer's own free fall: a layer that has had n substeps of h
    falls v0 n h + g h^2 n (n + 1) / 2 (semi-implicit Euler: g t^2 / 2 + g t h / 2), to round-off; its front
    layer lags that by a few per cent, held back by the cohesion of the stretching liquid behind it. Each
    particle of the lone droplet, unstrained, falls exactly so."""
    scene, _, (em, drop_em) = _scene(upper=(0.5, 0.5, 1.0), cube=False, max_particles=3000, n_emitters=2)
    scene.build()
    v0, dt, z0, S = 2.0, scene.dt, 0.85, scene.sim_options.substeps
    h = dt / S
    emitted = []  # (step of emission, first index, count)
    steps = 60
    for k in range(steps):
        before = em.high_water
        em.emit(droplet_shape="circle", droplet_size=0.1, pos=(0.3, 0.3, z0), direction=(0, 0, -1), speed=v0)
        if em.high_water > before:
            emitted.append((k, before, em.high_water - before))
        if k == 10:
            drop_em.emit(droplet_shape="sphere", droplet_size=0.08, droplet_length=0.08, pos=(0.15, 0.15, z0),
                         direction=(0, 0, -1), speed=v0)
        scene.step()
    assert len(emitted) >= 10 and emitted[0][0] in (4, 5)  # the 4 mm a step add up to one 2 cm particle
    assert all(n == 21 for _, _, n in emitted)  # a 5 x 5 lattice of 2 cm in a 10 cm circle, one layer
    z = em.entity.get_particles_pos()[:em.high_water, 2].numpy()
    vz = em.entity.get_particles_vel()[:em.high_water, 2].numpy()
    drops, speeds = np.zeros_like(z), np.zeros_like(z)
    for k, i, n in emitted:
        ns = (steps - k) * S
        drops[i:i + n] = v0 * ns * h + G * h * h * ns * (ns + 1) / 2
        speeds[i:i + n] = v0 + G * ns * h
    assert abs((z0 - z).sum() - drops.sum()) < 1e-9 * drops.sum()
    assert abs(-vz.sum() - speeds.sum()) < 1e-9 * speeds.sum()
    assert z.min() > 0.2  # it touched nothing
    k1, i1, n1 = emitted[0]
    t = (steps - k1) * dt
    front = z0 - z[i1:i1 + n1].mean()
    assert 0.9 * (v0 * t + 0.5 * G * t * t) < front < v0 * t + 0.5 * G * t * t
    # the lone droplet: 4^3 particles of 2 cm in an 8 cm box, those within 4 cm of its centre
    n = drop_em.high_water
    ns = (steps - 10) * S
    x = drop_em.entity.get_particles_pos()[:n].numpy()
    assert n > 20
    expected = v0 * ns * h + G * h * h * ns * (ns + 1) / 2  # 0.225 m
    lattice = np.array([[a, b, c] for a in (-3, -1, 1, 3) for b in (-3, -1, 1, 3) for c in (-3, -1, 1, 3)]) * 0.01
    lattice = lattice[np.linalg.norm(lattice, axis=1) <= 0.04]
    assert len(lattice) == n
    start = np.array([0.15, 0.15, z0]) + lattice
    back = x + np.array([0.0, 0.0, expected])  # each particle moved up by the analytic drop

    def rows(a):  # the points in one order (lexicographic), whatever order they were emitted in
        return a[np.lexsort(np.round(a, 6).T[::-1])]

    assert np.abs(rows(back) - rows(start)).max() < 1e-9


def test_grid_mass_is_the_entities_plus_the_emitted_particles():
    """Mass on the grid after a step: the cube's alone before any emission (the emitter's particles
    weigh nothing), plus rho * droplet volume after a 10 x 10 x 4 cm box of liquid is emitted; those
    particles, and only those, are active (get_particles_active)."""
    scene, cube, (em,) = _scene(particle_size=0.01)
    scene.build()
    cube_mass = 1000.0 * 0.1 ** 3
    scene.step()
    assert _grid_mass(scene) == pytest.approx(cube_mass, rel=1e-12)
    em.emit(droplet_shape="square", droplet_size=0.1, droplet_length=0.04, pos=(0.25, 0.25, 0.45), speed=0.5)
    for _ in range(3):
        scene.step()
        assert _grid_mass(scene) == pytest.approx(cube_mass + 1000.0 * 0.1 * 0.1 * 0.04, rel=1e-12)
    assert em.entity.get_mass() == pytest.approx(0.4, rel=1e-12)
    # Genesis's get_particles_active: the 10 x 10 x 4 emitted particles (of 1 cm) and none of the rest;
    # every particle of an ordinary entity
    act = em.entity.get_particles_active()
    assert act.dtype == torch.bool and act.shape == (2000,) and int(act.sum()) == 400
    assert bool((em.entity.get_particles_pos()[act][:, 2] < 1.0).all())
    assert not bool((em.entity.get_particles_pos()[~act] != NOWHERE).any())
    assert bool(cube.get_particles_active().all())


def test_an_unemitted_emitter_behind_an_emitting_one_stays_out():
    """Two emitters, the second emitting: the first's particles (inside the solver's count, behind the
    second's) still weigh nothing and read as nowhere, and the cube and the emitted liquid move as in
    the scene with the second emitter alone (to round-off: the particles waiting in the count change the
    order of the grid's sums in the last bit). Then the first emits too."""
    out = []
    for n_em in (1, 2):
        scene, cube, ems = _scene(n_emitters=n_em, particle_size=0.01)
        scene.build()
        for k in range(12):
            if k == 0:
                ems[-1].emit(droplet_shape="square", droplet_size=0.06, droplet_length=0.06,
                             pos=(0.25, 0.25, 0.45), speed=1.0)
            scene.step()
        out.append((cube.get_particles_pos().clone(), ems[-1].entity.get_particles_pos()[:216].clone()))
        if n_em == 2:
            first = ems[0].entity
            assert torch.equal(first.get_particles_pos(), NOWHERE.expand(2000, 3)) and first.get_mass() == 0.0
            assert _grid_mass(scene) == pytest.approx(1.0 + 0.216, rel=1e-12)
            ems[0].emit(droplet_shape="sphere", droplet_size=0.06, pos=(0.1, 0.1, 0.3), speed=0.0)
            n0 = ems[0].next_particle
            scene.step()
            assert _grid_mass(scene) == pytest.approx(1.0 + 0.216 + n0 * 1e-3, rel=1e-12)
            assert torch.isfinite(first.get_particles_pos()[:n0]).all()
    for a, b in zip(*out):
        assert torch.allclose(a, b, rtol=0, atol=1e-12)
    assert out[0][1][:, 2].max() < 0.45  # the liquid moved


def test_particles_are_recycled_as_in_genesis():
    """Genesis's rule: after a batch, if another batch of its size would pass max_particles, the next
    starts again from particle 0; emitted particles stay in the simulation."""
    scene, _, (em,) = _scene(particle_size=0.01, cube=False, max_particles=250)
    scene.build()
    nexts = []
    for _ in range(4):
        em.emit(droplet_shape="square", droplet_size=0.1, droplet_length=0.01, pos=(0.25, 0.25, 0.3), speed=0.0)
        nexts.append(em.next_particle)
    assert nexts == [100, 0, 100, 0] and em.high_water == 200
    assert torch.equal(em.entity.get_particles_pos()[200:], NOWHERE.expand(50, 3))


def test_reset_takes_the_emitted_particles_back():
    """scene.reset(): the emitter's particles are unemitted again (as in Genesis, which restores their
    `active` flags and restarts the emitter), and the same emissions give the same trajectory."""
    scene, cube, (em,) = _scene(particle_size=0.01)
    scene.build()

    def run():
        for k in range(6):
            em.emit(droplet_shape="circle", droplet_size=0.06, droplet_length=0.02, pos=(0.25, 0.25, 0.45))
            scene.step()
        return em.entity.get_particles_pos().clone(), cube.get_particles_pos().clone()

    a = run()
    scene.reset()
    assert em.next_particle == 0 and em.entity.get_mass() == 0.0
    assert torch.equal(em.entity.get_particles_pos(), NOWHERE.expand(2000, 3))
    b = run()
    # the same to round-off (the grid's atomic sums run in a varying order over threads)
    assert torch.allclose(a[0], b[0], rtol=0, atol=1e-12) and torch.allclose(a[1], b[1], rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------------ bad input
def test_bad_input_is_refused_with_a_message():
    scene, _, (em,) = _scene()
    with pytest.raises(GenesisException, match="before scene.build"):
        em.emit(droplet_shape="circle", droplet_size=0.04)
    scene.build()
    with pytest.raises(GenesisException, match="after scene.build"):
        scene.add_emitter(material=gs.materials.MPM.Liquid())
    with pytest.raises(GenesisException, match="unsupported droplet_shape 'triangle'.*circle"):
        em.emit(droplet_shape="triangle", droplet_size=0.04, pos=(0.25, 0.25, 0.4))
    with pytest.raises(GenesisException, match="zero-length direction"):
        em.emit(droplet_shape="circle", droplet_size=0.04, pos=(0.25, 0.25, 0.4), direction=(0, 0, 0))
    with pytest.raises(GenesisException, match="rectangle.*width, height"):
        em.emit(droplet_shape="rectangle", droplet_size=0.04, pos=(0.25, 0.25, 0.4))
    with pytest.raises(GenesisException, match="outside the MPM domain along z"):
        em.emit(droplet_shape="circle", droplet_size=0.04, droplet_length=0.04, pos=(0.25, 0.25, 0.59))
    with pytest.raises(GenesisException, match=r"\d+ particles, more than the emitter's max_particles \(2000\)"):
        em.emit(droplet_shape="square", droplet_size=0.3, droplet_length=0.3, pos=(0.25, 0.25, 0.3))  # 15^3
    with pytest.raises(GenesisException, match="droplet_length must be a positive"):
        em.emit(droplet_shape="circle", droplet_size=0.04, droplet_length=-1.0, pos=(0.25, 0.25, 0.4))
    assert em.high_water == 0 and em.next_particle == 0  # nothing was emitted by the refused calls


def test_emitters_refuse_gradients_and_other_materials():
    """As in Genesis: no emitter in a differentiable scene; MPM materials here (an SPH / PBD one: the test
    below)."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(requires_grad=True),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.5, 0.5, 0.5)))
    with pytest.raises(GenesisException, match="not differentiable.*requires_grad=False"):
        scene.add_emitter(material=gs.materials.MPM.Liquid())
    scene = gs.Scene(mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.5, 0.5, 0.5)))
    with pytest.raises(TypeError, match="MPM"):
        scene.add_emitter(material=gs.materials.Rigid())
    with pytest.raises(GenesisException, match="max_particles"):
        scene.add_emitter(material=gs.materials.MPM.Liquid(), max_particles=0)


def test_per_env_reset_cannot_undo_an_emission():
    scene, _, (em,) = _scene()
    scene.build(n_envs=2)
    state = scene.get_state()
    em.emit(droplet_shape="circle", droplet_size=0.06, droplet_length=0.02, pos=(0.25, 0.25, 0.45))
    x = em.entity.get_particles_pos()
    assert x.shape == (2, 2000, 3) and torch.equal(x[0], x[1])  # the same droplet in every env
    with pytest.raises(GenesisException, match="emitter_1' has \\d+ particles emitted now and had 0.*for all envs"):
        scene.reset(state, envs_idx=[1])
    later = scene.get_state()
    scene.reset(later, envs_idx=[1])  # a state taken after the emission is fine


def test_a_camera_draws_only_the_emitted_particles():
    """Unemitted particles are 'nowhere' and not drawn; emitted ones are, at the particle size."""
    scene, _, (em,) = _scene(cube=False, particle_size=0.01)
    cam = scene.add_camera(res=(64, 64), pos=(0.25, -0.6, 0.3), lookat=(0.25, 0.25, 0.3), fov=40)
    scene.build()
    seg = cam.render(rgb=False, segmentation=True)[2]
    assert not (seg == 0).any()  # the emitter is entity 0: nothing of it in view
    em.emit(droplet_shape="sphere", droplet_size=0.1, pos=(0.25, 0.25, 0.3), speed=0.0, droplet_length=0.01)
    seg = cam.render(rgb=False, segmentation=True)[2]
    rows, cols = np.nonzero(seg == 0)
    # a 10 cm ball 0.85 m away in a 40 degree view of 64 px: about 10 px across (11 with the particles' radius)
    assert 8 <= cols.max() - cols.min() + 1 <= 14 and 8 <= rows.max() - rows.min() + 1 <= 14
    assert len(rows) > 0.6 * np.pi / 4 * (cols.max() - cols.min() + 1) ** 2  # a filled disc, not dots


def test_an_sph_emitter_is_left_out_with_a_warning_and_emits_nothing():
    """water_wheel's default: an SPH liquid's emitter. Out of genesis_lite's scope: add_emitter warns that it is
    left out, emit() adds nothing (after build, as any emitter), the scene steps as without it (a sphere
    falling beside it, to the bit), and the emitter's entity raises when read."""
    def run(with_emitter):
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=4e-3),
                         mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.5, 0.5, 0.5)),
                         sph_options=gs.options.SPHOptions(particle_size=0.02))
        em = None
        if with_emitter:
            with pytest.warns(GenesisWarning, match=r"scene.add_emitter: gs.materials.SPH.Liquid needs Genesis's SPH "
                                                    r"solver.*left out of the simulation.*MPM.Liquid"):
                em = scene.add_emitter(material=gs.materials.SPH.Liquid(sampler="regular"), max_particles=1000)
            with pytest.raises(GenesisException, match="before scene.build"):
                em.emit(pos=(0.25, 0.25, 0.4), direction=(0, 0, -1), speed=1.0, droplet_shape="circle",
                        droplet_size=0.05)
        ball = scene.add_entity(gs.morphs.Sphere(radius=0.05, pos=(0.25, 0.25, 0.3)))
        with pytest.warns(GenesisWarning, match="mpm_options were given but the scene has no MPM entity"):
            scene.build()
        zs = []
        for _ in range(30):
            if em is not None:
                em.emit(pos=(0.25, 0.25, 0.4), direction=(0, 0, -1), speed=1.0, droplet_shape="circle",
                        droplet_size=0.05)
            scene.step()
            zs.append(ball.get_pos().clone())
        return scene, em, torch.stack(zs)

    scene, em, zs = run(True)
    assert scene.emitters == [em] and em.entity in scene.entities and em.max_particles == 1000
    with pytest.raises(GenesisException, match=r"'emitter_0' \(gs.materials.SPH.Liquid\) has no 'get_particles_pos'"):
        em.entity.get_particles_pos()
    assert torch.equal(zs, run(False)[2])
