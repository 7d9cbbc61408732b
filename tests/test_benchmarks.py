"""The benchmark harness (benchmarks/run_all.py, issue #9): its bookkeeping, its references, and a run.

- Pure logic, no simulation: the work-precision front and the equal-error ratio on points whose answer is known
  by construction, the bisection of the largest time step, the sweep's sample times, the stress verdicts on
  made-up figures (a NaN or a tunnelling sphere must FAIL).
- References no one here wrote: the analytic sliding box; MuJoCo and Pinocchio reading the same Panda file
  (MuJoCo's RK4 at a small dt lands on Pinocchio + DOP853), which is what makes the MuJoCo rows comparable.
- A smoke run of run_all.py with one row of each kind (work-precision, stress, gradient norm, unused-feature
  cost, headline), checking that results.md holds the tables and that every pass / fail cell agrees with
  the criterion applied here to the raw figures in results.json.
- The whole `run_all.py --quick` (slow).
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
sys.path.insert(0, str(BENCH))

import bench_stress as bs  # noqa: E402
import bench_workprecision as wp  # noqa: E402
import scenes as S  # noqa: E402


def _pt(wall, error, diverged=False):
    return {"integrator": "Euler", "dt": 0.01, "substeps": 1, "wall": wall, "error": error, "diverged": diverged}


# --- work-precision bookkeeping -------------------------------------------------------------------------------


def test_front_keeps_only_points_that_buy_accuracy():
    pts = [_pt(1.0, 1e-2), _pt(2.0, 1e-2), _pt(3.0, 1e-4), _pt(0.5, 1e3, diverged=True), _pt(4.0, 1e-3)]
    assert wp.front(pts) == [(1e-2, 1.0), (1e-4, 3.0)]
    assert wp.time_at(wp.front(pts), 1e-3) == 3.0
    assert wp.time_at(wp.front(pts), 1e-5) == math.inf


def test_equal_error_ratio_on_a_known_pair():
    # b needs twice a's time for every error level, over a common range 1e-4 .. 1e-2
    a = [_pt(1.0, 1e-2), _pt(2.0, 1e-3), _pt(4.0, 1e-4), _pt(8.0, 1e-6)]
    b = [_pt(2.0, 1e-2), _pt(4.0, 1e-3), _pt(8.0, 1e-4), _pt(0.1, 5.0)]
    mx, med, (lo, hi) = wp.equal_error_ratio(a, b)
    assert (lo, hi) == (1e-4, 1e-2)
    assert mx == pytest.approx(0.5) and med == pytest.approx(0.5)
    mx, _, _ = wp.equal_error_ratio(b, a)
    assert mx == pytest.approx(2.0)
    # no common range: one engine never gets below 1e-1 (the cap of useful accuracy)
    assert wp.equal_error_ratio(a, [_pt(1.0, 0.5)]) is None


def test_time_to_error_follows_each_integrator_not_the_front_of_all_runs():
    """Between two runs of one integrator the time is the log-log line through them; a run of another integrator
    that lands between them (error between theirs, time just below the finer one's) does not raise it, as it
    did when the line ran along the front of all runs together (here 14.9 at 1e-3 instead of 10; the
    quadruped's Euler run among implicitfast's, 2026-12-06)."""
    imp = [dict(_pt(1.0, 1e-2), integrator="implicitfast"), dict(_pt(100.0, 1e-4), integrator="implicitfast")]
    eul = [dict(_pt(99.0, 2e-4), integrator="Euler")]
    assert wp.time_to_error(imp, 1e-3) == pytest.approx(10.0)
    assert wp.time_to_error(imp + eul, 1e-3) == pytest.approx(10.0)
    assert wp.time_to_error(imp + eul, 2e-4) == pytest.approx(100.0 ** (np.log(50.0) / np.log(100.0)))
    assert wp.time_to_error(imp + [dict(_pt(20.0, 2e-4), integrator="Euler")], 2e-4) == 20.0  # the cheaper run
    assert wp.time_to_error(imp + eul, 1e-5) == math.inf
    peer = [_pt(5.0, 1e-2), _pt(50.0, 1e-4)]
    assert wp.equal_error_ratio(imp + eul, peer)[0] <= wp.equal_error_ratio(imp, peer)[0] + 1e-12


def test_time_at_equal_error_interpolates_between_runs():
    """Between two runs of a front the time to an error is the log-log line through them (error ~ dt^p, time ~
    1 / dt), above the cheapest run its time (no extrapolation), below the best run none. Two engines running the
    same algorithm, whose errors at the coarsest step agree to rounding (the double pendulum's Euler at 20 ms,
    2026-12-01: 0.016770 rad for both), compare at their run times, not a whole halving of dt apart."""
    fr = [(1e-2, 1.0), (1e-4, 100.0)]
    assert wp.time_at_interp(fr, 1e-3) == pytest.approx(10.0)
    assert wp.time_at_interp(fr, 1e-1) == 1.0
    assert wp.time_at_interp(fr, 1e-4) == pytest.approx(100.0)
    assert wp.time_at_interp(fr, 1e-5) == math.inf
    assert wp.time_at_interp([(1e-2, 1.0), (0.0, 3.0)], 1e-3) == 3.0  # an exact run: no log of 0
    a = [_pt(1.0, 0.0167701), _pt(2.0, 0.00848)]
    b = [_pt(1.5, 0.0167700), _pt(3.0, 0.00848)]
    assert wp.equal_error_ratio(a, b, interpolate=False)[0] == pytest.approx(2.0 / 1.5)
    mx, med, _ = wp.equal_error_ratio(a, b)
    assert mx == pytest.approx(1.0 / 1.5, rel=1e-3) and med == pytest.approx(1.0 / 1.5, rel=1e-3)


def test_sample_times_must_be_whole_steps():
    assert wp._samples(wp.SCENES["box"], 0.005) == [40, 160]
    with pytest.raises(ValueError, match="not a multiple"):
        wp._samples(wp.SCENES["box"], 0.003)
    for engine in ("genesis_lite", "mujoco", "genesis"):
        for batched in (False, True):
            for quick in (False, True):
                for integ, dt, sub in wp.sweep(engine, batched, quick):
                    for key in ("pendulum", "panda", "box", "quadruped"):
                        wp._samples(wp.SCENES[key], dt)  # raises if a sample time falls between steps


def test_error_measure_flags_nan_and_averages_the_envs_each_against_its_start():
    """Each env's error is its worst observable; the scene's is their mean; env i is compared with the reference's
    row i % rows (one row a start: the quadrupeds' envs start from QUAD_STARTS drops)."""
    assert wp._error([[0.0, 1.0], [0.0, 1.5]], [0.0, 1.0], "pendulum") == pytest.approx(0.25)
    assert wp._error([[0.0, 1.0], [0.0, 1.0]], [0.0, 1.0], "pendulum") == 0.0
    assert wp._error([[np.nan, 1.0]], [0.0, 1.0], "pendulum") == math.inf
    ref = [[0.0, 1.0], [2.0, 3.0]]  # two starts
    assert wp._error([[0.0, 1.0], [2.0, 3.0], [0.0, 1.0], [2.0, 3.0]], ref, "pendulum") == 0.0
    assert wp._error([[0.0, 1.0], [2.0, 3.0], [0.0, 1.4], [2.0, 3.0]], ref, "pendulum") == pytest.approx(0.1)
    assert wp._error([[0.0, 1.0]], ref, "pendulum") == 0.0  # one env: start 0
    assert wp._error([[3.0, 4.0, 0.0]], [0.0, 0.0, 0.0], "quadruped") == pytest.approx(5.0)
    # the quadruped's samples (x, y, z) at each sample time: the worst one's norm
    assert wp._error([[0.0, 0.0, 1.0, 3.0, 4.0, 0.0]], [0.0] * 6, "quadruped_armature") == pytest.approx(5.0)


def test_quadruped_starts_are_fixed_and_start_0_is_the_level_drop():
    """The batched quadruped rows start QUAD_STARTS drops: the same ones in every run and in both engines (one draw,
    seeded), start 0 the one-env row's (level, at BASE_Z, the standing pose), the others each moved, with unit
    quaternions; MuJoCo's initial states take one row a start, env i row i % rows."""
    from bench_contact import BASE_Z, standing_pose

    names = ["LF_HAA", "LF_HFE", "LF_KFE", "RF_HAA", "RF_HFE", "RF_KFE", "LH_HAA", "LH_HFE", "LH_KFE", "RH_HAA",
             "RH_HFE", "RH_KFE"]
    pos, quat, q = wp.quad_starts(names, wp.QUAD_STARTS)
    pos2, quat2, q2 = wp.quad_starts(names, wp.QUAD_STARTS)
    assert np.array_equal(pos, pos2) and np.array_equal(quat, quat2) and np.array_equal(q, q2)
    assert np.array_equal(pos[0], [0.0, 0.0, BASE_Z]) and np.array_equal(quat[0], [1.0, 0.0, 0.0, 0.0])
    assert np.array_equal(q[0], standing_pose(names))
    assert np.allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-12)
    moved = np.abs(np.concatenate([pos - pos[0], quat - quat[0], q - q[0]], axis=1)).max(axis=1)
    assert moved[0] == 0.0 and np.all(moved[1:] > 1e-3)
    assert np.all(np.abs(q - q[0]) <= 0.1) and np.all(np.abs(pos[:, 2] - BASE_Z) <= 0.03)
    assert wp.SCENES["quadruped"].starts == wp.SCENES["quadruped_armature"].starts == wp.QUAD_STARTS


def test_mujoco_initial_states_take_a_row_a_start():
    mujoco = pytest.importorskip("mujoco")
    m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><body><freejoint/><geom size="0.1"/></body></worldbody>'
                                       '</mujoco>')
    rows = np.array([[0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0], [0.5, -0.2, 2.0, 0.0, 1.0, 0.0, 0.0]])
    qs, _ = S.mujoco_state_slices(m)
    st = S.mujoco_initial_states(m, rows, np.zeros(6), 5)
    assert st.shape[0] == 5
    assert np.array_equal(st[:, qs], rows[[0, 1, 0, 1, 0]])
    assert np.array_equal(S.mujoco_initial_states(m, rows[1], np.zeros(6), 3)[:, qs], rows[[1, 1, 1]])


