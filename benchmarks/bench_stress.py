"""Stability under stress: each scene passes or fails a stated criterion, with MuJoCo's figure beside it, and the
largest time step each engine survives (bisected); then the gradient norm against horizon on a chaotic system.

    python benchmarks/bench_stress.py [--quick] [--rows energy,stiff,...] [--no-bisect]

Scenes (genesis_lite defaults unless said: implicitfast, dt = 0.01 s, contact stiffness 1e6 N/m; MuJoCo the same
bodies, floor, masses, integrator and dt with its own default soft contacts, elliptic cones):
- energy: the frictionless double pendulum (assets/urdf/double_pendulum.urdf, released from (0.9, -0.6) rad,
  (0, 0.8) rad/s as in bench_integrators.py), 100,000 steps of dt = 0.01 s (1,000 s; --quick: 10,000) per
  integrator, the energy sampled every 100 steps. Pass: max abs(E - E0) / abs(E0) <= 5 % and finite.
- stiff: a 1 kg, 0.2 m box dropped from 0.1 m onto the ground with contact_stiffness 1e8 N/m (100x the
  default). MuJoCo: solref = (-1e8, -4e4), i.e. the same stiffness and damping per unit mass in MuJoCo's direct
  form. Pass: finite, at rest after 2 s (speed < 1 cm/s), penetration at rest < 1 mm, no bounce above the drop.
- mass ratio 1:10, 1:100, 1:1000: a 1 kg box (0.2 m) with a box of 10, 100, 1000 kg (0.2 m) set on it 5 mm
  above. Pass: finite, at rest after 2 s (speed < 1 cm/s), upper box still on the lower one (no sliding
  off: horizontal drift < 1 cm), each box's sinking (into the ground, into the other box) < 1 cm.
- impact: a 1 kg sphere of radius 0.1 m hitting the ground at 20 m/s, landing at 3 phases of the step.
  Pass: finite, not tunnelled (the centre never more than one radius below the surface, and the sphere back
  on top at rest after 2 s: centre within 1 cm of r), rebound speed <= impact speed (no energy gained; the sphere
  starts 3 steps above the ground, so gravity adds a little). At 20 m/s a 10 ms step is two radii: without
  continuous collision detection the centre can pass below the surface for a step.
- chain: the 30-link chain (assets/urdf/chain30.urdf, free base 1 kg, links 0.1 kg) falling 0.2 m onto the
  ground, 2 s. Pass: finite, total energy never above its start by more than 1 %, at rest in the end
  (max link speed < 5 cm/s).
- mpm: an elastic MPM cube (0.12 m, 1,728 particles, E = 3e5 Pa, nu = 0.2) resting on the floor, its top thrown
  down at 27 m/s (v_z linear in height): squeezed to ~30 % of its height, then left alone for 1 s (--quick: 0.5 s),
  dt = 2e-3 s with 10 substeps. Pass: finite, every particle in the domain, the grid's mass equal to the particles'
  (relative 1e-12: mass is conserved exactly up to round-off), the mean volume (mean det F) over the last 0.1 s within
  3 % of the rest volume. Largest dt: bisected with 10 substeps between 2e-3 and 0.03 s with genesis_lite's
  build-time CFL check bypassed in that child, beside the CFL estimate (0.9 dx / c per substep) and whether the
  build refuses a dt 5 % above it. MuJoCo has no MPM.
Largest dt survived: bisection (in log dt, 6 steps between 1e-3 and 0.1 s; energy rows between 1e-3 and 0.2 s over
20 s of simulated time, sampled every 10 steps) of the scene's pass criterion over the same simulated time,
substeps 1 (the MPM row: its own bracket, above). A bracket end that already fails (or passes) is reported as such.
--quick bisects the stiff-contact and MPM rows only, with 2 steps. Each row runs in its own child process.
Gradient norm: the double pendulum with requires_grad, semi-implicit Euler, dt = 0.01 s, from the tumbling
(chaotic) state q0 = (1.8, 2.4) rad at rest; loss = sum of the joint angles at step T; norm of d loss / d q0 for
T = 50 ... 1,600 steps; beside it the same derivative by
central differences in float64 and by MuJoCo (the product of its one-step Jacobians, mjd_transitionFD).
Whether genesis_lite warns (Python warnings or its logger at WARNING) when the norm explodes is recorded.
"""
from __future__ import annotations

import argparse
import functools
import json
import logging
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(HERE.parent))  # genesis_lite without an install
from common import print_table, progress, run_python  # noqa: E402
import scenes as S  # noqa: E402
import stress_faults as F  # noqa: E402  (the fault rows of issue #21)

ENERGY_TOL = 0.05
REST_SPEED = 0.01  # m/s
CHAIN_REST_SPEED = 0.05  # m/s
BISECT = (1e-3, 0.1, 6)  # s, s, iterations (the bracket is known to a factor 100^(1/64) = 1.07)
QUICK_BISECT_ROWS = ("stiff", "mpm")  # --quick bisects these rows only, with 2 steps
GRAD_HORIZONS = (50, 100, 200, 400, 800, 1600)
GRAD_HORIZONS_QUICK = (50, 200, 800)
# a high-energy start: the pendulum tumbles chaotically (at (0.9, -0.6) rad it swings regularly and the
# gradient stays of order 1 for 16 s; from here it grows by ~1e7 over 16 s, MuJoCo's Jacobians agree)
GRAD_Q0 = np.array([1.8, 2.4])  # rad
GRAD_V0 = np.zeros(2)  # rad/s
GRAD_EXPLODED = 1e4  # a gradient norm above this, with inputs and outputs of order 1, has exploded
STIFF_K, STIFF_C = 1e8, 4e4
ENERGY_EVERY = 100  # steps between energy samples
ENERGY_BISECT_T = 20.0  # s of simulated time per bisection step of the energy rows


