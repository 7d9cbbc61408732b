"""Where the work-precision quadruped's step time goes (issue #24: "profile first").

The scene is bench_workprecision.py's quadruped (ANYmal B dropped on a plane from 0.62 m, PD kp 100, kv 5
holding the standing pose; its builder `_gl_build_quad` is imported), float64, dt = 5 ms with 1 substep, after
a warm-up that lands it (it then stands on its four feet). For each integrator (implicitfast, genesis_lite's
default and the work-precision sweep's first-order choice, and RK4) and each env count (1 and 1024) it measures,
each in a child process of its own (one gs.init per process):

1. the wall time of plain `scene.step()` (no gradients: one launch of the fused kernel `kernel_step_fused`),
   in a process without Taichi's kernel profiler, split into the kernel itself (timed by the profiler in the
   second process), the Python around the launch (the bare `step_core.kernel_step_fused` call), the solver's
   Python (`RigidSolver.step`, with the contact watch) and the scene's (`scene.step`), each as the wall time
   minus the kernel's recorded time, step by step, in the profiler's process; for a batch, also with one CPU
   thread (`gs.init(num_threads=1)`), to tell what the two threads gain;
2. the same step op by op with Taichi's kernel profiler on (`gs.init(kernel_profiler=True)`, which
   genesis_lite passes to `ti.init`): every dynamics stage as its own launch of the core's
   `kernel_dynamics_part(k, k + 1, ...)` (the kernels the gradient path uses, one stage each), the contact
   solve of the no-gradient path (`func_contact_solve`, the very function the fused kernel runs, in a kernel
   of this script), `kernel_integrate` and `kernel_finish` (copy-back and NaN check). The state advances
   through these launches exactly as through the fused step. Each stage's kernel time comes from the
   profiler's per-launch records; the launch overhead is the wall time of the launches minus their kernel time;
3. two side measurements that do not advance the state: the narrow-phase geometry alone
   (`func_slot_geometry` of every slot of an active pair, in a kernel of this script; the rest of the slot
   stage is the normal force law and its accumulation onto the links) and one plain factor-solve of the mass
   matrix (`kernel_mass_solve`), to tell how much of the contact solve its 2 to 4 factorisations are; and the
   gradient path's split of the contact solve (`ContactSolver.factor_solve`'s launches: the passes over every
   slot and the three solves, then the final factor-solve), which does more work than the no-gradient solve;
4. MuJoCo (the same URDF and floor, bench_contact.mujoco_quadruped; 1 env, the same integrator and dt):
   `mj_step`'s time, and the step's parts called one by one from Python (mj_fwdPosition .. mj_implicit /
   mj_RungeKutta), with mj_fwdPosition split into kinematics, mass matrix + factor, collision, constraint
   making (those sub-calls are repeated after the step: they do not advance the state).

Times are per step (all envs); minima over rounds of each round's mean, and the median of per-step walls.
The machine is shared: the file records the load (uptime) before and after.

    python benchmarks/quadruped_profile.py [--quick] [--out benchmarks/results/quadruped_profile.md]

--quick: fewer steps and rounds, implicitfast only (about 2 minutes; the full run about 8).
The "Reading" section at the end of the committed results file was written by hand from its run; a rerun
writes the measured sections only.
"""

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(HERE.parent))

DT = 5e-3  # s, 1 substep
WARM_S = 0.5  # s of simulated time before measuring: the robot has landed and stands

