"""The fault rows of bench_stress.py (issue #21): scenes a careless or unlucky user builds, each with a pass
criterion from physics, genesis_lite's figure and MuJoCo's where it can run the same scene.

- spin1e3, spin1e6: a 1 kg, 0.2 m box whose bottom face is 6 cm above the ground, spinning about a horizontal
  axis (x) at 1e3 (1e6) rad/s, 5 steps of dt: its edges sweep down to 1.9 cm above the ground (half its face
  diagonal, 14.1 cm, from a centre at 16 cm) at 141 m/s (1.4e5 m/s), less the 1.2 mm gravity lowers it, and
  never touch it, so its momentum must follow free fall exactly. Before issue #21 a speculative contact whose
  gap never closed threw such a box at 28.8 m/s (125 m/s at 1e6 rad/s).
- fast: the same box dropped at 1e6 m/s from 0.5 m (its centre reaches the ground in 0.5 us, far inside one
  10 ms step). Pass: the box stays above the ground (never more than half its size below the surface, at rest
  on it after 1 s), or the library says the step is too long for it (an exception or a warning naming the
  body: "said").
- heavy: a 400 t, 0.2 m box resting on the ground (the contact stiffness must carry 3.9 MN). Pass: finite,
  sinking < 1 cm after 2 s, at rest (speed < 1 cm/s), or the library says the contact cannot hold it.
- soft4t, soft400t: a 0.15 m rigid box of 4 t (400 t) laid on an elastic MPM block (0.2 m, E = 1e5 Pa,
  nu = 0.3) on the floor of the MPM domain, which is the ground plane of the rigid solver, 2 s. Pass: finite;
  at the end, once the crushed jelly has stopped ringing, no particle inside the box (its exact geometry, less
  1/4 of a grid cell); the box's lowest point never below the ground by more than a grid cell. The figure also
  gives the particles inside at 1 s, while the jelly still rings: the 4 t box then had a few within half a cell
  of its top edges, coming and going (none from 1.5 s on). MuJoCo has no MPM.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

import scenes as S

BOX = 0.2  # m
SPIN_STEPS = 5
SPIN_GAP = 0.06  # m between the box's lowest face and the ground
FAST_V = 1e6  # m/s
FAST_Z0 = 0.5  # m
HEAVY_MASS = 4e5  # kg
SOFT_DX = 1.0 / 64
SOFT_EDGE = 0.2  # m, the MPM block
SOFT_BOX = 0.15  # m, the rigid box on it


def _scene(gs, dt, substeps=1, **kw):
    return gs.Scene(sim_options=gs.options.SimOptions(dt=dt, substeps=substeps), **kw)


def _box(gs, scene, pos, mass, size=BOX):
    return scene.add_entity(gs.morphs.Box(size=(size,) * 3, pos=pos), material=gs.materials.Rigid(rho=mass / size**3))


def _spin_verdict(v, w, v_ref, w_ref, omega):
    finite = bool(np.all(np.isfinite(v)) and np.all(np.isfinite(w)))
    if not finite:
        return {"pass": False, "metrics": {"finite": False}, "figure": "diverged (NaN)"}
    dv = float(np.linalg.norm(np.subtract(v, v_ref)))
    dw = float(np.linalg.norm(np.subtract(w, w_ref))) / omega
    return {"pass": bool(dv < 1e-6 and dw < 1e-6), "metrics": {"finite": True, "dv": dv, "dw_rel": dw},
            "figure": f"velocity off free fall by {dv:.1e} m/s, spin off by {dw:.1e} (relative)"}


def gl_spin(gs, dt, omega):
    import torch

    scene = _scene(gs, dt)
    scene.add_entity(gs.morphs.Plane())
    box = _box(gs, scene, (0, 0, BOX / 2 + SPIN_GAP), 1.0)
    scene.build()
    box.set_dofs_velocity(torch.tensor([0, 0, 0, omega, 0, 0], dtype=gs.tc_float))
    for _ in range(SPIN_STEPS):
        scene.step()
    vel = box.get_dofs_velocity().numpy()
    return _spin_verdict(vel[:3], vel[3:], (0, 0, -S.G * dt * SPIN_STEPS), (omega, 0, 0), omega)


def mj_spin(dt, omega):
    import mujoco

    spec = mujoco.MjSpec()
    S.mujoco_free_box(spec, "box", (0, 0, BOX / 2 + SPIN_GAP), BOX, 1.0)
    m = S.mujoco_on_floor(spec, dt)
    d = mujoco.MjData(m)
    d.qvel[3] = omega  # body frame; the cube's inertia is isotropic, so the spin stays about the world's x
    for _ in range(SPIN_STEPS):
        mujoco.mj_step(m, d)
    w = _quat_to_R(d.qpos[3:7]) @ d.qvel[3:6]
    return _spin_verdict(d.qvel[:3], w, (0, 0, -S.G * dt * SPIN_STEPS), (omega, 0, 0), omega)


def _said(caught):
    """The first warning genesis_lite gave about the contact (the library "said" the step or the stiffness
    cannot handle the scene), or None."""
    for w in caught:
        if "contact" in str(w.message).lower():
            return f"{w.category.__name__}: {str(w.message).splitlines()[0]}"
    return None


def _fast_verdict(zmin, zend, vend, said=None, raised=None):
    if raised is not None:
        return {"pass": True, "metrics": {"refused": True}, "figure": f"refused: {raised[:140]}"}
    finite = all(math.isfinite(x) for x in (zmin, zend, vend))
    note = f"; said: {said[:140]}" if said else ""
    if not finite:
        return {"pass": bool(said), "metrics": {"finite": False, "said": bool(said)}, "figure": "diverged (NaN)" + note}
    ok = (zmin > 0.0 and abs(zend - BOX / 2) < 0.01 and vend < 0.01) or bool(said)
    return {"pass": bool(ok), "metrics": {"finite": True, "zmin": zmin, "zend": zend, "vend": vend, "said": bool(said)},
            "figure": f"lowest centre {zmin:.3g} m (half size {BOX / 2} m), after 1 s at {zend:.3g} m, "
            f"{vend:.2g} m/s" + note}


def gl_fast(gs, dt, t_end=1.0):
    import torch

    from genesis_lite.errors import GenesisException

    scene = _scene(gs, dt)
    scene.add_entity(gs.morphs.Plane())
    box = _box(gs, scene, (0, 0, FAST_Z0), 1.0)
    scene.build()
    box.set_dofs_velocity(torch.tensor([0, 0, -FAST_V, 0, 0, 0], dtype=gs.tc_float))
    zmin = math.inf
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            for _ in range(int(round(t_end / dt))):
                scene.step()
                zmin = min(zmin, float(box.get_pos()[2]))
        except GenesisException as e:
            return _fast_verdict(zmin, math.nan, math.nan, raised=f"{type(e).__name__}: {e}")
    return _fast_verdict(zmin, float(box.get_pos()[2]), float(torch.linalg.norm(box.get_vel())), said=_said(caught))


def mj_fast(dt, t_end=1.0):
    import mujoco

    spec = mujoco.MjSpec()
    S.mujoco_free_box(spec, "box", (0, 0, FAST_Z0), BOX, 1.0)
    m = S.mujoco_on_floor(spec, dt)
    d = mujoco.MjData(m)
    d.qvel[2] = -FAST_V
    zmin = math.inf
    for _ in range(int(round(t_end / dt))):
        mujoco.mj_step(m, d)
        zmin = min(zmin, float(d.qpos[2]))
    return _fast_verdict(zmin, float(d.qpos[2]), float(np.linalg.norm(d.qvel[:3])))


def _heavy_verdict(z, v, said=None):
    note = f"; said: {said[:140]}" if said else ""
    if not (math.isfinite(z) and math.isfinite(v)):
        return {"pass": bool(said), "metrics": {"finite": False}, "figure": "diverged (NaN)" + note}
    sink = BOX / 2 - z
    return {"pass": bool((sink < 0.01 and v < 0.01) or said), "metrics": {"finite": True, "sink": sink, "speed": v,
                                                                         "said": bool(said)},
            "figure": f"sinks {sink * 1e3:.2f} mm, speed {v:.1e} m/s after 2 s" + note}


def gl_heavy(gs, dt, t_end=2.0):
    import torch

    scene = _scene(gs, dt)
    scene.add_entity(gs.morphs.Plane())
    box = _box(gs, scene, (0, 0, BOX / 2), HEAVY_MASS)
    scene.build()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(int(round(t_end / dt))):
            scene.step()
    return _heavy_verdict(float(box.get_pos()[2]), float(torch.linalg.norm(box.get_vel())), said=_said(caught))


def mj_heavy(dt, t_end=2.0):
    import mujoco

    spec = mujoco.MjSpec()
    S.mujoco_free_box(spec, "box", (0, 0, BOX / 2), BOX, HEAVY_MASS)
    m = S.mujoco_on_floor(spec, dt)
    d = mujoco.MjData(m)
    for _ in range(int(round(t_end / dt))):
        mujoco.mj_step(m, d)
    return _heavy_verdict(float(d.qpos[2]), float(np.linalg.norm(d.qvel[:3])))


def _inside(box, block):
    """Particles of block inside the box by more than a quarter of a grid cell, in the box's frame (it may
    have tilted)."""
    p = box.get_pos().numpy()
    local = (block.get_particles_pos().numpy() - p) @ _quat_to_R(box.get_quat().numpy())
    return int(np.sum(np.all(np.abs(local) < SOFT_BOX / 2 - SOFT_DX / 4, axis=1)))


def gl_soft(gs, dt, mass, t_end=2.0, substeps=20):
    """A rigid box of `mass` kg on an elastic MPM block on the floor (dt is the scene step; the MPM substep is
    dt / substeps, within the build's time-step check for this material)."""
    import torch

    floor = 3 * SOFT_DX  # the MPM domain's floor wall: the rigid ground plane is put there too
    scene = _scene(gs, dt, substeps=substeps,
                   mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.6, 0.6, 0.6),
                                                     grid_density=1.0 / SOFT_DX))
    scene.add_entity(gs.morphs.Plane(pos=(0, 0, floor)))
    block = scene.add_entity(gs.morphs.Box(pos=(0.3, 0.3, floor + 0.002 + SOFT_EDGE / 2), size=(SOFT_EDGE,) * 3),
                             material=gs.materials.MPM.Elastic(E=1e5, nu=0.3, rho=1000.0))
    z_box = floor + 0.002 + SOFT_EDGE + 0.004 + SOFT_BOX / 2
    box = _box(gs, scene, (0.3, 0.3, z_box), mass, size=SOFT_BOX)
    scene.build()
    zlow = math.inf
    inside_1s = None
    for k in range(int(round(t_end / dt))):
        scene.step()
        zlow = min(zlow, float(box.get_pos()[2]) - SOFT_BOX / 2)
        if k + 1 == int(round(1.0 / dt)):
            inside_1s = _inside(box, block)
    inside = _inside(box, block)
    p = box.get_pos().numpy()
    x = block.get_particles_pos().numpy()
    finite = bool(np.all(np.isfinite(x)) and np.all(np.isfinite(p)))
    if not finite:
        return {"pass": False, "metrics": {"finite": False}, "figure": "diverged (NaN)"}
    below = floor - zlow
    ok = inside == 0 and below < SOFT_DX
    return {"pass": bool(ok), "metrics": {"finite": True, "inside": inside, "inside_at_1s": inside_1s, "below_floor": below,
                                          "box_bottom_end": float(p[2]) - SOFT_BOX / 2 - floor},
            "figure": f"{inside} of {len(x)} particles inside the box after {t_end:g} s ({inside_1s} at 1 s); its bottom {(float(p[2]) - SOFT_BOX / 2 - floor) * 1e3:.1f}"
            f" mm above the floor at the end, lowest {-below * 1e3:.1f} mm"}


