"""A bare textbook MLS-MPM kernel in Taichi: the peer that bench_mpm.py measures genesis_lite's MPM against.

    python benchmarks/bare_mpm.py [--quick] [--threads N] [--precision 32|64] [--particles 8000] [--scene cube|filled]

The scene of bench_mpm.py's worker: an elastic cube (E = 3e5 Pa, nu = 0.2, rho = 1000 kg/m^3, fixed-corotated)
of particles on the regular lattice of spacing 0.01 m centred at (0.5, 0.5, 0.4) (edge 0.2 m: 8,000
particles), on the grid of [0, 1]^3 with cell 1/64 m (65^3 nodes, as genesis_lite's grid_density=64), gravity
-9.81 z, dt = 2e-3 s in 10 substeps. The kernel is what a textbook (mpm88 / mpm99 style) writes: one Taichi
kernel per substep holding four loops, each parallel over its elements: clear every grid node, particle to
grid (F <- (I + dt C) F, ti.svd, corotated Kirchhoff stress, APIC momentum, atomic adds to the 27 nodes of
the quadratic B-spline stencil), a dense sweep over every node (momentum to velocity, gravity, walls of 3
nodes that take the velocity into them), grid to particle (velocity, affine C, position). No adjoints,
no particle state history, no checks: the cost of the physics alone.
`--scene filled`: a domain the material fills, where a dense sweep wastes nothing: the grid of [0, 0.5]^3
(33^3 nodes, same cell) and a cube of edge 0.4 m centred at (0.25, 0.25, 0.25) (40^3 = 64,000 particles).

Prints one JSON line: particle-substeps/s (median over repeats of `steps` steps after a warm-up), the
particle count and the CPU threads Taichi ran with (`cpu_max_num_threads`). Taichi's worker threads are placed
as gs.init places genesis_lite's (each on a core of its own where they span the cores; GS_PIN_THREADS=0: left
to the scheduler; solvers/taichi_compat/threads.py), so that the two engines differ in their kernels only.
"""

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import taichi as ti

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from solvers.taichi_compat import threads as threads_compat  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="20 steps, 3 repeats")
    ap.add_argument("--threads", type=int, default=os.cpu_count(), help="Taichi's cpu_max_num_threads")
    ap.add_argument("--precision", default="32", choices=("32", "64"))
    ap.add_argument("--particles", type=int, default=8000, help="a cube of round(n^(1/3))^3 particles (scene cube)")
    ap.add_argument("--scene", default="cube", choices=("cube", "filled"))
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=None)
    args = ap.parse_args()
    steps = args.steps or (20 if args.quick else 50)
    repeats = args.repeats or (3 if args.quick else 5)
    f = ti.f64 if args.precision == "64" else ti.f32
    before = threads_compat.thread_ids()
    ti.init(arch=ti.cpu, default_fp=f, cpu_max_num_threads=args.threads, offline_cache=True, log_level=ti.ERROR,
            kernel_profiler=bool(os.environ.get("BARE_PROFILE")))
    pinning = threads_compat.place_workers(True, threads_compat.switch_env(), threads_compat.thread_ids() - before,
                                           args.threads)["why"]

    spacing = 0.01
    side, centre, res = (40, (0.25, 0.25, 0.25), 33) if args.scene == "filled" else \
        (round(args.particles ** (1.0 / 3.0)), (0.5, 0.5, 0.4), 65)
    axis = (np.arange(side) - (side - 1) / 2.0) * spacing
    lattice = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) + np.array(centre)
    n = len(lattice)
    E, nu, rho = 3e5, 0.2, 1000.0
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    p_vol = spacing ** 3
    p_mass = p_vol * rho
    dx = 1.0 / 64.0
    inv_dx = 1.0 / dx
    dt = 2e-3 / 10
    bound = 3
    gravity = ti.Vector([0.0, 0.0, -9.81])

    x = ti.Vector.field(3, f, shape=n)
    v = ti.Vector.field(3, f, shape=n)
    C = ti.Matrix.field(3, 3, f, shape=n)
    F = ti.Matrix.field(3, 3, f, shape=n)
    grid_v = ti.Vector.field(3, f, shape=(res, res, res))  # momentum, then velocity
    grid_m = ti.field(f, shape=(res, res, res))

    @ti.kernel
    def reset(pos: ti.types.ndarray()):
        for p in x:
            x[p] = ti.Vector([pos[p, 0], pos[p, 1], pos[p, 2]])
            v[p] = ti.Vector.zero(f, 3)
            C[p] = ti.Matrix.zero(f, 3, 3)
            F[p] = ti.Matrix.identity(f, 3)

    @ti.kernel
    def substep():
        for I in ti.grouped(grid_m):
            grid_v[I] = ti.Vector.zero(f, 3)
            grid_m[I] = 0.0
        for p in x:
            base = (x[p] * inv_dx - 0.5).cast(int)
            fx = x[p] * inv_dx - base.cast(f)
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
            F[p] = (ti.Matrix.identity(f, 3) + dt * C[p]) @ F[p]
            U, sig, V = ti.svd(F[p])
            J = sig[0, 0] * sig[1, 1] * sig[2, 2]
            kirchhoff = 2.0 * mu * (F[p] - U @ V.transpose()) @ F[p].transpose() \
                + ti.Matrix.identity(f, 3) * lam * J * (J - 1.0)
            affine = (-dt * p_vol * 4.0 * inv_dx * inv_dx) * kirchhoff + p_mass * C[p]
            for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                offset = ti.Vector([i, j, k])
                dpos = (offset.cast(f) - fx) * dx
                weight = w[i][0] * w[j][1] * w[k][2]
                grid_v[base + offset] += weight * (p_mass * v[p] + affine @ dpos)
                grid_m[base + offset] += weight * p_mass
        for I in ti.grouped(grid_m):
            if grid_m[I] > 0:
                vel = grid_v[I] / grid_m[I] + dt * gravity
                for d in ti.static(range(3)):
                    if (I[d] < bound and vel[d] < 0) or (I[d] > res - 1 - bound and vel[d] > 0):
                        vel[d] = 0.0
                grid_v[I] = vel
        for p in x:
            base = (x[p] * inv_dx - 0.5).cast(int)
            fx = x[p] * inv_dx - base.cast(f)
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
            new_v = ti.Vector.zero(f, 3)
            new_C = ti.Matrix.zero(f, 3, 3)
            for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                offset = ti.Vector([i, j, k])
                dpos = offset.cast(f) - fx
                g_v = grid_v[base + offset]
                weight = w[i][0] * w[j][1] * w[k][2]
                new_v += weight * g_v
                new_C += 4.0 * inv_dx * weight * g_v.outer_product(dpos)
            v[p] = new_v
            C[p] = new_C
            x[p] += dt * new_v

    def run():
        reset(lattice)
        ti.sync()
        t0 = time.perf_counter()
        for _ in range(steps * 10):
            substep()
        ti.sync()
        return time.perf_counter() - t0

    run()  # compile and warm up
    secs = [run() for _ in range(repeats)]
    pos = x.to_numpy()
    assert np.isfinite(pos).all() and pos[:, 2].min() > 0.0
    med = statistics.median(secs)
    if os.environ.get("BARE_PROFILE"):
        ti.profiler.print_kernel_profiler_info("count")
    print(json.dumps({"engine": "bare", "scene": args.scene, "precision": args.precision, "n_particles": n, "threads": args.threads,
                      "pinning": pinning, "steps": steps, "repeats": repeats, "rate": n * 10 * steps / med, "step_ms": 1e3 * med / steps,
                      "runs_s": secs, "z_mean": float(pos[:, 2].mean())}))


if __name__ == "__main__":
    main()
