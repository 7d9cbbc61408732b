"""Taichi's CPU worker threads kept on a core each (solvers/taichi_compat/threads.py): with default options
gs.init pins each worker to its own core when the process's threads span its cores, the pinned threads are
the ones that run Taichi's parallel loops (each on its core), and pinning changes no number (a batched
contact rollout and an MPM rollout bitwise the same with GS_PIN_THREADS=0). Fresh processes: pinning is
done once per process by gs.init."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from solvers.taichi_compat.threads import switch_env, target_cores

WORKER = Path(__file__).parent / "workers" / "thread_digest.py"
GRAD_WORKER = Path(__file__).parent / "workers" / "grad_digest.py"


def test_cores_chosen_only_where_no_two_processes_can_pile_up():
    # a process whose threads span its cores: worker i on the i-th
    assert target_cores([0, 1], 2) == [0, 1]
    assert target_cores([2, 5, 7], 3) == [2, 5, 7]
    # fewer threads than cores (GS_NUM_THREADS, gs.init(num_threads=k)): other processes may use the rest
    assert target_cores([0, 1, 2, 3], 2) is None
    assert target_cores([0, 1, 2, 3], 2, force=True) == [0, 1]
    # more threads than cores (a taskset narrower than Taichi's thread count): nothing to choose
    assert target_cores([0], 2) is None
    # one worker: nothing to gain unless asked
    assert target_cores([0, 1], 1) is None
    assert target_cores([0, 1], 1, force=True) == [0]
    # torchrun: rank r of N on its own slice of the node's cores, when every rank's threads fit
    assert target_cores(list(range(8)), 2, local_rank=0, local_size=4) == [0, 1]
    assert target_cores(list(range(8)), 2, local_rank=3, local_size=4) == [6, 7]
    assert target_cores(list(range(8)), 3, local_rank=1, local_size=4) is None
    assert target_cores(list(range(8)), 2, local_rank=4, local_size=4) is None
    assert target_cores([0, 1], 1, local_rank=1, local_size=2) == [1]


def test_switch_names_what_it_takes(monkeypatch):
    monkeypatch.delenv("GS_PIN_THREADS", raising=False)
    assert switch_env() is None
    monkeypatch.setenv("GS_PIN_THREADS", "0")
    assert switch_env() is False
    monkeypatch.setenv("GS_PIN_THREADS", "yes")
    with pytest.raises(ValueError, match="GS_PIN_THREADS='yes': use 0 or 1"):
        switch_env()


def test_init_rejects_a_pin_threads_that_is_not_a_bool():
    done = subprocess.run([sys.executable, "-c", "import genesis_lite as gs; gs.init(pin_threads='yes')"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode != 0
    assert "gs.init(pin_threads='yes'): use True, False or None" in done.stderr


def _run(env_extra, worker=WORKER, *args):
    """A worker's JSON line, run in a fresh process alone on the machine's cores (no GS_NUM_THREADS or torchrun
    share inherited) with env_extra."""
    env = dict(os.environ)
    env.pop("GS_NUM_THREADS", None)
    env.pop("LOCAL_WORLD_SIZE", None)
    env.update(env_extra)
    done = subprocess.run([sys.executable, str(worker), *args], env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2
                    or len(os.sched_getaffinity(0)) != os.cpu_count(),
                    reason="needs a Linux process that may run on every core of a machine of 2 or more")
def test_default_init_pins_the_workers_and_changes_no_number():
    env = {"GS_PIN_THREADS": ""}
    pinned, off = _run(env), _run({"GS_PIN_THREADS": "0"})
    cores = pinned["affinity"]
    p = pinned["pinning"]
    assert p["why"] == "pinned", p
    assert len(p["workers"]) == pinned["cpu_threads"] == len(cores)
    assert sorted(p["cores"]) == cores  # one core each, every core used
    for tid, core in zip(p["workers"], p["cores"]):
        w = pinned["work"].get(str(tid))
        assert w is not None, f"the pinned thread {tid} is gone"
        assert w["affinity"] == [core]
        # the pinned threads are the ones that run the parallel loop (~0.2 s each), on their core
        assert w["ticks"] >= 5, (tid, w)
        assert w["core"] == core
    # no other thread of the process was narrowed
    for tid, w in pinned["work"].items():
        if int(tid) not in p["workers"]:
            assert w["affinity"] == cores, (tid, w)
    # switched off: nothing pinned, Taichi's workers still run the loop
    assert off["pinning"]["workers"] == [] and off["pinning"]["why"].startswith("switched off")
    assert all(w["affinity"] == cores for w in off["work"].values())
    assert sum(w["ticks"] >= 5 for w in off["work"].values()) >= 1
    # where the threads run changes no number
    assert pinned["contact"] == off["contact"]
    assert pinned["mpm"] == off["mpm"]


def test_few_threads_run_the_env_loops_serially_with_the_same_gradients():
    """A 32-env scene (more than SERIAL_MAX_ENVS) runs its env loops serially with one Taichi thread or two
    (core.runs_serially), in parallel loops with four (fresh processes, default options otherwise). Its contact
    rollout's gradients and loss: the same to the bit on one thread and two (one serial code), those of the
    parallel loops to rounding (another compiled code: 6.5e-14 of the largest, 12, when written)."""
    runs = {n: _run({"GS_NUM_THREADS": str(n)}, GRAD_WORKER, "envs32") for n in (1, 2, 4)}
    assert {n: r["cpu_threads"] for n, r in runs.items()} == {1: 1, 2: 2, 4: 4}
    assert {n: r["serial"] for n, r in runs.items()} == {1: True, 2: True, 4: False}
    serial, parallel = np.array(runs[1]["contact"]), np.array(runs[4]["contact"])
    assert serial.size == 32 * 7 + 1 and np.abs(serial).max() > 1.0
    np.testing.assert_array_equal(serial, np.array(runs[2]["contact"]))
    np.testing.assert_allclose(parallel, serial, rtol=0, atol=1e-12 * np.abs(serial).max())