def _wave_speed(E, nu, rho):
    """Pressure wave speed sqrt((lam + 2 mu) / rho) (m/s) of an isotropic elastic solid, from the textbook Lame
    parameters (not from genesis_lite's materials)."""
    mu = E / (2 * (1 + nu))
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    return math.sqrt((lam + 2 * mu) / rho)


def test_mpm_sweep_stays_inside_the_cfl_limit_and_on_the_sample_times():
    """Every point of the MPM work-precision sweep (and its references) is a run genesis_lite's build accepts (a
    substep below 0.9 dx / c) whose sample times fall on whole steps, and the reference is far finer than the sweep."""
    wps = wp.SCENES["mpm"]
    h_max = 0.9 * (1 / 64) / _wave_speed(3e5, 0.2, 1000.0)
    assert h_max == pytest.approx(7.7e-4, rel=0.01)
    pts = wps.sweep("genesis_lite", False, False) + wps.sweep("genesis_lite", False, True)
    refs = [wp.MPM_REF, wp.MPM_REF_CHECK, wp.MPM_REF_QUICK, wp.MPM_REF_CHECK_QUICK]
    for scheme, dt, sub in pts + refs:
        assert dt / sub <= h_max, (dt, sub)
        wp._samples(wps, dt)
    finest = min(dt / sub for _, dt, sub in pts)
    assert wp.MPM_REF[1] / wp.MPM_REF[2] <= finest / 8
    assert wp.MPM_REF_QUICK[1] / wp.MPM_REF_QUICK[2] <= min(dt / sub for _, dt, sub in wps.sweep("genesis_lite", False, True)) / 4
    ref = wps.reference({})
    assert ref.kind == "fine" and "float64" in ref.label and "640 substeps" in ref.label
    assert not wps.batched and wps.mj_build is None  # 1 env, genesis_lite only: no MuJoCo MPM


