"""Per-step, per-env detection of NaN / inf in the scene's state, and what to do about it
(SimOptions.nan_policy).

After every scene step each solver's bridge is asked one cheap question. Without gradients the
state is in the solver's fields: the rigid solver's fused step records, per env, the first step whose
state is not finite while it copies the state (so nearly free) and returns how many envs have such a
record with the launch; the MPM solver runs one pass over its particles that does the same. With
gradients the state is a torch tensor and is checked there. Only when the count grew does the scene
read the state to find the envs, the entity and the quantity.

nan_policy="raise" (default): a SimulationNaNError names the step, the env(s), the entity and the
quantity. "mask": the failed envs are logged once, recorded (scene.get_error_envs_mask()) and keep
stepping as NaN, each env being independent of the others, until scene.reset(envs_idx=mask) restores
them. "off": no check after the steps (get_error_envs_mask() then checks the current state).
"""
from __future__ import annotations

import logging

import numpy as np
import torch

from .errors import SimulationNaNError

logger = logging.getLogger("genesis_lite")

ADVICE = ("The simulation diverged: reduce dt or raise substeps, lower gains/stiffness (or, for MPM, raise "
          "substeps or lower E), or check the inputs set before this step.")


class NaNWatch:
    """The failed envs of one scene: `fail[i_b]` is the first step after which env i_b's state was not
    finite (0: none since build or since it was reset)."""

    def __init__(self, scene, policy):
        self.scene = scene
        self.policy = policy
        self.B = max(scene.n_envs, 1)
        self.fail = np.zeros(self.B, dtype=np.int64)
        self._seen = {}  # bridge -> the count of envs with a record it reported last

    def _bridges(self):
        s = self.scene
        out = []
        if s._rigid is not None and s.rigid_options.check_nan:
            out.append(s._rigid)
        if s._mpm is not None:
            out.append(s._mpm)
        return out

    @property
    def any_failed(self):
        return bool(self.fail.any())

    def _poll(self, step, force=False):
        """{env: description} of envs found non-finite now that had no record; records them at `step`."""
        new = {}
        for b in self._bridges():
            n = b.count_nonfinite(step)
            if n is not None and not force and n == self._seen.get(b, 0):
                continue  # the fused check found nothing new: no state read
            self._seen[b] = n if n is not None else 0
            for i_b, what in b.check_finite().items():
                if self.fail[i_b] == 0:
                    new.setdefault(i_b, what)
        for i_b in new:
            self.fail[i_b] = step
        return new

    def after_step(self, step):
        if self.policy == "off":
            return
        new = self._poll(step)
        if not new:
            return
        batched = self.scene.n_envs > 0
        envs = sorted(new)
        more = " ..." if len(envs) > 8 else ""
        in_envs = f"in env{'s' if len(envs) > 1 else ''} {envs[:8]}{more}"
        if self.policy == "raise":
            if batched:
                where = "; ".join(f"env {i}: {new[i]}" for i in envs[:8]) + more
                raise SimulationNaNError(
                    f"the state became NaN or infinite at step {step} {in_envs} ({where}). {ADVICE} To let the other envs go on, "
                    "build with SimOptions(nan_policy='mask') and restore the failed ones with "
                    "scene.reset(envs_idx=scene.get_error_envs_mask()).")
            raise SimulationNaNError(f"{new[0]} at step {step}: the state became NaN or infinite. {ADVICE}")
        logger.warning(
            f"scene: the state became NaN or infinite at step {step} {in_envs} ({new[envs[0]]}); nan_policy='mask': "
            f"{'they go' if len(envs) > 1 else 'it goes'} on as NaN, the other envs are not affected. "
            "scene.get_error_envs_mask() marks the failed envs; scene.reset(envs_idx=mask) restores them.")

    def mask(self, step):
        """Bool tensor (B,) of the envs with a record; checks the state now when the scene does not
        check it after every step (policy 'off', or a RigidOptions(check_nan=False) rigid solver)."""
        if self.policy == "off":
            self._poll(step, force=True)
        return torch.as_tensor(self.fail > 0)

    def clear(self, envs_mask):
        """Forget the records of the envs in envs_mask (numpy bool (B,)), in the solvers too."""
        self.fail[envs_mask] = 0
        s = self.scene
        for b in (s._rigid, s._mpm):
            if b is not None:
                self._seen[b] = b.count_nonfinite(None, clear=envs_mask) or 0

    # ---------------------------------------------------------------- backward
    def grad_context(self):
        """For a backward call: None when no env has failed, else (failed envs mask, fail steps)."""
        if not self.any_failed:
            return None
        return self.fail > 0, self.fail
