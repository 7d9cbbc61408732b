"""Finds the loop shape whose gradient Taichi 1.7.4 gets silently wrong: two sibling loops inside a loop
body (a stage's loops run inside the loop over envs) where a later loop reads a field an earlier one
writes. Taichi's reverse mode runs the adjoints of such sibling loops in their forward order, so the later
loop's adjoint adds to the field's adjoint after the earlier loop's adjoint has read it: every gradient
through that field is lost (tests/test_autodiff_rules.py shows it on a kernel of eight lines). Top-level
loops of a kernel, statically unrolled loops, a statement and a loop, and loops sharing only locals are
differentiated correctly. The rule here: in a stage whose adjoint Taichi computes, no loop reads a field
that an earlier sibling loop writes; such a stage is split into stages (each its own loop over envs).

`scan(func)` reads a Taichi function's source, follows the Taichi functions it calls (by the function's
globals and closure), and returns the offending pairs. Field names are the subscripted attribute's name
(`s.link_pos[i_b, i]` -> link_pos; a template parameter takes its argument's), so two fields of one name
on different objects count as one: it can flag too much, never too little for what it can read. A call it
cannot resolve (a method of another object, a function kept in a variable) is skipped."""
from __future__ import annotations

import ast
import inspect
import re
import textwrap
from dataclasses import dataclass, field


def _python_function(f):
    """The function as written: Taichi's decorators keep it in `.func` (of a wrapper, or of a Func)."""
    g = getattr(f, "_primal", f)  # a kernel: its primal's function
    for _ in range(5):
        if not hasattr(g, "func"):
            break
        g = g.func
    if inspect.isfunction(g) or inspect.ismethod(g):
        return g
    raise TypeError(f"not a Python function: {f!r}")


@dataclass
class _Loop:
    where: str
    branch: tuple  # ((id of an if, branch taken), ...) from the sequence's root
    reads: set = field(default_factory=set)
    writes: set = field(default_factory=set)
    children: list = field(default_factory=list)