# dynamics stage -> category (the stage functions' names, core.DYNAMICS + contact.CONTACT_STAGES)
CATEGORY = {
    "func_forward_kinematics": "kinematics", "func_dof_subspace": "kinematics", "func_velocity": "kinematics",
    "func_dof_subspace_dot": "kinematics", "func_world_inertia": "kinematics",
    "func_link_inertia": "mass matrix (CRBA)", "func_composite_inertia": "mass matrix (CRBA)",
    "func_dof_momentum": "mass matrix (CRBA)", "func_mass_matrix": "mass matrix (CRBA)",
    "func_link_forces": "bias forces (RNEA)", "func_free_gyro": "bias forces (RNEA)",
    "func_accumulate_forces": "bias forces (RNEA)",
    "func_project_forces": "bias forces (RNEA)",
    "func_generalized_force": "actuation + joint limits",
    "func_geom_pose": "broad phase (geom poses + pair culling)", "func_broad_phase": "broad phase (geom poses + pair culling)",
    "func_contact_clear": "narrow phase + normal force law + accumulation",
    "func_contact_slots": "narrow phase + normal force law + accumulation",
    "func_contact_tree": "contact J^T f, J^T W J onto the dofs", "func_contact_dof": "contact J^T f, J^T W J onto the dofs",
    "func_contact_project": "contact J^T f, J^T W J onto the dofs",
    "contact_solve": "contact solve (passes + 2-4 factor-solves)",
    "integrate": "integration", "finish": "copy-back + NaN check",
}
ORDER = ["kinematics", "mass matrix (CRBA)", "bias forces (RNEA)", "actuation + joint limits",
         "broad phase (geom poses + pair culling)", "narrow phase + normal force law + accumulation",
         "contact J^T f, J^T W J onto the dofs", "contact solve (passes + 2-4 factor-solves)", "integration",
         "copy-back + NaN check"]


def uptime():
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return "?"


# ----------------------------------------------------------------------------------------- genesis_lite child


def _records():
    """The kernel profiler's records since the last clear, grouped into launches: [(kernel name, seconds)].
    On the CPU backend a record is one offloaded task (a top-level loop, or the serial code around them)
    named '<kernel instance>_kernel_<task index>_<kind>'; a launch is a run of tasks whose index grows."""
    from taichi.profiler.kernel_profiler import get_default_kernel_profiler

    p = get_default_kernel_profiler()
    p._update_records()
    out = []
    prev_name, prev_idx = None, None
    for r in p._traced_records:
        m = re.match(r"^(.*)_kernel_(\d+)_", r.name)
        name, idx = (m.group(1), int(m.group(2))) if m else (r.name, 0)
        if name == prev_name and idx > prev_idx:
            out[-1][1] += r.kernel_time * 1e-3
        else:
            out.append([name, r.kernel_time * 1e-3])
        prev_name, prev_idx = name, idx
    return out


def _clear():
    import taichi as ti

    ti.profiler.clear_kernel_profiler_info()


def robust_mean(v):
    """Mean without the preempted outliers (above 3 x the median + 2 us): the profiler's CPU times come in
    steps of ~1 us, so a mean (not a median) resolves sub-microsecond kernels."""
    cut = 3 * statistics.median(v) + 2e-6
    return float(np.mean([x for x in v if x <= cut]))


