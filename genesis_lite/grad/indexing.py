"""Out-of-place, differentiable indexed writes into the torch mirrors of solver state and parameters,
shared by every solver's bridge and entity."""
import math
from contextlib import contextmanager

import torch

from ..errors import SimulationNaNError


def all_finite(*tensors):
    """Whether every entry of the tensors (None skipped) is finite. Their sums first: one pass that allocates
    nothing, and a NaN or an infinity anywhere makes the sum non-finite; only then entry by entry (finite
    entries whose sum overflows pass there). The NaN watch and the gradient checks run it every step: at 1,024
    envs the rigid state's check took 66 us a step as torch.isfinite, 13 us so."""
    ts = [t.detach() for t in tensors if t is not None]
    if math.isfinite(sum(float(t.sum()) for t in ts)):
        return True
    return all(bool(torch.isfinite(t).all()) for t in ts)


def as_slices(envs, n):
    return len(envs) == n and bool((envs == torch.arange(n, device=envs.device)).all())


def as_span(idx):
    """idx as a slice when it is a run of consecutive indices, else None."""
    if len(idx) == 0:
        return None
    start = int(idx[0])
    if bool((idx == torch.arange(start, start + len(idx), device=idx.device)).all()):
        return slice(start, start + len(idx))
    return None


def index_put(base, envs, idx, values):
    """base with base[envs][:, idx] = values, out of place (differentiable in base and values)."""
    values = values.to(base.dtype).reshape((len(envs), len(idx)) + base.shape[2:])
    out = base.clone()
    span = as_span(idx)
    if span is not None and as_slices(envs, base.shape[0]):
        out[:, span] = values
    else:
        out[envs[:, None], idx[None, :]] = values
    return out


# the gradients handed to the node whose backward is running, and the scene's NaN record (nan_watch.py)
_INCOMING = [None]


@contextmanager
def incoming_grads(grads, watch=None):
    """Within it, raise_if_nan_grad knows the gradients the running backward call received: an env
    whose incoming gradient is exactly zero gets exactly zero gradients (the envs of a step are
    independent), even where its forward state was NaN (an env that failed under
    SimOptions(nan_policy='mask') and that the loss leaves out), instead of the 0 * NaN of the
    adjoint kernels."""
    prev = _INCOMING[0]
    _INCOMING[0] = (grads, watch)
    try:
        yield
    finally:
        _INCOMING[0] = prev


def _zero_envs(grads):
    """Bool (B,) of the envs whose incoming gradients are all exactly zero (None counts as zero)."""
    zero = None
    for g in grads:
        if g is None or g.dim() == 0:
            continue
        z = (g.detach().reshape(g.shape[0], -1) == 0).all(1)
        zero = z if zero is None else zero & z
    return zero


def raise_if_nan_grad(grads, step):
    if all_finite(*grads):
        return
    envs, failed = [], ""
    ctx = _INCOMING[0]
    if ctx is not None:
        incoming, watch = ctx
        zero = _zero_envs(incoming)
        if zero is not None and bool(zero.any()):
            for g in grads:
                if g is not None and g.dim() and g.shape[0] == zero.shape[0]:
                    g[zero.to(g.device)] = 0  # in place: the bridges hand over fresh tensors
            if all_finite(*grads):
                return
        B = zero.shape[0] if zero is not None else 0
        bad = torch.zeros(B, dtype=torch.bool)
        for g in grads:
            if g is not None and g.dim() and g.shape[0] == B:
                bad |= ~torch.isfinite(g.detach()).reshape(B, -1).all(1).cpu()
        envs = torch.nonzero(bad).reshape(-1).tolist()
        if watch is not None and envs and watch.scene.n_envs > 0:
            rec = [(i, int(watch.fail[i])) for i in envs if watch.fail[i] > 0]
            if rec:
                failed = (" The loss depends on env(s) " + ", ".join(f"{i} (NaN since step {k})" for i, k in rec[:8])
                          + ", whose state became NaN (nan_policy='mask'): their gradient is undefined. Leave the "
                          "failed envs out of the loss (e.g. weight each env by ~scene.get_error_envs_mask()), or "
                          "reset them (scene.reset(envs_idx=...)) before the steps the loss reads.")
    where = f" (env{'s' if len(envs) > 1 else ''} {envs[:8]})" if envs and _batched(ctx) else ""
    raise SimulationNaNError(
        f"a gradient became NaN or infinite in the backward pass of step {step}{where}: the rollout is not "
        "differentiable there (a diverging state, a singular pose, or a saturated quantity). Shorten the "
        f"horizon, reduce dt, or check the loss.{failed}")


def _batched(ctx):
    return ctx is not None and ctx[1] is not None and ctx[1].scene.n_envs > 0