def _quat_to_R(q):
    w, x, y, z = (float(v) for v in q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


GL_ROWS = {
    "spin1e3": lambda gs, dt: gl_spin(gs, dt, 1e3),
    "spin1e6": lambda gs, dt: gl_spin(gs, dt, 1e6),
    "fast": lambda gs, dt: gl_fast(gs, dt),
    "heavy": lambda gs, dt: gl_heavy(gs, dt),
    "soft4t": lambda gs, dt: gl_soft(gs, dt, 4e3),
    "soft400t": lambda gs, dt: gl_soft(gs, dt, 4e5),
}
MJ_ROWS = {
    "spin1e3": lambda dt: mj_spin(dt, 1e3),
    "spin1e6": lambda dt: mj_spin(dt, 1e6),
    "fast": lambda dt: mj_fast(dt),
    "heavy": lambda dt: mj_heavy(dt),
}
ROW_TITLES = {
    "spin1e3": "box spinning at 1e3 rad/s, 6 cm above the ground",
    "spin1e6": "box spinning at 1e6 rad/s, 6 cm above the ground",
    "fast": "box dropped at 1e6 m/s onto the ground",
    "heavy": "400 t box (0.2 m) resting on the ground",
    "soft4t": "4 t box (0.15 m) on an elastic MPM block (E 1e5 Pa)",
    "soft400t": "400 t box (0.15 m) on an elastic MPM block (E 1e5 Pa)",
}
CRITERIA = {
    "spin1e3": "never touches: velocity and spin follow free fall (1e-6)",
    "spin1e6": "never touches: velocity and spin follow free fall (1e-6)",
    "fast": "refused with a message, or never below the ground and at rest on it after 1 s",
    "heavy": "finite, sinks < 1 cm, at rest after 2 s",
    "soft4t": "no particle inside the box after 2 s; box never a grid cell below the floor",
    "soft400t": "no particle inside the box after 2 s; box never a grid cell below the floor",
}
DT = {"soft4t": 0.01, "soft400t": 0.01}
