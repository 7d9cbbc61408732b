"""Every use of Taichi's private API in genesis_lite, behind a check of the Taichi version it was written for.

- `frontend`: lighter Python-side bookkeeping in Taichi's kernel front end (the same IR and cache
  keys) and a launch path that skips Taichi's per-call key building for repeated launches.
- `adstack`: the size of the autodiff stacks of reverse-mode kernels (the compile option
  `ad_stack_size`), always fixed, never Taichi's adaptive sizing.
- `checked_runtime`: a copy of Taichi's LLVM runtime whose autodiff-stack operations check their
  bounds, for the test suite and for GS_CHECK_AD_STACK=1 (Taichi 1.7.4 checks them in no mode).
- `compile_options`: Taichi's advanced IR optimisation switched around forward and adjoint launches.
- `threads`: Taichi's CPU worker threads (started by ti.init, woken by every parallel launch) each kept on
  a core of its own by gs.init where the process's threads span its cores (GS_PIN_THREADS=0: never).
- `config()`, `inside_kernel()`, `subscript()`: the compile configuration in force and the two
  `taichi.lang.impl` calls the solvers' static-or-runtime size lookups need; `compiling_adjoint()`: whether
  the kernel being compiled is one Taichi differentiates (its autodiff mode);
  `default_offline_cache_path()`: Taichi's default kernel-cache folder (gs.init clears a stale lock there).

The speed-ups (`frontend`) are one switch: GS_TAICHI_SPEEDUPS=0 in the environment, or
`gs.init(taichi_speedups=False)`, keeps Taichi's own functions everywhere (the two finer switches
GS_TAICHI_FAST_FRONTEND=0 / GS_TAICHI_FAST_LAUNCH=0 remain). They are installed only on the Taichi
version they were written for (`TAICHI_VERSION`); on another one they stay off and say so in a log line.
Nothing here changes a computed value: the suite checks the IR, the offline-cache keys and bitwise
gradients with and without them (tests/test_build_overheads.py, tests/test_determinism.py), and CI
runs the gradient matrix once with them off.
"""
from __future__ import annotations

import logging
import os

from . import frontend as _frontend

_frontend.import_taichi()  # (before the first `import taichi` below: see its docstring)

TAICHI_VERSION = (1, 7, 4)
_log = logging.getLogger("genesis_lite")


def installed_version() -> tuple:
    import taichi as ti

    v = ti.__version__  # a tuple in Taichi 1.7
    return tuple(int(x) for x in (v.split(".") if isinstance(v, str) else v)[:3])


def version_ok() -> bool:
    """True when the installed Taichi is the version these helpers were written and checked for."""
    try:
        return installed_version() == TAICHI_VERSION
    except Exception:
        return False


def cache_root() -> str:
    """genesis_lite's on-disk caches: $GS_CACHE_DIR, else ~/.cache/genesis_lite ($XDG_CACHE_HOME honoured)."""
    return os.environ.get("GS_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "genesis_lite")


def speedups_requested() -> bool:
    return os.environ.get("GS_TAICHI_SPEEDUPS", "1") != "0"


def install_speedups() -> dict:
    """Install the front-end and launch speed-ups (before any kernel is decorated) when the switch
    allows and Taichi is TAICHI_VERSION; returns which are in place."""
    from . import frontend

    if not speedups_requested():
        return {"frontend": False, "fast_launch": False}
    if not version_ok():
        _log.info("Taichi %s is not the %s that genesis_lite's front-end speed-ups were written for: running "
                  "without them", ".".join(map(str, installed_version())), ".".join(map(str, TAICHI_VERSION)))
        return {"frontend": False, "fast_launch": False}
    frontend.install()
    frontend.install_fast_launch()
    return frontend.installed()


def uninstall_speedups() -> None:
    """Taichi's own front-end and launch functions from now on."""
    from . import frontend

    frontend.uninstall()


from taichi.lang import impl as _impl  # noqa: E402

# the compile configuration kernels compiled from now on get
config = _impl.current_cfg
# whether Python is running inside a kernel's compilation (a size lookup then emits a field load)
inside_kernel = _impl.inside_kernel


def compiling_adjoint() -> bool:
    """Inside a kernel's compilation: whether Taichi may differentiate what is being emitted, i.e. the kernel
    is not a primal one (autodiff mode NONE). A primal kernel is never differentiated: its adjoint (`.grad`)
    is another kernel, compiled anew from the same source in its own mode, so a stage may emit forms there
    that Taichi's reverse mode could not take (a plain read-modify-write instead of `+=`). Unknown (outside a
    kernel, or another Taichi whose runtime says nothing of it): True, the form every kernel can take."""
    try:
        from taichi.lang.enums import AutodiffMode
    except ImportError:
        return True
    kernel = getattr(_impl.get_runtime(), "current_kernel", None)
    return kernel is None or getattr(kernel, "autodiff_mode", None) != AutodiffMode.NONE


def subscript(field, *index):
    """A field load emitted while compiling a kernel (`impl.subscript` without an AST node)."""
    return _impl.subscript(None, field, *index)


def default_offline_cache_path() -> str:
    """Taichi's kernel-cache folder when neither ti.init nor TI_OFFLINE_CACHE_FILE_PATH names one."""
    return _impl.default_cfg().offline_cache_file_path


def time_kernel_work() -> dict:
    """From now on, accumulate into the returned dict the seconds spent in Taichi's kernel front end
    ("frontend": Python AST to IR) and in kernel launches ("launch": a first launch loads the kernel from
    the offline cache or compiles it, then runs it). For benchmarks (benchmarks/bench_build.py)."""
    from taichi.lang import kernel_impl

    import time

    acc = {"frontend": 0.0, "launch": 0.0}
    materialize, launch = kernel_impl.Kernel.materialize, kernel_impl.Kernel.launch_kernel

    def timed_materialize(self, key=None, args=None, arg_features=None):
        t = time.perf_counter()
        try:
            return materialize(self, key, args, arg_features)
        finally:
            acc["frontend"] += time.perf_counter() - t

    def timed_launch(self, t_kernel, *args):
        t = time.perf_counter()
        try:
            return launch(self, t_kernel, *args)
        finally:
            acc["launch"] += time.perf_counter() - t

    kernel_impl.Kernel.materialize, kernel_impl.Kernel.launch_kernel = timed_materialize, timed_launch
    return acc
