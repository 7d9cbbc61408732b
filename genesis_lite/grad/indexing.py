"""Out-of-place, differentiable indexed writes into the torch mirrors of solver state and parameters,
shared by every solver's bridge and entity."""
import torch

from ..errors import SimulationNaNError


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


def raise_if_nan_grad(grads, step):
    for g in grads:
        if g is not None and not torch.isfinite(g).all():
            raise SimulationNaNError(
                f"a gradient became NaN or infinite in the backward pass of step {step}: the rollout is not "
                "differentiable there (a diverging state, a singular pose, or a saturated quantity). Shorten the "
                "horizon, reduce dt, or check the loss.")