# --- the scenes, genesis_lite side (child process) ------------------------------------------------------------


def _gl_energy(gs, integrator, dt, steps, every=ENERGY_EVERY):
    """Relative energy drift of the pendulum of bench_integrators.py (its scene builder, tests/test_integrators.py),
    sampled every `every` steps: bench_integrators.energy_run reads the energy after every step, and a read costs
    far more than a step (~100x), which would make 100,000 steps take most of an hour."""
    sys.path.insert(0, str(HERE.parent / "tests"))
    import test_integrators as ti_

    scene, pend = ti_.build(integrator, dt)
    pend.set_dofs_position(S.PENDULUM_Q0)
    pend.set_dofs_velocity(S.PENDULUM_V0)
    e0 = float(pend.get_total_energy())
    worst, e = 0.0, e0
    for i in range(steps):
        scene.step()
        if (i + 1) % every == 0 or i == steps - 1:
            e = float(pend.get_total_energy())
            worst = max(worst, abs(e - e0) / abs(e0)) if math.isfinite(e) else math.inf
    row = {"max_drift": worst, "final_drift": (e - e0) / abs(e0), "steps": steps}
    finite = math.isfinite(row["max_drift"])
    return {"max_drift": row["max_drift"], "final_drift": row["final_drift"], "steps": row["steps"],
            "pass": bool(finite and row["max_drift"] <= ENERGY_TOL),
            "metrics": {"finite": finite, "max_drift": row["max_drift"]},
            "figure": f"max {row['max_drift']:.2e}, final {row['final_drift']:+.2e} ({row['steps']:,} steps)"}


def _gl_scene(gs, dt, substeps=1, **rigid):
    return gs.Scene(sim_options=gs.options.SimOptions(dt=dt, substeps=substeps),
                    rigid_options=gs.options.RigidOptions(**{"integrator": gs.integrator.implicitfast, **rigid}))


def _run_steps(scene, n, every, probe):
    """Step n times, probe() every `every` steps; a NaN stop (SimulationNaNError) ends the run early."""
    for i in range(n):
        scene.step()
        if (i + 1) % every == 0 or i == n - 1:
            probe(i + 1)


def _gl_stiff(gs, dt, t_end=2.0):
    import torch

    scene = _gl_scene(gs, dt, contact_stiffness=STIFF_K, contact_damping=STIFF_C)
    scene.add_entity(gs.morphs.Plane())
    box = scene.add_entity(gs.morphs.URDF(file=str(_box_urdf()), fixed=False, pos=(0, 0, 0.2), default_armature=None))
    scene.build()
    st = {"zmin": 1e9, "zmax_after": -1e9, "landed": False}

    def probe(i):
        z = float(box.get_pos()[2])
        st["zmin"] = min(st["zmin"], z)
        if z < 0.1 + 1e-3:
            st["landed"] = True
        elif st["landed"]:
            st["zmax_after"] = max(st["zmax_after"], z)

    _run_steps(scene, int(round(t_end / dt)), 1, probe)
    z, v = float(box.get_pos()[2]), float(torch.linalg.norm(box.get_vel()))
    return _stiff_verdict(z, v, st["zmin"], st["zmax_after"])


@functools.lru_cache(maxsize=None)
def _box_urdf():
    return S.write_box_urdf()


def _stiff_verdict(z, v, zmin, zmax_after):
    finite = all(math.isfinite(x) for x in (z, v, zmin))
    pen = (0.1 - z) * 1e3
    ok = finite and v < REST_SPEED and pen < 1.0 and zmax_after < 0.2
    return {"pass": bool(ok), "metrics": {"finite": finite, "speed": v, "pen_mm": pen, "zmax_after": zmax_after},
            "figure": f"at rest: penetration {pen:.3f} mm, speed {v:.1e} m/s; deepest {(0.1 - zmin) * 1e3:.2f} mm"
            + (f"; bounced to {zmax_after:.3f} m" if zmax_after > 0.1 + 1e-3 else "") if finite else "diverged (NaN)"}


def _gl_ratio(gs, dt, ratio, t_end=2.0):
    scene = _gl_scene(gs, dt)
    scene.add_entity(gs.morphs.Plane())
    a = 0.2
    light = scene.add_entity(gs.morphs.Box(size=(a, a, a), pos=(0, 0, a / 2)), material=gs.materials.Rigid(rho=1.0 / a**3))
    heavy = scene.add_entity(gs.morphs.Box(size=(a, a, a), pos=(0, 0, 1.5 * a + 0.005)),
                             material=gs.materials.Rigid(rho=ratio / a**3))
    scene.build()
    _run_steps(scene, int(round(t_end / dt)), 10, lambda i: None)
    pl, ph = light.get_pos().numpy(), heavy.get_pos().numpy()
    v = max(float(np.linalg.norm(light.get_vel().numpy())), float(np.linalg.norm(heavy.get_vel().numpy())))
    return _ratio_verdict(pl, ph, v, a)


def _ratio_verdict(pl, ph, v, a):
    if not (np.all(np.isfinite(pl)) and np.all(np.isfinite(ph)) and math.isfinite(v)):
        return {"pass": False, "metrics": {"finite": False}, "figure": "diverged (NaN)"}
    sink_l = a / 2 - pl[2]
    sink_h = (pl[2] + a) - ph[2]
    drift = float(np.linalg.norm(ph[:2] - pl[:2]))
    ok = v < REST_SPEED and drift < 0.01 and sink_l < 0.01 and sink_h < 0.01
    return {"pass": bool(ok), "metrics": {"finite": True, "speed": v, "drift": drift, "sink_l": float(sink_l),
                                          "sink_h": float(sink_h)},
            "figure": f"light box into ground {sink_l * 1e3:.2f} mm, heavy into light {sink_h * 1e3:.2f} mm, "
            f"drift {drift * 1e3:.1f} mm, speed {v:.1e} m/s"}


