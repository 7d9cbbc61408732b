"""Issue #7: the MPM solver (elastic, plasticine, sand, liquid), its gradients and its errors.

Physics is checked against analytic results (free fall, conservation of mass, linear and angular
momentum) and qualitative laws with measured figures (an elastic cube bounces and recovers its
shape, plasticine keeps its dent, water levels out keeping its volume, sand piles at an angle set by
its friction angle). Gradients of every input kind are checked against central finite differences in
float64, projected on random directions (every entry of every input moves at once), on rollouts
that hit the floor (wall friction), yield (plasticity) and span several steps and substeps.
"""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

import genesis_lite as gs
from genesis_lite.errors import GenesisException, GenesisWarning

F64 = dict(dtype=torch.float64)
G = 9.81


def _scene(dt=2e-3, substeps=10, requires_grad=False, lower=(0, 0, 0), upper=(0.5, 0.5, 0.5), density=32,
           gravity=(0, 0, -G), checkpoint_every=None, wall_friction=0.5):
    return gs.Scene(sim_options=gs.options.SimOptions(dt=dt, substeps=substeps, requires_grad=requires_grad,
                                                      gravity=gravity, checkpoint_every=checkpoint_every),
                    mpm_options=gs.options.MPMOptions(lower_bound=lower, upper_bound=upper, grid_density=density,
                                                      wall_friction=wall_friction))


# ------------------------------------------------------------------------------------------------ physics
def test_free_fall_follows_half_g_t_squared():
    scene = _scene(density=32, upper=(0.5, 0.5, 1.0))
    cube = scene.add_entity(gs.morphs.Box(pos=(0.25, 0.25, 0.8), size=(0.1, 0.1, 0.1)),
                            material=gs.materials.MPM.Elastic(E=1e5, nu=0.3))
    scene.build()
    z0 = cube.get_pos()[2].item()
    T = 150  # 0.3 s: falls 0.44 m, the cube's bottom stays above the floor's wall cells
    for _ in range(T):
        scene.step()
    t = T * scene.dt
    drop = z0 - cube.get_pos()[2].item()
    assert abs(drop - 0.5 * G * t * t) < 0.01 * (0.5 * G * t * t), (drop, 0.5 * G * t * t)
    assert abs(cube.get_vel()[2].item() + G * t) < 1e-9 * G * t
    assert cube.get_particles_pos()[:, 2].min().item() > 3 / 32  # it touched nothing


def test_the_walls_hold_material_where_genesis_s_do_frictionless_unless_told():
    """The domain's walls are Genesis's boundary: material rests 3 cells in from the floor (lower_bound +
    3 dx, where Genesis's CubeBoundary holds it), and they stop only the velocity into them, so a cube
    set sliding on the floor keeps its speed; with MPMOptions(wall_friction=mu) it slows at mu g
    (Coulomb), the analytic value within 3 %, and with one coefficient per axis only the floor's (the
    faces normal to z) acts on it."""
    dens = 32
    dx = 1.0 / dens
    spacing = 0.01 * 64 / dens  # the particles' spacing (MPMOptions.particle_size's default)
    for friction, mu in ((None, 0.0), (0.3, 0.3), ((0.3, 0.3, 0.0), 0.0), ((0.0, 0.0, 0.3), 0.3)):
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=10),
                         mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(1.0, 0.5, 0.5),
                                                           grid_density=dens,
                                                           **({} if friction is None else {"wall_friction": friction})))
        cube = scene.add_entity(gs.morphs.Box(pos=(0.3, 0.25, 3 * dx + 0.051), size=(0.1, 0.1, 0.1)),
                                material=gs.materials.MPM.Elastic(E=1e5, nu=0.3))
        scene.build()
        for _ in range(100):  # 0.2 s: it settles on the floor
            scene.step()
        z = cube.get_particles_pos()[:, 2]
        # its lowest particles (half a spacing above its bottom face) sit on the plane 3 cells in
        assert 3 * dx < z.min().item() < 3 * dx + spacing, (z.min().item(), 3 * dx)
        v = cube.get_particles_vel().clone()
        v[:, 0] += 1.0
        cube.set_particles_vel(v)
        v0 = cube.get_vel()[0].item()
        for _ in range(50):
            scene.step()
        v1 = cube.get_vel()[0].item()
        if mu == 0.0:
            assert abs(v1 - v0) < 1e-9, (friction, v0, v1)
        else:
            decel = (v0 - v1) / (50 * 2e-3)
            assert abs(decel - mu * G) < 0.03 * mu * G, (friction, decel, mu * G)
    for bad in (-0.1, (0.1, 0.2), (0.1, float("nan"), 0.0), "rough", True):
        with pytest.raises(ValueError, match="wall_friction"):
            gs.options.MPMOptions(wall_friction=bad)


