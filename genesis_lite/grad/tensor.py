"""genesis_lite.grad.Tensor: the torch.Tensor subclass returned by every getter."""
import torch


class Tensor(torch.Tensor):
    """A torch.Tensor that came out of (or goes into) a genesis_lite scene. It behaves exactly like
    torch.Tensor (autograd included); the subclass marks where it came from."""

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        return super().__torch_function__(func, types, args, kwargs or {})

    def backward(self, gradient=None, retain_graph=None, create_graph=False, inputs=None):
        if not self.requires_grad:
            from ..errors import GenesisException

            raise GenesisException(
                "backward() on a tensor that does not require grad: it was computed from a scene's getters while "
                "nothing upstream required grad. A scene gives gradients only when built with "
                "gs.options.SimOptions(requires_grad=True) and given, through a setter or a control, a tensor "
                "with requires_grad=True (set_dofs_velocity, control_dofs_force, set_links_mass, ...), outside "
                "torch.no_grad().")
        return super().backward(gradient, retain_graph, create_graph, inputs)

    def zero_grad(self):
        """Zero this leaf's accumulated gradient in place (Genesis's gs.Tensor.zero_grad); nothing when it has none."""
        if self.grad is not None:
            self.grad.zero_()

    def __format__(self, spec):
        # torch formats 0-d tensors with a spec (f"{x:.3f}") only for the exact torch.Tensor type
        return torch.Tensor.__format__(self.as_subclass(torch.Tensor), spec)


def wrap(t: torch.Tensor) -> Tensor:
    return t.as_subclass(Tensor)