@pytest.mark.slow
def test_mpm_workprecision_row_runs_small(tmp_path):
    """The MPM row as --quick runs it (a child process runs genesis_lite): 4 and 8 substeps of 2 ms against 32 (the
    quick reference, checked against 16). Errors are finite, positive, and smaller with more substeps (closer to
    the reference's substep; at this fixed grid the ringing does not converge in the substep, see the row's comment,
    but it moves monotonically), 1 env only, no MuJoCo, and the table names the reference."""
    res = wp.run(["mpm"], [0, 1024], True, 1, False, tmp_path, log=lambda *a: None)
    entry = res["mpm"]
    assert list(entry["envs"]) == ["1"] and list(entry["envs"]["1"]) == ["genesis_lite"]
    pts = entry["envs"]["1"]["genesis_lite"]["points"]
    err = {p["substeps"]: p["error"] for p in pts}
    assert set(err) == {4, 8}
    assert all(math.isfinite(e) and e > 0 for e in err.values()), pts
    assert err[8] < err[4], err
    assert all(p["wall"] > 0 and not p["diverged"] for p in pts)
    self_err = entry["ref_self_error"]["genesis_lite"]
    assert math.isfinite(self_err) and 0 < self_err
    text = "\n".join(wp.tables(res))
    assert "32 substeps" in text and "float64" in text and "#### mpm" in text and "1 env only" in text