# Genesis 0.4.5's numbers for its MPM tutorial (examples/tutorials/mpm.py), measured with
# benchmarks/mpm_tutorial_probe.py --side genesis (genesis-world 0.4.5 in its own venv, CPU, float32;
# benchmarks/results/mpm_tutorial.md): step -> (mean z of the elastic box, the liquid, the plastic
# sphere; the liquid's extent along y)
GENESIS_MPM_TUTORIAL = {40: (0.1521, 0.1465, 0.2241, 0.636), 60: (0.2220, 0.0849, 0.1219, 1.079)}


def test_genesis_s_mpm_tutorial_gives_genesis_s_answers():
    """Genesis's MPM tutorial scene (an elastic box, a liquid box and a plasticine sphere dropped into a
    2 m domain: benchmarks/mpm_tutorial_probe.py builds it the same way) follows Genesis's run: each
    body's mean height within 3 mm and the spreading liquid's extent within 5 cm, at steps 40 and 60
    (the bodies have landed, the elastic box has bounced and the liquid spreads). Before the walls were
    Genesis's (frictionless, the material resting 3 cells in: it rested 2 cells in, on friction 0.5), the
    liquid's front lagged by 22 cm and the box sat 14 mm low at step 60."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    try:
        import mpm_tutorial_probe as probe
    finally:
        sys.path.pop(0)

    scene, bodies = probe.build(gs)
    for step in range(1, 61):
        scene.step()
        if step in GENESIS_MPM_TUTORIAL:
            got = probe.probe(bodies)
            ref = GENESIS_MPM_TUTORIAL[step]
            for name, z in zip(("elastic", "liquid", "plastic"), ref[:3]):
                assert abs(got[name]["z_mean"] - z) < 3e-3, (step, name, got[name]["z_mean"], z)
            spread = got["liquid"]["y_max"] - got["liquid"]["y_min"]
            assert abs(spread - ref[3]) < 0.05, (step, spread, ref[3])


def _momenta(cube, dx):
    """Total linear momentum and angular momentum about the origin, APIC's affine part included
    (with quadratic B-splines the inertia-like tensor D is dx^2/4 I, so particle p adds
    m_p dx^2 / 4 * axial(C_p - C_p^T))."""
    m = cube._masses()[:, None]
    x, v, C = cube.get_particles_pos(), cube.get_particles_vel(), cube.get_particles_C()
    P = (m * v).sum(0)
    skew = C - C.transpose(-1, -2)
    axial = torch.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], -1)
    L = (m * torch.cross(x, v, dim=-1)).sum(0) + (m * axial).sum(0) * dx * dx / 4.0
    return P, L


def test_free_flight_conserves_linear_and_angular_momentum():
    """No gravity, no wall in reach: a spinning, tumbling elastic cube keeps its momentum and angular
    momentum (APIC transfers and a symmetric Kirchhoff stress conserve both) while it deforms."""
    scene = _scene(gravity=(0, 0, 0), density=32)
    cube = scene.add_entity(gs.morphs.Box(pos=(0.25, 0.25, 0.25), size=(0.1, 0.08, 0.06)),
                            material=gs.materials.MPM.Elastic(E=5e4, nu=0.3))
    scene.build()
    x = cube.get_particles_pos()
    c = x.mean(0)
    w = torch.tensor([3.0, -2.0, 5.0], **F64)
    v = torch.tensor([0.05, -0.03, 0.02], **F64) + torch.cross(w.expand_as(x), x - c, dim=-1)
    v = v + 0.02 * torch.randn(x.shape, generator=torch.Generator().manual_seed(0), **F64)  # and deformation
    cube.set_particles_vel(v)
    P0, L0 = _momenta(cube, 1 / 32)
    for _ in range(40):
        scene.step()
    P1, L1 = _momenta(cube, 1 / 32)
    assert (P1 - P0).norm() < 1e-12 * P0.norm() * 100, (P0, P1)
    assert (L1 - L0).norm() < 1e-10 * L0.norm(), (L0, L1, (L1 - L0).norm() / L0.norm())
    assert cube.get_particles_pos()[:, 2].min().item() > 3 / 32 + 0.02


def test_mass_is_conserved_and_particles_stay_in_the_domain():
    """A block thrown at a corner at 6 m/s: the grid receives exactly the particles' mass every
    substep (partition of unity of the B-spline weights; the grid loops cover only the block of nodes
    the particles reach), and no particle leaves the domain."""
    scene = _scene(density=32)
    block = scene.add_entity(gs.morphs.Box(pos=(0.3, 0.3, 0.3), size=(0.1, 0.1, 0.1)),
                             material=gs.materials.MPM.Liquid(E=1e5, nu=0.3))
    scene.build()
    block.set_velocity(torch.tensor([4.0, 3.0, -3.0], **F64))
    total = block._masses().sum().item()
    lo, hi = np.zeros(3), np.full(3, 0.5)
    for _ in range(60):
        scene.step()
        x = block.get_particles_pos().numpy()
        assert (x >= lo).all() and (x <= hi).all()
        s = scene.mpm_solver
        (l0, l1, l2), (n0, n1, n2) = s.active_lo[None], s.active_n[None]
        grid_mass = s.grid_m.to_numpy()[0, l0:l0 + n0, l1:l1 + n1, l2:l2 + n2].sum()
        assert abs(grid_mass - total) < 1e-12 * total


@pytest.mark.slow
def test_elastic_cube_bounces_back_to_shape_and_plasticine_keeps_its_dent():
    scene = _scene(density=64, upper=(0.8, 0.4, 0.6))
    size = 0.12
    jelly = scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 0.3), size=(size,) * 3),
                             material=gs.materials.MPM.Elastic(E=1e5, nu=0.3))
    clay = scene.add_entity(gs.morphs.Box(pos=(0.6, 0.2, 0.3), size=(size,) * 3),
                            material=gs.materials.MPM.ElastoPlastic(E=1e5, nu=0.3, yield_stress=2e3))
    scene.build()
    rest = jelly.get_particles_pos().clone()
    up = {jelly: 0.0, clay: 0.0}
    for _ in range(300):
        scene.step()
        for e in up:
            up[e] = max(up[e], e.get_vel()[2].item())
    impact = (2 * G * (0.3 - size / 2 - 3 / 64)) ** 0.5  # 1.95 m/s
    # it left the floor again at over half its impact speed ...
    assert up[jelly] > 0.5 * impact, up
    x = jelly.get_particles_pos()
    dev = ((x - x.mean(0)) - (rest - rest.mean(0))).norm(dim=1)
    # ... and its shape is the rest shape up to vibrations of a few % of its size
    assert dev.max().item() < 0.1 * size, dev.max()
    assert up[clay] < 0.1 * impact, up  # plasticine hardly bounces (restitution < 0.1) ...
    z = clay.get_particles_pos()[:, 2]
    assert (z.max() - z.min()).item() < 0.8 * size  # ... and stays flattened
    assert abs(clay.get_vel()[2].item()) < 1e-2


def _pile_slope(x, dx, floor):
    """Mean slope (degrees) of a pile's two flanks: the free-surface height (95th percentile of z per
    column of width dx) fitted by a line between 20 % and 80 % of the pile's height."""
    xs, zs = x[:, 0], x[:, 2] - floor
    hx, hz = [], []
    for b in np.arange(xs.min(), xs.max(), dx):
        sel = (xs >= b) & (xs < b + dx)
        if sel.sum() > 5:
            hx.append(b + dx / 2)
            hz.append(np.percentile(zs[sel], 95))
    hx, hz = np.array(hx), np.array(hz)
    H, top = hz.max(), hx[np.argmax(hz)]
    slopes = []
    for side in (hx < top, hx > top):
        m = side & (hz > 0.2 * H) & (hz < 0.8 * H)
        slopes.append(np.degrees(np.arctan(abs(np.polyfit(hx[m], hz[m], 1)[0]))))
    return np.mean(slopes)


