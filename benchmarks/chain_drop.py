"""A 30-link chain (assets/urdf/chain30.urdf: a 1 kg base, 30 links of 0.1 kg, no damping, no armature) hanging
from height z0 and dropped onto the ground, as tests/test_contact.py's stress test: from several heights, with
genesis_lite (dt = 10 ms, substeps 8, 16 and 32, both friction slip-speed laws) and with MuJoCo (the same URDF
through scenes.mujoco_from_urdf, links colliding with the ground only, at the same steps h = 1.25, 0.625,
0.3125 ms), whether the run diverges and the most its energy rose. The chain whips on the ground (joint speeds of
100-200 rad/s), where a first-order step of 1.25 ms gains energy: the second table runs the chain in the air (no
ground) from one state of genesis_lite's capped run at 8 substeps for 10 ms at h / 1, 4, 16, 64 with each
integrator.

    python benchmarks/chain_drop.py [--quick] [--md benchmarks/results/chain_drop.md]

--quick: one height, MuJoCo's first-order integrators only, no free-flight table. Not timed: these are numbers of
stability, not speed.
"""
import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import scenes as S  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
URDF = ROOT / "assets" / "urdf" / "chain30.urdf"
HEIGHTS = (3.15, 3.18, 3.19, 3.2, 3.21, 3.22, 3.25)
DT, STEPS = 0.01, 400  # genesis_lite: 4 s
FREE_FROM = (3.2, 8, 162)  # the free-flight table's state: height, substeps, step of the capped run


# --- genesis_lite ------------------------------------------------------------------------------------------------
def _gl_scene(gs, z0, substeps, accel):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=DT, substeps=substeps),
                     rigid_options=gs.options.RigidOptions(friction_smoothing_accel=accel))
    scene.add_entity(gs.morphs.Plane())
    chain = scene.add_entity(gs.morphs.URDF(file=str(URDF), fixed=False, pos=(0, 0, z0), default_armature=None))
    scene.build()
    return scene, chain


def gl_drop(gs, z0, substeps, accel, keep_step=None):
    """(status, max E - E0, max |dof velocity|, the state after step keep_step or None)."""
    scene, chain = _gl_scene(gs, z0, substeps, accel)
    e0 = float(chain.get_total_energy())
    emax, vmax, kept, status = e0, 0.0, None, "ok"
    for k in range(STEPS):
        try:
            scene.step()
        except gs.GenesisException:  # the NaN watch (SimulationNaNError)
            status = f"diverged at step {k}"
            break
        emax = max(emax, float(chain.get_total_energy()))
        vmax = max(vmax, float(chain.get_dofs_velocity().abs().max()))
        if k == keep_step:
            kept = (chain.get_qpos().clone(), chain.get_dofs_velocity().clone())
    return status, emax - e0, vmax, kept


def gl_free_flight(gs, state, integrator, div):
    """Energy change of the chain in the air over 10 ms from `state`, steps of 1.25 ms / div."""
    h = DT / FREE_FROM[1] / div
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=h),
                     rigid_options=gs.options.RigidOptions(integrator=getattr(gs.integrator, integrator),
                                                           enable_collision=False))
    chain = scene.add_entity(gs.morphs.URDF(file=str(URDF), fixed=False, pos=(0, 0, 3.2), default_armature=None))
    scene.build()
    chain.set_qpos(state[0])
    chain.set_dofs_velocity(state[1])
    e0 = float(chain.get_total_energy())
    for _ in range(int(round(0.01 / h))):
        scene.step()
    return float(chain.get_total_energy()) - e0


# --- MuJoCo ------------------------------------------------------------------------------------------------------
def mj_model(z0):
    """MuJoCo's chain (scenes.mujoco_from_urdf: a free base at height z0, the URDF's inertials, axes and limits,
    no damping or armature, links colliding with a ground plane of friction 1 only), with MuJoCo's default
    pyramidal friction cones: with elliptic ones the chain landed on its end and stood there for the 4 s from
    every height (joint speeds at most 2.2 rad/s), so nothing whipped and no step's stability was compared; the
    pyramid's asymmetry topples it, as genesis_lite's chain falls."""
    return S.mujoco_from_urdf(URDF, free=True, base_pos=(0.0, 0.0, z0), floor_mu=1.0, elliptic=False)