@pytest.mark.slow
def test_push_row_engines_agree_on_the_push(tmp_path):
    """The manipulation row's two models are the same scene: in MuJoCo and genesis_lite (implicitfast, dt = 1 ms,
    default contact models) the arm's sphere pushes the box from x = 0.41 m, which leaves it sliding and comes to
    rest on the floor; both engines' final box positions agree within 3 mm (measured 2026-11-29: 0.5584 and
    0.5595 m), y within 2 mm and z at the box's half height. A model mismatch (the sphere, the friction, the
    gravity compensation, the gains) moves the box by centimetres (without gravity compensation the arm sagged
    and the sphere dragged on the floor: 0.499 against 0.431 m)."""
    import mujoco
    from mujoco import rollout

    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")
    files = wp._push_files(tmp_path)
    dt, n = 1e-3, 1000
    scene, reset, observe = wp._gl_build_push(gs, files, "implicitfast", dt, 1, 0)
    reset()
    for _ in range(n):
        scene.step()
    ours = observe()[0]
    m, q0, v0, obs, ctrl0 = wp._mj_build_push(files, "implicitfast", dt)
    init = S.mujoco_initial_states(m, q0, v0, 1)
    buf = np.empty((1, n, init.shape[1]))
    rollout.rollout(m, [mujoco.MjData(m)], init, np.tile(np.asarray(ctrl0, float), (1, n, 1)), nstep=n, state=buf)
    theirs = obs(buf[:, -1])[0]
    assert ours[0] > S.PUSH_BOX_POS[0] + 0.1, ours  # pushed
    assert abs(ours[0] - theirs[0]) < 3e-3, (ours, theirs)
    assert abs(ours[1] - theirs[1]) < 2e-3, (ours, theirs)
    assert abs(ours[2] - S.PUSH_BOX_SIZE / 2) < 1e-3 and abs(theirs[2] - S.PUSH_BOX_SIZE / 2) < 1e-3


# --- references -------------------------------------------------------------------------------------------------


def test_box_analytic_reference():
    t_stop = S.BOX_V0 / (S.BOX_MU * S.G)
    assert S.box_slide_analytic(t_stop) == pytest.approx(S.BOX_V0**2 / (2 * S.BOX_MU * S.G))
    assert S.box_slide_analytic(10.0) == pytest.approx(S.box_slide_analytic(t_stop))  # stays at rest
    assert S.box_slide_analytic(0.1) == pytest.approx(S.BOX_V0 * 0.1 - 0.5 * S.BOX_MU * S.G * 0.01)


def test_mujoco_and_pinocchio_read_the_same_panda_file(tmp_path):
    pytest.importorskip("mujoco")
    pytest.importorskip("pinocchio")
    files = wp._panda_files(tmp_path)
    ref = wp._panda_ref(files)
    m, q0, v0, observe, ctrl = wp._mj_build_arm("urdf", S.PANDA_ARM_HOME, np.zeros(7))(files, "RK4", 0.0025)
    assert m.nq == m.nv == 7 and ctrl is None
    assert not m.jnt_limited.any()
    res = wp.run_mj(wp.SCENES["panda"], files, [("RK4", 0.0025, 1)], 0, 1)
    err = wp._error(np.asarray(res["points"][0]["obs"]), ref.obs, "panda")
    # RK4's global error at this dt is ~1e-6 rad (bench_workprecision's full sweep): a wrong joint order, mass or
    # axis would be off by far more
    assert err < 1e-4


# --- stress verdicts ----------------------------------------------------------------------------------------------


def test_bisect_finds_the_threshold():
    dt, note = bs.bisect(lambda dt: dt <= 0.0123, 1e-4, 0.1, 12)
    assert 0.0123 / 1.01 < dt <= 0.0123
    assert bs.bisect(lambda dt: True, 1e-4, 0.1, 5)[0] == 0.1
    assert bs.bisect(lambda dt: False, 1e-4, 0.1, 5)[0] is None


def test_verdicts_fail_what_they_should():
    rest = [0.1] * 3
    assert not bs._impact_verdict([float("nan")] * 3, [1.0] * 3, rest, 0.01)["pass"]
    assert not bs._impact_verdict([-0.15, 0.05, 0.05], [5.0] * 3, rest, 0.01)["pass"]  # wholly below ground
    assert not bs._impact_verdict([0.05] * 3, [5.0] * 3, [0.1, -0.5, 0.1], 0.01)["pass"]  # ended up below: through
    assert not bs._impact_verdict([0.05] * 3, [25.0, 1.0, 1.0], rest, 0.01)["pass"]  # gained energy
    assert bs._impact_verdict([-0.05, 0.05, 0.05], [10.0] * 3, rest, 0.01)["pass"]
    assert not bs._chain_verdict(-10.0, -9.0, -20.0, 0.0)["pass"]  # energy rose 10 %
    assert not bs._chain_verdict(-10.0, -10.0, -20.0, 1.0)["pass"]  # still moving
    assert bs._chain_verdict(-10.0, -10.0, -20.0, 0.001)["pass"]
    a = 0.2
    assert not bs._ratio_verdict(np.array([0, 0, 0.1]), np.array([0.05, 0, 0.3]), 0.0, a)["pass"]  # slid off
    assert bs._ratio_verdict(np.array([0, 0, 0.0999]), np.array([0, 0, 0.2995]), 0.001, a)["pass"]
    assert not bs._stiff_verdict(0.1, 0.5, 0.09, -1e9)["pass"]  # still moving
    assert bs._stiff_verdict(0.09999, 0.001, 0.0999, -1e9)["pass"]


