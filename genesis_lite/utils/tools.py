"""Genesis's `gs.tools` (its genesis.utils.tools) that example scripts call: `Timer`."""
from __future__ import annotations

import shutil
import time


class Timer:
    """Wall-clock stamps for a script's phases, as Genesis's `gs.tools.Timer`: `stamp(msg)` prints the
    milliseconds since the previous stamp (or reset) and since the reset, with their means over the stamps
    of the same `msg`, and keeps them in `accu_log[msg] = [count, step_ms_sum, accu_ms_sum]`. `reset()`
    restarts both clocks (a top-level timer, level=0, prints a rule). `skip=True` makes it record and print
    nothing; `level` indents a nested timer's lines. `sync=True` (Genesis's `qd_sync`, formerly `ti_sync`)
    waits for the Taichi kernels queued so far before reading the clock, which matters on gs.gpu, where a
    launch returns before its kernel ends."""

    def __init__(self, skip=False, level=0, sync=False, qd_sync=None, ti_sync=None):
        if not isinstance(level, int) or isinstance(level, bool) or level < 0:
            raise ValueError(f"gs.tools.Timer(level={level!r}): give an integer >= 0 (the nesting depth)")
        self.skip = bool(skip)
        self.level = level
        self.sync = bool(sync or qd_sync or ti_sync)
        self.accu_log = {}
        self.msg_width = 0
        self.reset()

    def _now(self):
        if self.sync:
            import taichi as ti

            ti.sync()
        return time.perf_counter()

    def reset(self):
        self.just_reset = True
        if self.level == 0 and not self.skip:
            print("\u2500" * shutil.get_terminal_size((80, 24)).columns)
        self.prev_time = self.init_time = self._now()

    def stamp(self, msg="", _ratio=1.0):
        """Record and print the time since the previous stamp (step) and since reset (accu), in ms, each
        multiplied by `_ratio` (Genesis's scaling, e.g. 1 / steps for a per-step time)."""
        if self.skip:
            return
        now = self._now()
        step_ms = 1000.0 * (now - self.prev_time) * _ratio
        accu_ms = 1000.0 * (now - self.init_time) * _ratio
        log = self.accu_log.setdefault(msg, [0, 0.0, 0.0])
        log[0] += 1
        log[1] += step_ms
        log[2] += accu_ms
        self.msg_width = max(self.msg_width, len(msg))
        prefix = "    " * self.level
        print(f"{prefix}[{msg.ljust(self.msg_width)}] step: {step_ms:5.3f}ms | accu: {accu_ms:5.3f}ms | "
              f"step_avg: {log[1] / log[0]:5.3f}ms | accu_avg: {log[2] / log[0]:5.3f}ms")
        self.prev_time = self._now()
        self.just_reset = False
