"""A setter's value that is a view of a larger tensor requiring grad (`controls[t]` of a (T, envs, dofs) leaf).

Torch's backward of a view builds a gradient of the whole base for each view (the backward of `controls[t]`
fills a zero tensor the size of all the controls, puts the row in, and adds it to the sum of the others), so a
rollout that feeds `controls[t]` step after step pays T full-size fills and adds in its backward: O(T^2), 1.7 ms
a step for a Panda's 100 x 1,024 x 9 controls against a backward of ~6 ms a step.

Here the value enters the step node through two small nodes instead. One node per base and rollout (`_BaseNode`,
made at the first view of that base) has the base as its input; each view's node (`_ViewNode`) takes the values
of the view, and in backward adds its gradient into a buffer of the base's shape, in place, at the view's
place, returning nothing to torch. The base node consumes every view node's output, so torch runs it after all
of them in a backward pass; it hands the buffer to the base. One fill of the base per backward pass, and a
row's add per step. Buffers belong to one backward pass (torch's graph task): a pass that stopped half way
leaves nothing in the next.

Only where it is exact: a base that is contiguous, a view whose elements do not overlap, and neither a hook nor
retain_grad() on the view (the view itself is not in the graph: `torch.autograd.grad(loss, view)` cannot be
asked; ask for the base). A base changed in place since its node was made gets a new node (the views of the new
version must reach the new version's history). Only where it pays: a base with at least ROUTE_MIN elements
outside the view (a view of all of its base, such as a gs.Tensor, an alias of a plain tensor, costs torch no
more than its size; at 1 env a Panda's 100 x 9 controls cost torch less than the two nodes). Elsewhere, and
everywhere with the environment variable GS_ROUTE_VIEWS=0, the value keeps torch's own view backward.
"""
import os
import weakref

import torch

from . import torch_compat


# the least number of the base's elements outside the view for which routing pays: torch's backward of a view fills
# and adds the whole base (~1.8 ns an element in float64 on this machine), the two nodes here cost ~25 us in the
# forward and ~10 us in the backward (at 1 env, a Panda's 100 x 9 controls, routing made the rollout 8 % slower)
ROUTE_MIN = 1 << 15


class _Sum:
    """The base's gradient summed over the view nodes' backward calls of one backward pass."""

    def __init__(self, base):
        self.shape, self.dtype, self.device = base.shape, base.dtype, base.device
        self.task, self.buf = None, None

    def add(self, geometry, g):
        task = torch_compat.graph_task_id()
        if self.task != task:  # a new backward pass: nothing of an earlier one (say, one that raised) is kept
            self.task, self.buf = task, torch.zeros(self.shape, dtype=self.dtype, device=self.device)
        self.buf.as_strided(*geometry).add_(g)  # g has the view's dtype, the base's (_geometry)

    def take(self):
        """The sum of this backward pass, or None where no view node of it ran; the buffer goes to torch (which
        may keep it as the leaf's .grad), so the next pass fills a new one."""
        buf = self.buf if self.task == torch_compat.graph_task_id() else None
        self.task, self.buf = None, None
        return buf


class _BaseNode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, base, total):
        ctx.total = total
        ctx.set_materialize_grads(False)
        return base.new_zeros(())  # a token: only its graph edge matters

    @staticmethod
    def backward(ctx, _):
        return ctx.total.take(), None


class _ViewNode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, token, values, total, geometry):
        ctx.total, ctx.geometry = total, geometry
        ctx.set_materialize_grads(False)
        return values.clone()

    @staticmethod
    def backward(ctx, g):
        if g is not None:
            ctx.total.add(ctx.geometry, g)
        return None, None, None, None


def _geometry(x, base):
    """The view's (shape, strides, offset) in a contiguous buffer of the base, where its gradient can be added
    there in place: a contiguous base holding every element of the view, and a view whose elements are distinct
    (sorted by stride, each dimension steps past the span of the smaller ones); else None."""
    if not base.is_contiguous() or x.dtype != base.dtype or x.device != base.device:
        return None
    offset = x.storage_offset() - base.storage_offset()
    extent = 1  # one past the largest offset the smaller dimensions reach
    for stride, size in sorted((st, s) for s, st in zip(x.shape, x.stride()) if s > 1):
        if stride < extent:
            return None
        extent += stride * (size - 1)
    if offset < 0 or offset + extent > base.numel():
        return None
    return tuple(x.shape), tuple(x.stride()), offset


def _base_of(x):
    """The tensor whose history x's gradient joins: the tensor x views where that requires grad (a torch leaf,
    or a computed tensor); else the leaf at the end of x's chain of views (a gs.Tensor leaf is an alias of a
    tensor that does not require grad: gs.zeros(..., requires_grad=True)), or None."""
    root = torch_compat.view_base(x)
    if root is None:
        return None
    if root.requires_grad:
        return root
    node = x.grad_fn
    for _ in range(16):  # a view of a leaf: only views between them (any other op would make a new base)
        if node is None:
            return None
        leaf = getattr(node, "variable", None)  # an AccumulateGrad node's tensor
        if leaf is not None:
            same = leaf.untyped_storage().data_ptr() == root.untyped_storage().data_ptr()
            return leaf if same and leaf.requires_grad else None
        node = node.next_functions[0][0] if node.next_functions else None
    return None


def routed(x, nodes):
    """x itself, or, for a view of a base that requires grad (see the module's docstring), the same values
    through a view node of the base's node in `nodes` (a dict the simulator clears at each new rollout)."""
    if not (torch.is_tensor(x) and x.grad_fn is not None and torch.is_grad_enabled() and torch_compat.can_route()):
        return x
    if os.environ.get("GS_ROUTE_VIEWS", "1") == "0":  # torch's own backward (benchmarks/bench_view_grads.py)
        return x
    base = _base_of(x)
    if base is None or base.numel() - x.numel() < ROUTE_MIN or torch_compat.has_hooks(x):
        return x
    geometry = _geometry(x, base)
    if geometry is None:
        return x
    key = id(base)
    entry = nodes.get(key)
    if entry is None or entry[0]() is not base or entry[1] != torch_compat.version(base):
        total = _Sum(base)
        entry = (weakref.ref(base), torch_compat.version(base), _BaseNode.apply(base, total), total)
        nodes[key] = entry
    _, _, token, total = entry
    return _ViewNode.apply(token, x.detach(), total, geometry)