def test_mpm_stress_verdict_fails_what_it_should():
    good = dict(finite=True, hmin=0.31, jmin=0.04, vol_mean=1.0001, vol_dev=0.02, grid_mass=1.0, total=1.0, inside=True)
    assert bs._mpm_verdict(**good)["pass"]
    assert not bs._mpm_verdict(**{**good, "finite": False})["pass"]
    assert not bs._mpm_verdict(**{**good, "vol_mean": float("nan")})["pass"]
    assert not bs._mpm_verdict(**{**good, "vol_mean": 0.5})["pass"]  # flattened for good: volume lost
    assert not bs._mpm_verdict(**{**good, "vol_mean": 1.05})["pass"]  # gained 5 %
    assert not bs._mpm_verdict(**{**good, "grid_mass": 1.0 + 1e-9})["pass"]  # mass not conserved
    assert not bs._mpm_verdict(**{**good, "inside": False})["pass"]  # particles left the domain


# --- a run of the harness -------------------------------------------------------------------------------------


def _run_all(tmp_path, *args, timeout):
    cmd = [sys.executable, str(BENCH / "run_all.py"), "--out-dir", str(tmp_path), *args]
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, p.stderr[-3000:]
    text = (tmp_path / "results.md").read_text()
    data = json.loads((tmp_path / "results.json").read_text())
    return text, data


def _check_fault_row(r):
    """A fault row's verdicts from its raw figures, per side; MuJoCo has no MPM (soft rows: "-")."""
    F = bs.F
    for side in ("gl", "mj"):
        m = r.get(f"{side}_metrics")
        if m is None:
            assert side == "mj" and r["key"].startswith("soft") and r["mj_pass"] == "-", r
            continue
        if m.get("refused"):  # the library refused the step with a message: the fast row's accepted answer
            assert r["key"] == "fast" and r[f"{side}_pass"] == "PASS", r
            continue
        said = bool(m.get("said"))
        if not m.get("finite", False):
            assert r[f"{side}_pass"] == ("PASS" if said and r["key"] in ("fast", "heavy") else "FAIL"), r
            continue
        if r["key"].startswith("spin"):
            ok = m["dv"] < 1e-6 and m["dw_rel"] < 1e-6
        elif r["key"] == "fast":
            ok = (m["zmin"] > 0.0 and abs(m["zend"] - F.BOX / 2) < 0.01 and m["vend"] < 0.01) or said
        elif r["key"] == "heavy":
            ok = (m["sink"] < 0.01 and m["speed"] < 0.01) or said
        else:
            ok = m["inside"] == 0 and m["below_floor"] < F.SOFT_DX
        assert r[f"{side}_pass"] == ("PASS" if ok else "FAIL"), r


def _check_stress(data):
    """Every stress verdict equals its criterion applied here to the raw figures."""
    rows = data["stress"]["table"]
    assert rows
    for r in rows:
        if r["key"] == "mpm":
            m = r.get("gl_metrics") or {}
            ok = (m.get("finite", False) and m["inside"] and m["mass_err"] <= bs.MPM_MASS_TOL
                  and abs(m["vol_mean"] - 1.0) <= bs.MPM_VOLUME_TOL)
            assert r["gl_pass"] == ("PASS" if ok else "FAIL"), r
            assert r["mj"] == "MuJoCo has no MPM"
            assert r["cfl_dt"] == pytest.approx(0.9 * (1 / 64) / _wave_speed(3e5, 0.2, 1000.0) * bs.MPM_SUBSTEPS)
            continue
        if r["key"] in bs.F.GL_ROWS:  # the fault rows (benchmarks/stress_faults.py)
            _check_fault_row(r)
            continue
        for side in ("gl", "mj"):
            m = r.get(f"{side}_metrics") or {}
            if not m.get("finite", False):
                assert r[f"{side}_pass"] == "FAIL", r
                continue
            if r["key"] == "impact":
                ok = m["zmin"] > -0.1 and m["zend_err"] < 0.01 and m["rebound"] <= m["v_hit"]
            elif r["key"] == "energy":
                ok = m["max_drift"] <= bs.ENERGY_TOL
            elif r["key"] == "chain":
                ok = m["gain"] <= 0.01 and m["vmax"] < bs.CHAIN_REST_SPEED
            elif r["key"] == "stiff":
                ok = m["speed"] < bs.REST_SPEED and m["pen_mm"] < 1.0 and m["zmax_after"] < 0.2
            else:
                ok = m["speed"] < bs.REST_SPEED and m["drift"] < 0.01 and max(m["sink_l"], m["sink_h"]) < 0.01
            assert r[f"{side}_pass"] == ("PASS" if ok else "FAIL"), r
    for g in data["stress"].get("grad") or []:
        exploded = g["norm"] > bs.GRAD_EXPLODED
        warned = g["n_warnings"] > 0
        assert g["exploded"] == ("yes" if exploded else "no")
        assert g["verdict"].startswith("PASS" if exploded == warned else "FAIL"), g
        # the derivative is that of the simulation: central differences agree where they are meaningful
        if g["T"] <= 100:
            assert g["fd_rel"] < 1e-4, g
            assert g["mj_rel"] < 1e-3, g