class _Reader:
    def __init__(self, max_depth=40):
        self.max_depth = max_depth
        self.parsed = {}

    def parse(self, fn):
        fn = _python_function(fn)
        if fn not in self.parsed:
            src = textwrap.dedent(inspect.getsource(fn))
            node = ast.parse(src).body[0]
            line0 = fn.__code__.co_firstlineno - 1
            names = dict(fn.__globals__)
            names.update(inspect.getclosurevars(fn).nonlocals)
            if "." in fn.__qualname__ and "<locals>" not in fn.__qualname__:  # a method: self.f(...) on its class
                names["self"] = names.get(fn.__qualname__.split(".")[0])
            self.parsed[fn] = (node, names, f"{fn.__code__.co_filename.rsplit('/', 1)[-1]}:{fn.__name__}", line0)
        return self.parsed[fn]

    def callee(self, call, names):
        f = call.func
        obj = None
        if isinstance(f, ast.Name) and f.id in names:
            obj = names[f.id]
        elif isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) and f.value.id == "self" and names.get("self"):
            obj = getattr(names["self"], f.attr, None)
        if obj is not None:
            if hasattr(obj, "func") or getattr(obj, "_is_taichi_function", False):
                try:
                    _python_function(obj)
                except TypeError:
                    return None
                return obj
        return None

    @staticmethod
    def field_name(expr, env):
        while isinstance(expr, ast.Subscript):
            expr = expr.value
        if isinstance(expr, ast.Attribute):
            if expr.attr == "grad":
                inner = _Reader.field_name(expr.value, env)
                return inner and inner + ".grad"
            return expr.attr
        if isinstance(expr, ast.Name):
            return env.get(expr.id)
        return None

    def call_env(self, call, node, env):
        new = {}
        params = [a.arg for a in node.args.args]
        if params[:1] == ["self"] and isinstance(call.func, ast.Attribute):
            params = params[1:]
        for prm, arg in zip(params, call.args):
            if isinstance(arg, ast.Attribute):
                new[prm] = arg.attr
            elif isinstance(arg, ast.Name) and arg.id in env:
                new[prm] = env[arg.id]
        return new

    def access(self, tree, env, names, depth):
        """Fields read and written anywhere in tree (calls followed)."""
        reads, writes = set(), set()
        for sub in ast.walk(tree):
            if isinstance(sub, ast.Subscript):
                n = self.field_name(sub, env)
                if n:
                    (writes if isinstance(sub.ctx, ast.Store) else reads).add(n)
            elif isinstance(sub, ast.Call) and depth < self.max_depth:
                fn = self.callee(sub, names)
                if fn is not None:
                    node, fnames, _, _ = self.parse(fn)
                    r, w = self.access_body(node.body, self.call_env(sub, node, env), fnames, depth + 1)
                    reads |= r
                    writes |= w
        return reads, writes

    def access_body(self, stmts, env, names, depth):
        reads, writes = set(), set()
        for st in stmts:
            r, w = self.access(st, env, names, depth)
            reads |= r
            writes |= w
        return reads, writes

    def loops(self, stmts, env, names, where, line0, branch, depth):
        """The dynamic loops at this level (static loops, ifs and called functions flattened into it)."""
        out = []
        for st in stmts:
            if isinstance(st, ast.For) and ast.unparse(st.iter).startswith("ti.static"):
                out += self.loops(st.body, env, names, where, line0, branch, depth)
            elif isinstance(st, (ast.For, ast.While)):
                r, w = self.access_body(st.body, env, names, depth)
                r |= self.access(st.iter if isinstance(st, ast.For) else st.test, env, names, depth)[0]
                loop = _Loop(f"{where}:{line0 + st.lineno}", branch, r, w)
                loop.children = self.loops(st.body, env, names, where, line0, (), depth)
                out.append(loop)
            elif isinstance(st, ast.If) and _GRAD_BRANCH.fullmatch(ast.unparse(st.test)):
                # `if ti.static(s.requires_grad)`: only the gradient path's branch is differentiated
                take_else = ast.unparse(st.test).startswith("ti.static(not ")
                out += self.loops(st.orelse if take_else else st.body, env, names, where, line0, branch, depth)
            elif isinstance(st, ast.If):
                out += self.loops(st.body, env, names, where, line0, branch + ((id(st), 0),), depth)
                out += self.loops(st.orelse, env, names, where, line0, branch + ((id(st), 1),), depth)
            elif depth < self.max_depth:
                for sub in ast.walk(st):
                    if isinstance(sub, ast.Call):
                        fn = self.callee(sub, names)
                        if fn is not None:
                            node, fnames, fwhere, fline0 = self.parse(fn)
                            out += self.loops(node.body, self.call_env(sub, node, env), fnames, fwhere, fline0,
                                              branch, depth + 1)
        return out


_GRAD_BRANCH = re.compile(r"ti\.static\((not )?\w+\.requires_grad\)")


def _exclusive(a, b):
    ia = dict(a)
    return any(k in ia and ia[k] != v for k, v in b)


def _pairs(loops, found):
    for i, a in enumerate(loops):
        for b in loops[i + 1:]:
            common = a.writes & b.reads
            if common and not _exclusive(a.branch, b.branch):
                found.append((a.where, b.where, tuple(sorted(common))))
    for lp in loops:
        _pairs(lp.children, found)


def _top_loops(func):
    """The dynamic loops at func's top level, with their nested ones (calls followed)."""
    reader = _Reader()
    node, names, where, line0 = reader.parse(func)
    env = {a.arg: a.arg for a in node.args.args}  # its own parameters are fields by their names
    return reader.loops(node.body, env, names, where, line0, (), 0)


def scan(func, inside_loop=True):
    """[(earlier loop, later loop, shared fields)] of func; inside_loop: func's own top level runs inside a
    loop (a stage, called in the loop over envs), else only its loops' bodies are checked (a kernel)."""
    loops = _top_loops(func)
    found = []
    if inside_loop:
        _pairs(loops, found)
    else:
        for lp in loops:
            _pairs(lp.children, found)
    return found


def loop_count(func):
    """How many dynamic loops the scan reads in func, its calls followed (what it checked)."""

    def count(ls):
        return sum(1 + count(lp.children) for lp in ls)

    return count(_top_loops(func))