def child_gl(integrator, n_envs, steps, rounds, profile, threads=0):
    import taichi as ti
    import bench_workprecision as W
    import genesis_lite as gs
    from solvers.rigid.schedule import pack_span

    kw = {"kernel_profiler": True} if profile else {}
    if threads:
        kw["num_threads"] = threads
    gs.init(backend=gs.cpu, precision="64", logging_level="warning", **kw)
    files = W._quad_files(Path(tempfile.mkdtemp()))
    t0 = time.perf_counter()
    scene, reset, observe = W._gl_build_quad(gs, files, integrator, DT, 1, n_envs)
    reset()
    scene.step()
    sol = scene.sim.rigid_solver
    s, core, c = sol.step_core, sol.core, sol.contact
    out = {"integrator": integrator, "n_envs": n_envs, "steps": steps, "rounds": rounds, "profile": profile,
           "build_s": time.perf_counter() - t0, "specialized": bool(sol.specialized), "serial": bool(sol.serial),
           "n_slots": int(c.n_slots), "n_pairs": int(c.n_pairs), "n_dofs": int(sol.n_dofs)}
    for _ in range(int(round(WARM_S / DT))):
        scene.step()
    step_no = [10_000]

    def walls(fn, n):
        ts = []
        for _ in range(n):
            a = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - a)
        return ts

    def bare():
        step_no[0] += 1
        s.kernel_step_fused(step_no[0], pack_span(0, sol.n_ops, 1))

    def solver_step():
        step_no[0] += 1
        sol.step(step_no[0])

    # 1. the fused step: scene.step, solver.step, the bare launch, interleaved step by step (the same load)
    variants = (("scene.step", scene.step), ("solver.step", solver_step), ("bare launch", bare))
    if not profile:  # only scene.step's wall is read from the process without the profiler
        variants = variants[:1]
    fused = {k: [] for k, _ in variants}
    kern, over = [], {k: [] for k in fused}  # profiler on: the kernel's time, and wall - kernel, per step
    for _ in range(rounds):
        if profile:
            _clear()
        w = {k: [] for k in fused}
        for _ in range(steps):
            for key, fn in variants:
                a = time.perf_counter()
                fn()
                w[key].append(time.perf_counter() - a)
        for key in fused:
            fused[key].append(w[key])
        if profile:
            k = [t for name, t in _records() if name.startswith("kernel_step_fused")]
            assert len(k) == len(variants) * steps, (len(k), steps)
            kern += k
            for j, key in enumerate(fused):
                over[key] += [a - b for a, b in zip(w[key], k[j::len(variants)])]
    out["fused"] = {k: {"min": min(min(r) for r in v), "median": statistics.median([x for r in v for x in r]),
                        "round_means": [float(np.mean(r)) for r in v]} for k, v in fused.items()}
    if profile:
        out["fused"]["kernel"] = {"mean": robust_mean(kern), "min": min(kern), "median": statistics.median(kern)}
        out["fused"]["overhead"] = {k: statistics.median(v) for k, v in over.items()}
    if threads:
        return out

    # 2. the step op by op: one launch per dynamics stage, the no-gradient contact solve, integrate, finish
    from solvers.rigid.collision import func_slot_geometry
    from solvers.rigid.contact import func_contact_solve
    from solvers.rigid.schedule import OP_DYN, OP_INT, OP_SOLVE

    @ti.kernel
    def k_contact_solve(s: ti.template(), e: ti.i32):
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                func_contact_solve(s, i_b, e)

    sink = ti.field(s.dtype, shape=s.cap_envs)

    @ti.kernel
    def k_geometry(s: ti.template()):
        c = s.contact
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                acc = ti.cast(0.0, s.dtype)
                for i_p in range(c.n_pairs):
                    if c.pair_active[i_b, i_p] == 1:
                        for i_s in range(c.pair_s0[i_p], c.pair_s0[i_p + 1]):
                            pos, n, depth = func_slot_geometry(s, i_b, i_s)
                            acc += depth + pos.sum() + n.sum()
                sink[i_b] = acc

    names = [getattr(f, "__name__", str(f)) for f in s.dynamics_stages]

    def run_ops(labels, dynamics, solve):
        """One step of the schedule's ops, each op a launch of its own: dynamics(e, src, h, labels) and
        solve(e, labels) launch (and label) the evaluation and solve ops, integration and finish as the
        fused step does them."""
        step_no[0] += 1
        for kind_op, kind, e, base, src, dst, h in sol.ops:
            if kind_op == OP_DYN:
                dynamics(e, src, h, labels)
            elif kind_op == OP_SOLVE:
                solve(e, labels)
            elif kind_op == OP_INT:
                core.kernel_integrate(kind, e, base, src, dst, h)
                labels.append("integrate")
        core.kernel_finish(step_no[0], 1)
        labels.append("finish")

    def dynamics_by_stage(e, src, h, labels):
        for k in range(len(names)):
            s.kernel_dynamics_part(k, k + 1, e, src, h)
            labels.append(names[k])

    def no_grad_solve(e, labels):
        k_contact_solve(s, e)
        labels.append("contact_solve")

    def dynamics_whole(e, src, h, labels):
        s.kernel_dynamics(e, src, h)
        labels.append("dynamics (all stages)")

    def grad_solve(e, labels):
        """The solve op as ContactSolver.factor_solve's launches (the gradient path's)."""
        for which in ("solve_candidates", "relinearise_pass", "solve_normal", "coulomb_pass",
                      "solve_coulomb", "friction_pass"):
            c.kernel_run(s, which)
            labels.append(which)
        s.kernel_mass_solve(e, False)
        labels.append("final factor-solve")
        c.kernel_report(s, e)
        labels.append("report")

    def op_by_op(labels):
        run_ops(labels, dynamics_by_stage, no_grad_solve)

    def grad_path_solve(labels):
        """One step whose solve op runs as ContactSolver.factor_solve's launches (the gradient path's)."""
        run_ops(labels, dynamics_whole, grad_solve)

    def side(labels):
        """Measurements that leave the state as it is: the narrow-phase geometry, one factor-solve of M."""
        k_geometry(s)
        labels.append("narrow-phase geometry alone")
        s.kernel_mass_solve(sol.n_evals - 1, False)  # recomputes the last evaluation's qacc from its M, force
        labels.append("one factor-solve of M")

    def measure(fn, n):
        """Kernel time per step of each launch label (the median over steps, all rounds), their sum, and the
        step's wall time (median over steps), with the kernel profiler on."""
        for _ in range(3):  # compiles
            fn([])
        per_step, lw, per_launch = {}, [], None
        for _ in range(rounds):
            labels = []
            _clear()
            for _ in range(n):
                a = time.perf_counter()
                fn(labels)
                lw.append(time.perf_counter() - a)
            recs = [r for r in _records() if not r[0].startswith("snode_")]
            if len(recs) != len(labels):
                raise RuntimeError(f"{len(recs)} profiler launches for {len(labels)} launches made")
            per_launch = len(labels) // n
            for i in range(n):
                step = {}
                for lab, (_, t) in zip(labels[i * per_launch:(i + 1) * per_launch],
                                       recs[i * per_launch:(i + 1) * per_launch]):
                    step[lab] = step.get(lab, 0.0) + t
                for lab, t in step.items():
                    per_step.setdefault(lab, []).append(t)
        kernel = {lab: robust_mean(v) for lab, v in per_step.items()}
        return {"kernel": kernel, "kernel_total": sum(kernel.values()), "wall_median": statistics.median(lw),
                "launches": per_launch, "names_order": list(kernel)}

    if not profile:  # the op-by-op step's wall without the profiler's cost per launch
        for _ in range(3):
            op_by_op([])
        ts = [walls(lambda: op_by_op([]), steps) for _ in range(rounds)]
        out["op_by_op_wall"] = {"median": statistics.median([x for r in ts for x in r]),
                                "min_round_mean": min(float(np.mean(r)) for r in ts)}
        out["z"] = float(observe()[:, 2].mean())
        return out
    out["op_by_op"] = measure(op_by_op, steps)
    out["side"] = measure(side, steps)
    try:
        out["grad_path"] = measure(grad_path_solve, steps)
    except Exception as exc:  # noqa: BLE001 - reported, not fatal
        out["grad_path_error"] = f"{type(exc).__name__}: {exc}"
    # the fused step again, after the op-by-op runs (drift of the state or of the machine's load)
    again = walls(bare, steps)
    out["fused_after"] = {"min": min(again), "median": statistics.median(again)}
    out["z"] = float(observe()[:, 2].mean())
    out["n_on"] = float(c.n_on.to_numpy()[:max(n_envs, 1)].mean())
    return out


