"""Lighter Python-side bookkeeping in Taichi 1.7's kernel front end: the same IR, fewer seconds.

Taichi compiles a kernel from its Python source at the first launch of every process, even when the
compiled kernel then comes from the offline cache (the cache key is a hash of the IR the front end
builds), so the front end's Python time is paid on every warm start. Two of its costs have nothing to
do with the kernel and grow with the number of modules loaded (torch brings ~2,000):

- `_inside_class`, run once per `@ti.func` / `@ti.kernel` decoration, reads one source line through
  `inspect.getframeinfo`, whose module lookup scans `sys.modules`; the contact stages decorate their
  functions when a scene is built, after torch is loaded. Here the line comes from `linecache`
  directly (the same line: the frame's file and current line).
- `_get_tree_and_ctx`, run for every call of a `@ti.func` inside every kernel being compiled (hundreds
  per kernel), finds the function's source with `inspect` (another `sys.modules` scan), normalises
  every line with `textwrap.fill` and dedents it. Here that text is computed once per function per
  process and only parsed again (`ast.parse`: the transformer annotates the tree, so each compile
  needs a fresh one).

- `get_traceback`, run for every field, SNode and ndarray Taichi creates (and a field with gradients
  is two), formats the whole Python stack with `traceback`, whose Python 3.11 formatting re-parses
  every source line to draw carets. The text is kept only for error messages (a field declared but
  never placed). Here: the same frames, files, lines and source lines, without the caret lines.

The first two return exactly what Taichi's own functions return, so the IR, the offline-cache keys and
the compiled kernels are unchanged (tests/test_build_overheads.py compares them).
GS_TAICHI_FAST_FRONTEND=0 keeps Taichi's own functions.
"""
from __future__ import annotations

import ast
import inspect
import linecache
import os
import sys
import textwrap
import weakref


def install() -> bool:
    """Replace the two front-end helpers in taichi.lang.kernel_impl; True if installed (or already)."""
    if os.environ.get("GS_TAICHI_FAST_FRONTEND") == "0":
        return False
    try:
        from taichi.lang import kernel_impl as K
    except ImportError:
        return False
    if getattr(K._get_tree_and_ctx, "_gs_fast", False):
        return True
    needed = ("_inside_class", "_get_tree_and_ctx", "_get_global_vars", "_KERNEL_CLASS_STACKFRAME_STMT_RES",
              "getsourcefile", "getsourcelines", "ASTTransformerContext")
    if not all(hasattr(K, n) for n in needed):  # another Taichi layout: leave it alone
        return False
    patterns = K._KERNEL_CLASS_STACKFRAME_STMT_RES
    code_position = getattr(inspect, "_get_code_position", None)

    def _inside_class(level_of_class_stackframe):
        # Taichi's: the first statement of inspect.getframeinfo(frame)[3] matched against `class ` /
        # `@data_oriented`. getframeinfo's line is the start line of the frame's current instruction.
        try:
            frame = sys._getframe(level_of_class_stackframe)
            lineno = frame.f_lineno
            if code_position is not None:
                pos = code_position(frame.f_code, frame.f_lasti)
                if pos[0] is not None:
                    lineno = pos[0]
            line = linecache.getline(frame.f_code.co_filename, lineno, frame.f_globals).strip()
            return any(p.match(line) for p in patterns)
        except Exception:
            return False

    sources = weakref.WeakKeyDictionary()  # python function -> (file, normalised lines, first line, text)

    def _get_tree_and_ctx(self, excluded_parameters=(), is_kernel=True, arg_features=None, args=None,
                          ast_builder=None, is_real_function=False):
        fn = self.func
        hit = sources.get(fn)
        if hit is None:
            file = K.getsourcefile(fn)
            src, start_lineno = K.getsourcelines(fn)
            src = [textwrap.fill(line, tabsize=4, width=9999) for line in src]
            hit = (file, src, start_lineno, textwrap.dedent("\n".join(src)))
            sources[fn] = hit
        file, src, start_lineno, text = hit
        tree = ast.parse(text)
        tree.body[0].decorator_list = []
        global_vars = K._get_global_vars(fn)
        if is_kernel or is_real_function:
            for i in self.template_slot_locations:
                global_vars[self.arguments[i].name] = args[i]
        return tree, K.ASTTransformerContext(
            excluded_parameters=excluded_parameters, is_kernel=is_kernel, func=self, arg_features=arg_features,
            global_vars=global_vars, argument_data=args, src=src, start_lineno=start_lineno, file=file,
            ast_builder=ast_builder, is_real_function=is_real_function)

    _get_tree_and_ctx._gs_fast = True
    _inside_class._gs_fast = True
    K._taichi_inside_class, K._taichi_get_tree_and_ctx = K._inside_class, K._get_tree_and_ctx
    K._inside_class, K._get_tree_and_ctx = _inside_class, _get_tree_and_ctx
    _install_light_traceback()
    return True


def light_traceback(stacklevel=1):
    """taichi.lang.util.get_traceback without caret lines: the caller's stack, outermost first, less
    the `stacklevel` innermost frames, in traceback's "  File ..., line ..., in ...\n    source\n" form."""
    frames = []
    f = sys._getframe(1)
    while f is not None:
        frames.append(f)
        f = f.f_back
    frames.reverse()
    if stacklevel > 0:
        frames = frames[: len(frames) - stacklevel]
    out = []
    for f in frames:
        code = f.f_code
        out.append(f'  File "{code.co_filename}", line {f.f_lineno}, in {code.co_name}\n')
        line = linecache.getline(code.co_filename, f.f_lineno).strip()
        if line:
            out.append(f"    {line}\n")
    return "".join(out)


light_traceback._gs_fast = True


def _install_light_traceback():
    import importlib

    try:
        from taichi.lang import util
    except ImportError:
        return
    original = getattr(util, "get_traceback", None)
    if original is None or getattr(original, "_gs_fast", False):
        return
    util._taichi_get_traceback = original
    # every module that imported the function by name holds its own reference
    for name in ("taichi.lang.util", "taichi.lang.impl", "taichi.lang.matrix", "taichi.lang.snode",
                 "taichi.lang._ndarray"):
        try:
            mod = importlib.import_module(name)
        except ImportError:
            continue
        if getattr(mod, "get_traceback", None) is original:
            mod.get_traceback = light_traceback
