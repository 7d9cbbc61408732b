"""Genesis's MPM tutorial scene (examples/tutorials/mpm.py of Genesis v0.4.5) on either engine, probed
along the way: the mean, lowest and highest z of each body's particles and the liquid's extent along y,
every 10 steps.

    python benchmarks/mpm_tutorial_probe.py --side ours [--steps 100] [--json out.json]
    /work/gvenv/bin/python benchmarks/mpm_tutorial_probe.py --side genesis     # genesis-world in its venv

The scene as the tutorial builds it: dt = 4 ms, 10 substeps, the domain (-0.5, -1, 0) .. (0.5, 1, 1), a
plane, an elastic box (0.2 m, at y = -0.5), a liquid box (0.3 m, at y = 0) and an elasto-plastic
sphere (r = 0.1 m, at y = 0.5), default materials and options, float32 (gs.init's default) on the CPU.
tests/test_mpm.py::test_genesis_s_mpm_tutorial holds Genesis's numbers of this probe (steps 40 and 60);
benchmarks/results/mpm_tutorial.md has both sides' whole runs.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def build(gs):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=4e-3, substeps=10),
                     mpm_options=gs.options.MPMOptions(lower_bound=(-0.5, -1.0, 0.0), upper_bound=(0.5, 1.0, 1)),
                     show_viewer=False)
    scene.add_entity(morph=gs.morphs.Plane())
    bodies = {
        "elastic": scene.add_entity(material=gs.materials.MPM.Elastic(),
                                    morph=gs.morphs.Box(pos=(0.0, -0.5, 0.25), size=(0.2, 0.2, 0.2))),
        "liquid": scene.add_entity(material=gs.materials.MPM.Liquid(),
                                   morph=gs.morphs.Box(pos=(0.0, 0.0, 0.25), size=(0.3, 0.3, 0.3))),
        "plastic": scene.add_entity(material=gs.materials.MPM.ElastoPlastic(),
                                    morph=gs.morphs.Sphere(pos=(0.0, 0.5, 0.35), radius=0.1)),
    }
    scene.build()
    return scene, bodies


def positions(entity) -> np.ndarray:
    p = entity.get_particles_pos()
    p = p.detach().cpu().numpy() if hasattr(p, "detach") else np.asarray(p)
    return p.reshape(-1, 3).astype(np.float64)


def probe(bodies) -> dict:
    out = {}
    for name, e in bodies.items():
        p = positions(e)
        out[name] = {"z_mean": float(p[:, 2].mean()), "z_min": float(p[:, 2].min()), "z_max": float(p[:, 2].max()),
                     "y_min": float(p[:, 1].min()), "y_max": float(p[:, 1].max())}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--side", choices=("ours", "genesis"), required=True)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--precision", default="32", help="gs.init's (the tutorial's default: 32)")
    args = ap.parse_args()
    if args.side == "ours":
        sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
        import genesis_lite as gs
    else:
        import genesis as gs
    gs.init(backend=gs.cpu, precision=args.precision, logging_level="warning")
    scene, bodies = build(gs)
    rows = {0: probe(bodies)}
    t0 = time.perf_counter()
    for i in range(1, args.steps + 1):
        scene.step()
        if i % 10 == 0:
            rows[i] = probe(bodies)
            r = rows[i]
            print(f"step {i:4d}  " + "  ".join(f"{n}: z {v['z_mean']:.4f} [{v['z_min']:.4f}, {v['z_max']:.4f}] "
                                                 f"y [{v['y_min']:.3f}, {v['y_max']:.3f}]" for n, v in r.items())
                  + f"  ({time.perf_counter() - t0:.0f} s)", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"side": args.side, "steps": rows}, indent=1))


if __name__ == "__main__":
    main()
