"""gs.grad.check: autograd gradients of a user's rollout against central finite differences."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Dict, List, Sequence, Union

import torch


@dataclass
class GradCheckReport:
    """Per input: the autograd gradient, the finite-difference gradient and their relative error
    ||g_ad - g_fd|| / max(||g_fd||, atol)."""

    names: List[str]
    autograd: List[torch.Tensor]
    finite_diff: List[torch.Tensor]
    rel_err: List[float]
    eps: float
    tol: float
    ok: bool = field(init=False)

    def __post_init__(self):
        self.ok = all(e <= self.tol for e in self.rel_err)

    @property
    def max_rel_err(self) -> float:
        return max(self.rel_err) if self.rel_err else 0.0

    def __str__(self):
        lines = [f"gradient check (central differences, eps={self.eps:g}, tolerance {self.tol:g}): "
                 f"{'OK' if self.ok else 'FAILED'}"]
        for n, a, f, e in zip(self.names, self.autograd, self.finite_diff, self.rel_err):
            lines.append(f"  {n:<20s} rel.err {e:9.2e}  |grad| {f.norm().item():10.4e}  "
                         f"{'ok' if e <= self.tol else 'MISMATCH'}")
        return "\n".join(lines)


def check(fn: Callable[..., torch.Tensor], inputs: Union[Sequence[torch.Tensor], Dict[str, torch.Tensor]],
          eps: float = 1e-6, tol: float = 1e-6, atol: float = 1e-10) -> GradCheckReport:
    """Compare torch.autograd gradients of the scalar `fn(*inputs)` (a whole rollout: reset, set
    inputs, step, loss) with central finite differences in float64, element by element, with steps
    eps * max(1, |x|).
    `inputs` is a list or a name -> tensor dict; returns a GradCheckReport (printable, `.ok`)."""
    if isinstance(inputs, dict):
        names, xs = list(inputs.keys()), list(inputs.values())
    else:
        xs = list(inputs)
        names = [f"input[{i}]" for i in range(len(xs))]
    for n, x in zip(names, xs):
        if x.dtype != torch.float64:
            raise TypeError(f"gs.grad.check: {n} has dtype {x.dtype}; finite differences need float64 "
                            "(gs.init(precision=\"64\") and float64 inputs)")
    leaves = [x.detach().clone().requires_grad_(True) for x in xs]
    out = fn(*leaves)
    if out.numel() != 1:
        raise ValueError(f"gs.grad.check: fn must return a scalar, got shape {tuple(out.shape)}")
    ad = torch.autograd.grad(out, leaves, allow_unused=True)
    ad = [torch.zeros_like(l) if g is None else g.detach() for g, l in zip(ad, leaves)]
    fds = []
    with torch.no_grad():
        for i, x in enumerate(xs):
            fd = torch.zeros_like(x, dtype=torch.float64)
            flat = fd.view(-1)
            for k in range(x.numel()):
                # step relative to the entry's magnitude: absolute steps drown in round-off on large entries
                h = eps * max(1.0, abs(float(x.reshape(-1)[k])))
                vals = []
                for sgn in (1.0, -1.0):
                    args = [l.detach().clone() for l in leaves]
                    args[i].view(-1)[k] += sgn * h
                    vals.append(float(fn(*args)))
                flat[k] = (vals[0] - vals[1]) / (2 * h)
            fds.append(fd)
    errs = [float((a - f).norm() / max(f.norm().item(), atol)) for a, f in zip(ad, fds)]
    return GradCheckReport(names, ad, fds, errs, eps, tol)