# ----------------------------------------------------------------------------------------------- MuJoCo child


def child_mj(integrator, steps, rounds):
    import mujoco
    import bench_workprecision as W

    files = W._quad_files(Path(tempfile.mkdtemp()))
    m, q0, v0, _, target = W._mj_build_quad(files, integrator, DT)
    d = mujoco.MjData(m)
    d.qpos[:] = np.atleast_2d(q0)[0]  # start 0 (the batched work-precision rows' others: W.quad_starts)
    d.qvel[:] = v0
    d.ctrl[:] = target
    for _ in range(int(round(WARM_S / DT))):
        mujoco.mj_step(m, d)
    integ = {"Euler": mujoco.mj_Euler, "implicitfast": mujoco.mj_implicit, "RK4": None}[integrator]
    out = {"integrator": integrator, "z": None}
    step_w = []
    for _ in range(rounds):
        ts = []
        for _ in range(steps):
            a = time.perf_counter()
            mujoco.mj_step(m, d)
            ts.append(time.perf_counter() - a)
        step_w.append(ts)
    out["mj_step"] = {"min": min(min(r) for r in step_w), "median": statistics.median([x for r in step_w for x in r]),
                      "min_round_mean": min(float(np.mean(r)) for r in step_w)}
    # the step's parts one by one (mj_step's order; RK4 runs mj_RungeKutta, which calls mj_forward itself
    # for its later stages, so the parts are those of the first stage plus the rest under "integration")
    parts = [("bookkeeping (checks, sensors, energy)", lambda: (mujoco.mj_checkPos(m, d), mujoco.mj_checkVel(m, d))),
             ("position stage (mj_fwdPosition)", lambda: mujoco.mj_fwdPosition(m, d)),
             ("bookkeeping (checks, sensors, energy)", lambda: (mujoco.mj_sensorPos(m, d), mujoco.mj_energyPos(m, d))),
             ("velocity stage (mj_fwdVelocity: bias forces, passive)", lambda: mujoco.mj_fwdVelocity(m, d)),
             ("bookkeeping (checks, sensors, energy)", lambda: (mujoco.mj_sensorVel(m, d), mujoco.mj_energyVel(m, d))),
             ("actuation + acceleration (mj_fwdActuation, mj_fwdAcceleration)",
              lambda: (mujoco.mj_fwdActuation(m, d), mujoco.mj_fwdAcceleration(m, d))),
             ("constraint solve (mj_fwdConstraint)", lambda: mujoco.mj_fwdConstraint(m, d)),
             ("bookkeeping (checks, sensors, energy)", lambda: (mujoco.mj_sensorAcc(m, d), mujoco.mj_checkAcc(m, d)))]
    if integ is not None:
        parts.append(("integration", lambda: integ(m, d)))
    else:
        parts = [("RK4 step (mj_RungeKutta, 4 stages, forward included)", lambda: mujoco.mj_RungeKutta(m, d, 4))]
    sub = [("  kinematics (mj_kinematics, mj_comPos)", lambda: (mujoco.mj_kinematics(m, d), mujoco.mj_comPos(m, d))),
           ("  mass matrix + factor (mj_makeM, mj_factorM)", lambda: (mujoco.mj_makeM(m, d), mujoco.mj_factorM(m, d))),
           ("  collision (broad + narrow, mj_collision)", lambda: mujoco.mj_collision(m, d)),
           ("  constraints (mj_makeConstraint, mj_projectConstraint)",
            lambda: (mujoco.mj_makeConstraint(m, d), mujoco.mj_projectConstraint(m, d)))]
    res = []
    ncon = []
    for _ in range(rounds):
        per = {}
        for _ in range(steps):
            for lab, fn in parts + sub:
                a = time.perf_counter()
                fn()
                per[lab] = per.get(lab, 0.0) + (time.perf_counter() - a) / steps
            ncon.append(d.ncon)
        res.append(per)
    out["parts"] = {lab: min(r[lab] for r in res) for lab in res[0]}
    out["parts_order"] = list(res[0])
    out["sub_labels"] = [lab for lab, _ in sub]
    out["ncon"] = float(np.mean(ncon))
    out["z"] = float(d.qpos[2])
    return out