def _gl_impact(gs, dt, t_end=2.0):
    import torch

    zmins, ups, zends = [], [], []
    for phase in PHASES:  # where in a step the sphere reaches the ground
        scene = _gl_scene(gs, dt)
        scene.add_entity(gs.morphs.Plane())
        ball = scene.add_entity(gs.morphs.Sphere(radius=0.1, pos=(0, 0, _impact_z0(dt, phase))),
                                material=gs.materials.Rigid(rho=1.0 / (4 / 3 * math.pi * 0.1**3)))
        scene.build()
        ball.set_dofs_velocity(torch.tensor([0, 0, -20.0, 0, 0, 0], dtype=gs.tc_float))
        st = {"zmin": 1e9, "up": 0.0}

        def probe(i):
            st["zmin"] = min(st["zmin"], float(ball.get_pos()[2]))
            st["up"] = max(st["up"], float(ball.get_vel()[2]))

        _run_steps(scene, int(round(t_end / dt)), 1, probe)
        zmins.append(st["zmin"])
        ups.append(st["up"])
        zends.append(float(ball.get_pos()[2]))
    return _impact_verdict(zmins, ups, zends, dt)


PHASES = (0.0, 1 / 3, 2 / 3)


def _impact_z0(dt, phase):
    """Start height (m) of the sphere's centre: it reaches the ground (z = r = 0.1 m) after 3 + phase steps."""
    return 0.1 + 20.0 * dt * (3 + phase)


def _impact_verdict(zmins, ups, zends, dt):
    if not (np.all(np.isfinite(zmins)) and np.all(np.isfinite(ups)) and np.all(np.isfinite(zends))):
        return {"pass": False, "metrics": {"finite": False}, "figure": "diverged (NaN)"}
    # the speed at the ground, gravity included (the sphere starts 20 m/s x 3 steps above it)
    v_hit = max(math.sqrt(20.0**2 + 2 * S.G * (_impact_z0(dt, p) - 0.1)) for p in PHASES)
    # without continuous collision detection a step of 20 m/s x dt (0.2 m at 10 ms, two radii) can carry the
    # centre below the surface; what matters is that the ground pushes it back out instead of letting it through
    ok = min(zmins) > -0.1 and max(abs(z - 0.1) for z in zends) < 0.01 and max(ups) <= v_hit
    return {"pass": bool(ok), "metrics": {"finite": True, "zmin": min(zmins), "rebound": max(ups), "v_hit": v_hit,
                                          "zend_err": max(abs(z - 0.1) for z in zends)},
            "figure": f"deepest centre {min(zmins) * 1e3:.1f} mm (r = 100 mm), at rest at {min(zends) * 1e3:.1f}.."
            f"{max(zends) * 1e3:.1f} mm, max rebound {max(ups):.2f} m/s (impact {v_hit:.1f} m/s)"}


def _gl_chain(gs, dt, t_end=2.0):
    import torch

    scene = _gl_scene(gs, dt)
    scene.add_entity(gs.morphs.Plane())
    chain = scene.add_entity(gs.morphs.URDF(file=str(S.CHAIN30_URDF), fixed=False, pos=(0, 0, 3.2),
                                                default_armature=None))
    scene.build()
    e0 = float(chain.get_total_energy())
    st = {"emax": e0}

    def probe(i):
        st["emax"] = max(st["emax"], float(chain.get_total_energy()))

    _run_steps(scene, int(round(t_end / dt)), 1, probe)
    vmax = float(torch.linalg.norm(chain.get_links_vel(), dim=-1).max())
    return _chain_verdict(e0, st["emax"], float(chain.get_total_energy()), vmax)


def _chain_verdict(e0, emax, e1, vmax):
    if not all(math.isfinite(x) for x in (e0, emax, e1, vmax)):
        return {"pass": False, "metrics": {"finite": False}, "figure": "diverged (NaN)"}
    gain = (emax - e0) / abs(e0)
    ok = gain <= 0.01 and vmax < CHAIN_REST_SPEED
    return {"pass": bool(ok), "metrics": {"finite": True, "gain": gain, "vmax": vmax},
            "figure": f"energy {e0:.2f} J -> max {emax:.2f} J ({gain:+.1%}) -> {e1:.2f} J, "
            f"max link speed at the end {vmax:.1e} m/s"}


# elastic MPM block under large deformation ------------------------------------------------------------------------
# A 0.12 m elastic cube (1,728 particles on the 0.01 m lattice, 64 cells per metre on [0, 0.6]^3; E = 3e5 Pa,
# nu = 0.2, rho = 1000 kg/m^3, corotated: the bench's material) resting on the floor, its top thrown down at
# MPM_V (v_z growing linearly from 0 at the bottom): it is squeezed to about 30 % of its height within ~10 ms, then
# left alone under gravity for the rest of the run (it springs back, leaves the floor, lands and rings down).
MPM_V = 27.0  # m/s at the top: squeezes it to 31 % of its height (measured: 24 m/s gives 42 %, 30 m/s 19 %, 36 m/s
# flattens it for good)
MPM_EDGE = 0.12  # m
MPM_DX = 1.0 / 64
MPM_T = 1.0  # s (--quick: 0.5 s)
MPM_VOLUME_TOL = 0.03  # the mean volume over the last 0.1 s within 3 % of the rest volume (gravity: ~0.1 %)
MPM_MASS_TOL = 1e-12  # relative: the grid's mass equals the particles' (float64 round-off)
MPM_BISECT = (2e-3, 0.03, 6)  # s: dt with 10 substeps (substeps of 0.2 .. 3 ms; the CFL check allows 0.77 ms)
MPM_SUBSTEPS = 10


