"""A watch on the gradient of the state as a backward pass carries it back through a rollout.

In a chaotic or unstable rollout (a double pendulum swinging for seconds, a controller that
diverges) the gradient with respect to early states and inputs grows exponentially with the horizon:
it is correct, but it measures the sensitivity to tiny perturbations and is useless as a descent
direction. Nothing fails, so the user sees an optimiser that does not converge, or NaNs much later.

Each step node's backward hands `GrowthMonitor.record` the gradient of its outputs (the state after
the step, |g_in|) and of its state inputs (the state before it, |g_out|). The amplification of the
backward pass from a later state back to an earlier one is the product of the per-step ratios
|g_out| / |g_in| between them: the growth of the propagated gradient itself, so loss terms that join
at some steps (a loss summed over the rollout, weighted or discounted) neither raise nor mask it. At
the end of the backward pass (a callback queued on torch's engine) the largest amplification over any
window of steps is compared with GROWTH_WARN_FACTOR, and one GradientGrowthWarning per backward pass
names the window.

Cost: nothing in the forward pass. In backward, each step node's state gradients are held (32 steps at
most) and their norms taken in one batched op per 32 steps, kept as tensors (no device sync per step);
the arithmetic runs once per backward pass: well under 1 % of a 100-step Panda backward.
"""
from __future__ import annotations

import math
import warnings

import torch

from ..errors import GradientGrowthWarning

# Warn when the backward pass amplifies the gradient of the state by more than this factor over any
# window of steps. A stable rollout stays within a few orders of magnitude even with stiff gains (the
# norm mixes position and velocity gradients, whose ratio alone can be ~ the stiffest natural frequency);
# 1e6 is beyond that and is reached by a chaotic double pendulum in a few seconds. math.inf turns the
# watch off (nothing is recorded).
GROWTH_WARN_FACTOR = 1e6


def _queue_end_of_backward(fn):
    """Run fn once torch's current backward pass has finished (False where torch cannot)."""
    try:
        torch.autograd.Variable._execution_engine.queue_callback(fn)
        return True
    except (AttributeError, RuntimeError):
        return False


class GrowthMonitor:
    """Per simulator: records each step node's gradient norms during a backward pass, warns at its end."""

    BATCH = 32  # step nodes whose gradients are held before their norms are taken in one batched op

    def __init__(self):
        self.reset()

    def reset(self):
        self._active = False  # a backward pass is being recorded
        self._queued = False
        self._last_step = None
        self._pending = []  # per node not reduced yet: its output gradients, then its state-input gradients
        self._steps = []  # node step index s (its input is the state after s steps, its output after s + 1)
        self._n_in = []
        self._chunks = []  # (n_nodes, n_tensors) norms of the reduced nodes, in recording order

    def record(self, step, incoming, outgoing):
        """One step node's backward: `incoming` the gradients of its outputs, `outgoing` those of its
        state inputs (None where not needed)."""
        if not GROWTH_WARN_FACTOR < math.inf:
            return
        if not self._active or self._last_step is None or step >= self._last_step:
            # a new backward pass (nodes of one pass run in decreasing step order); a pass that raised
            # before its end leaves its records behind: they are dropped here
            self.reset()
            self._active = True
            self._queued = _queue_end_of_backward(self.finish)
        self._last_step = step
        ins = [g for g in incoming if g is not None]
        outs = [g for g in outgoing if g is not None]
        if ins and outs:
            self._steps.append(step)
            self._n_in.append(len(ins))
            self._pending.append(ins + outs)
            if len(self._pending) >= self.BATCH:
                self._reduce()
        if not self._queued and step == 0:
            self.finish()

    def _reduce(self):
        """Norms of the pending nodes' gradients: one stack and one norm per tensor slot when the nodes
        have the same shapes (a few microseconds of dispatch per op dominate these small tensors)."""
        pending, self._pending = self._pending, []
        if not pending:
            return
        shapes = [tuple(g.shape) for g in pending[0]]
        if all([tuple(g.shape) for g in p] == shapes for p in pending):
            cols = [torch.linalg.vector_norm(torch.stack([p[j] for p in pending]).flatten(1), dim=1)
                    for j in range(len(shapes))]
            self._chunks.append(torch.stack(cols, 1))
        else:
            for p in pending:
                self._chunks.append(torch.stack([torch.linalg.vector_norm(g) for g in p])[None])

    def finish(self):
        """End of a backward pass: warn once if some window of steps amplified the gradient too much."""
        self._reduce()
        steps, n_in, chunks = self._steps, self._n_in, self._chunks
        self.reset()
        if not steps:
            return
        rows = [row for c in chunks for row in c.detach().double().cpu().tolist()]  # one transfer per chunk
        worst = _worst_growth(steps, n_in, rows)
        if worst is None or worst[0] <= math.log10(GROWTH_WARN_FACTOR):
            return
        log_factor, (late, late_norm), (early, early_norm) = worst
        warnings.warn(
            f"gradient growth: the backward pass amplified the gradient of the state by {10 ** log_factor:.1e} from "
            f"step {late} back to step {early} (backward through steps {early + 1}-{late}; |dL/dstate| "
            f"{late_norm:.1e} after step {late}, {early_norm:.1e} after step {early}; warning threshold "
            f"{GROWTH_WARN_FACTOR:.0e}, genesis_lite.grad.growth.GROWTH_WARN_FACTOR). The rollout is chaotic or "
            "unstable over this horizon, so its gradient measures the sensitivity to tiny perturbations rather "
            "than a useful descent direction: shorten the horizon (or optimise over shorter windows), add damping "
            "or lower the gains, reduce dt, or use a loss less sensitive to the exact late states.",
            GradientGrowthWarning, stacklevel=2)


def _worst_growth(steps, n_in, rows):
    """(log10 factor, (later state, its norm), (earlier state, its norm)) of the window of steps with
    the largest product of per-step ratios |g_out| / |g_in|, or None. Nodes come in the order torch ran
    them (decreasing step); a node with a zero or non-finite ratio cuts the chain (nothing propagates
    through it, or the NaN check reports it)."""
    best = None
    low = None  # (cumulative log10 amplification, state, norm) of the smallest point of the current chain
    P = 0.0
    for s, k, row in zip(steps, n_in, rows):
        g_in = math.sqrt(sum(x * x for x in row[:k]))
        g_out = math.sqrt(sum(x * x for x in row[k:]))
        if not (g_in > 0 and g_out > 0 and math.isfinite(g_in) and math.isfinite(g_out)):
            low = None
            continue
        if low is None or P < low[0]:
            low = (P, s + 1, g_in)
        P += math.log10(g_out / g_in)
        if best is None or P - low[0] > best[0]:
            best = (P - low[0], (low[1], low[2]), (s, g_out))
    return best
