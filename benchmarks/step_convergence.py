"""Does a work-precision scene converge as dt halves, in each engine and integrator? (issue #24)

Runs one scene of bench_workprecision.py (its starts as envs: 16 for the quadrupeds, 1 for the box and the push)
with Euler and implicitfast at dt = 0.3125 ms / 2^k and RK4 at 0.625 ms / 2^k (k = 0 .. 5), and prints each run's
change from the run at twice its step (the scene's own error measure, bench_workprecision._error). At first order
the change halves with dt and is about the coarser run's error; a change that does not shrink means no reference of
that engine can be trusted below it.

--variant changes MuJoCo's solver or contact settings (VARIANTS) after its model is built, to see whether a
scene's non-convergence is those settings'. --trace follows the box of the box or the push scene in both engines
(Euler at TRACE_DT, from TRACE_FROM to TRACE_T s: sliding, then coming to rest): how often it stands on fewer than
its four floor corners, how far it rises above its height at TRACE_T and how far it tilts.

Measured 2026-12-06 (MuJoCo 4.0.1; results/step_convergence.md): MuJoCo's box hops as it slides. On fewer than its
four corners in 90 % (box) / 79 % (push) of the steps, on none in 55 % / 26 %, rising up to 2.5 / 0.5 mm and
tilting up to 1.0e-2 / 6.1e-3 rad; ours stays on four, rising 3.5e-7 / 4.2e-6 m and tilting 1.2e-4 / 2.9e-4 rad.
MuJoCo's changes per halving at dt <= 39 us stay at 0.9-8.5e-4 m (box) and 0.9e-4-6.4e-3 m (push), with each of
VARIANTS and each integrator; ours halve (Euler at 9.8 us: 9.0e-6 m box, 5.6e-7 m push).

    python benchmarks/step_convergence.py [--scene push|box|quadruped|quadruped_armature] [--engine mujoco|genesis_lite]
                                          [--variant tight]     # seconds (MuJoCo) to minutes
    python benchmarks/step_convergence.py --trace [--scene box]  # the box in both engines, ~1 min
"""
import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_workprecision as W  # noqa: E402

TRACE_DT, TRACE_T = 1.5625e-4, 0.4  # s
TRACE_FROM = 0.025  # s: the box is sliding (the push has begun)


def _mj_option(**values):
    def tweak(m):
        for k, v in values.items():
            setattr(m.opt, k, v)
    return tweak


def _mj_variants():
    import mujoco

    return {"default": lambda m: None,
            "tight": _mj_option(tolerance=1e-15, ls_tolerance=1e-12, iterations=500),  # the solver run to round-off
            "nowarm": _mj_option(disableflags=int(mujoco.mjtDisableBit.mjDSBL_WARMSTART)),
            "noslip": _mj_option(noslip_iterations=20),
            "pyramidal": _mj_option(cone=int(mujoco.mjtCone.mjCONE_PYRAMIDAL)),
            "impratio": _mj_option(impratio=10.0),  # MuJoCo's documented remedy for slip: friction 10x harder
            "stiff": lambda m: m.geom_solref.__setitem__(slice(None), (0.004, 1.0))}  # contacts 5x stiffer (timeconst)


VARIANTS = ("default", "tight", "nowarm", "noslip", "pyramidal", "impratio", "stiff")


def with_variant(wps, variant):
    """wps with MuJoCo's model changed by VARIANTS' `variant` after it is built."""
    tweak = _mj_variants()[variant]

    def build(files, integ, dt):
        m, *rest = wps.mj_build(files, integ, dt)
        tweak(m)
        return (m, *rest)

    return dataclasses.replace(wps, mj_build=build)


def trace_mujoco(key, files):
    import mujoco

    m, q0, v0, _, ctrl = W.SCENES[key].mj_build(files, "Euler", TRACE_DT)
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = q0, v0
    if ctrl is not None:
        d.ctrl[:] = ctrl
    box = m.nbody - 1  # the free box is the last body of both scenes, its free joint the last 7 of qpos
    rows = []
    for _ in range(int(round(TRACE_T / TRACE_DT))):
        mujoco.mj_step(m, d)
        floor = sum(1 for c in d.contact[:d.ncon] if {int(m.geom_bodyid[c.geom1]), int(m.geom_bodyid[c.geom2])} == {0, box})
        rows.append((d.time, floor, d.qpos[-5], *d.qpos[-4:]))
    return np.array(rows)


