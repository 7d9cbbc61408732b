"""Torch bridge: the gs.grad.Tensor subclass, tensor creation and gradient checking."""
from .tensor import Tensor  # noqa: F401
from .check import check, GradCheckReport  # noqa: F401