def mj_drop(mujoco, z0, integrator, h):
    """MuJoCo's drop over the same 4 s: (status, max E - E0, max |qvel|); energy = mj_energyPos + mj_energyVel
    (without the soft constraints' stored energy)."""
    model = S.set_mujoco_integrator(mj_model(z0), integrator, h)
    model.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
    data = mujoco.MjData(model)

    def energy():
        mujoco.mj_forward(model, data)
        return float(data.energy[0] + data.energy[1])

    e0 = energy()
    emax, vmax = e0, 0.0
    for k in range(int(round(STEPS * DT / h))):
        mujoco.mj_step(model, data)
        v = float(np.abs(data.qvel).max()) if np.all(np.isfinite(data.qvel)) else math.inf
        if v > 1e4:
            return f"diverged at t = {(k + 1) * h:.3f} s", math.nan, v
        vmax = max(vmax, v)
        emax = max(emax, energy())
    return "ok", emax - e0, vmax


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--md", type=Path, help="write the tables here (markdown)")
    a = ap.parse_args()
    import genesis_lite as gs
    import mujoco
    from tqdm import tqdm
    gs.init(backend=gs.cpu, precision="64", logging_level="error")
    heights = (3.2,) if a.quick else HEIGHTS
    runs = [("genesis_lite", f"{law}, {sub} substeps (h = {DT / sub * 1e3:g} ms)", z0, (sub, accel))
            for sub in (8, 16, 32) for law, accel in (("fixed slip speed", None), ("capped slip speed (default)", 0.25))
            for z0 in heights]
    mj_integs = ("Euler", "implicitfast") if a.quick else ("Euler", "implicitfast", "implicit", "RK4")
    runs += [("MuJoCo " + mujoco.__version__, f"{integ}, h = {h * 1e3:g} ms", z0, (integ, h))
             for h in (DT / 8, DT / 16, DT / 32) for integ in mj_integs for z0 in heights]
    rows, state = [], None
    for engine, variant, z0, args in tqdm(runs, desc="chain drops"):
        if engine == "genesis_lite":
            keep = FREE_FROM[2] if (z0, args[0], args[1]) == (FREE_FROM[0], FREE_FROM[1], 0.25) else None
            status, de, vmax, kept = gl_drop(gs, z0, *args, keep_step=keep)
            state = kept if kept is not None else state
        else:
            status, de, vmax = mj_drop(mujoco, z0, *args)
        rows.append((engine, variant, z0, status, de, vmax))
    lines = ["| engine | variant | z0 m | result | max E - E0 (J) | max abs dof velocity |",
             "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {e} | {v} | {z0:g} | {s} | {de:+.3g} | {vm:.3g} |" for e, v, z0, s, de, vm in rows]
    tally = {}
    for e, v, _z0, s, _de, _vm in rows:
        n, d = tally.get((e, v), (0, 0))
        tally[(e, v)] = (n + 1, d + (s != "ok"))
    lines += ["", "| engine | variant | diverged / heights |", "| --- | --- | --- |"]
    lines += [f"| {e} | {v} | {d} / {n} |" for (e, v), (n, d) in tally.items()]
    if not a.quick and state is not None:
        z0, sub, k = FREE_FROM
        lines += ["", f"The chain in the air (no ground), from the state after step {k} of genesis_lite's capped run "
                  f"from {z0} m at {sub} substeps, energy change over 10 ms (J):", "",
                  "| integrator | h = 1.25 ms | h / 4 | h / 16 | h / 64 |", "| --- | --- | --- | --- | --- |"]
        for integ in ("approximate_implicitfast", "implicitfast", "Euler", "RK4"):
            lines.append(f"| {integ} | " + " | ".join(f"{gl_free_flight(gs, state, integ, div):+.4g}"
                                                       for div in (1, 4, 16, 64)) + " |")
    text = "\n".join(lines)
    print(text)
    if a.md:
        a.md.write_text("# Chain drops (`benchmarks/chain_drop.py`)\n\n" + text + "\n")


if __name__ == "__main__":
    main()