@pytest.mark.slow
def test_run_all_smoke(tmp_path):
    """One row of each kind: work-precision (double pendulum, RK4, 1 env, genesis_lite + MuJoCo), two stress rows
    (stiff contact and the gradient norm), the MPM import check, and the headline built from them."""
    text, data = _run_all(tmp_path, "--quick", "--sections", "workprecision,stress,unused,headline",
                          "--scenes", "pendulum", "--integrators", "RK4", "--envs", "0",
                          "--stress-rows", "stiff,grad", "--unused-parts", "mpm", "--no-genesis", "--no-bisect",
                          timeout=900)
    for heading in ("## Machine", "## Headline", "## Work-precision", "## Stability under stress",
                    "## The cost of what a scene does not use"):
        assert heading in text
    # work-precision: both engines' RK4 runs with an error against the named reference
    pend = data["workprecision"]["pendulum"]
    assert "DOP853" in pend["reference"] and "DOP853" in text
    for engine in ("genesis_lite", "mujoco"):
        pts = pend["envs"]["1"][engine]["points"]
        assert pts and all(p["integrator"] == "RK4" and p["wall"] > 0 for p in pts)
        # RK4 at dt = 0.005 s on this pendulum: ~1e-8 rad against DOP853 (bench_integrators' convergence table)
        assert min(p["error"] for p in pts) < 1e-6
    # the same integrator, dt and model: genesis_lite and MuJoCo agree on the state, so on the error
    e_gl = sorted(p["error"] for p in pend["envs"]["1"]["genesis_lite"]["points"])
    e_mj = sorted(p["error"] for p in pend["envs"]["1"]["mujoco"]["points"])
    assert np.allclose(e_gl, e_mj, rtol=1e-3, atol=1e-12)
    _check_stress(data)
    mpm = data["unused"]["mpm"]
    assert len(mpm) == 2 and all("error" not in r for r in mpm)
    assert not any(r["imported_after_build"] for r in mpm)
    assert "rigid scene leaves MPM unimported" in text
    # the headline's equal-error row: met / NOT MET agrees with its ratio
    eq = [r for r in data["headline"] if r["goal"].startswith("at equal error")]
    assert len(eq) == 1, (data.get("equal_error"), data.get("workprecision", {}).get("pendulum"))
    assert eq[0]["met"] == ("met" if eq[0]["ratio"] <= 1.0 else "NOT MET")


@pytest.mark.slow
def test_run_all_mpm_rows(tmp_path):
    """genesis_lite's MPM rows of every other kind, small: the MPM section (125-particle cube, f32; real Genesis
    skipped, which its row and the headline say), the gradient section's MPM backward / forward and memory rows
    (125 particles, 5 steps), the stress row (the squeezed block, 0.5 s, not bisected) and the headline."""
    text, data = _run_all(tmp_path, "--quick", "--sections", "grad,stress,mpm,headline", "--grad-parts", "mpm",
                          "--stress-rows", "mpm", "--mpm-particles", "125", "--mpm-memory", "5,125", "--no-genesis",
                          "--no-bisect", timeout=900)
    for heading in ("## Headline", "## Gradient cost", "## Stability under stress", "## MPM: genesis_lite against real Genesis"):
        assert heading in text
    # the MPM section: a measured rate, no peer figure, and a table that says why
    (row,) = data["mpm"]["rows"]
    assert row["precision"] == "32" and row["n_particles"] == 125
    assert math.isfinite(row["gl_rate"]) and row["gl_rate"] > 0 and row["g_rate"] is None
    assert row["goal"] == "not measured" and "--no-genesis" in row["note"]
    assert "genesis_lite M particle-substeps/s" in text and ">= 1.5x Genesis" in text
    # the gradient section: backward / forward and memory with and without checkpointing
    (g,) = data["grad"]["mpm"]["ratio"]
    assert g["n_particles"] == 125 and g["steps"] == 20 and g["fwd_ms"] > 0 and g["bwd_ms"] > 0
    assert g["met"] == ("yes" if g["ratio"] <= 2.5 else "NO")
    mem = {m["ckpt"]: m for m in data["grad"]["mpm"]["memory"]}
    assert set(mem) == {"none", "10"} and all(m["horizon"] == 5 for m in mem.values())
    # without checkpoints torch keeps every step's particle state (x, v, C, F); with checkpoint_every = 10 only
    # the checkpoints are kept and the window is replayed in backward
    assert mem["none"]["saved_MiB"] >= 5 * mem["none"]["state_KiB"] / 1024 * 0.99
    assert mem["none"]["replayed"] == 0 and mem["10"]["replayed"] > 0
    assert mem["10"]["saved_MiB"] < mem["none"]["saved_MiB"]
    assert "MPM memory kept for backward" in text
    # the stress row: its verdict follows the criterion applied to its figures (see _check_stress)
    _check_stress(data)
    (st,) = data["stress"]["table"]
    assert st["key"] == "mpm" and st["gl_metrics"]["finite"] and st["gl_metrics"]["hmin"] < 0.4
    assert st["refused"], "genesis_lite's build should refuse a substep above the CFL limit"
    # the headline: MPM speed against Genesis (not measurable without it) and MPM backward / forward
    goals = {r["goal"]: r for r in data["headline"]}
    mpm_goal = next(r for k, r in goals.items() if k.startswith("MPM: >= 1.5x real Genesis"))
    assert mpm_goal["met"] == "not measured (no Genesis figure)"
    bf = next(r for k, r in goals.items() if k.startswith("backward <= 2.5x forward (MPM"))
    assert bf["met"] == ("met" if bf["ratio"] <= 2.5 else "NOT MET")