@pytest.mark.slow
@pytest.mark.parametrize("phi", [25.0, 35.0])
def test_sand_column_collapses_to_a_pile_at_its_friction_angle(phi):
    """A long sand block (plane strain: between smooth walls) 24 cm wide and 12 cm tall collapses on a
    floor with friction 1; the pile's flanks settle at an angle set by the friction angle."""
    dens = 64
    scene = _scene(density=dens, upper=(1.0, 0.25, 0.5), wall_friction=(0.0, 0.0, 1.0))
    sand = scene.add_entity(gs.morphs.Box(pos=(0.5, 0.125, 3 / dens + 0.06), size=(0.24, 0.25 - 6 / dens - 0.002, 0.12)),
                            material=gs.materials.MPM.Sand(E=3e5, nu=0.3, friction_angle=phi))
    scene.build()
    for _ in range(400):
        scene.step()
    assert sand.get_particles_vel().norm(dim=1).max().item() < 0.05  # at rest
    slope = _pile_slope(sand.get_particles_pos().numpy(), 1 / dens, 3 / dens)
    print(f"friction angle {phi}: pile slope {slope:.1f} deg")
    assert abs(slope - phi) < 5.0, slope


@pytest.mark.slow
def test_water_settles_flat_keeping_its_volume():
    """A 20 cm column of viscous water released in a box spreads into a flat layer (its free surface
    level to within one grid cell) that keeps the poured volume within 5 %: inside the layer, away from
    the walls and the surface, particles are as densely packed as in the poured column, and the
    deformation gradients' determinants (the particles' own volume ratios) average 1 within 5 %."""
    dens = 64
    L = 0.3
    scene = _scene(density=dens, upper=(L, L, 0.4), wall_friction=0.0)
    water = scene.add_entity(gs.morphs.Box(pos=(0.11, 0.15, 3 / dens + 0.1), size=(0.12, L - 6 / dens - 0.002, 0.2)),
                             material=gs.materials.MPM.Liquid(E=2e5, nu=0.3, viscosity=5.0))
    scene.build()
    for _ in range(1000):
        scene.step()
    assert np.abs(water.get_particles_vel().numpy()).max() < 0.05  # settled
    x = water.get_particles_pos().numpy()
    half = scene.mpm_options.particle_size / 2
    lo, hi = x.min(0) - half, x.max(0) + half
    tops = []
    for b in np.linspace(lo[0], hi[0], 9)[:-1]:  # the free surface over 8 strips across the layer
        sel = (x[:, 0] >= b) & (x[:, 0] < b + (hi[0] - lo[0]) / 8)
        tops.append(np.percentile(x[sel, 2], 98) + half)
    tops = np.array(tops)
    assert tops.max() - tops.min() < 1.0 / dens, tops  # flat to within a grid cell
    thickness = np.median(tops) - lo[2]
    inner = ((x[:, :2] > lo[:2] + 0.05) & (x[:, :2] < hi[:2] - 0.05)).all(1) & \
            (x[:, 2] > lo[2] + 0.02) & (x[:, 2] < lo[2] + thickness - 0.02)
    inner_volume = np.prod(hi[:2] - lo[:2] - 0.1) * (thickness - 0.04)
    packing = inner.sum() * water._vol / inner_volume  # 1: as dense as poured
    J = np.linalg.det(water.get_particles_F().numpy())
    print(f"layer {thickness * 100:.1f} cm thick, packing {packing:.3f}, mean J {J.mean():.4f}, surface {tops.round(4)}")
    assert abs(packing - 1.0) < 0.05
    assert abs(J.mean() - 1.0) < 0.05