def _mpm_cfl_dt(gs, substeps=MPM_SUBSTEPS):
    """The largest dt genesis_lite's build accepts for this block (bridges.mpm.check_time_step: a substep of at most
    0.9 dx / c, c the material's pressure wave speed)."""
    c = gs.materials.MPM.Elastic(E=3e5, nu=0.2, rho=1000.0).wave_speed()
    return 0.9 * MPM_DX / c * substeps, c


def _gl_mpm(gs, dt, t_end=MPM_T, bypass_cfl=False):
    import torch

    import genesis_lite.bridges.mpm as ms

    check = ms.check_time_step
    if bypass_cfl:  # to find the true stability limit beyond the build-time check (this child process only)
        ms.check_time_step = lambda *a, **k: None
    try:
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, substeps=MPM_SUBSTEPS),
                         mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.6, 0.6, 0.6),
                                                           grid_density=1.0 / MPM_DX))
        z_floor = 3 * MPM_DX
        block = scene.add_entity(gs.morphs.Box(pos=(0.3, 0.3, z_floor + 0.002 + MPM_EDGE / 2), size=(MPM_EDGE,) * 3),
                                 material=gs.materials.MPM.Elastic(E=3e5, nu=0.2, rho=1000.0))
        scene.build()
    finally:
        ms.check_time_step = check
    x = block.get_particles_pos()
    zb, h0 = float(x[:, 2].min()), float(x[:, 2].max() - x[:, 2].min())
    v = torch.zeros_like(x)
    v[:, 2] = -MPM_V * (x[:, 2] - zb) / h0
    block.set_particles_vel(v)
    n = int(round(t_end / dt))
    window = max(1, int(round(0.1 / dt)))
    st = {"hmin": math.inf, "vols": [], "jmin": math.inf}

    def probe(i):
        x = block.get_particles_pos()
        st["hmin"] = min(st["hmin"], float(x[:, 2].max() - x[:, 2].min()) / h0)
        J = torch.linalg.det(block.get_particles_F())
        st["jmin"] = min(st["jmin"], float(J.min()))
        if i > n - window:
            st["vols"].append(float(J.mean()))  # equal particle volumes: mean J = volume / rest volume

    _run_steps(scene, n, 1, probe)
    x = block.get_particles_pos().numpy()
    s = scene.mpm_solver
    (l0, l1, l2), (n0, n1, n2) = s.active_lo[None], s.active_n[None]
    grid_mass = float(s.grid_m.to_numpy()[0, l0:l0 + n0, l1:l1 + n1, l2:l2 + n2].sum())
    total = float(block._masses().sum())
    inside = bool(np.all(x >= 0.0) and np.all(x <= 0.6))
    return _mpm_verdict(np.all(np.isfinite(x)), st["hmin"], st["jmin"], float(np.mean(st["vols"])),
                        float(np.max(np.abs(np.asarray(st["vols"]) - 1.0))), grid_mass, total, inside)


def _mpm_verdict(finite, hmin, jmin, vol_mean, vol_dev, grid_mass, total, inside):
    finite = bool(finite and all(math.isfinite(v) for v in (hmin, jmin, vol_mean, vol_dev, grid_mass)))
    if not finite:
        return {"pass": False, "metrics": {"finite": False}, "figure": "diverged (NaN)"}
    mass_err = abs(grid_mass - total) / total
    ok = inside and mass_err <= MPM_MASS_TOL and abs(vol_mean - 1.0) <= MPM_VOLUME_TOL
    return {"pass": bool(ok), "metrics": {"finite": True, "hmin": hmin, "jmin": jmin, "vol_mean": vol_mean,
                                          "vol_dev": vol_dev, "mass_err": mass_err, "inside": inside},
            "figure": f"squeezed to {hmin:.0%} of its height (min det F {jmin:.2f}); volume over the last 0.1 s "
                      f"{vol_mean:.4f} x rest (swing {vol_dev:.1e}); grid mass - particle mass {mass_err:.1e} "
                      "(relative)" + ("" if inside else "; particles left the domain")}


def _safe(fn, *a, **kw):
    """A run that raises (genesis_lite raises on NaN) fails its criterion with the reason as its figure."""
    try:
        return fn(*a, **kw)
    except Exception as e:
        msg = str(e).splitlines()[0][:140] if str(e) else ""
        return {"pass": False, "metrics": {"finite": False, "raised": type(e).__name__}, "figure": f"{type(e).__name__}: {msg}"}


def bisect(survives, lo, hi, iters):
    """Largest dt in [lo, hi] for which survives(dt) holds, by bisection in log dt. Returns (dt, note)."""
    if survives(hi):
        return hi, f">= {hi:g} (the largest tried)"
    if not survives(lo):
        return None, f"< {lo:g} (fails at the smallest tried)"
    for _ in range(iters):
        mid = math.sqrt(lo * hi)
        if survives(mid):
            lo = mid
        else:
            hi = mid
    return lo, f"{lo:.3g} (fails at {hi:.3g})"


