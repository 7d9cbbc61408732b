"""A batched scene's start, cold and warm (issue #25: "a 64-env scene compiles in under 20 s cold"): a Panda over
a plane at --envs environments, import to the end of the first step, in fresh processes.

    python benchmarks/cold_start_envs.py [--envs 64] [--rounds 2] [--precision 32]

Each round runs one process on new, empty caches (TI_OFFLINE_CACHE_FILE_PATH for Taichi's kernels, GS_CACHE_DIR for
loaded models: "cold") and one more on the caches it left ("warm"), and prints import + init, build, first step and
their sum, and the wall time of the whole process. The robot: Genesis's MJCF Panda (xml/franka_emika_panda/panda.xml,
resolved in GS_ASSETS_DIR or a Genesis install's assets, as a Genesis script loads it) where one is found, else
example-robot-data's Panda URDF.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

from common import panda_urdf

CHILD = r"""
import sys, time
t0 = time.perf_counter()
import genesis_lite as gs
gs.init(backend=gs.cpu, precision=sys.argv[2], logging_level="warning")
t1 = time.perf_counter()
scene = gs.Scene(show_viewer=False)
scene.add_entity(gs.morphs.Plane())
try:
    scene.add_entity(gs.morphs.MJCF(file="xml/franka_emika_panda/panda.xml"))
    robot = "Genesis's MJCF Panda"
except FileNotFoundError:  # no Genesis assets here
    scene.add_entity(gs.morphs.URDF(file=sys.argv[3], fixed=True))
    robot = "example-robot-data's Panda URDF"
scene.build(n_envs=int(sys.argv[1]))
t2 = time.perf_counter()
scene.step()
t3 = time.perf_counter()
print(f"RESULT {t1 - t0:.2f} {t2 - t1:.2f} {t3 - t2:.2f} {t3 - t0:.2f} {robot}")
"""


def run(envs, precision, cache):
    env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=os.path.join(cache, "taichi"),
               GS_CACHE_DIR=os.path.join(cache, "genesis_lite"))
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", CHILD, str(envs), precision, str(panda_urdf())], env=env,
                         capture_output=True, text=True)
    wall = time.perf_counter() - t
    line = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT")]
    if out.returncode or not line:
        raise RuntimeError(f"child failed:\n{out.stderr[-3000:]}")
    imp, build, step, total, robot = line[0].split(" ", 5)[1:]
    return float(imp), float(build), float(step), float(total), wall, robot


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--precision", default="32", choices=("32", "64"), help="gs.init precision (Genesis's default 32)")
    args = ap.parse_args()
    print(f"| round | cache | import + init s | build s | first step s | import to first step s | process s |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    robot = None
    for r in range(args.rounds):
        with tempfile.TemporaryDirectory() as cache:
            for kind in ("cold", "warm"):
                imp, build, step, total, wall, robot = run(args.envs, args.precision, cache)
                print(f"| {r + 1} | {kind} | {imp:.1f} | {build:.1f} | {step:.1f} | {total:.1f} | {wall:.1f} |", flush=True)
    print(f"\n{robot} over a plane, {args.envs} envs, float{args.precision}, CPU backend.")


if __name__ == "__main__":
    main()
