"""Energy drift and convergence order of the rigid integrators on the frictionless double pendulum.

    python benchmarks/bench_integrators.py [--t-end 10] [--dts 0.01 0.005 0.001] [--no-convergence]
                                           [--out benchmarks/results/integrators.md] [--plot out.png]

The pendulum is assets/urdf/double_pendulum.urdf (two 1 kg point masses on 1 m rods), fixed base,
no damping / armature / friction, joint limits and collisions off, released from q = (0.9, -0.6) rad,
q' = (0, 0.8) rad/s. Its total energy E = kinetic + potential (potential -sum m g.c, zero at the
pivot height) is conserved by the exact flow; for each integrator (Euler, implicitfast, RK4) and dt
the table gives, over t_end seconds:
- max |E - E0| / |E0| over every step, and the final drift (E_end - E0) / |E0|;
- the wall time of the stepping loop alone (energy reads and the build are not timed) and steps/s.
Second table: the convergence order of q(1 s) against a DOP853 + Pinocchio reference, the same
measurement as tests/test_integrators.py (whose helpers it uses).
A PNG of |E - E0| / |E0| against time is written when matplotlib is installed (--plot).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(ROOT))  # genesis_lite without an install
sys.path.insert(2, str(ROOT / "tests"))
from common import print_table  # noqa: E402

INTEGRATORS = ("Euler", "implicitfast", "RK4")


def energy_run(integrator: str, dt: float, t_end: float):
    """Energy history of one run; returns a result row and (t, rel. drift) arrays for the plot."""
    import test_integrators as ti_

    scene, pend = ti_.build(integrator, dt)
    pend.set_dofs_position(ti_.Q0)
    pend.set_dofs_velocity(ti_.V0)
    scene.step()  # compile outside the timed loop, then start again
    scene.reset()
    pend.set_dofs_position(ti_.Q0)
    pend.set_dofs_velocity(ti_.V0)
    n = int(round(t_end / dt))
    e0 = pend.get_total_energy().item()
    # the reference's energy of the same state (Pinocchio leaves the fixed base out: it sits at z = 0)
    ref = ti_.PendulumReference()
    e0_pin = ref.energy(ti_.Q0, ti_.V0)
    energies = np.empty(n)
    stepping = 0.0
    for i in range(n):
        t0 = time.perf_counter()
        scene.step()
        stepping += time.perf_counter() - t0
        energies[i] = pend.get_total_energy().item()
    rel = (energies - e0) / abs(e0)
    row = dict(integrator=integrator, dt=dt, steps=n, max_drift=float(np.abs(rel).max()),
               final_drift=float(rel[-1]), wall=stepping, rate=n / stepping,
               e0=e0, e0_err=abs(e0 - e0_pin))
    return row, (dt * np.arange(1, n + 1), np.abs(rel))


def _git_label() -> str:
    """The commit measured (read-only git queries), '+ uncommitted changes' when the tree is dirty."""
    import subprocess

    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "no git checkout"
    return f"commit {rev}" + (" + uncommitted changes" if dirty else "")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-end", type=float, default=10.0, help="simulated seconds per run (default 10)")
    ap.add_argument("--dts", type=float, nargs="+", default=[0.01, 0.005, 0.001])
    ap.add_argument("--no-convergence", action="store_true", help="skip the convergence table")
    ap.add_argument("--label", default=None, help="what code was measured (default: the git commit, if any)")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "integrators.md")
    ap.add_argument("--plot", type=Path, default=HERE / "results" / "integrators_energy.png",
                    help="PNG of the energy drift (written only when matplotlib is installed)")
    args = ap.parse_args()

    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")
    import test_integrators as ti_

    rows, curves = [], {}
    for integ in INTEGRATORS:
        for dt in args.dts:
            print(f"{integ:>12} dt={dt:g}: {int(round(args.t_end / dt))} steps ...", flush=True)
            row, curve = energy_run(integ, dt, args.t_end)
            rows.append(row)
            curves[(integ, dt)] = curve
    assert max(r["e0_err"] for r in rows) < 1e-9, "our E0 disagrees with Pinocchio's"
    header = (f"# Rigid integrators on the frictionless double pendulum\n\n"
              f"genesis_lite {gs.__version__} ({args.label or _git_label()}), float64, Taichi CPU backend. "
              f"q0 = {ti_.Q0.tolist()} rad, v0 = {ti_.V0.tolist()} rad/s, E0 = {rows[0]['e0']:.6f} J "
              f"(equal to Pinocchio's to {max(r['e0_err'] for r in rows):.1e} J).")
    text = [header]
    text.append(print_table(rows, [
        ("integrator", "integrator", ""), ("dt", "dt (s)", "g"), ("steps", "steps", "d"),
        ("max_drift", "max abs(E - E0) / abs(E0)", ".3e"), ("final_drift", "final (E - E0) / abs(E0)", "+.3e"),
        ("wall", "wall time (s)", ".3f"), ("rate", "steps/s", ".0f")],
        title=f"## Energy drift over {args.t_end:g} s (wall time: the stepping loop only)"))

    if not args.no_convergence:
        conv = []
        for integ in INTEGRATORS:
            print(f"convergence of {integ} ...", flush=True)
            pts, order = ti_.convergence(integ)
            for dt, err in pts:
                conv.append(dict(integrator=integ, dt=dt, err=err, order=None))
            conv.append(dict(integrator=integ, dt=None, err=None, order=order))
        text.append(print_table(conv, [
            ("integrator", "integrator", ""), ("dt", "dt (s)", ".6f"), ("err", "max abs(q - q_ref) at t = 1 s", ".3e"),
            ("order", "fitted order", ".2f")],
            title="## Convergence of q(1 s) against DOP853 (rtol = atol = 1e-12) on Pinocchio's dynamics"))

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(text) + "\n")
    print(f"\nwrote {args.out}")

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no plot", file=sys.stderr)
        return
    fig, ax = plt.subplots(figsize=(8, 5))
    for (integ, dt), (t, rel) in curves.items():
        ax.semilogy(t, np.maximum(rel, 1e-17), label=f"{integ}, dt={dt:g}")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("|E - E0| / |E0|")
    ax.set_title("double pendulum: energy drift")
    ax.legend(fontsize=8)
    args.plot.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.plot, dpi=120, bbox_inches="tight")
    print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
