"""The CUDA backend (gs.gpu) against the CPU backend: the same scenes, the same numbers, and the speed.

    python benchmarks/gpu_check.py [--out benchmarks/results/gpu.md] [--envs 4096]

Needs a CUDA device that torch sees; each backend runs in its own process (one gs.init per process).
Scenes, float64 (benchmarks/trajectory_fingerprint.py's, with every input on the backend's device):
  contact   three boxes and a sphere on a plane, 4 envs, 40 steps, gradients to initial velocities, a
            mass and a friction coefficient
  coupling  a rigid box pushing an elastic MPM cube (two-way), 10 steps, gradients to the box's initial
            velocity and mass
For each recorded tensor it prints the largest difference between the backends, relative to the
tensor's largest magnitude. Speed, float32, no gradients, medians of 5 repeats after a warm-up:
  arm       assets/urdf/arm.urdf (fixed base, collision off) under PD control, --envs envs, 100 steps:
            env-steps/s
  mpm       an 8,000-particle elastic cube on a 64^3 grid, dt 2e-3 s, 10 substeps, 20 steps:
            particle-substeps/s
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent


def _tensors(backend):
    import numpy as np
    import torch

    import genesis_lite as gs

    sys.path.insert(0, str(HERE))
    import trajectory_fingerprint as fp

    gs.init(backend=backend, precision="64", logging_level="warning")
    fp.F64["device"] = gs.device  # the scenes build their inputs with **F64
    out = {}
    for name, fn in (("contact", fp.contact_scene), ("coupling", fp.coupling_scene)):
        for k, v in fn().items():
            out[f"{name}.{k}"] = np.asarray(v.detach().cpu().numpy(), dtype=np.float64).tolist()
    torch.cuda.synchronize() if gs.device.type == "cuda" else None
    return out


def _speed(backend, envs):
    import torch

    import genesis_lite as gs

    gs.init(backend=backend, precision="32", logging_level="warning")
    sync = torch.cuda.synchronize if gs.device.type == "cuda" else (lambda: None)
    rows = {}
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01),
                     rigid_options=gs.options.RigidOptions(enable_collision=False))
    arm = scene.add_entity(gs.morphs.URDF(file=str(REPO / "assets" / "urdf" / "arm.urdf"), fixed=True))
    t0 = time.perf_counter()
    scene.build(n_envs=envs)
    rows["arm_build_s"] = time.perf_counter() - t0
    target = torch.full((envs, arm.n_dofs), 0.3, device=gs.device, dtype=gs.tc_float)
    arm.control_dofs_position(target)

    def arm_run():
        for _ in range(100):
            scene.step()
        arm.get_dofs_position()
        sync()

    rows["arm_env_steps_per_s"] = envs * 100 / _median_time(arm_run)
    del scene, arm

    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=10),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(1, 1, 1), grid_density=64))
    cube = scene.add_entity(gs.morphs.Box(pos=(0.5, 0.5, 0.4), size=(0.2, 0.2, 0.2)),
                            material=gs.materials.MPM.Elastic(E=3e5, nu=0.2))
    scene.build()

    def mpm_run():
        for _ in range(20):
            scene.step()
        cube.get_particles_pos()
        sync()

    rows["mpm_particles"] = cube.n_particles
    rows["mpm_particle_substeps_per_s"] = cube.n_particles * 20 * 10 / _median_time(mpm_run)
    return rows


def _median_time(fn, repeats=5):
    fn()  # compile, warm
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _worker(backend, what, envs):
    import genesis_lite as gs

    b = gs.gpu if backend == "gpu" else gs.cpu
    res = _tensors(b) if what == "tensors" else _speed(b, envs)
    print("RESULT " + json.dumps(res), flush=True)


def _run(backend, what, envs):
    cmd = [sys.executable, __file__, "--worker", backend, what, "--envs", str(envs)]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=1200, cwd=REPO,
                         env={**os.environ, "PYTHONUNBUFFERED": "1"})
    lines = [l for l in out.stdout.splitlines() if l.startswith("RESULT ")]
    if out.returncode != 0 or not lines:
        raise RuntimeError(f"{backend} {what} worker failed (rc {out.returncode}):\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}")
    return json.loads(lines[-1][len("RESULT "):])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", nargs=2, metavar=("BACKEND", "WHAT"))
    ap.add_argument("--envs", type=int, default=4096)
    ap.add_argument("--out", default=None, help="also write the report (markdown) here")
    args = ap.parse_args()
    if args.worker:
        return _worker(args.worker[0], args.worker[1], args.envs)
    import numpy as np
    import torch

    if not torch.cuda.is_available():
        sys.exit("gpu_check: torch sees no CUDA device")
    t_start = time.time()
    lines = [f"# CUDA backend against the CPU backend", "",
             f"`python benchmarks/gpu_check.py --envs {args.envs}`, {time.strftime('%Y-%m-%d %H:%M')}, "
             f"{torch.cuda.get_device_name(0)}, {os.cpu_count()} CPU cores, torch {torch.__version__}.", "",
             "## The same numbers (float64)", "",
             "| tensor | shape | max abs difference / max abs value |", "| --- | --- | --- |"]
    cpu, gpu = _run("cpu", "tensors", args.envs), _run("gpu", "tensors", args.envs)
    worst = 0.0
    for k in cpu:
        a, b = np.asarray(cpu[k]), np.asarray(gpu[k])
        rel = float(np.abs(a - b).max() / max(np.abs(a).max(), 1e-300))
        worst = max(worst, rel)
        lines.append(f"| {k} | {a.shape} | {rel:.2e} |")
    lines += ["", f"Worst: {worst:.2e}.", "", "## Speed (float32, no gradients, medians of 5)", "",
              "| row | CPU backend | CUDA backend | CUDA / CPU |", "| --- | --- | --- | --- |"]
    sc, sg = _run("cpu", "speed", args.envs), _run("gpu", "speed", args.envs)
    for k, unit in (("arm_env_steps_per_s", f"arm, {args.envs} envs: env-steps/s"),
                    ("mpm_particle_substeps_per_s", f"MPM cube, {sc['mpm_particles']} particles: particle-substeps/s"),
                    ("arm_build_s", f"arm, {args.envs} envs: scene.build() s (kernels compile later, at the first step)")):
        lines.append(f"| {unit} | {sc[k]:,.3g} | {sg[k]:,.3g} | {sg[k] / sc[k]:.2f} |")
    lines += ["", f"Total {time.time() - t_start:.0f} s."]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        Path(args.out).write_text(text)


if __name__ == "__main__":
    main()
