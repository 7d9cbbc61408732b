"""Scenes built in a loop in one process (issue #21): a parameter sweep builds a new scene per value. Each
scene here is an MPM cube with gradients (optionally pushed by a rigid box, coupled both ways): build, a
few steps, a backward pass, then `del` and `gc.collect()`. Prints, per scene, its wall time and the
process's resident memory (RSS) after it, and at the end the RSS growth from scene 5 to the last one
(the first scenes compile and fill Taichi's caches; later ones should take the pooled solvers and add
nothing).

    python benchmarks/bench_scene_loop.py [--scenes 50] [--coupled] [--steps 3]
"""
import argparse
import gc
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def rss_mb():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def one_scene(gs, torch, coupled, steps, E):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=4, requires_grad=True),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.4, 0.4, 0.4),
                                                       grid_density=32))
    cube = scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 0.15), size=(0.1,) * 3),
                            material=gs.materials.MPM.Elastic(E=E, nu=0.3))
    pusher = None
    if coupled:
        pusher = scene.add_entity(gs.morphs.Box(pos=(0.12, 0.2, 0.15), size=(0.05, 0.12, 0.1)),
                                  material=gs.materials.Rigid(rho=2000))
    scene.build()
    v = torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64, requires_grad=True)
    if coupled:
        pusher.set_dofs_velocity(torch.cat([v, torch.zeros(3, dtype=torch.float64)]))
    else:
        cube.set_velocity(v)
    for _ in range(steps):
        scene.step()
    loss = (cube.get_particles_pos()[:, 0] ** 2).sum()
    loss.backward()
    g = float(v.grad.abs().sum())
    del scene, cube, pusher, loss
    return g


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=50)
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--coupled", action="store_true", help="a rigid box pushes the cube (two-way coupling)")
    args = ap.parse_args()
    import torch
    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64")
    rows = []
    for i in range(args.scenes):
        t0 = time.perf_counter()
        g = one_scene(gs, torch, args.coupled, args.steps, E=1e4 * (1 + 0.01 * i))
        gc.collect()
        rows.append((time.perf_counter() - t0, rss_mb()))
        print(f"scene {i + 1:3d}: {rows[-1][0]:6.2f} s, RSS {rows[-1][1]:7.1f} MB, |grad| {g:.4e}", flush=True)
    k = min(4, len(rows) - 1)
    later = sorted(r[0] for r in rows[1:]) or [rows[0][0]]
    print(f"first scene {rows[0][0]:.1f} s; later scenes median {later[len(later) // 2]:.2f} s, max {later[-1]:.2f} s")
    print(f"RSS after scene {k + 1}: {rows[k][1]:.1f} MB; after scene {len(rows)}: {rows[-1][1]:.1f} MB; growth "
          f"{rows[-1][1] - rows[k][1]:+.1f} MB over {len(rows) - k - 1} scenes "
          f"({(rows[-1][1] - rows[k][1]) / max(len(rows) - k - 1, 1) * 1e3:+.0f} kB a scene)")


if __name__ == "__main__":
    main()
