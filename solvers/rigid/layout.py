"""Env-major placement of per-env fields, shared by the rigid core (solver.RigidCore) and the contact
solver (contact.FieldTree).

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