@pytest.mark.slow
def test_run_all_quick(tmp_path):
    """The whole --quick run: every section and table, plots beside results.md."""
    text, data = _run_all(tmp_path, "--quick", "--no-genesis", timeout=3600)
    for heading in ("## Headline", "## Stepping speed and build time", "## Work-precision", "## Gradient cost",
                    "## Stability under stress", "## The cost of what a scene does not use",
                    "## MPM: genesis_lite against real Genesis"):
        assert heading in text
    _check_stress(data)
    goals = {r["goal"].split(":")[0] for r in data["headline"]}
    assert any(g.startswith("Panda, 1024 envs") for g in goals)
    assert any(g.startswith("build") for g in goals)
    assert any(g.startswith("backward") for g in goals)
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return
    assert (tmp_path / "workprecision_1env.png").stat().st_size > 10_000
    assert (tmp_path / "workprecision_1024env.png").stat().st_size > 10_000


# --- Genesis's scripts: the recorded Genesis column (benchmarks/genesis_scripts.py) ----------------------------


def test_genesis_scripts_recorded_column_round_trip(tmp_path):
    """A results table's Genesis column (escaped pipes in error cells, several probes per script, a later
    table of another run ignored) is read back as the harness's own entries, and a table made with them
    says that the Genesis column is a recorded run."""
    import genesis_scripts as g

    md = "\n".join([
        "| script | ours | ours error (category: line) | s | Genesis | Genesis error | s | GS_RESULT ours | GS_RESULT Genesis | difference |",
        "|---|---|---|---|---|---|---|---|---|---|",
        "| pyramid | no | `X`: a \\| b | 8 | yes |  | 12 | - | boxes_mean_z=0.4577; top_box_z=0.1248 | - |",
        "| tower | yes |  | 59 | no | `Y`: ValueError: bad | 66 | top_box_z=3.249 | - | - |",
        "", "| pyramid | yes |  | 1 | yes |  | 1 | - | boxes_mean_z=9 | - |"])
    rec = g.recorded_from_markdown(md)
    assert set(rec) == {"pyramid", "tower"}
    assert rec["pyramid"]["results"] == {"boxes_mean_z": [0.4577], "top_box_z": [0.1248]}
    assert rec["pyramid"]["ok"] and rec["pyramid"]["wall_s"] == 12.0 and rec["pyramid"]["recorded"]
    assert not rec["tower"]["ok"] and rec["tower"]["error"] == "`Y`: ValueError: bad" and rec["tower"]["results"] == {}
    ours = {"pyramid": dict(script="pyramid", side="ours", ok=True, rc=0, timed_out=False, wall_s=8.0, error="",
                            category="", results={"boxes_mean_z": [0.4583], "top_box_z": [0.125]})}
    meta = {"machine": "m", "source": "s", "genesis_recorded": {"genesis_version": "genesis-world 0.4.5",
                                                                 "date": "2026-11-25", "file": "f.json"}}
    g.write_table({"ours": ours, "genesis": rec}, tmp_path / "t.md", meta)
    text = (tmp_path / "t.md").read_text()
    assert "**The Genesis column is a recorded run**, not today's: genesis-world 0.4.5, 2026-11-25" in text
    row = next(l for l in text.splitlines() if l.startswith("| pyramid |"))
    assert "boxes_mean_z: max abs diff 0.0006" in row