def trace_ours(key, files):
    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")
    scene, reset, _ = W.SCENES[key].gl_build(gs, files, "Euler", TRACE_DT, 1, 0)
    reset()
    plane, box = scene.entities[0], scene.entities[-1]  # both builders add the floor first and the box last
    rows = []
    for k in range(int(round(TRACE_T / TRACE_DT))):
        scene.step()
        c = box.get_contacts(with_entity=plane)
        floor = int(((c["force_a"] * c["normal"]).sum(-1) > 0).sum())  # the floor's contacts that push
        rows.append(((k + 1) * TRACE_DT, floor, float(box.get_pos()[..., 2]), *box.get_quat().reshape(-1).tolist()))
    return np.array(rows)


def trace(key):
    with tempfile.TemporaryDirectory(prefix="step_conv_") as tmp:
        files = W.SCENES[key].files(Path(tmp))
        print(f"{key}: the box, Euler at dt = {TRACE_DT * 1e6:g} us, from {TRACE_FROM} to {TRACE_T} s (sliding, coming "
              f"to rest); rest height: its height at {TRACE_T} s")
        print("| engine | steps on < 4 floor contacts | on 0 | rise above rest, max (m) | tilt, max (rad) |")
        print("| --- | --- | --- | --- | --- |")
        for name, rows in (("MuJoCo", trace_mujoco(key, files)), ("genesis_lite", trace_ours(key, files))):
            r = rows[rows[:, 0] >= TRACE_FROM - 1e-12]
            tilt = 2 * np.arcsin(np.clip(np.linalg.norm(r[:, 4:6], axis=1), 0, 1))  # the quaternion's x, y part
            print(f"| {name} | {np.mean(r[:, 1] < 4):.0%} | {np.mean(r[:, 1] == 0):.0%} | "
                  f"{(r[:, 2] - rows[-1, 2]).max():.1e} | {tilt.max():.1e} |", flush=True)


PLAN = {"Euler": [0.3125e-3 / 2**k for k in range(6)], "implicitfast": [0.3125e-3 / 2**k for k in range(6)],
        "RK4": [0.625e-3 / 2**k for k in range(6)]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="push", choices=["push", "box", "quadruped", "quadruped_armature"])
    ap.add_argument("--engine", default="mujoco", choices=["mujoco", "genesis_lite"])
    ap.add_argument("--variant", default="default", choices=VARIANTS, help="MuJoCo's settings (module docstring)")
    ap.add_argument("--trace", action="store_true", help="follow the box of --scene push or box in both engines (docstring)")
    a = ap.parse_args()
    if a.trace:
        if a.scene not in ("push", "box"):
            ap.error("--trace follows the box of --scene push or box")
        return trace(a.scene)
    if a.variant != "default" and a.engine != "mujoco":
        ap.error("--variant changes MuJoCo's model: give --engine mujoco")
    wps = W.SCENES[a.scene] if a.variant == "default" else with_variant(W.SCENES[a.scene], a.variant)
    with tempfile.TemporaryDirectory(prefix="step_conv_") as tmp:
        files = wps.files(Path(tmp))
        for integ, dts in PLAN.items():
            pts, t0 = [(integ, dt, 1) for dt in dts], time.time()
            res, err = W.run_engine(a.engine, wps, files, pts, wps.starts, 1)
            if res is None:
                raise SystemExit(f"step_convergence.py: the run failed: {err}")
            obs = [p.get("obs") for p in res["points"]]
            print(f"{a.engine}{'' if a.variant == 'default' else ' (' + a.variant + ')'} {integ} "
                  f"({time.time() - t0:.0f} s)", flush=True)
            for i in range(1, len(dts)):
                ch = (W._error(obs[i - 1], np.asarray(obs[i]), a.scene) if obs[i] is not None and obs[i - 1]
                      is not None else float("nan"))
                print(f"  dt {dts[i]:.3e} s: change from 2 dt {ch:.3e}", flush=True)


if __name__ == "__main__":
    main()