# ------------------------------------------------------------------------------------------------ gradients
MATERIALS = {
    "corotated": lambda: gs.materials.MPM.Elastic(E=2e4, nu=0.3),
    "neohooken": lambda: gs.materials.MPM.Elastic(E=2e4, nu=0.3, model="neohooken"),
    "plasticine": lambda: gs.materials.MPM.ElastoPlastic(E=2e4, nu=0.3, yield_stress=300.0),
    "sand": lambda: gs.materials.MPM.Sand(E=2e4, nu=0.3, friction_angle=30.0),
    "liquid": lambda: gs.materials.MPM.Liquid(E=2e4, nu=0.3, viscosity=0.5),
}
EXTRA = {"plasticine": ("yield_stress", 300.0), "sand": ("friction_angle", 30.0), "liquid": ("viscosity", 0.5)}


# every material with -m slow: the default run's gradient matrix (tests/gradient_cases.py, mpm_four: one cube of
# each material, every MPM input kind, per-step particle forces included) covers these paths against central
# differences; these per-material runs add a floor hit with wall friction and yield (suite time: issue #21)
@pytest.mark.slow
@pytest.mark.parametrize("kind", list(MATERIALS))
def test_gradients_of_every_input_match_finite_differences(kind):
    """Initial positions and velocities (per particle), forces (per particle, changed every step), E,
    nu and the material's own parameter, all set in one rollout of 4 steps x 4 substeps in which the
    cube hits the floor (wall friction) and, for plasticine and sand, yields. Directional derivatives
    along random directions of every input against central differences in float64."""
    scene = _scene(dt=4e-3, substeps=4, requires_grad=True, density=32)
    cube = scene.add_entity(gs.morphs.Box(pos=(0.25, 0.25, 0.15), size=(0.1, 0.1, 0.1)), material=MATERIALS[kind]())
    scene.build()
    n = cube.n_particles
    rng = np.random.default_rng(0)
    t = lambda a: torch.tensor(a, **F64)  # noqa: E731
    x0 = cube.get_particles_pos().detach().clone()
    w = t(rng.normal(size=(n, 3)))
    extra_key, extra_val = EXTRA.get(kind, (None, 1.0))

    def rollout(dpos, vel, force, E, nu, extra):
        scene.reset()
        cube.set_particles_pos(x0 + dpos)
        cube.set_particles_vel(vel)
        cube.set_material(E=E, nu=nu)
        if extra_key:
            cube.set_material(**{extra_key: extra})
        for k in range(4):
            cube.set_particles_force(force * (1.0 + k))
            scene.step()
        return (w * cube.get_particles_pos()).sum() + 0.1 * (cube.get_particles_vel() ** 2).sum()

    inputs = {"dpos": t(rng.normal(0, 0.002, (n, 3))), "vel": t(rng.normal(0, 0.3, (n, 3)) + [0.0, 0.0, -1.5]),
              "force": t(rng.normal(0, 0.05, (n, 3))), "E": t(2e4), "nu": t(0.3), "extra": t(extra_val)}
    leaves = {k: v.clone().requires_grad_(True) for k, v in inputs.items()}
    rollout(**leaves).backward()
    assert cube.get_particles_pos()[:, 2].min().item() < 3 / 32 + 0.01  # the floor's wall cells were reached
    for k, x in inputs.items():
        if k == "extra" and extra_key is None:
            assert leaves[k].grad is None
            continue
        d = t(rng.normal(size=x.shape))
        h = 1e-7 * max(1.0, x.abs().max().item())
        with torch.no_grad():
            fp = rollout(**{**inputs, k: x + h * d}).item()
            fm = rollout(**{**inputs, k: x - h * d}).item()
        fd = (fp - fm) / (2 * h)
        ad = (leaves[k].grad * d).sum().item()
        print(f"{kind:10s} {k:6s} autograd {ad: .10e} fd {fd: .10e}")
        assert abs(ad - fd) <= 2e-6 * abs(fd) + 1e-12, (k, ad, fd)