GL_ROWS = {
    "stiff": lambda gs, dt: _gl_stiff(gs, dt),
    "ratio10": lambda gs, dt: _gl_ratio(gs, dt, 10),
    "ratio100": lambda gs, dt: _gl_ratio(gs, dt, 100),
    "ratio1000": lambda gs, dt: _gl_ratio(gs, dt, 1000),
    "impact": lambda gs, dt: _gl_impact(gs, dt),
    "chain": lambda gs, dt: _gl_chain(gs, dt),
}


def _gl_grad(gs, horizons, dt=0.01):
    import torch

    def build(requires_grad):
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, requires_grad=requires_grad),
                         rigid_options=gs.options.RigidOptions(integrator=gs.integrator.Euler, enable_collision=False,
                                                               enable_joint_limit=False))
        pend = scene.add_entity(gs.morphs.URDF(file=str(S.PENDULUM_URDF), fixed=True, default_armature=None))
        scene.build()
        pend.set_dofs_damping([0.0, 0.0])
        pend.set_dofs_armature([0.0, 0.0])
        return scene, pend

    sg, pg = build(True)
    sf, pf = build(False)

    def loss_of(scene, pend, q0, T):
        scene.reset()
        pend.set_dofs_position(q0)
        pend.set_dofs_velocity(torch.as_tensor(GRAD_V0, dtype=torch.float64))
        for _ in range(T):
            scene.step()
        return pend.get_dofs_position().sum()

    rows = []
    for T in horizons:
        q0 = torch.tensor(GRAD_Q0, dtype=torch.float64, requires_grad=True)
        records = []
        handler = _Collect()
        log = logging.getLogger("genesis_lite")
        log.addHandler(handler)
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                loss = loss_of(sg, pg, q0, T)
                loss.backward()
            records = [str(w.message)[:120] for w in caught] + handler.messages
        finally:
            log.removeHandler(handler)
        g = q0.grad.numpy().copy()
        # central differences in float64, the step shrunk with the sensitivity so that the perturbation stays linear
        h = 1e-6 / max(1.0, float(np.linalg.norm(g)))
        fd = np.zeros(2)
        with torch.no_grad():
            for k in range(2):
                e = np.zeros(2)
                e[k] = h
                lp = float(loss_of(sf, pf, torch.as_tensor(GRAD_Q0 + e), T))
                lm = float(loss_of(sf, pf, torch.as_tensor(GRAD_Q0 - e), T))
                fd[k] = (lp - lm) / (2 * h)
        rows.append({"T": T, "grad": g.tolist(), "norm": float(np.linalg.norm(g)), "fd": fd.tolist(),
                     "fd_norm": float(np.linalg.norm(fd)), "fd_h": h,
                     "fd_rel": float(np.linalg.norm(g - fd) / max(np.linalg.norm(fd), 1e-300)),
                     "warnings": records})
    return rows


class _Collect(logging.Handler):
    def __init__(self):
        super().__init__(level=logging.WARNING)
        self.messages = []

    def emit(self, record):
        self.messages.append(record.getMessage()[:120])


def worker_gl(key, quick, bisect_on, iters) -> dict:
    """One row in this (child) process: its figure at dt = 0.01 s and, with bisect_on, its largest dt."""
    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")
    t0 = time.perf_counter()
    if key == "energy":
        steps = 10_000 if quick else 100_000
        res = {integ: _safe(_gl_energy, gs, integ, 0.01, steps) for integ in ("Euler", "implicitfast", "RK4")}
        if bisect_on:
            for integ in ("Euler", "RK4"):  # implicitfast is Euler here (no damping, no gains)
                dtmax, note = bisect(lambda dt: _safe(_gl_energy, gs, integ, dt, int(round(ENERGY_BISECT_T / dt)),
                                                      10)["pass"], 1e-3, 0.2, iters)
                res[integ]["dt_max"], res[integ]["dt_note"] = dtmax, note + f", over {ENERGY_BISECT_T:g} s"
    elif key == "grad":
        res = {"rows": _gl_grad(gs, GRAD_HORIZONS_QUICK if quick else GRAD_HORIZONS)}
    elif key == "mpm":
        t_end = MPM_T / 2 if quick else MPM_T
        res = _safe(_gl_mpm, gs, 2e-3, t_end)
        cfl_dt, c = _mpm_cfl_dt(gs)
        res["cfl_dt"], res["wave_speed"] = cfl_dt, c
        from genesis_lite.errors import GenesisException

        try:  # does the build refuse a step just above the CFL estimate? (one step is run if it does not)
            _gl_mpm(gs, cfl_dt * 1.05, t_end=cfl_dt * 1.05)
            res["refused"] = None
        except GenesisException as e:
            res["refused"] = f"{type(e).__name__}: {str(e).splitlines()[0][:100]}" if "too long" in str(e) else None
            res["refused_other"] = None if res["refused"] else str(e)[:200]
        if bisect_on:
            dtmax, note = bisect(lambda dt: _safe(_gl_mpm, gs, dt, t_end, bypass_cfl=True)["pass"], MPM_BISECT[0],
                                 MPM_BISECT[1], iters)
            res["dt_max"] = dtmax
            res["dt_note"] = (f"{note} with {MPM_SUBSTEPS} substeps, build-time CFL check bypassed; CFL estimate "
                              f"{cfl_dt:.3g} (c = {c:.1f} m/s), "
                              + ("which the build refuses above" if res["refused"] else "NOT enforced at build"))
    else:
        fn = GL_ROWS[key]
        res = _safe(fn, gs, F.DT.get(key, 0.01))
        if bisect_on and key not in F.GL_ROWS:
            res["dt_max"], res["dt_note"] = bisect(lambda dt: _safe(fn, gs, dt)["pass"], BISECT[0], BISECT[1], iters)
    res["seconds"] = time.perf_counter() - t0
    return res


