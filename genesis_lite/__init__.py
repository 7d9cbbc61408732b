"""genesis_lite: a differentiable rigid-body simulator on Taichi with the API of Genesis.

    import genesis_lite as gs
    gs.init(backend=gs.cpu, precision="64")
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True))
"""
from __future__ import annotations

import logging
import os
import time

import numpy as np

# torch's OpenMP threads spin for a while after each of its parallel ops (GNU OpenMP's default active wait),
# on the cores that Taichi's threads need for the kernel launched next: with 2 cores, a 1,024-env Panda's
# 100-step rollout spent ~0.25 s of its 0.75 s forward in a control upload of 0.13 ms when they sleep at
# once (benchmarks/results/omp_wait.md). Read when torch loads its OpenMP runtime: effective when
# genesis_lite is imported before torch; a value the user set is kept.
import sys  # noqa: E402

# torch loaded before this line read the variable already (Scene.build warns when that can cost: many envs)
TORCH_IMPORTED_FIRST = "torch" in sys.modules and "OMP_WAIT_POLICY" not in os.environ
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# Lighter Taichi front-end bookkeeping and launches (same IR; solvers/taichi_compat), before any kernel
# is decorated.
from solvers import taichi_compat  # noqa: E402  (isort: skip)

taichi_compat.install_speedups()
# The solvers (and Taichi) before torch: decorating a Taichi function looks its frame's module up in
# sys.modules (inspect.getframeinfo), a scan that torch's ~2,000 modules make several times longer.
import solvers.rigid.solver  # noqa: E402,F401  (isort: skip)
from solvers.taichi_compat import adstack, checked_runtime  # noqa: E402  (isort: skip)
from solvers.taichi_compat import threads as threads_compat  # noqa: E402  (isort: skip)
import torch  # noqa: E402

from . import materials, morphs, options, surfaces, utils
from .utils import tools  # Genesis's gs.tools (Timer)
from .utils.uid import UID
from .errors import GenesisException
from .options import constraint_solver, integrator

__version__ = "0.1.0"

cpu = "cpu"
gpu = "gpu"
cuda = "gpu"

logger = logging.getLogger("genesis_lite")

# set by init()
device = torch.device("cpu")
tc_float = torch.float32
tc_int = torch.int32  # Genesis's integer and boolean tensor types
tc_bool = torch.bool
np_float = np.float32
ti_float = None
backend = None
cpu_threads = None  # CPU threads of this process (Taichi's and torch's); None until init() on gs.cpu
# what init() did with Taichi's CPU worker threads (threads_compat.pin_workers' answer); None before init()
thread_pinning = None
_initialized = False


