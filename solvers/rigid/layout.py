"""Env-major placement of per-env fields, shared by the rigid core (solver.RigidCore) and the contact
solver (FieldTree).

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
        B = self.B
        if B is not None and shape[0] == B:
            self.groups.setdefault((0, shape[1:]), []).append(x)
        elif B is not None and len(shape) >= 2 and shape[0] == 1 and shape[1] == B:
            self.groups.setdefault((1, (1,) + shape[2:]), []).append(x)
        else:
            self.fb.dense(ti.axes(*range(len(shape))), shape).place(x)
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
