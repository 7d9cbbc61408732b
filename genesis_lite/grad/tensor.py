"""genesis_lite.grad.Tensor: the torch.Tensor subclass returned by every getter."""
import torch


class Tensor(torch.Tensor):
    """A torch.Tensor that came out of (or goes into) a genesis_lite scene. It behaves exactly like
    torch.Tensor (autograd included); the subclass marks where it came from."""

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        return super().__torch_function__(func, types, args, kwargs or {})


def wrap(t: torch.Tensor) -> Tensor:
    return t.as_subclass(Tensor)
