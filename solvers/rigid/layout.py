"""Env-major placement of per-env fields, shared by the rigid core (core.RigidCore) and the contact
solver (FieldTree), and the zeroing of a scene's block of them (ZeroPlan).

A step reads one env's links, dofs, slots and banks across dozens of fields. A field per array puts
them dozens of streams apart, at offsets that are multiples of large powers of two (env capacity x
element capacity x 4 bytes), which fall into the same cache sets, and leaves the capacity's unused
elements in the middle of every stream. Placed env-major, each env's data is one contiguous block,
the fields of one element side by side: one env's step walks a few KiB, and unused elements are
never read (ANYmal's batched step ran ~20 % faster once the contact fields were placed so too).
"""
import taichi as ti


def place_env_major(parent, B, groups):
    """Place per-env fields under `parent` (ti.root or a FieldsBuilder). groups: (env axis, extents of the
    other axes, fields), in placement order; the env axis is 0 for fields [B, ...] and 1 for fields
    [n, B, ...] (indexed slot first, laid out env first). One env node of B cells per env axis; each
    group's fields share the cells of one dense node under it. Empty groups are skipped."""
    envs = {}
    for axis, rest, xs in groups:
        if not xs:
            continue
        if axis not in envs:
            envs[axis] = parent.dense(ti.axes(axis), B)
        if rest:
            others = tuple(a for a in range(len(rest) + 1) if a != axis)
            envs[axis].dense(ti.axes(*others), rest).place(*xs)
        else:
            envs[axis].place(*xs)


def env_axis(shape, B):
    """The env axis of a per-env field of `shape`: 0 for (B, ...), 1 for (1, B, ...) (a leading axis of 1,
    the slot of a bank with one), None for a field that is not per env (or when B is None). The one rule
    by which FieldTree places its fields and ZeroPlan finds the env axis of a solver's own."""
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    if B is None:
        return None
    if shape[0] == B:
        return 0
    if len(shape) >= 2 and shape[0] == 1 and shape[1] == B:
        return 1
    return None


def by_env_axis(fields, B):
    """fields (a FieldTree's, or their adjoints) sorted by env_axis into ([env, ...], [1, env, ...]), the
    way ZeroPlan takes them; ValueError for a field without an env axis of length B (it cannot be zeroed
    env by env)."""
    out = ([], [])
    for x in fields:
        axis = env_axis(x.shape, B)
        if axis is None:
            raise ValueError(f"a field of shape {x.shape} has no env axis of length B = {B} (first, or second "
                             f"after a leading 1); it cannot be zeroed env by env")
        out[axis].append(x)
    return out


class FieldTree:
    """Fields placed in an SNode tree of their own. Taichi caps the SNodes of one tree (1024; every
    component of a vector or matrix field and of its adjoint is one), and a scene's contact fields with
    their adjoints would take the rigid solver's tree past it: each AccBank and the rest of the contact
    solver get their own tree. finalize() after the last field, before any is used.

    Fields with an env axis of length `B` (first, or second after a leading axis of 1: shapes (B, ...)
    and (1, B, ...)) are placed env-major by finalize() (layout.place_env_major, as the core's), fields
    of the same shape side by side."""

    def __init__(self, dtype, grad, B=None):
        self.fb = ti.FieldsBuilder()
        self.dtype, self.grad = dtype, grad
        self.B = B
        self.groups = {}  # (env axis, other extents) -> fields, placed env-major by finalize()

    def _place(self, x, shape):
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        axis = env_axis(shape, self.B)
        if axis is None:
            self.fb.dense(ti.axes(*range(len(shape))), shape).place(x)
        else:
            self.groups.setdefault((axis, tuple(d for k, d in enumerate(shape) if k != axis)), []).append(x)
        return x

    def F(self, shape, grad=None):
        return self._place(ti.field(self.dtype, needs_grad=self.grad if grad is None else grad), shape)

    def I(self, shape):  # noqa: E741, E743
        return self._place(ti.field(ti.i32), shape)

    def V3(self, shape, grad=None):
        return self._place(ti.Vector.field(3, self.dtype, needs_grad=self.grad if grad is None else grad), shape)

    def M3(self, shape, grad=None):
        return self._place(ti.Matrix.field(3, 3, self.dtype, needs_grad=self.grad if grad is None else grad), shape)

    def finalize(self):
        place_env_major(self.fb, self.B, [(axis, rest, xs) for (axis, rest), xs in self.groups.items()])
        if self.grad:
            self.fb.lazy_grad()
        return self.fb.finalize()