@pytest.mark.slow
def test_batched_environments_match_single_runs_and_get_their_own_gradients():
    def make(n_envs):
        scene = _scene(requires_grad=True, density=32)
        cube = scene.add_entity(gs.morphs.Box(pos=(0.25, 0.25, 0.2), size=(0.06, 0.06, 0.06)),
                                material=gs.materials.MPM.Elastic(E=2e4, nu=0.3))
        scene.build(n_envs=n_envs)
        return scene, cube

    vels = torch.tensor([[0.3, 0.0, -1.0], [-0.2, 0.4, 0.5]], **F64)
    scene, cube = make(2)
    v = vels.clone().requires_grad_(True)
    cube.set_velocity(v)
    for _ in range(5):
        scene.step()
    z = cube.get_pos()[:, 2]
    z[1].backward()
    assert v.grad[0].abs().max().item() == 0.0  # env 0 does not move env 1
    assert v.grad[1, 2].item() > 0
    single, cube1 = make(0)
    for i in range(2):
        single.reset()
        v1 = vels[i].clone().requires_grad_(True)
        cube1.set_velocity(v1)
        for _ in range(5):
            single.step()
        assert abs(cube1.get_pos()[2].item() - z[i].item()) < 1e-12
        if i == 1:
            cube1.get_pos()[2].backward()
            assert torch.allclose(v1.grad, v.grad[1], rtol=1e-10, atol=1e-14)


def test_elastic_stress_is_the_corotated_law_at_any_stretch_and_for_inverted_particles():
    """The elastic constitutive update (F's rotation by Newton's polar iteration, the SVD where that does
    not apply: inverted or nearly flat particles) against the corotated law written with numpy and
    scipy's polar decomposition, tau = 2 mu (F - R) F^T + lam (J - 1) J I, R the rotation nearest to F
    (for det F < 0: U diag(1, 1, -1) V^T of its SVD, the rotation the signed SVD takes)."""
    from scipy.linalg import polar
    from scipy.spatial.transform import Rotation

    E, nu = 3e5, 0.2
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    scene = _scene()
    cube = scene.add_entity(gs.morphs.Box(pos=(0.25, 0.25, 0.25), size=(0.1, 0.1, 0.1)),
                            material=gs.materials.MPM.Elastic(E=E, nu=nu))
    scene.build()
    scene.step()  # uploads the material parameters
    s = scene.mpm_solver
    P = cube.n_particles
    assert np.allclose(s.mu.to_numpy()[0, :P], mu) and np.allclose(s.lam.to_numpy()[0, :P], lam)
    rng = np.random.default_rng(11)
    rot = lambda n: Rotation.random(n, random_state=rng).as_matrix()  # noqa: E731
    groups = {  # name: (P_g, 3, 3) deformation gradients
        "small strain": rot(P) @ (np.eye(3) + 1e-3 * rng.standard_normal((P, 3, 3))),
        "moderate": rot(P) @ (np.eye(3) + 0.3 * rng.standard_normal((P, 3, 3))),
        "stretches 0.05-8": rot(P) @ (np.eye(3)[None] * np.exp(rng.uniform(np.log(0.05), np.log(8), (P, 1, 3)))) @ rot(P),
        "nearly flat": rot(P) @ (np.eye(3)[None] * np.array([1.3, 0.8, 1e-7])[None, :, None]) @ rot(P),
        "inverted": rot(P) @ (np.eye(3)[None] * np.array([1.1, 0.9, -0.2])[None, :, None]) @ rot(P),
    }
    B = s.n_envs
    x = np.tile(cube.get_particles_pos().detach().numpy()[None], (B, 1, 1))
    zeros3, zeros33 = np.zeros((B, P, 3)), np.zeros((B, P, 3, 3))
    for name, F in groups.items():
        s.kernel_set_state(0, x, zeros3, zeros33, np.ascontiguousarray(np.tile(F[None], (B, 1, 1, 1))))
        s.kernel_constitutive_svd(0, 0, 1e-4)  # C = 0: the trial F is F itself
        tau = s.tau.to_numpy()[0, 0, :P]
        assert np.allclose(s.F.to_numpy()[0, 0, :P], F, rtol=0, atol=1e-15), name  # elastic keeps F
        J = np.linalg.det(F)
        R = np.empty_like(F)
        for i in range(P):
            if J[i] > 0:
                R[i] = polar(F[i])[0]
            else:
                U, _, Vt = np.linalg.svd(F[i])
                R[i] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        want = 2 * mu * (F - R) @ F.transpose(0, 2, 1) + (lam * (J - 1) * J)[:, None, None] * np.eye(3)
        scale = (2 * mu + lam) * np.maximum(np.linalg.norm(F, axis=(1, 2)) ** 2, 1.0)
        err = np.abs(tau - want).max(axis=(1, 2)) / scale
        assert err.max() < 1e-12, (name, err.max())


