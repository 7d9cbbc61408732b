"""Every use of Taichi's private API in genesis_lite, behind a check of the Taichi version it was written for.

- `adstack`: the size of the autodiff stacks of reverse-mode kernels (the compile option
  `ad_stack_size`, read and raised through `taichi.lang.impl.current_cfg()`).
- `checked_runtime`: a copy of Taichi's LLVM runtime whose stack operations check their bounds, for
  the test suite and for `GS_CHECK_AD_STACK=1` (Taichi 1.7.4 checks them in no mode, debug included).

These are written against `TAICHI_VERSION`; `version_ok()` says whether the installed Taichi is that one.
"""
from __future__ import annotations

TAICHI_VERSION = (1, 7, 4)


def installed_version() -> tuple:
    import taichi as ti

    return tuple(int(v) for v in ti.__version__[:3])


def version_ok() -> bool:
    """True when the installed Taichi is the version these helpers were written and checked for."""
    try:
        return installed_version() == TAICHI_VERSION
    except Exception:
        return False
