"""Every use of torch's private API, in one place, with the versions it was checked on.

views.py routes a view's gradient to its base itself, which needs: the base of a view (`Tensor._base`), a
tensor's in-place version counter (`Tensor._version`), whether a tensor has a backward hook
(`Tensor._backward_hooks`) and which backward pass is running (`torch._C._current_graph_task_id`, what
torch.utils.checkpoint uses). Checked on torch 2.13 only (the version pyproject.toml pins): on any other
version, or one without these, `can_route()` is False and views keep torch's own backward (slower, exact) until
the range below is widened after checking tests/test_grad_views.py there."""
import torch

CHECKED = ((2, 13), (2, 13))  # first and last minor version on which views.py's uses were checked


def _minor(version: str):
    parts = version.split("+")[0].split(".")
    try:
        return int(parts[0]), int(parts[1])
    except (IndexError, ValueError):
        return None


_MINOR = _minor(torch.__version__)
_OK = (_MINOR is not None and CHECKED[0] <= _MINOR <= CHECKED[1]
       and hasattr(torch._C, "_current_graph_task_id") and hasattr(torch.Tensor, "_base")
       and hasattr(torch.Tensor, "_version"))


def can_route() -> bool:
    return _OK


def graph_task_id():
    """An id of the backward pass running now (-1 outside one)."""
    return torch._C._current_graph_task_id()


def view_base(x):
    """The tensor x is a view of (None when x owns its storage)."""
    return x._base


def version(t) -> int:
    """t's in-place version counter: it grows with every in-place change."""
    return t._version


def has_hooks(x) -> bool:
    """Whether x has a backward hook or retains its gradient (then x itself must stay in the graph)."""
    return bool(getattr(x, "_backward_hooks", None)) or bool(x.retains_grad)