def _available_cores() -> int:
    """Cores this process may run on (its affinity mask where the OS has one, as taskset and
    container CPU sets narrow it), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def default_num_threads() -> int | None:
    """The CPU threads a process gets by default: under torchrun (LOCAL_WORLD_SIZE set to N > 1, one
    process per rank on this node) its share of the cores, cores // N (at least 1), so that N ranks
    do not each start a thread per core; None (Taichi's and torch's own defaults: every core)
    otherwise. GS_NUM_THREADS overrides both."""
    env = os.environ.get("GS_NUM_THREADS")
    if env:
        try:
            n = int(env)
        except ValueError:
            raise GenesisException(f"GS_NUM_THREADS={env!r}: give a positive integer") from None
        if n < 1:
            raise GenesisException(f"GS_NUM_THREADS={env!r}: give a positive integer")
        return n
    try:
        local = int(os.environ.get("LOCAL_WORLD_SIZE", "1"))
    except ValueError:
        local = 1
    if local > 1:
        return max(1, _available_cores() // local)
    return None


# Taichi's offline cache serialises its metadata writes with a lock file that it creates and removes
# (ticache.lock, held while a process writes its new kernels at exit: milliseconds to seconds). A process
# killed meanwhile (torchrun stops every rank when one fails) leaves it behind, and every later process
# then neither reads nor writes the cache (Taichi's "Lock ... failed" warning is below gs.init's default
# log level: silently). Older than this, it is such a leftover (tests/test_distributed.py).
STALE_CACHE_LOCK_S = 120.0


def kernel_cache_cap_bytes() -> int:
    """The size cap of Taichi's kernel cache that gs.init sets: GS_KERNEL_CACHE_MB (MiB, 1 to 2047: Taichi
    holds the cap in a 32-bit int), default 1024."""
    env = os.environ.get("GS_KERNEL_CACHE_MB", "1024")
    try:
        mb = int(env)
        if not 1 <= mb <= 2047:
            raise ValueError
    except ValueError:
        raise GenesisException(f"GS_KERNEL_CACHE_MB={env!r}: give a number of MiB from 1 to 2047") from None
    return mb << 20


def _remove_stale_cache_lock(folder) -> None:
    lock = os.path.join(folder, "ticache.lock")
    try:
        age = time.time() - os.stat(lock).st_mtime
        if age > STALE_CACHE_LOCK_S:
            os.unlink(lock)  # (another process starting at the same moment may have removed it first)
            logger.info("removed %s, left %.0f s ago by a Taichi process that did not finish writing its kernel "
                        "cache", lock, age)
    except OSError:
        pass


def init(backend=cpu, precision="32", seed=None, logging_level="warning", debug=False, taichi_speedups=None,
         num_threads=None, performance_mode=False, assets_dir=None, pin_threads=None, **taichi_kwargs):
    """Initialise Taichi on `backend` (gs.cpu or gs.gpu, which is Taichi's CUDA backend) with
    floats of `precision` bits ("32" or "64"). One call per process; later calls with the same
    arguments are no-ops and different ones raise. `taichi_speedups=False` runs on Taichi's own
    front-end and launch functions (solvers/taichi_compat; as GS_TAICHI_SPEEDUPS=0); extra keyword
    arguments go to `ti.init`. `num_threads` (gs.cpu) is the CPU threads of this process, for
    Taichi's kernels (`cpu_max_num_threads`) and torch (`torch.set_num_threads`) alike; by default
    every core, except under torchrun with N processes on the node, where each gets cores // N
    (`default_num_threads`; GS_NUM_THREADS overrides); `gs.cpu_threads` says what it got. Taichi's CPU
    worker threads are each kept on a core of their own where the process's threads span its cores (or
    its rank's share of them): `pin_threads` (GS_PIN_THREADS) False never, True also with fewer threads
    than cores (solvers/taichi_compat/threads.py; `gs.thread_pinning` says what was done). Seeds and
    the environments a rank simulates are the script's business: see
    examples/distributed_identification.py and README's "Several processes". `assets_dir` is a
    folder that morphs' relative file names are looked up in (genesis_lite/loaders/assets.py: like
    the GS_ASSETS_DIR variable; a Genesis install's assets are found without it)."""
    global device, tc_float, np_float, ti_float, _initialized, _init_args, cpu_threads, thread_pinning
    import taichi as ti

    # Genesis's performance_mode trades its compile time for run time; genesis_lite chooses per scene
    # (RigidOptions.specialize_kernels), so the flag is accepted and changes nothing
    if not isinstance(performance_mode, bool):
        raise ValueError(f"gs.init(performance_mode={performance_mode!r}): use True or False")

    if assets_dir is not None:
        from .loaders.assets import set_init_dir

        set_init_dir(assets_dir)  # (not part of the init identity: it changes no kernel)
    if num_threads is None and "cpu_max_num_threads" in taichi_kwargs:
        num_threads = taichi_kwargs.pop("cpu_max_num_threads")
    args = (backend, str(precision), bool(debug), tuple(sorted(taichi_kwargs.items())))
    if taichi_speedups is not None:
        args += (("taichi_speedups", bool(taichi_speedups)),)
    if num_threads is not None:
        args += (("num_threads", num_threads),)
    if pin_threads is None:
        pin_threads = threads_compat.switch_env()
    if pin_threads is not None and not isinstance(pin_threads, bool):
        raise ValueError(f"gs.init(pin_threads={pin_threads!r}): use True, False or None")
    if pin_threads is not None:
        args += (("pin_threads", pin_threads),)
    if _initialized:
        if args != _init_args:
            raise GenesisException(f"gs.init was already called with backend={_init_args[0]!r}, precision={_init_args[1]!r}, "
                                   f"debug={_init_args[2]}, taichi options {dict(_init_args[3])}; now with different "
                                   "arguments. genesis_lite is initialised once per process: restart Python to change them")
        if seed is not None:
            torch.manual_seed(seed)
            np.random.seed(seed)
        return
    if str(precision) not in ("32", "64"):
        raise ValueError(f"gs.init(precision={precision!r}): use \"32\" or \"64\"")
    if backend not in (cpu, gpu):
        raise ValueError(f"gs.init(backend={backend!r}): use gs.cpu or gs.gpu")
    if num_threads is not None and (isinstance(num_threads, bool) or not isinstance(num_threads, int)
                                    or num_threads < 1):
        raise ValueError(f"gs.init(num_threads={num_threads!r}): give a positive integer")
    if taichi_speedups is False:
        taichi_compat.uninstall_speedups()
    level = logging_level.upper() if isinstance(logging_level, str) else logging_level
    logger.setLevel(level)
    if backend == gpu:
        if not torch.cuda.is_available():
            raise GenesisException("gs.init(backend=gs.gpu): torch sees no CUDA device; use backend=gs.cpu")
        arch, device = ti.cuda, torch.device("cuda", 0)
    else:
        arch, device = ti.cpu, torch.device("cpu")
    ti_float = ti.f64 if str(precision) == "64" else ti.f32
    tc_float = torch.float64 if str(precision) == "64" else torch.float32
    np_float = np.float64 if str(precision) == "64" else np.float32
    # Taichi's advanced IR optimisation makes the gradient kernels compile 2-5x slower for ~10 %
    # faster steps, so float64 goes without it. float32 cannot: without it, Taichi 1.7.4's reverse
    # mode gives zero adjoints to every local accumulated in float32 (`acc += x`, and so `dot`, `norm`,
    # `sum`) and crashes on some kernels (tests/test_precision.py checks float32 gradients against float64).
    kw = dict(arch=arch, default_fp=ti_float, default_ip=ti.i32, debug=debug, unrolling_limit=0,
              advanced_optimization=str(precision) == "32",
              log_level=ti.ERROR if logger.level > logging.INFO else ti.INFO, offline_cache=True)
    # Taichi caps its kernel cache at 100 MB and evicts a quarter of it when over: the library's kernels
    # alone pass that (the test suite's checked-runtime cache is ~120 MB), so scenes evicted each other and
    # recompiled on later runs. GS_KERNEL_CACHE_MB sets the cap (default 1024).
    kw["offline_cache_max_size_of_files"] = kernel_cache_cap_bytes()
    kw.update(taichi_kwargs)
    threads = None
    if arch == ti.cpu:
        threads = num_threads if num_threads is not None else default_num_threads()
        if threads is not None:
            # Taichi's CPU thread pool (one per process, sized at ti.init) and torch's intra-op pool:
            # under torchrun (which sets OMP_NUM_THREADS=1 for torch alone) every rank would
            # otherwise start a Taichi thread per core
            kw["cpu_max_num_threads"] = threads
            torch.set_num_threads(threads)
    # Autodiff stacks of a fixed size, never Taichi's adaptive sizing (wrong gradients in 1.7.4):
    # solvers/taichi_compat/adstack.py. The solvers raise it at build for their longest loops.
    kw["ad_stack_size"] = adstack.init_size(taichi_kwargs.get("ad_stack_size"))
    env_cache = None
    if checked_runtime.requested() and arch == ti.cpu:
        # GS_CHECK_AD_STACK=1: stack operations that check their bounds (the test suite runs with it);
        # their kernels never share a cache with the ones compiled against Taichi's own runtime
        kw.setdefault("offline_cache_file_path", checked_runtime.install())
        env_cache = os.environ.pop("TI_OFFLINE_CACHE_FILE_PATH", None)  # (Taichi warns of the override)
    _remove_stale_cache_lock(os.environ.get("TI_OFFLINE_CACHE_FILE_PATH") or kw.get("offline_cache_file_path")
                             or taichi_compat.default_offline_cache_path())
    _freeze_imports()
    before = threads_compat.thread_ids()
    try:
        ti.init(**kw)
    finally:
        if env_cache is not None:
            os.environ["TI_OFFLINE_CACHE_FILE_PATH"] = env_cache
    thread_pinning = threads_compat.place_workers(arch == ti.cpu, pin_threads, threads_compat.thread_ids() - before,
                                                  threads or os.cpu_count() or 1)
    logger.info("Taichi's CPU worker threads: %s", thread_pinning)
    if seed is not None:
        torch.manual_seed(seed)
        np.random.seed(seed)
    cpu_threads = threads if threads is not None else (_available_cores() if arch == ti.cpu else None)
    _init_args = args
    _initialized = True


def _freeze_imports():
    """Move every object alive before ti.init (torch's, Taichi's, numpy's modules: ~10^6 objects, most of
    them torch's) to the collector's permanent generation (gc.freeze), so that neither the collections of
    the run nor the interpreter's exit scan them again: a full collection took 0.10 s with them, and the
    exit after `import torch` alone 0.43 s, 0.15 s without its three collections; the README's main
    example, warm, 5.87 s against 6.38 s (medians of 8, alternated). Objects made later, the scenes and
    the user's, are collected as before; what was alive at gs.init and later becomes garbage in a
    reference cycle is not freed until the process ends. Taichi's runtime object is one of the frozen,
    and Taichi writes its kernel cache when that object's Program is destroyed, which a frozen cycle
    never is at exit: so the exit resets Taichi first (`_reset_taichi_at_exit`), as a script's own
    ti.reset() does (tests/test_build_overheads.py checks that a run leaves its cache). GS_GC_FREEZE=0
    skips both."""
    if os.environ.get("GS_GC_FREEZE", "1") == "0":
        return
    import atexit
    import gc

    gc.freeze()
    atexit.register(_reset_taichi_at_exit)


def _reset_taichi_at_exit():
    import taichi as ti

    ti.reset()


def _assert_initialized():
    if not _initialized:
        raise GenesisException("genesis_lite is not initialised: call gs.init(backend=gs.cpu) first")


from . import grad  # noqa: E402
from .grad.creation import from_torch, ones, rand, tensor, zeros  # noqa: E402
from .scene import Scene  # noqa: E402

__all__ = ["init", "default_num_threads", "Scene", "options", "morphs", "materials", "integrator",
           "constraint_solver", "tc_int", "tc_bool", "cpu", "gpu", "tools", "UID",
           "device", "tensor", "zeros", "ones", "rand", "from_torch", "grad", "surfaces", "GenesisException"]
