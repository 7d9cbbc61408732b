"""The peer: real Genesis (`genesis-world`) stepping the stripped Panda, 1 env, on the CPU.

Runs in its own virtual environment, never the project's (Genesis brings its own Taichi fork):

    python3 -m venv /tmp/gvenv && /tmp/gvenv/bin/pip install torch==2.13.0 genesis-world
    /tmp/gvenv/bin/python benchmarks/peer_genesis.py [--urdf panda_stripped.urdf] [--steps 1000]

Same scene as bench_rigid.py: fixed base, gravity, zero control, Euler at dt = 0.01 s, damping and
armature 0, joint limits on, the Panda's "ready" pose. Prints a human line, then one JSON line
({"rate": steps/s, "build_s", "version", "precision"}) that bench_rigid.py reads.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

DT = 0.01
PANDA_HOME = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785, 0.04, 0.04]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--urdf", type=Path, default=None, help="default: write the stripped Panda (needs example-robot-data)")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--precision", default="64", choices=["32", "64"])
    args = ap.parse_args()
    if args.urdf is None:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from common import write_stripped_panda

        args.urdf = write_stripped_panda()

    import genesis as gs
    import torch

    t0 = time.perf_counter()
    gs.init(backend=gs.cpu, precision=args.precision, logging_level="warning")
    scene = gs.Scene(
        sim_options=gs.options.SimOptions(dt=DT, substeps=1, gravity=(0.0, 0.0, -9.81)),
        rigid_options=gs.options.RigidOptions(integrator=gs.integrator.Euler),
        show_viewer=False,
    )
    robot = scene.add_entity(gs.morphs.URDF(file=str(args.urdf), fixed=True))
    scene.build()
    n = robot.n_dofs
    dtype = torch.float64 if args.precision == "64" else torch.float32
    robot.set_dofs_damping(torch.zeros(n, dtype=dtype))
    robot.set_dofs_armature(torch.zeros(n, dtype=dtype))

    def reset():
        robot.set_dofs_position(torch.tensor(PANDA_HOME[:n], dtype=dtype))
        robot.set_dofs_velocity(torch.zeros(n, dtype=dtype))

    reset()
    scene.step()
    build_s = time.perf_counter() - t0

    def once():
        reset()
        t = time.perf_counter()
        for _ in range(args.steps):
            scene.step()
        dt = time.perf_counter() - t
        q = robot.get_dofs_position().cpu().numpy()
        assert np.all(np.isfinite(q)), "Genesis diverged"
        return dt

    once()
    rate = statistics.median(args.steps / once() for _ in range(args.repeats))
    version = getattr(gs, "__version__", "")
    print(f"Genesis {version} CPU f{args.precision}: {rate:,.0f} steps/s (1 env), build + first step {build_s:.1f} s",
          file=sys.stderr)
    print(json.dumps({"rate": rate, "build_s": build_s, "version": version, "precision": args.precision}))


if __name__ == "__main__":
    main()
