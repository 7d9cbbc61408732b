"""The MPM peer: real Genesis (`genesis-world`) stepping an elastic cube with its MPM solver on the CPU.

Runs in Genesis's own venv (never the project's: Genesis brings its own Taichi fork), one process per
precision (one gs.init per process):

    $GENESIS_PYTHON benchmarks/peer_genesis_mpm.py [--precision 32] [--particles 8000,27000] [--steps 50]

The scene: MPMOptions(lower_bound=(0, 0, 0), upper_bound=(1, 1, 1), grid_density=64) (so dx = 1/64 m and
Genesis's default particle size 0.01 m), SimOptions(dt=2e-3, substeps=10), gravity -9.81 z, one
gs.materials.MPM.Elastic() cube sampled on a regular lattice ("regular" sampler) with its centre at
(0.5, 0.5, 0.4): edge 0.2 m gives 20^3 = 8,000 particles, 0.3 m gives 27,000.
Reported per particle count:
- build_s: Scene() to the end of build() (the first scene of the process compiles the kernels);
- rate: particle-substeps/s, warm: n_particles * substeps * steps / seconds of `steps` scene.step() calls,
  median of `repeats` after a warm-up (each run starts from scene.reset());
- with --grad: a second scene built with requires_grad=True; forward = reset + 20 steps +
  `loss = (entity.get_state().pos ** 2).sum()`, backward = `loss.backward()`; medians of the times and of
  their ratio over `repeats` rollouts after a warm-up rollout.
Prints a human line per row on stderr and one JSON line on stdout.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

DT, SUBSTEPS = 2e-3, 10
CENTRE = (0.5, 0.5, 0.4)
PARTICLE_SIZE = 0.01  # m: Genesis's default for grid_density 64


def edge_for(n_particles: int) -> float:
    """Edge (m) of a cube holding about n_particles on the regular lattice of spacing PARTICLE_SIZE."""
    return round(n_particles ** (1.0 / 3.0)) * PARTICLE_SIZE


def build(gs, edge, requires_grad):
    t0 = time.perf_counter()
    scene = gs.Scene(
        sim_options=gs.options.SimOptions(dt=DT, substeps=SUBSTEPS, gravity=(0.0, 0.0, -9.81),
                                          requires_grad=requires_grad),
        mpm_options=gs.options.MPMOptions(lower_bound=(0.0, 0.0, 0.0), upper_bound=(1.0, 1.0, 1.0), grid_density=64),
        show_viewer=False,
    )
    cube = scene.add_entity(material=gs.materials.MPM.Elastic(sampler="regular"),
                            morph=gs.morphs.Box(pos=CENTRE, size=(edge, edge, edge)))
    scene.build()
    return scene, cube, time.perf_counter() - t0


def measure_rate(gs, edge, steps, repeats):
    import numpy as np

    scene, cube, build_s = build(gs, edge, False)
    n = cube.n_particles

    def once():
        scene.reset()
        t0 = time.perf_counter()
        for _ in range(steps):
            scene.step()
        dt = time.perf_counter() - t0
        pos = cube.get_particles_pos().cpu().numpy()
        if not np.all(np.isfinite(pos)):
            raise RuntimeError("Genesis MPM diverged")
        return dt

    t0 = time.perf_counter()
    once()
    first = time.perf_counter() - t0
    secs = [once() for _ in range(repeats)]
    rate = n * SUBSTEPS * steps / statistics.median(secs)
    return {"n_particles": n, "edge_m": edge, "build_s": build_s, "first_run_s": first, "rate": rate,
            "step_ms": 1e3 * statistics.median(secs) / steps, "repeats": repeats, "steps": steps}


def measure_grad(gs, edge, steps, repeats):
    import torch

    scene, cube, build_s = build(gs, edge, True)

    def once():
        scene.reset()
        t0 = time.perf_counter()
        for _ in range(steps):
            scene.step()
        state = cube.get_state()
        loss = (state.pos ** 2).sum()
        t1 = time.perf_counter()
        loss.backward()
        t2 = time.perf_counter()
        if not torch.isfinite(loss.detach()).all():
            raise RuntimeError("Genesis MPM rollout diverged")
        return t1 - t0, t2 - t1

    t0 = time.perf_counter()
    first = once()
    first_total = time.perf_counter() - t0
    runs = [once() for _ in range(repeats)]
    return {"grad_build_s": build_s, "grad_first_fwd_s": first[0], "grad_first_bwd_s": first[1],
            "grad_first_total_s": first_total, "fwd_s": statistics.median(r[0] for r in runs),
            "bwd_s": statistics.median(r[1] for r in runs), "bwd_over_fwd": statistics.median(r[1] / r[0] for r in runs),
            "grad_steps": steps}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--precision", default="32", choices=["32", "64"])
    ap.add_argument("--particles", default="8000,27000", help="comma-separated target particle counts")
    ap.add_argument("--steps", type=int, default=50, help="scene.step() calls per timed run (x substeps)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--grad", action="store_true", help="also time backward / forward of a 20-step rollout")
    ap.add_argument("--grad-steps", type=int, default=20)
    args = ap.parse_args()

    import genesis as gs

    t0 = time.perf_counter()
    gs.init(backend=gs.cpu, precision=args.precision, logging_level="warning")
    init_s = time.perf_counter() - t0
    rows = []
    for target in (int(x) for x in args.particles.split(",")):
        edge = edge_for(target)
        row = {"target": target, "precision": args.precision}
        try:
            row.update(measure_rate(gs, edge, args.steps, args.repeats))
            if args.grad:
                row.update(measure_grad(gs, edge, args.grad_steps, args.repeats))
        except Exception as e:  # one failing row leaves the others
            row["error"] = f"{type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''}"
        rows.append(row)
        msg = (f"Genesis MPM f{args.precision} {row.get('n_particles', target):,} particles: "
               + (f"{row['rate'] / 1e6:.2f} M particle-substeps/s, build {row['build_s']:.1f} s"
                  if "rate" in row else row.get("error", "")))
        if "bwd_over_fwd" in row:
            msg += f", backward/forward {row['bwd_over_fwd']:.2f} ({args.grad_steps} steps)"
        print(msg, file=sys.stderr, flush=True)
    print(json.dumps({"version": getattr(gs, "__version__", ""), "init_s": init_s, "dt": DT, "substeps": SUBSTEPS,
                      "grid_density": 64, "rows": rows}))


if __name__ == "__main__":
    main()