# --------------------------------------------------------------------------------------------------- report


def ms(x):
    return f"{x * 1e3:.3f}"


def fmt(x, n):
    """Seconds as us (1 env) or ms (a batch)."""
    return f"{x * 1e6:.1f}" if n == 1 else f"{x * 1e3:.2f}"


def table_gl(r, prof, lines, one=None):
    n = r["n_envs"]
    u = "us" if n == 1 else "ms"
    f = r["fused"]
    kern = prof["fused"]["kernel"]["mean"]
    lines += [f"### {r['integrator']}, {n} env{'s' if n > 1 else ''}"
              f" ({'specialised core, ' if prof['specialized'] else ''}{'serial' if prof['serial'] else 'parallel'}"
              f" env loop; {prof['n_pairs']} geom pairs, {prof['n_slots']} slots, {prof['n_on']:.1f} slots in "
              f"contact per env; base z {prof['z']:.3f} m)", ""]
    # 1. the fused step and the Python around it
    tot = f["scene.step"]["median"]
    ov = prof["fused"]["overhead"]
    pf = prof["fused"]
    lines += [f"**Fused step**, `scene.step()`: median {fmt(tot, n)} {u} per step (min {fmt(f['scene.step']['min'], n)}) "
              f"without the kernel profiler; with it, {fmt(pf['scene.step']['median'], n)}. The split, from the "
              f"profiler's run (per step: wall minus the kernel's recorded time, median over steps, kernel: mean; the "
              f"profiler's own cost per launch is in the launch row; the last column: the same from the minima of "
              f"the walls and of the kernel's time, which a loaded machine disturbs least):",
              "", f"| part | {u} per step | share |", "| --- | --- | --- |"]
    mins = {k: pf[k]["min"] for k in ("scene.step", "solver.step", "bare launch")}
    rows = [("kernel_step_fused (the whole step's computation)", kern, pf["kernel"]["min"]),
            ("launch of the kernel (bare call - kernel)", ov["bare launch"], mins["bare launch"] - pf["kernel"]["min"]),
            ("RigidSolver.step's Python (contact watch)", ov["solver.step"] - ov["bare launch"],
             mins["solver.step"] - mins["bare launch"]),
            ("scene.step's Python (simulator, NaN bookkeeping)", ov["scene.step"] - ov["solver.step"],
             mins["scene.step"] - mins["solver.step"])]
    rows = [(lab, max(t, 0.0), max(m, 0.0)) for lab, t, m in rows]
    sm = sum(t for _, t, _ in rows)
    lines[-2] = lines[-2].replace("| share |", "| share | from minima |")
    lines[-1] = lines[-1] + " --- |"
    for lab, t, m in rows:
        lines.append(f"| {lab} | {fmt(t, n)} | {100 * t / sm:.0f}% | {fmt(m, n)} |")
    lines.append(f"| **sum** | **{fmt(sm, n)}** | 100% | {fmt(sum(m for _, _, m in rows), n)} |")
    if n > 1:
        lines.append(f"| per env-step (scene.step without profiler / {n}) | {tot / n * 1e6:.2f} us | |")
    lines.append("")
    if one is not None:
        t1 = one["fused"]["scene.step"]["median"]
        lines += [f"With one CPU thread (`gs.init(num_threads=1)`) the same step takes {fmt(t1, n)} {u} "
                  f"({t1 / n * 1e6:.2f} us per env-step; 2 threads: {tot / t1 * 100:.0f}% of that time).", ""]
    # 2. op by op
    o = prof["op_by_op"]
    cat = {}
    for lab, t in o["kernel"].items():
        k = CATEGORY.get(lab, lab)
        cat[k] = cat.get(k, 0.0) + t
    ks = o["kernel_total"]
    wall = r["op_by_op_wall"]["median"]
    launch = max(wall - ks, 0.0)
    lines += [f"**Op by op** ({o['launches']} launches per step; kernel time per stage from the kernel profiler, "
              f"mean over steps without preempted outliers; the last column scales the stage's share of the op-by-op kernel sum to the fused "
              f"kernel's {fmt(kern, n)} {u}, an estimate of its time inside the fused step):",
              "", f"| stage | {u} per step (op by op) | share of kernel sum | est. {u} in the fused kernel |",
              "| --- | --- | --- | --- |"]
    for k in ORDER + [k for k in cat if k not in ORDER]:
        if k in cat:
            lines.append(f"| {k} | {fmt(cat[k], n)} | {100 * cat[k] / ks:.1f}% | {fmt(kern * cat[k] / ks, n)} |")
    lines.append(f"| **kernel sum** | **{fmt(ks, n)}** | 100% | {fmt(kern, n)} |")
    lines.append(f"| Python launch overhead (op-by-op wall without profiler - kernel sum) | {fmt(launch, n)} | | |")
    lines.append(f"| **op-by-op wall** (no profiler; {fmt(o['wall_median'], n)} with it) | **{fmt(wall, n)}** | | |")
    lines += ["", f"The op-by-op kernels sum to {ks / kern:.2f} x the fused kernel ({fmt(ks, n)} vs {fmt(kern, n)} {u}); "
              f"with launches, the op-by-op step takes {wall / tot:.2f} x the fused `scene.step` ({fmt(wall, n)} vs "
              f"{fmt(tot, n)} {u}). Fused launch again after the op-by-op runs (profiler on): median "
              f"{fmt(prof['fused_after']['median'], n)} {u}.", ""]
    sd = prof["side"]["kernel"]
    geo = sd["narrow-phase geometry alone"]
    slots = o["kernel"].get("func_contact_slots", 0.0)
    fs = sd["one factor-solve of M"]
    lines += [f"Side measurements (kernel time, {u} per step): the narrow-phase geometry alone (every slot of an active "
              f"pair) {fmt(geo, n)}, of the slot stage's {fmt(slots, n)} (the rest is the speculative-contact "
              f"prediction, the normal force law and its accumulation onto the links); one plain factor-solve of M "
              f"{fmt(fs, n)} (the contact solve, {fmt(o['kernel'].get('contact_solve', 0.0), n)}, factors 2 to 4 "
              f"times per evaluation, {'4 evaluations' if r['integrator'] == 'RK4' else '1 evaluation'} per step).", ""]
    lines.append("<details><summary>per-stage kernel times (op by op), and the gradient path's split of the "
                 "contact solve</summary>")
    lines += ["", f"| kernel (stage) | {u} per step |", "| --- | --- |"]
    for lab in o["names_order"]:
        lines.append(f"| {lab} | {fmt(o['kernel'][lab], n)} |")
    lines.append("")
    g = prof.get("grad_path")
    if g is not None:
        lines += ["The gradient path's solve op (ContactSolver.factor_solve: passes over every slot, three solves, "
                  "the final factor-solve; more work than the no-gradient solve above):", "",
                  f"| launch | {u} per step |", "| --- | --- |"]
        for lab in g["names_order"]:
            lines.append(f"| {lab} | {fmt(g['kernel'][lab], n)} |")
        lines.append(f"| kernel sum / wall (profiler on) | {fmt(g['kernel_total'], n)} / {fmt(g['wall_median'], n)} |")
    else:
        lines.append(f"Gradient path's solve split: not measured ({prof.get('grad_path_error')}).")
    lines += ["", "</details>", ""]
    return tot, kern, o, cat