# --- MuJoCo side (in this process) -------------------------------------------------------------------------------


def _mj_energy(integrator, dt, steps, every=ENERGY_EVERY):
    """MuJoCo's side of the energy rows, sampled like genesis_lite's (mj_forward recomputes the energy of the
    current state: after mj_step, d.energy is that of an intermediate evaluation)."""
    import mujoco

    m = S.mujoco_from_urdf(S.PENDULUM_URDF, limits=False, contacts=False)
    S.set_mujoco_integrator(m, integrator, dt)
    m.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
    d = mujoco.MjData(m)
    d.qpos[:] = S.PENDULUM_Q0
    d.qvel[:] = S.PENDULUM_V0
    mujoco.mj_forward(m, d)
    e0 = float(d.energy.sum())
    worst = 0.0
    for i in range(steps):
        mujoco.mj_step(m, d)
        if (i + 1) % every == 0 or i == steps - 1:
            mujoco.mj_forward(m, d)
            worst = max(worst, abs(float(d.energy.sum()) - e0) / abs(e0))
    final = (float(d.energy.sum()) - e0) / abs(e0)
    finite = math.isfinite(worst) and np.all(np.isfinite(d.qpos))
    return {"pass": bool(finite and worst <= ENERGY_TOL), "max_drift": worst,
            "metrics": {"finite": bool(finite), "max_drift": worst},
            "figure": f"max {worst:.2e}, final {final:+.2e} ({steps:,} steps)"}


def _mj_bad(d):
    import mujoco

    w = mujoco.mjtWarning
    return sum(int(d.warning[int(k)].number) for k in (w.mjWARN_BADQACC, w.mjWARN_BADQPOS, w.mjWARN_BADQVEL))


def _mj_run(m, d, n, probe):
    import mujoco

    for i in range(n):
        mujoco.mj_step(m, d)
        probe(i + 1)
        if _mj_bad(d):
            raise FloatingPointError("MuJoCo: NaN / huge acceleration (it resets such states)")


def _mj_stiff(dt, t_end=2.0):
    import mujoco

    spec = mujoco.MjSpec()
    b = S.mujoco_free_box(spec, "box", (0, 0, 0.2), 0.2, 1.0)
    b.geoms[0].solref = [-STIFF_K, -STIFF_C]
    m = S.mujoco_on_floor(spec, dt)
    d = mujoco.MjData(m)
    st = {"zmin": 1e9, "zmax_after": -1e9, "landed": False}

    def probe(i):
        z = float(d.qpos[2])
        st["zmin"] = min(st["zmin"], z)
        if z < 0.1 + 1e-3:
            st["landed"] = True
        elif st["landed"]:
            st["zmax_after"] = max(st["zmax_after"], z)

    _mj_run(m, d, int(round(t_end / dt)), probe)
    return _stiff_verdict(float(d.qpos[2]), float(np.linalg.norm(d.qvel[:3])), st["zmin"], st["zmax_after"])


def _mj_ratio(dt, ratio, t_end=2.0):
    import mujoco

    a = 0.2
    spec = mujoco.MjSpec()
    S.mujoco_free_box(spec, "light", (0, 0, a / 2), a, 1.0)
    S.mujoco_free_box(spec, "heavy", (0, 0, 1.5 * a + 0.005), a, float(ratio))
    m = S.mujoco_on_floor(spec, dt)
    d = mujoco.MjData(m)
    _mj_run(m, d, int(round(t_end / dt)), lambda i: None)
    v = max(float(np.linalg.norm(d.qvel[0:3])), float(np.linalg.norm(d.qvel[6:9])))
    return _ratio_verdict(d.qpos[0:3].copy(), d.qpos[7:10].copy(), v, a)


def _mj_impact(dt, t_end=2.0):
    import mujoco

    zmins, ups, zends = [], [], []
    for phase in PHASES:
        spec = mujoco.MjSpec()
        b = spec.worldbody.add_body(name="ball", pos=[0, 0, _impact_z0(dt, phase)])
        b.add_freejoint()
        b.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.1, 0, 0], mass=1.0)
        m = S.mujoco_on_floor(spec, dt)
        d = mujoco.MjData(m)
        d.qvel[2] = -20.0
        st = {"zmin": 1e9, "up": 0.0}

        def probe(i):
            st["zmin"] = min(st["zmin"], float(d.qpos[2]))
            st["up"] = max(st["up"], float(d.qvel[2]))

        _mj_run(m, d, int(round(t_end / dt)), probe)
        zmins.append(st["zmin"])
        ups.append(st["up"])
        zends.append(float(d.qpos[2]))
    return _impact_verdict(zmins, ups, zends, dt)


def _mj_chain(dt, t_end=2.0):
    import mujoco

    m = S.mujoco_from_urdf(S.CHAIN30_URDF, free=True, base_pos=(0, 0, 3.2), floor_mu=1.0)
    S.set_mujoco_integrator(m, "implicitfast", dt)
    m.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    e0 = float(d.energy.sum())
    st = {"emax": e0}

    def probe(i):
        st["emax"] = max(st["emax"], float(d.energy.sum()))  # energy of the state before the step: fine for a max

    _mj_run(m, d, int(round(t_end / dt)), probe)
    mujoco.mj_forward(m, d)
    vel = np.zeros(6)
    vmax = 0.0
    for b in range(1, m.nbody):
        mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, b, vel, 0)
        vmax = max(vmax, float(np.linalg.norm(vel[3:])))
    return _chain_verdict(e0, st["emax"], float(d.energy.sum()), vmax)


