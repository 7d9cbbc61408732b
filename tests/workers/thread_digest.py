"""Worker for tests/test_threads.py: what gs.init did with Taichi's CPU worker threads, which threads ran a
parallel kernel of ~0.2 s and on which core, and sha256 digests of a batched contact rollout (1,024 envs:
parallel loops over envs, core.runs_serially) and of an MPM rollout; prints one JSON line."""
import json
import os

import numpy as np
import taichi as ti
import torch
from grad_digest import F64, digest  # (this folder is the script's: first on sys.path)

import genesis_lite as gs


def stat(tid):
    """(user + system CPU ticks, the core it last ran on) of thread tid."""
    with open(f"/proc/self/task/{tid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12]), int(fields[36])


def threads():
    return sorted(int(t) for t in os.listdir("/proc/self/task"))


@ti.kernel
def busy(x: ti.types.ndarray(), m: ti.i32):
    for i in x:
        a = x[i]
        for _ in range(m):
            a = ti.sin(a) + 0.5
        x[i] = a


def who_works():
    """Each thread's CPU ticks during a parallel kernel of ~0.2 s a thread, and its last core."""
    x = np.zeros(1024, np.float64)
    busy(x, 10)
    before = {t: stat(t) for t in threads()}
    busy(x, 40000)
    out = {}
    for t, (ticks, _) in before.items():
        try:
            ticks1, core = stat(t)
        except OSError:
            continue
        out[t] = {"ticks": ticks1 - ticks, "core": core, "affinity": sorted(os.sched_getaffinity(t))}
    return out


def contact_rollout():
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=5e-3))
    scene.add_entity(gs.morphs.Plane())
    box = scene.add_entity(gs.morphs.Box(pos=(0, 0, 0.12), size=(0.2, 0.2, 0.2)))
    scene.build(n_envs=1024)
    assert not scene.rigid_solver.core.serial
    rng = np.random.default_rng(3)
    box.set_dofs_velocity(torch.tensor(rng.normal(0.0, 1.0, (1024, 6)), **F64))
    for _ in range(40):
        scene.step()
    return digest(box.get_pos(), box.get_quat(), box.get_dofs_velocity())


def mpm_rollout():
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=10),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.4, 0.4, 0.4),
                                                       grid_density=32))
    block = scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 0.15), size=(0.15, 0.15, 0.1)),
                             material=gs.materials.MPM.Elastic(E=3e4, nu=0.2))
    scene.build()
    for _ in range(5):
        scene.step()
    return digest(block.get_particles_pos(), block.get_particles_vel())


if __name__ == "__main__":
    gs.init(backend=gs.cpu, precision="64")
    print(json.dumps({"pinning": gs.thread_pinning, "cpu_threads": gs.cpu_threads,
                      "affinity": sorted(os.sched_getaffinity(0)), "work": who_works(),
                      "contact": contact_rollout(), "mpm": mpm_rollout()}))
