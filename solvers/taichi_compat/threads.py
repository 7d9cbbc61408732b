"""Taichi's CPU worker threads, each kept on a core of its own.

Taichi 1.7.4's CPU backend runs every parallel loop of a kernel as one task of its thread pool: the launching
thread wakes the pool's workers (one per `cpu_max_num_threads`, started by `ti.init`) and sleeps until they
have taken every chunk of the loop. Left to the Linux scheduler, both woken workers are often queued on the
waker's core, one behind the other: on this project's 2-core machine a parallel loop over 1,024 items cost
~100 us even when empty, and a loop of 1.4 ms of work took as long on two threads as on one (the second
worker woke when the first had taken every chunk). With worker i kept on core i, the empty loop took ~40 us
and the 1.4 ms loop 0.75 ms (`benchmarks/results/threads.md`).

`pin_workers` finds the workers by what they do (the threads `ti.init` started whose voluntary context
switches follow the launches of a small parallel kernel: each launch wakes every worker once) and sets each
one's CPU affinity to one core. It pins only where that cannot pile processes onto the same cores: when the
workers are as many as the cores this process may run on (its affinity mask), or, under torchrun
(LOCAL_WORLD_SIZE = N > 1), on rank LOCAL_RANK's own slice of the cores when every rank's threads fit side
by side. A process with fewer threads than cores (GS_NUM_THREADS=1, gs.init(num_threads=k)) is left to the
scheduler. Thread placement changes no number: each parallel loop's chunks are the same whichever core runs
them (tests/test_threads.py compares trajectories bitwise).

This depends on how Taichi's thread pool works (its workers started by ti.init, all woken by every parallel
launch), so it runs only on the Taichi version it was checked on (taichi_compat.TAICHI_VERSION) and on
Linux (per-thread affinity through os.sched_setaffinity)."""

import os
import threading

PROBE_LAUNCHES = 16


def switch_env() -> bool | None:
    """GS_PIN_THREADS: "0" never pins, "1" pins wherever a core per worker can be chosen, unset: None (the
    default policy of `target_cores`)."""
    v = os.environ.get("GS_PIN_THREADS")
    if v is None or v == "":
        return None
    if v not in ("0", "1"):
        raise ValueError(f"GS_PIN_THREADS={v!r}: use 0 or 1")
    return v == "1"


def thread_ids() -> set:
    """The ids of this process's threads (Linux: /proc/self/task), empty where there is no such folder."""
    try:
        return {int(t) for t in os.listdir("/proc/self/task")}
    except OSError:
        return set()


def _switches(tid: int):
    try:
        with open(f"/proc/self/task/{tid}/status") as f:
            for line in f:
                if line.startswith("voluntary_ctxt_switches:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def target_cores(cpus, n_workers: int, local_rank: int = 0, local_size: int = 1, force: bool = False):
    """The cores to keep the workers on (worker i on the i-th), or None to leave them to the scheduler.

    cpus: the cores this process may run on, sorted; under torchrun local_size > 1 ranks on this node. A
    single process pins when its workers are exactly as many as its cores; rank r of N takes cores
    r*n .. (r+1)*n-1 when N*n cores are there for n workers a rank (one worker a rank included). force
    (GS_PIN_THREADS=1): also a process with fewer workers than cores, or one worker, on its first cores (for
    a script that knows it runs alone)."""
    cpus = list(cpus)
    if n_workers < 1 or not cpus:
        return None
    if local_size > 1:
        lo = local_rank * n_workers
        if 0 <= local_rank < local_size and local_size * n_workers <= len(cpus):
            return cpus[lo:lo + n_workers]
        return None
    if (n_workers >= 2 and n_workers == len(cpus)) or (force and n_workers <= len(cpus)):
        return cpus[:n_workers]
    return None


def find_workers(candidates, launches: int = PROBE_LAUNCHES) -> list:
    """Of the thread ids `candidates` (those ti.init started), the ones woken by the launches of a small
    parallel kernel (at least every other one: a worker still awake when the next launch comes does not
    sleep in between; the other threads of ti.init do not wake at all), sorted; [] when they cannot be
    told (no /proc: then nothing is launched)."""
    if not candidates:
        return []
    import numpy as np
    import taichi as ti

    @ti.kernel
    def probe(x: ti.types.ndarray()):
        for i in x:
            x[i] += 1

    x = np.zeros(64, np.int32)
    probe(x)  # compiled (or loaded from the kernel cache) before counting
    me = threading.get_native_id()
    before = {t: _switches(t) for t in candidates if t != me}
    for _ in range(launches):
        probe(x)
    out = []
    for t, a in before.items():
        b = _switches(t)
        if a is not None and b is not None and b - a >= launches // 2:
            out.append(t)
    return sorted(out)


def pin_workers(candidates, n_threads: int, force: bool = False) -> dict:
    """Keep each of Taichi's n_threads CPU workers (found among `candidates`, the threads ti.init started) on a
    core of its own where `target_cores` allows; the workers are looked for only then. Returns {"workers":
    [...], "cores": [...] or None, "why": str}."""
    if not hasattr(os, "sched_setaffinity"):
        return {"workers": [], "cores": None, "why": "no per-thread CPU affinity on this OS"}
    try:
        local_size = int(os.environ.get("LOCAL_WORLD_SIZE", "1"))
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    except ValueError:
        local_size, local_rank = 1, 0
    mask = os.sched_getaffinity(0)
    cores = target_cores(sorted(mask), n_threads, local_rank, local_size, force)
    if cores is None:
        return {"workers": [], "cores": None,
                "why": f"{n_threads} worker thread(s) on {len(mask)} core(s): left to the scheduler"}
    workers = find_workers(candidates)
    if len(workers) != n_threads:
        return {"workers": workers, "cores": None,
                "why": f"found {len(workers)} worker threads, expected {n_threads}"}
    try:
        for tid, core in zip(workers, cores):
            os.sched_setaffinity(tid, {core})
    except OSError as e:  # a thread gone, or a container that forbids it: leave every worker as it was
        for tid in workers:
            try:
                os.sched_setaffinity(tid, mask)
            except OSError:
                pass
        return {"workers": workers, "cores": None, "why": f"could not set a thread's CPU affinity: {e}"}
    return {"workers": workers, "cores": cores, "why": "pinned"}


def place_workers(on_cpu: bool, pin, candidates, n_threads: int) -> dict:
    """gs.init's call: pin_workers unless the backend is not the CPU, pinning is switched off (pin False) or
    the installed Taichi is not the version this was checked on; pin True forces (target_cores)."""
    from . import version_ok

    if not on_cpu:
        return {"workers": [], "cores": None, "why": "not the CPU backend"}
    if pin is False:
        return {"workers": [], "cores": None, "why": "switched off (pin_threads=False or GS_PIN_THREADS=0)"}
    if not version_ok():
        return {"workers": [], "cores": None, "why": "not the Taichi version it was checked on"}
    return pin_workers(candidates, n_threads, force=bool(pin))