def table_mj(r, lines):
    st = r["mj_step"]
    parts = r["parts"]
    main = [k for k in r["parts_order"] if k not in r["sub_labels"]]
    tot = sum(parts[k] for k in main)
    lines += [f"### MuJoCo {r['integrator']}, 1 env ({r['ncon']:.1f} contacts; base z {r['z']:.3f} m)", "",
              f"`mj_step`: median {fmt(st['median'], 1)} us, min {fmt(st['min'], 1)} us per step. Its parts called "
              f"one by one from Python (each call adds ~0.3-1 us of Python; minima of round means):",
              "", "| part | us per step | share of the parts' sum |", "| --- | --- | --- |"]
    for k in main:
        lines.append(f"| {k} | {fmt(parts[k], 1)} | {100 * parts[k] / tot:.0f}% |")
        if k.startswith("position stage"):
            for s in r["sub_labels"]:
                lines.append(f"| {s} (repeated after the step) | {fmt(parts[s], 1)} | ({100 * parts[s] / tot:.0f}%) |")
    lines += [f"| **sum of the parts** | **{fmt(tot, 1)}** | 100% |", ""]
    return st["median"]


def run_child(kind, args_list, timeout=600):
    cmd = [sys.executable, __file__, "--child", kind] + [str(a) for a in args_list]
    env = dict(os.environ)
    env["PYTHONPATH"] = str(HERE.parent) + os.pathsep + env.get("PYTHONPATH", "")
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"child {kind} {args_list} failed:\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps and rounds, implicitfast only")
    ap.add_argument("--out", default=str(HERE / "results" / "quadruped_profile.md"))
    ap.add_argument("--envs", default="1,1024")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        kind = args.child[0]
        if kind == "gl":
            integ, n, steps, rounds, prof, threads = args.child[1:]
            res = child_gl(integ, int(n), int(steps), int(rounds), prof == "1", int(threads))
        else:
            integ, steps, rounds = args.child[1:]
            res = child_mj(integ, int(steps), int(rounds))
        print("RESULT " + json.dumps(res), flush=True)
        return
    integrators = ["implicitfast"] if args.quick else ["implicitfast", "RK4"]
    envs = [int(x) for x in args.envs.split(",")]
    t0 = time.time()
    load0 = uptime()
    lines = ["# Quadruped step profile (issue #24)", "",
             "`benchmarks/quadruped_profile.py" + (" --quick" if args.quick else "") + "`: the work-precision "
             "quadruped (ANYmal B on a plane, PD holding the standing pose), float64, genesis_lite on Taichi's CPU "
             f"backend, dt = {DT * 1e3:g} ms, 1 substep, measured after {WARM_S} s of simulated time (standing). "
             "See the script's docstring for what each number is. Times are per step (all envs): us for 1 env, ms "
             "for a batch.", "",
             f"Load at start: `{load0}` (2 cores, shared with other runs: the numbers are noisy; medians over steps "
             "are reported, and means without preempted outliers for the profiler's ~1 us-grained kernel times).", ""]
    summary = []
    for integ in integrators:
        steps_1, steps_b = (200, 40) if args.quick else (400, 100 if integ != "RK4" else 50)
        rounds = 2 if args.quick else 3
        lines += [f"## {integ}", ""]
        for n in envs:
            steps = steps_1 if n == 1 else steps_b
            print(f"[{time.time() - t0:.0f}s] genesis_lite {integ} {n} envs", flush=True)
            plain = run_child("gl", [integ, n, steps, rounds, 0, 0])
            prof = run_child("gl", [integ, n, steps, rounds, 1, 0])
            one = run_child("gl", [integ, n, steps, rounds, 0, 1]) if n > 1 else None
            tot, kern, o, cat = table_gl(plain, prof, lines, one)
            summary.append((integ, n, tot, kern, o, cat))
        if 1 in envs:
            print(f"[{time.time() - t0:.0f}s] mujoco {integ}", flush=True)
            try:
                mj = run_child("mj", [integ, 2000 if not args.quick else 1000, rounds])
                t_mj = table_mj(mj, lines)
                summary.append((integ, "mujoco", t_mj, None, None, None))
            except Exception as exc:  # noqa: BLE001
                lines += [f"MuJoCo: not measured ({exc})", ""]
    lines += ["## Summary", "", "| integrator | envs | scene.step ms | fused kernel ms | op-by-op kernel sum ms | "
              "largest stages (share of the op-by-op kernel sum) |", "| --- | --- | --- | --- | --- | --- |"]
    for integ, n, tot, kern, o, cat in summary:
        if n == "mujoco":
            lines.append(f"| {integ} | MuJoCo, 1 | {ms(tot)} (mj_step) | | | |")
            continue
        big = sorted(cat, key=cat.get, reverse=True)[:3]
        lines.append(f"| {integ} | {n} | {ms(tot)} | {ms(kern)} | {ms(o['kernel_total'])} | "
                     + "; ".join(f"{b} {100 * cat[b] / o['kernel_total']:.0f}%" for b in big) + " |")
    lines += ["", f"Load at end: `{uptime()}`. Total wall time {time.time() - t0:.0f} s.", ""]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