@ti.func
def func_set_zero(x: ti.template(), I: ti.template()):
    """x[I] = 0 as a constant of x's element type (ti.zero would be x * 0, which keeps a NaN)."""
    if ti.static(not hasattr(x, "n")):
        x[I] = ti.cast(0, x.dtype)
    elif ti.static(x.m == 1):
        x[I] = ti.Vector.zero(x.dtype, x.n)
    else:
        x[I] = ti.Matrix.zero(x.dtype, x.n, x.m)


@ti.func
def func_take(x: ti.template(), i_b, i):
    """x.grad[i_b, i], then zeroed: a store's adjoint, as Taichi's reads the stored entry's adjoint and zeroes it."""
    g = x.grad[i_b, i]
    func_set_zero(x.grad, (i_b, i))
    return g


class ZeroPlan:
    """Per-env fields grouped by the shape of their per-env part, so that one loop zeroes a whole group
    (one loop per field makes a kernel several times larger, and its size is what loading it costs).
    env0: core fields [B, ...]; env1: core fields [slot, B, ...]; other / other1: fields of the scene's
    own solvers (contact, forces), [env, ...] / [1, env, ...] (by_env_axis sorts a FieldTree's). For the
    core's fields a dimension equal to the element capacity runs to the scene's element count (a run-time
    bound); every other dimension runs to its full size."""

    def __init__(self, env0, env1, cap, other=(), other1=()):
        self.cap = cap
        groups = {}
        for axis, fields, core in ((0, env0, True), (1, env1, True), (0, other, False), (1, other1, False)):
            for x in fields:
                rest = tuple(d if not core or d != cap else -1 for k, d in enumerate(x.shape) if k != axis)
                if len(rest) > 2:  # func_zero_group loops over at most two dimensions besides the env's
                    raise ValueError(f"ZeroPlan: a field of shape {x.shape} has more than two dimensions besides "
                                     f"its env axis ({axis}); func_zero_group zeroes at most two")
                groups.setdefault((axis, rest), []).append(x)
        self.groups = [(axis, rest, tuple(fields)) for (axis, rest), fields in groups.items()]


@ti.func
def func_zero_group(fields: ti.template(), i_b, axis: ti.template(), rest: ti.template(), n):
    """One group of a ZeroPlan (rest: the per-env shape, -1 where the scene's n elements apply)."""
    if ti.static(len(rest) == 0):
        for x in ti.static(fields):
            func_set_zero(x, i_b)
    elif ti.static(len(rest) == 1):
        for j in range(n if ti.static(rest[0] < 0) else rest[0]):
            for x in ti.static(fields):
                func_set_zero(x, (i_b, j))
    elif ti.static(axis == 0):
        for j, k in ti.ndrange(n if ti.static(rest[0] < 0) else rest[0], n if ti.static(rest[1] < 0) else rest[1]):
            for x in ti.static(fields):
                func_set_zero(x, (i_b, j, k))
    else:
        for j, k in ti.ndrange(rest[0], n if ti.static(rest[1] < 0) else rest[1]):
            for x in ti.static(fields):
                func_set_zero(x, (j, i_b, k))


@ti.func
def func_zero_plan(plan: ti.template(), i_b, n):
    """Zero, for env i_b, every field of the plan (the scene's n elements of capacity dimensions)."""
    for g in ti.static(plan.groups):
        func_zero_group(g[2], i_b, g[0], g[1], n)