def test_chain_drop_mujoco_model_is_the_urdf_chain():
    """chain_drop.py's MuJoCo model (scenes.mujoco_from_urdf with a free base) against Pinocchio's reading of the
    URDF: the hinges' block of the mass matrix at a bent configuration (the free base's block depends on each library's frame for
    its velocity), the total mass, the limits, and links that collide with the ground only."""
    mujoco = pytest.importorskip("mujoco")
    pin = pytest.importorskip("pinocchio")
    import chain_drop as cd
    model = cd.mj_model(3.2)
    data = mujoco.MjData(model)
    qh = 0.5 * np.sin(1.0 + np.arange(30))  # every joint bent, none alike
    data.qpos[:] = np.concatenate([[0.0, 0.0, 3.2, 1.0, 0.0, 0.0, 0.0], qh])
    mujoco.mj_forward(model, data)
    m_mj = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, m_mj)
    pm = pin.buildModelFromUrdf(str(cd.URDF), pin.JointModelFreeFlyer())
    m_pin = pin.crba(pm, pm.createData(), np.concatenate([[0.0, 0.0, 3.2, 0.0, 0.0, 0.0, 1.0], qh]))
    m_pin = np.triu(m_pin) + np.triu(m_pin, 1).T
    assert model.nv == pm.nv == 36
    np.testing.assert_allclose(m_mj[6:, 6:], m_pin[6:, 6:], rtol=1e-9, atol=1e-15)
    assert model.body_mass.sum() == pytest.approx(sum(i.mass for i in pm.inertias))
    np.testing.assert_allclose(model.jnt_range[1:], np.tile([-3.1416, 3.1416], (30, 1)))
    plane = model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE
    assert plane.sum() == 1 and (model.geom_contype[~plane] & model.geom_conaffinity[~plane] == 0).all()
    assert (model.geom_contype[~plane] & model.geom_conaffinity[plane] == 1).all()


def test_mujoco_runs_longer_than_long_run_s_are_timed_once(tmp_path, monkeypatch):
    """bench_workprecision times a run `repeats` times, but once when its first timing exceeds LONG_RUN_S (the
    deep sweeps' runs of minutes); its warm-up is one rollout call, not a whole run. The observables must not
    depend on either."""
    pytest.importorskip("mujoco")
    wps = wp.SCENES["pendulum"]
    files = wps.files(tmp_path)
    pts = [("Euler", 0.005, 1)]
    many = wp.run_mj(wps, files, pts, 0, 3)["points"][0]
    monkeypatch.setattr(wp, "LONG_RUN_S", 0.0)
    once = wp.run_mj(wps, files, pts, 0, 3)["points"][0]
    assert len(many["walls"]) == 3 and len(once["walls"]) == 1
    assert once["obs"] == many["obs"] and once["steps"] == many["steps"] == 200


def test_step_convergence_variants_change_only_their_own_mujoco_model(tmp_path):
    """step_convergence.py --variant rebuilds MuJoCo's model of a scene with other solver or contact settings (to see
    whether a scene's non-convergence is those settings'): the variant's model has them, and neither the scene of
    bench_workprecision.SCENES nor a model built from it afterwards does."""
    pytest.importorskip("mujoco")
    import mujoco
    import step_convergence as sc

    wps = wp.SCENES["box"]
    files = wps.files(tmp_path)
    before = wps.mj_build(files, "Euler", 1e-3)[0]
    tight = sc.with_variant(wps, "tight").mj_build(files, "Euler", 1e-3)[0]
    pyr = sc.with_variant(wps, "pyramidal").mj_build(files, "Euler", 1e-3)[0]
    stiff = sc.with_variant(wps, "stiff").mj_build(files, "Euler", 1e-3)[0]
    after = wp.SCENES["box"].mj_build(files, "Euler", 1e-3)[0]
    assert tight.opt.tolerance == 1e-15 and tight.opt.iterations == 500
    assert pyr.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL
    assert np.all(stiff.geom_solref == [0.004, 1.0])
    for m in (before, after):
        assert m.opt.tolerance == before.opt.tolerance != 1e-15 and m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
        assert np.all(m.geom_solref[:, 0] == 0.02)
    assert wp.SCENES["box"].mj_build is wp._mj_build_box


@pytest.mark.parametrize("argv,message", [
    (["--variant", "tight", "--engine", "genesis_lite"], "--variant changes MuJoCo's model: give --engine mujoco"),
    (["--trace", "--scene", "quadruped"], "--trace follows the box of --scene push or box")])
def test_step_convergence_refuses_arguments_it_cannot_run(argv, message, monkeypatch, capsys):
    """step_convergence.py stops at once, naming the wrong argument and what to give, for a MuJoCo variant asked of
    genesis_lite and a box trace asked of a scene without the box: no run starts."""
    import step_convergence as sc

    monkeypatch.setattr(sys, "argv", ["step_convergence.py", *argv])
    monkeypatch.setattr(sc.W, "run_engine", lambda *a, **k: pytest.fail("a run started"))
    monkeypatch.setattr(sc, "trace", lambda *a, **k: pytest.fail("a trace started"))
    with pytest.raises(SystemExit) as e:
        sc.main()
    assert e.value.code == 2 and message in capsys.readouterr().err