def test_the_one_launch_substep_gives_the_staged_substeps_numbers():
    """Without gradients a substep is one kernel launch that adds to the grid without atomics (solver.py
    kernel_substep_nograd); with gradients, separate stages with atomic adds. The same scene of every
    material, 2 envs, both ways: the same trajectory up to the order of the sums at the grid nodes."""
    def run(requires_grad):
        scene = _scene(requires_grad=requires_grad, density=32)
        mats = [gs.materials.MPM.Elastic(E=2e4, nu=0.3), gs.materials.MPM.Elastic(E=2e4, nu=0.3, model="neohooken"),
                gs.materials.MPM.ElastoPlastic(E=2e4, nu=0.3, yield_stress=300.0),
                gs.materials.MPM.Sand(), gs.materials.MPM.Liquid()]
        ents = [scene.add_entity(gs.morphs.Box(pos=(0.122 + 0.064 * k, 0.25, 0.16), size=(0.05, 0.05, 0.05)),
                                 material=m) for k, m in enumerate(mats)]
        scene.build(n_envs=2)
        for e, v in zip(ents, ([0.3, 0.0, -1.0], [0.0, 0.2, -0.5], [-0.2, 0.1, -1.5], [0.1, 0.1, -1.0],
                                [0.0, -0.3, -0.8])):
            e.set_velocity(torch.tensor([v, [-v[0], -v[1], v[2]]], **F64))
        x0 = [e.get_particles_pos().detach().clone() for e in ents]
        with torch.no_grad():
            for _ in range(8):
                scene.step()
        return x0, [(e.get_particles_pos().detach().clone(), e.get_particles_vel().detach().clone()) for e in ents]

    x0, staged = run(True)
    _, fused = run(False)
    for start, (xs, vs), (xf, vf) in zip(x0, staged, fused):
        assert (xs - start).abs().max().item() > 5e-3  # every body moved (by 8 mm to 2.4 cm): not a trivial match
        assert torch.allclose(xf, xs, rtol=0, atol=1e-12), (xf - xs).abs().max()
        assert torch.allclose(vf, vs, rtol=0, atol=1e-10), (vf - vs).abs().max()