MJ_ROWS = {
    "stiff": lambda dt: _mj_stiff(dt),
    "ratio10": lambda dt: _mj_ratio(dt, 10),
    "ratio100": lambda dt: _mj_ratio(dt, 100),
    "ratio1000": lambda dt: _mj_ratio(dt, 1000),
    "impact": lambda dt: _mj_impact(dt),
    "chain": lambda dt: _mj_chain(dt),
}


def _mj_grad(horizons, dt=0.01):
    """d sum(q_T) / d q0 from MuJoCo: the product of its one-step transition Jacobians (finite differences of one
    step in float64, mjd_transitionFD, centred), Euler at dt, from the same state."""
    import mujoco

    m = S.mujoco_from_urdf(S.PENDULUM_URDF, limits=False, contacts=False)
    S.set_mujoco_integrator(m, "Euler", dt)
    d = mujoco.MjData(m)
    d.qpos[:] = GRAD_Q0
    d.qvel[:] = GRAD_V0
    nx = 2 * m.nv
    A = np.zeros((nx, nx))
    P = np.eye(nx)
    out, t = [], 0
    for T in horizons:
        while t < T:
            mujoco.mjd_transitionFD(m, d, 1e-8, 1, A, None, None, None)
            P = A @ P
            mujoco.mj_step(m, d)
            t += 1
        g = np.ones(m.nv) @ P[: m.nv, : m.nv]
        out.append({"T": T, "grad": g.tolist(), "norm": float(np.linalg.norm(g))})
    return out


# --- the study ----------------------------------------------------------------------------------------------------

ROW_TITLES = {
    "energy": "energy drift, frictionless double pendulum, dt = 0.01 s",
    "stiff": f"stiff contact: 1 kg box dropped 0.1 m, contact stiffness {STIFF_K:.0e} N/m",
    "ratio10": "mass ratio 1:10, box stack",
    "ratio100": "mass ratio 1:100, box stack",
    "ratio1000": "mass ratio 1:1,000, box stack",
    "impact": "20 m/s impact of a sphere on the ground",
    "chain": "30-link chain falling onto the ground",
    "mpm": f"elastic MPM block squeezed to ~30 % of its height (top thrown down at {MPM_V:g} m/s), released; "
           f"dt = 2e-3 s, {MPM_SUBSTEPS} substeps",
}
CRITERIA = {
    "energy": f"max abs(E - E0)/abs(E0) <= {ENERGY_TOL:.0%}",
    "stiff": "at rest (< 1 cm/s) within 2 s, penetration < 1 mm, no bounce above the drop",
    "ratio10": "at rest (< 1 cm/s) within 2 s, drift < 1 cm, sinking < 1 cm",
    "impact": "never wholly below ground (centre > -r), back on top at rest (centre within 1 cm of r) after 2 s, "
              "rebound <= impact speed",
    "chain": "energy never > E0 + 1 %, at rest (< 5 cm/s) after 2 s",
}
CRITERIA["ratio100"] = CRITERIA["ratio1000"] = CRITERIA["ratio10"]
CRITERIA["mpm"] = (f"finite, no particle out of the domain, grid mass = particle mass (rel. <= {MPM_MASS_TOL:.0e}), "
                   f"mean volume over the last 0.1 s within {MPM_VOLUME_TOL:.0%} of rest")
# the fault rows (benchmarks/stress_faults.py): their figures at their own dt, never bisected
GL_ROWS.update(F.GL_ROWS)
MJ_ROWS.update(F.MJ_ROWS)
ROW_TITLES.update(F.ROW_TITLES)
CRITERIA.update(F.CRITERIA)
ALL_ROWS = ("energy", "stiff", "ratio10", "ratio100", "ratio1000", "impact", "chain", "mpm") + tuple(F.GL_ROWS) + ("grad",)


