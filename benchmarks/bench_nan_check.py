"""Cost of the per-step NaN check (genesis_lite/nan_watch.py): time per scene step with the check on
(SimOptions(nan_policy="raise"), the default) and off ("off"), on the same scene, alternating.

    python benchmarks/bench_nan_check.py [--precision 32] [--quick] [--ref TREE] [--out benchmarks/results/nan_check.md]

Scenes (no-gradient path, default options otherwise): the stripped Panda (common.write_stripped_panda,
fixed base, no contacts, dt = 0.01 s) at 1 env and at 1,024 envs; an elastic MPM cube (bench_mpm.py's:
8,000 particles, E = 3e5 Pa, nu = 0.2, 64^3 grid on [0, 1]^3, dt = 2e-3 s, 10 substeps). Each
scene is built once; blocks of steps then alternate between the two policies (the policy is switched
on the built scene, so both sides run the same compiled kernels on the same memory), and the table
gives the medians of the per-step times of the blocks and the median of the per-pair ratios. On a
shared machine the difference of two step times is within their noise, so the check is also timed
alone: the scene's after-step call (the read, the comparison and, for MPM, the pass over the
particles), repeated on a stepped scene; "check alone / step off" is the overhead it adds to a step.

What "off" leaves out: for rigid scenes, the scene's per-step read of the count the fused step kernel
returns and its comparison (the kernel's own check, done while it copies the state, is compiled in
and runs in both columns); for MPM, the extra pass over the particles (kernel_count_nonfinite) and
its read.

The kernel-side part of the rigid check (the per-env record and the count the fused step kernel
returns) cannot be switched off; `--ref TREE` measures it against another checkout (e.g. `git archive
HEAD | tar -x -C TREE`, the code before the change, whose kernel kept one first-NaN step for all
envs and returned nothing): the fused step launches of the Panda's RigidSolver of each tree, in one
process, alternating blocks.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))
from common import machine_info, print_table, write_stripped_panda  # noqa: E402


def paired(scene, steps, repeats):
    """(median s/step on, median s/step off, median of per-pair ratios on/off)."""
    on, off = [], []
    for _ in range(2):  # warm-up: compile and caches
        scene.step()
    for r in range(repeats):
        order = (("raise", on), ("off", off)) if r % 2 == 0 else (("off", off), ("raise", on))
        for policy, out in order:
            scene._nan.policy = policy
            t0 = time.perf_counter()
            for _ in range(steps):
                scene.step()
            out.append((time.perf_counter() - t0) / steps)
    scene._nan.policy = "raise"
    ratios = [a / b for a, b in zip(on, off)]
    return statistics.median(on), statistics.median(off), statistics.median(ratios)


def check_alone(scene, calls, repeats):
    """Median s of the check itself, as the scene runs it after a step (nan_watch.NaNWatch.after_step),
    called on its own after a step: the same path (no state read when nothing failed)."""
    scene.step()
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(calls):
            scene._nan.after_step(scene.t)
        out.append((time.perf_counter() - t0) / calls)
    return statistics.median(out)


def solver_pair(ref_tree, urdf, n_envs, steps, repeats):
    """Median s per fused step launch of the Panda's RigidSolver from this tree and from ref_tree (its
    `solvers` package imported under another name), in this process, alternating blocks; and the
    median of the per-pair ratios. Both solvers are built as the scene builds them (default options,
    no contacts); what differs is only the solvers' code."""
    import importlib.util

    import genesis_lite as gs
    from genesis_lite.loaders import load_morph
    from solvers.rigid.solver import RigidSolver

    name = "ref_solvers"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, Path(ref_tree) / "solvers" / "__init__.py",
                                                      submodule_search_locations=[str(Path(ref_tree) / "solvers")])
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
    RefSolver = importlib.import_module(name + ".rigid.solver").RigidSolver
    opts = gs.options.RigidOptions()
    model = load_morph(gs.morphs.URDF(file=urdf, fixed=True), gs.materials.Rigid(), "panda")
    make = lambda cls: cls([model], max(n_envs, 1), 0.01, 1, int(opts.integrator), (0.0, 0.0, -9.81),  # noqa: E731
                           gs.ti_float, False, opts.enable_joint_limit, 1e4, 1e2,  # the limit springs: the ref tree's
                           contact_options=None, mimic=opts.enable_mimic,
                           specialize=opts.specialize_kernels)
    here, ref = make(RigidSolver), make(RefSolver)
    t_here, t_ref = [], []
    k = 0
    for s in (here, ref):
        for _ in range(5):
            k += 1
            s.step(k)
    for r in range(repeats):
        for s, out in ((here, t_here), (ref, t_ref)) if r % 2 == 0 else ((ref, t_ref), (here, t_here)):
            t0 = time.perf_counter()
            for _ in range(steps):
                k += 1
                s.step(k)
            out.append((time.perf_counter() - t0) / steps)
    ratios = [a / b for a, b in zip(t_here, t_ref)]
    return statistics.median(t_here), statistics.median(t_ref), statistics.median(ratios)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--precision", default="32", choices=["32", "64"])
    ap.add_argument("--quick", action="store_true", help="few repeats, 64 envs instead of 1,024 (a smoke run)")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "nan_check.md")
    ap.add_argument("--ref", type=Path, default=None, help="another checkout to compare the Panda step time with")
    a = ap.parse_args()

    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision=a.precision)
    urdf = str(write_stripped_panda())
    big = 64 if a.quick else 1024
    rows = []

    def panda(n_envs, steps, repeats):
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
        scene.add_entity(gs.morphs.URDF(file=urdf, fixed=True), name="panda")
        t0 = time.perf_counter()
        scene.build(n_envs=n_envs)
        scene.step()
        print(f"panda {n_envs} envs: built and first step in {time.perf_counter() - t0:.1f} s", flush=True)
        return ("Panda, rigid", n_envs, steps, repeats, scene)

    def mpm(steps, repeats):
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=10),
                         mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(1, 1, 1),
                                                           grid_density=64))
        scene.add_entity(gs.morphs.Box(pos=(0.5, 0.5, 0.4), size=(0.2, 0.2, 0.2)),
                         material=gs.materials.MPM.Elastic(E=3e5, nu=0.2))
        scene.build()
        scene.step()
        return ("MPM elastic cube, 8,000 particles", 1, steps, repeats, scene)

    q = a.quick
    for make in (lambda: panda(0, 200 if q else 1000, 5 if q else 21),
                 lambda: panda(big, 20 if q else 100, 5 if q else 21),
                 lambda: mpm(5 if q else 20, 3 if q else 11)):
        what, n_envs, steps, repeats, scene = make()
        t_on, t_off, ratio = paired(scene, steps, repeats)
        t_check = check_alone(scene, max(steps, 20), repeats)
        row = {"scene": what, "envs": max(n_envs, 1), "steps": f"{repeats} x {steps}", "on": t_on * 1e6,
               "off": t_off * 1e6, "pct": 100 * (ratio - 1), "check": t_check * 1e6,
               "share": 100 * t_check / t_off}
        print(row, flush=True)
        rows.append(row)
        del scene

    cols = [("scene", "scene", ""), ("envs", "envs", "d"), ("steps", "blocks x steps", ""),
            ("on", "check on, us/step", ".1f"), ("off", "check off, us/step", ".1f"),
            ("pct", "paired on/off - 1, %", "+.2f"), ("check", "the check alone, us", ".2f"),
            ("share", "check alone / step off, %", ".2f")]
    table = print_table(rows, cols)
    if a.ref is not None:
        ref_rows = []
        for n_envs, steps, repeats in ((0, 1000, 31), (big, 50, 31)):
            if q:
                steps, repeats = steps // 10, 5
            t_here, t_ref, ratio = solver_pair(a.ref, urdf, n_envs, steps, repeats)
            row = {"envs": max(n_envs, 1), "steps": f"{repeats} x {steps}", "here": t_here * 1e6, "ref": t_ref * 1e6,
                   "pct": 100 * (ratio - 1)}
            print(row, flush=True)
            ref_rows.append(row)
        table += ("\n\nThe rigid solver's fused step (the launch the scene makes once per step, kernel and launch "
                  f"path), this tree against `{a.ref}`, in one process, alternating blocks:\n\n" +
                  print_table(ref_rows, [("envs", "envs", "d"), ("steps", "blocks x steps", ""),
                                         ("here", "this tree, us/launch", ".2f"), ("ref", "ref tree, us/launch", ".2f"),
                                         ("pct", "paired this/ref - 1, %", "+.2f")]))
        off = {r["envs"]: r["off"] for r in rows if r["scene"].startswith("Panda")}
        check = {r["envs"]: r["check"] for r in rows if r["scene"].startswith("Panda")}
        lines = []
        for r in ref_rows:
            extra = check[r["envs"]] + r["here"] - r["ref"]
            lines.append(f"{r['envs']} env{'s' if r['envs'] > 1 else ''}: {check[r['envs']]:.2f} us (the check alone) "
                         f"{r['here'] - r['ref']:+.2f} us (the launch) = {extra:+.2f} us, "
                         f"{100 * extra / off[r['envs']]:+.2f} % of a step")
        table += "\n\nThe rigid check in all, per step: " + "; ".join(lines) + "."
    info = machine_info()
    text = (f"# Cost of the per-step NaN check (bench_nan_check.py)\n\n"
            f"`python benchmarks/bench_nan_check.py{' --quick' if q else ''} --precision {a.precision}`, "
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {info.get('cpu')}, {info.get('cores')} cores, "
            f"load {', '.join(f'{x:.1f}' for x in info.get('load', ()))} (a shared machine: other jobs ran at the same time).\n\n"
            + __doc__.split("\n\n", 2)[2].strip() + "\n\n" + table + "\n")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(text)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