def test_kept_substeps_give_the_recomputed_substeps_gradients_and_are_not_recomputed(monkeypatch):
    """A step node keeps its MPM substeps as its forward left them (bridges/mpm.py substep_states), up to a
    budget per rollout, and its backward records them on the Tape without computing them again; the steps
    past the budget recompute theirs. All kept, none kept and half kept give the same gradients of every
    input, and the backward computes exactly the substeps of the steps that kept none."""
    import genesis_lite.bridges.mpm as bridge

    scene = _scene(dt=4e-3, substeps=3, requires_grad=True, density=32)
    cube = scene.add_entity(gs.morphs.Box(pos=(0.25, 0.25, 0.15), size=(0.08, 0.08, 0.08)),
                            material=gs.materials.MPM.ElastoPlastic(E=2e4, nu=0.3, yield_stress=300.0))
    scene.build()
    sim = scene._simulator
    computed = []
    stages = sim._mpm_substep
    monkeypatch.setattr(sim, "_mpm_substep", lambda i, grad, replay=False: (computed.append(replay), stages(i, grad, replay)))
    n, per_step = cube.n_particles, 3 * cube.n_particles * 33 * 8  # 3 substeps of x, v, C, F and stress (f64)

    def gradients(budget):
        monkeypatch.setattr(bridge, "KEEP_SUBSTEPS_BYTES", budget)
        scene.reset()
        v = torch.tensor([0.3, -0.2, -1.2], **F64, requires_grad=True)
        E = torch.tensor(2e4, **F64, requires_grad=True)
        f = torch.linspace(-0.02, 0.02, n * 3, **F64).reshape(n, 3).requires_grad_(True)
        cube.set_velocity(v)
        cube.set_material(E=E)
        for _ in range(4):
            cube.set_particles_force(f)
            scene.step()
        loss = (cube.get_particles_pos() ** 2).sum() + 0.1 * (cube.get_particles_vel() ** 2).sum()
        computed.clear()
        loss.backward()
        return [v.grad, E.grad, f.grad], computed.count(False)

    g_all, fwd_all = gradients(4 * per_step)
    g_none, fwd_none = gradients(0)
    g_half, fwd_half = gradients(2 * per_step)
    assert (fwd_all, fwd_none, fwd_half) == (0, 4 * 3, 2 * 3)
    for a, b, c in zip(g_all, g_none, g_half):
        assert torch.allclose(a, b, rtol=1e-12, atol=0) and torch.allclose(a, c, rtol=1e-12, atol=0), (a, b, c)
    assert g_all[0].abs().min() > 0 and g_all[1].abs() > 0