def run(rows, quick, bisect_on, log=print) -> dict:
    """genesis_lite (a child process per row) and MuJoCo (here); returns the table rows and the gradient rows.
    --quick bisects QUICK_BISECT_ROWS only, with 2 steps; the full run every row with BISECT's steps."""
    rows = [r for r in rows if r in ALL_ROWS]
    res, errs = {}, {}
    for key in progress(rows, desc="stress"):
        on = bisect_on and (not quick or key in QUICK_BISECT_ROWS)
        r, err = run_python([str(Path(__file__).resolve()), "--worker", json.dumps(
            {"key": key, "quick": quick, "bisect_on": on,
             "iters": 2 if quick else (MPM_BISECT if key == "mpm" else BISECT)[2]})], timeout=7200)
        if r is None:
            log(f"  stress {key}: genesis_lite child FAILED: {err}")
            errs[key] = err
        else:
            res[key] = r
            res[key + "_s"] = r["seconds"]
    table = []
    energy_steps = 10_000 if quick else 100_000
    for key in rows:
        if key == "grad":
            continue
        if key == "mpm":
            g = res.get("mpm", {"pass": False, "figure": errs.get("mpm", "not run")})
            dt_note = g.get("dt_note")
            if dt_note is None and g.get("cfl_dt"):
                dt_note = (f"not bisected; CFL estimate {g['cfl_dt']:.3g} s with {MPM_SUBSTEPS} substeps, "
                           + ("refused above it at build" if g.get("refused") else "NOT enforced at build"))
            table.append({"key": "mpm", "row": ROW_TITLES["mpm"], "criterion": CRITERIA["mpm"], "gl_pass": _pf(g),
                          "gl": g["figure"], "gl_dt": dt_note, "mj_pass": "-", "mj": "MuJoCo has no MPM",
                          "gl_metrics": g.get("metrics"), "gl_s": res.get("mpm_s"), "cfl_dt": g.get("cfl_dt"),
                          "dt_max": g.get("dt_max"), "refused": g.get("refused")})
            continue
        if key == "energy":
            for integ in ("Euler", "implicitfast", "RK4"):
                g = res.get("energy", {}).get(integ, {"pass": False, "figure": errs.get("energy", "not run")})
                mj = _safe(_mj_energy, integ, 0.01, energy_steps)
                table.append({"key": "energy", "row": f"{ROW_TITLES['energy']}, {integ}", "criterion": CRITERIA["energy"],
                              "gl_pass": _pf(g), "gl": g["figure"], "mj_pass": _pf(mj), "mj": mj["figure"],
                              "gl_metrics": g.get("metrics"), "mj_metrics": mj.get("metrics"),
                              "gl_s": res.get("energy_s") if integ == "Euler" else None,
                              "gl_dt": g.get("dt_note"),
                              "mj_dt": (_mj_energy_bisect(integ, 2 if quick else BISECT[2])
                                        if bisect_on and not quick and integ != "implicitfast" else None)})
            continue
        g = res.get(key, {"pass": False, "figure": errs.get(key, "not run")})
        fn = MJ_ROWS.get(key)
        mj = _safe(fn, 0.01) if fn else {"pass": None, "figure": "MuJoCo has no MPM"}
        on = bisect_on and (not quick or key in QUICK_BISECT_ROWS) and key not in F.GL_ROWS
        mj_dt = bisect(lambda dt: _safe(fn, dt)["pass"], BISECT[0], BISECT[1], 2 if quick else BISECT[2])[1] if on else None
        table.append({"key": key, "row": ROW_TITLES[key], "criterion": CRITERIA[key], "gl_pass": _pf(g),
                      "gl": g["figure"], "mj_pass": _pf(mj), "mj": mj["figure"], "gl_dt": g.get("dt_note"),
                      "mj_dt": mj_dt, "gl_metrics": g.get("metrics"), "mj_metrics": mj.get("metrics"),
                      "gl_s": res.get(key + "_s")})
    grad = None
    if "grad" in rows:
        gl = res.get("grad", {}).get("rows", [])
        mj = _safe(lambda: {"rows": _mj_grad([r["T"] for r in gl] or list(GRAD_HORIZONS))})
        mj_by_T = {r["T"]: r for r in mj.get("rows", [])}
        grad = []
        for r in gl:
            m = mj_by_T.get(r["T"], {})
            exploded = r["norm"] > GRAD_EXPLODED
            grad.append({"T": r["T"], "t": r["T"] * 0.01, "norm": r["norm"], "fd_norm": r["fd_norm"],
                         "n_warnings": len(r["warnings"]),
                         "fd_rel": r["fd_rel"], "mj_norm": m.get("norm"),
                         "mj_rel": (float(np.linalg.norm(np.subtract(r["grad"], m["grad"])) / m["norm"])
                                    if m.get("norm") else None),
                         "exploded": "yes" if exploded else "no",
                         "warned": "yes: " + "; ".join(r["warnings"][:2]) if r["warnings"] else "no",
                         "verdict": ("PASS" if r["warnings"] else "FAIL") if exploded else
                                    ("PASS" if not r["warnings"] else "FAIL (warned without explosion)")})
        if not gl:
            grad.append({"T": "-", "warned": errs.get("grad", "genesis_lite child failed")})
    return {"table": table, "grad": grad, "seconds": {k: v for k, v in res.items() if k.endswith("_s")}}


def _mj_energy_bisect(integ, iters):
    dtmax, note = bisect(lambda dt: _safe(_mj_energy, integ, dt, int(round(ENERGY_BISECT_T / dt)), 10)["pass"], 1e-3,
                         0.2, iters)
    return note + f", over {ENERGY_BISECT_T:g} s"


def _pf(r):
    return "-" if r.get("pass") is None else "PASS" if r.get("pass") else "FAIL"


def tables(out) -> list[str]:
    t = [print_table(out["table"], [
        ("row", "scene", ""), ("criterion", "pass criterion", ""), ("gl_pass", "genesis_lite", ""),
        ("gl", "genesis_lite figure (dt = 0.01 s)", ""), ("gl_dt", "genesis_lite largest dt survived (s)", ""),
        ("mj_pass", "MuJoCo", ""), ("mj", "MuJoCo figure (dt = 0.01 s)", ""),
        ("mj_dt", "MuJoCo largest dt survived (s)", ""), ("gl_s", "genesis_lite wall s", ".0f")])]
    if out.get("grad"):
        t.append(print_table(out["grad"], [
            ("T", "steps", ""), ("t", "horizon s", "g"), ("norm", "genesis_lite norm d loss/d q0", ".3e"),
            ("fd_norm", "central differences (f64)", ".3e"), ("fd_rel", "rel. difference", ".1e"),
            ("mj_norm", "MuJoCo (product of mjd_transitionFD)", ".3e"), ("mj_rel", "rel. difference", ".1e"),
            ("exploded", f"norm > {GRAD_EXPLODED:.0e}", ""), ("warned", "genesis_lite warned", ""),
            ("verdict", "pass (warns iff exploded)", "")]))
    return t


def main():
    if len(sys.argv) > 2 and sys.argv[1] == "--worker":
        print(json.dumps(worker_gl(**json.loads(sys.argv[2]))), flush=True)
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--rows", default=",".join(ALL_ROWS))
    ap.add_argument("--no-bisect", action="store_true")
    a = ap.parse_args()
    out = run(a.rows.split(","), a.quick, not a.no_bisect)
    tables(out)


if __name__ == "__main__":
    main()
