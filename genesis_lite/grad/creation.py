"""Tensor creation ops on gs.device in the scene precision (Genesis's gs.tensor, gs.zeros, ...)."""
import torch

from .tensor import wrap


def _kw(dtype):
    import genesis_lite as gs

    gs._assert_initialized()
    return dict(dtype=dtype or gs.tc_float, device=gs.device)


def _leaf(t, requires_grad):
    # as_subclass of a tensor that requires grad is a non-leaf alias whose .grad is never filled:
    # wrap first, then ask for gradients, so the user's tensor is a leaf an optimizer can update
    out = wrap(t)
    return out.requires_grad_(True) if requires_grad else out


def tensor(data, dtype=None, requires_grad=False):
    """A gs.grad.Tensor with a copy of `data` on gs.device."""
    return _leaf(torch.tensor(data, **_kw(dtype)), requires_grad)


def zeros(*shape, dtype=None, requires_grad=False):
    return _leaf(torch.zeros(*shape, **_kw(dtype)), requires_grad)


def ones(*shape, dtype=None, requires_grad=False):
    return _leaf(torch.ones(*shape, **_kw(dtype)), requires_grad)


def rand(*shape, dtype=None, requires_grad=False):
    return _leaf(torch.rand(*shape, **_kw(dtype)), requires_grad)


def from_torch(t, dtype=None, requires_grad=None):
    """`t` moved to gs.device and the scene precision, keeping its autograd history."""
    import genesis_lite as gs

    gs._assert_initialized()
    out = t.to(device=gs.device, dtype=dtype or gs.tc_float)
    if requires_grad is not None and out.requires_grad != requires_grad:
        return _leaf(out.detach(), requires_grad)
    return wrap(out)