@pytest.mark.slow
def test_checkpointing_gives_identical_gradients_and_keeps_one_state_per_step():
    """Saved for backward: per step its input state and its substeps (x, v, C, F and the stress of each, which its
    backward then need not recompute); with checkpoints one state per checkpoint, and the window's."""
    def run(checkpoint_every):
        scene = _scene(requires_grad=True, density=32, checkpoint_every=checkpoint_every, substeps=5)
        cube = scene.add_entity(gs.morphs.Box(pos=(0.25, 0.25, 0.14), size=(0.06, 0.06, 0.06)),
                                material=gs.materials.MPM.Sand(E=2e4, nu=0.3))
        scene.build()
        v = torch.tensor([0.2, 0.0, -1.0], **F64, requires_grad=True)
        saved = {}

        def pack(t):  # bytes per distinct storage (a parameter tensor saved by every step counts once)
            saved[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
            return t

        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            cube.set_velocity(v)
            for _ in range(12):
                scene.step()
            loss = cube.get_particles_pos()[:, 2].sum()
        loss.backward()
        state_bytes = cube.n_particles * 24 * 8
        return v.grad, sum(saved.values()) / state_bytes, scene._simulator.buffer

    g_full, states_full, _ = run(None)
    g_ckpt, states_ckpt, buf = run(4)
    assert torch.allclose(g_full, g_ckpt, rtol=1e-12, atol=0), (g_full, g_ckpt)
    # 12 steps' inputs (24 numbers a particle) and their 5 substeps each (33 numbers: x, v, C, F, stress)
    assert 12 * (24 + 5 * 33) / 24 <= states_full < 12 * (24 + 5 * 33) / 24 + 1.5, states_full
    assert states_ckpt < 2.5, states_ckpt  # the buffer holds checkpoints (3) + one window (4), not the steps
    assert len(buf.checkpoints) == 3


def test_scene_without_gradients_keeps_only_the_current_state():
    scene = _scene(requires_grad=False)
    scene.add_entity(gs.morphs.Sphere(pos=(0.25, 0.25, 0.25), radius=0.05), material=gs.materials.MPM.Liquid())
    scene.build()
    s = scene.mpm_solver
    assert s.n_slots == 1 and s.x.shape[0] == 1 and not s.grad_fields


@pytest.mark.slow
def test_tape_validation_of_one_step_of_each_solver():
    """One step of the rigid solver and one substep of the MPM solver, each kernel launch recorded on a
    ti.ad.Tape(validation=True) in debug mode: Taichi checks the global data access rule of reverse
    mode (no global value overwritten after it was read) and raises otherwise."""
    code = textwrap.dedent("""
        import taichi as ti, torch, genesis_lite as gs
        gs.init(backend=gs.cpu, precision="64", debug=True)
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=1e-3, substeps=4, requires_grad=True),
                         mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.3, 0.3, 0.3),
                                                           grid_density=64))
        scene.add_entity(gs.morphs.Plane())
        scene.add_entity(gs.morphs.Box(pos=(0.15, 0.15, 0.1), size=(0.05, 0.05, 0.05)))
        scene.add_entity(gs.morphs.Box(pos=(0.15, 0.15, 0.2), size=(0.05, 0.05, 0.05)),
                         material=gs.materials.MPM.Sand())
        scene.add_entity(gs.morphs.Sphere(pos=(0.08, 0.08, 0.1), radius=0.03), material=gs.materials.MPM.Liquid())
        scene.build()
        sim = scene._simulator
        for b in sim.bridges:
            b.upload()
        rigid, mpm = scene.rigid_solver, scene.mpm_solver
        for launches in (lambda: (rigid.step_core.kernel_dynamics(0, 0, 1e-3), rigid.core.kernel_integrate(0, 0, 0, 0, 1, 1e-3)),
                         # the MPM substep's stages as its adjoint records them (the simulator's order; the
                         # hand-differentiated SVD constitutive update is not on a Tape), and the constitutive
                         # update that Taichi differentiates
                         lambda: (mpm.kernel_constitutive_ad(0, 1, mpm.h) if mpm.has_ad else None,
                                  sim._mpm_substep(0, True, replay=True))):
            with ti.ad.Tape(loss=ti.field(ti.f64, shape=(), needs_grad=True), validation=True, clear_gradients=False):
                launches()
        print("validated")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900,
                         cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert out.returncode == 0 and "validated" in out.stdout, out.stderr[-3000:]


# ------------------------------------------------------------------------------------------------ bad input
def test_entity_partly_outside_the_domain_is_an_error():
    scene = _scene()
    scene.add_entity(gs.morphs.Box(pos=(0.45, 0.25, 0.25), size=(0.1, 0.1, 0.1)), material=gs.materials.MPM.Elastic(),
                     name="jelly")
    with pytest.raises(GenesisException, match=r"jelly.*outside the MPM domain along x"):
        scene.build()


def test_too_long_time_step_is_caught_at_build_with_a_stable_substep_count():
    scene = _scene(dt=2e-3, substeps=2, density=64, upper=(0.5, 0.5, 0.5))
    scene.add_entity(gs.morphs.Box(pos=(0.25, 0.25, 0.25), size=(0.1, 0.1, 0.1)),
                     material=gs.materials.MPM.Elastic(E=1e6, nu=0.3), name="stiff")
    with pytest.raises(GenesisException, match=r"stiff.*substep.*SimOptions\(substeps=(\d+)\)") as e:
        scene.build()
    import re

    need = int(re.search(r"substeps=(\d+)", str(e.value)).group(1))
    c = gs.materials.MPM.Elastic(E=1e6, nu=0.3).wave_speed()
    assert 2e-3 / need * c / (1 / 64) <= 0.9 < 2e-3 / (need - 1) * c / (1 / 64)


@pytest.mark.parametrize("kw, match", [(dict(nu=0.5), "nu"), (dict(E=0.0), "E="), (dict(E=-1.0), "E="),
                                       (dict(rho=0.0), "rho")])
def test_bad_material_constants_are_errors(kw, match):
    with pytest.raises(ValueError, match=match):
        gs.materials.MPM.Elastic(**kw)


def test_open_mesh_cannot_be_filled(tmp_path):
    import trimesh

    m = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    m.update_faces(np.arange(len(m.faces)) != 0)  # a hole
    path = tmp_path / "open.stl"
    m.export(path)
    scene = _scene()
    with pytest.raises(GenesisException, match="not closed"):
        scene.add_entity(gs.morphs.Mesh(file=str(path), pos=(0.25, 0.25, 0.25)), material=gs.materials.MPM.Elastic(),
                         name="cup")


def test_mesh_entity_is_filled_with_its_volume(tmp_path):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3, radius=0.06)
    path = tmp_path / "ball.stl"
    m.export(path)
    scene = _scene(density=64)
    ball = scene.add_entity(gs.morphs.Mesh(file=str(path), pos=(0.25, 0.25, 0.25)), material=gs.materials.MPM.Elastic())
    assert abs(ball.n_particles * ball._vol - m.volume) < 0.05 * m.volume


def test_mpm_options_without_mpm_entity_are_unused_with_a_warning():
    """Genesis takes them (its water_wheel passes them on its SPH path); a warning says they are unused."""
    scene = _scene()
    scene.add_entity(gs.morphs.Plane())
    with pytest.warns(GenesisWarning, match="mpm_options were given but the scene has no MPM entity"):
        scene.build()
    scene.step()


def test_material_tensor_of_the_wrong_length_is_an_error():
    scene = _scene()
    cube = scene.add_entity(gs.morphs.Box(pos=(0.25, 0.25, 0.25), size=(0.05, 0.05, 0.05)),
                            material=gs.materials.MPM.Elastic(), name="jelly")
    scene.build()
    with pytest.raises(GenesisException, match=r"jelly.*E has shape \(7,\)"):
        cube.set_material(E=torch.full((7,), 1e5, **F64))
    with pytest.raises(GenesisException, match=r"jelly.*nu must be"):
        cube.set_material(nu=0.5)
    cube.set_material(E=torch.full((cube.n_particles,), 1e5, **F64))  # one per particle is fine
    assert cube.get_material("E").shape == (cube.n_particles,)
