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
  per kernel), finds the function's source with `inspect` (another `sys.modules` scan, then a
  tokenisation of the function), normalises every line with `textwrap.fill` and dedents it. Here that
  text is computed once per function and kept in memory and on disk (per source file, valid while the
  file's mtime and size are unchanged: `_SourceStore`), and only parsed again (`ast.parse`: the
  transformer annotates the tree, so each compile needs a fresh one).

- `ASTTransformerContext.get_pos_info`, run for every AST node the transformer visits, formats a
  source excerpt with a caret line, wrapped by textwrap, kept for error messages whether or not an
  error comes: half of the Python time of compiling a kernel. Here: the same file, line, function and
  source line, without the caret line and the wrapping.
- `get_traceback`, run for every field, SNode and ndarray Taichi creates (and a field with gradients
  is two), formats the whole Python stack with `traceback`, whose Python 3.11 formatting re-parses
  every source line to draw carets. The text is kept only for error messages (a field declared but
  never placed). Here: the same frames, files, lines and source lines, without the caret lines.

The first two return exactly what Taichi's own functions return, so the IR, the offline-cache keys and
the compiled kernels are unchanged (tests/test_build_overheads.py compares them).
GS_TAICHI_FAST_FRONTEND=0 keeps all of Taichi's own functions (GS_TAICHI_SPEEDUPS=0 or
gs.init(taichi_speedups=False) also the launch path below; `uninstall` restores Taichi's functions).
"""
from __future__ import annotations

import ast
import dis
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

    def _inside_class(level_of_class_stackframe):
        # Taichi's: the first statement of inspect.getframeinfo(frame)[3] matched against `class ` /
        # `@data_oriented`. getframeinfo's line is the start line of the frame's current instruction.
        try:
            frame = sys._getframe(level_of_class_stackframe)
            lineno, _ = _frame_position(frame)
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
            hit = _STORE.get(fn)
            if hit is None:
                file = K.getsourcefile(fn)
                src, start_lineno = K.getsourcelines(fn)
                src = [textwrap.fill(line, tabsize=4, width=9999) for line in src]
                hit = (file, src, start_lineno, textwrap.dedent("\n".join(src)))
                _STORE.put(fn, hit)
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
    _install_light_pos_info()
    return True


_INSPECT_GETFRAMEINFO = inspect.getframeinfo
_CODE_POSITION = getattr(inspect, "_get_code_position", None)


def _frame_position(frame):
    """(line, position) of the frame's current instruction, as inspect.getframeinfo finds them: the
    position's start line where it has one, else f_lineno (position None without _get_code_position)."""
    if _CODE_POSITION is None:
        return frame.f_lineno, None
    positions = _CODE_POSITION(frame.f_code, frame.f_lasti)
    return (positions[0] if positions[0] is not None else frame.f_lineno), positions


def light_getframeinfo(frame, context=1):
    """inspect.getframeinfo(frame, 1) without its `sys.modules` scan: the position of the frame's
    instruction and its line from linecache (through the frame's module globals); a pseudo-file
    ("<frozen importlib._bootstrap>": the frame above a module-level decoration) without source gives
    code_context and index None, as inspect does. Any other case goes to inspect's own."""
    if context != 1 or not inspect.isframe(frame) or _CODE_POSITION is None:
        return _INSPECT_GETFRAMEINFO(frame, context)
    try:
        lineno, positions = _frame_position(frame)
        file = frame.f_code.co_filename
        pseudo = file.startswith("<") and file.endswith(">")
        if not (os.path.isabs(file) or pseudo):
            return _INSPECT_GETFRAMEINFO(frame, context)
        lines = linecache.getlines(file, frame.f_globals)
        if not lines and pseudo:
            context_lines, index = None, None
        elif 0 < lineno <= len(lines) and not pseudo:
            context_lines, index = [lines[lineno - 1]], 0
        else:
            return _INSPECT_GETFRAMEINFO(frame, context)
        return inspect.Traceback(file, lineno, frame.f_code.co_name, context_lines, index,
                                 positions=dis.Positions(*positions))
    except Exception:
        return _INSPECT_GETFRAMEINFO(frame, context)


def import_taichi() -> None:
    """Import Taichi (once per process) with `inspect.getframeinfo` as `light_getframeinfo` while it
    runs: Taichi decorates ~90 of its own functions and kernels at import, and each decoration reads
    one source line through getframeinfo (its `_inside_class`, for a module-level decoration the frame
    of the import machinery, which has no source), whose module lookup scans `sys.modules`: with
    torch imported first, as scripts usually do, that doubled Taichi's import time. Restored when the
    import ends. GS_TAICHI_SPEEDUPS=0 or GS_TAICHI_FAST_FRONTEND=0: a plain import."""
    if "taichi" in sys.modules or os.environ.get("GS_TAICHI_SPEEDUPS") == "0" \
            or os.environ.get("GS_TAICHI_FAST_FRONTEND") == "0":
        import taichi  # noqa: F401
        return
    inspect.getframeinfo = light_getframeinfo
    try:
        import taichi  # noqa: F401
    finally:
        inspect.getframeinfo = _INSPECT_GETFRAMEINFO


class _SourceStore:
    """The normalised source of each function, kept on disk across processes: finding it (inspect
    tokenises the file from the function's first line to the end of its block) costs ~0.5 ms a
    function, and a scene's kernels call a hundred or more. One entry per source file, under
    $GS_CACHE_DIR/taichi_source (default ~/.cache/genesis_lite), valid while the file's mtime and
    size are those it was read with: an edited file is read again, as inspect would. Written at exit
    when it gained functions; GS_MODEL_CACHE=0 keeps it off like the model cache."""

    def __init__(self):
        self.files = {}  # path -> [(mtime_ns, size), {(first line, name): value}, dirty]
        self.registered = False

    @staticmethod
    def _key(fn):
        code = getattr(fn, "__code__", None)
        if code is None or not os.path.isabs(code.co_filename):
            return None, None
        try:
            st = os.stat(code.co_filename)
        except OSError:
            return None, None
        return (code.co_filename, (st.st_mtime_ns, st.st_size)), (code.co_firstlineno, code.co_name)

    def _entry_path(self, path):
        import hashlib

        from . import cache_root

        return os.path.join(cache_root(), "taichi_source", hashlib.sha256(path.encode()).hexdigest()[:32] + ".pkl")

    def _file(self, path, state):
        rec = self.files.get(path)
        if rec is None or rec[0] != state:
            funcs = {}
            try:
                import pickle

                with open(self._entry_path(path), "rb") as f:
                    stored = pickle.load(f)
                if stored.get("path") == path and stored.get("state") == state:
                    funcs = stored["funcs"]
            except Exception:  # none yet, or unreadable: start afresh
                pass
            rec = self.files[path] = [state, funcs, False]
        return rec

    def get(self, fn):
        if os.environ.get("GS_MODEL_CACHE", "1") == "0":
            return None
        (path, state), key = self._key(fn)
        if path is None:
            return None
        return self._file(path, state)[1].get(key)

    def put(self, fn, value):
        if os.environ.get("GS_MODEL_CACHE", "1") == "0":
            return
        (path, state), key = self._key(fn)
        if path is None:
            return
        rec = self._file(path, state)
        rec[1][key] = value
        rec[2] = True
        if not self.registered:
            import atexit

            atexit.register(self.flush)
            self.registered = True

    def flush(self):
        import pickle
        import tempfile

        for path, rec in self.files.items():
            if not rec[2]:
                continue
            tmp = None
            try:
                entry = self._entry_path(path)
                os.makedirs(os.path.dirname(entry), exist_ok=True)
                fd, tmp = tempfile.mkstemp(dir=os.path.dirname(entry), suffix=".tmp")
                with os.fdopen(fd, "wb") as f:
                    pickle.dump({"path": path, "state": rec[0], "funcs": rec[1]}, f, protocol=pickle.HIGHEST_PROTOCOL)
                os.replace(tmp, entry)
                rec[2] = False
            except Exception:
                if tmp is not None:
                    try:
                        os.unlink(tmp)
                    except OSError:
                        pass


_STORE = _SourceStore()


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


def _install_light_pos_info():
    try:
        from taichi.lang.ast import ast_transformer_utils as atu
    except ImportError:  # another Taichi layout: leave it alone
        return
    ctx_cls = getattr(atu, "ASTTransformerContext", None)
    if ctx_cls is None or getattr(ctx_cls.get_pos_info, "_gs_fast", False):
        return

    def get_pos_info(self, node):
        line = node.lineno + self.lineno_offset
        src = self.src[node.lineno - 1] if 0 < node.lineno <= len(self.src) else ""
        return f'File "{self.file}", line {line}, in {self.func.func.__name__}:\n{src}\n'

    get_pos_info._gs_fast = True
    ctx_cls._taichi_get_pos_info = ctx_cls.get_pos_info
    ctx_cls.get_pos_info = get_pos_info


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


# ---------------------------------------------------------------------------------------------------
# Kernel launches
#
# Every `Kernel.__call__` of Taichi 1.7 builds the kernel's template key from all its arguments
# (`mapper.lookup`: an isinstance chain per argument, and for a @ti.data_oriented owner attribute
# lookups through its __getattribute__), checks every field of the program for placement
# (`runtime.materialize`), and sets the launch arguments through closures it defines anew on each
# call: ~35 us per launch on this machine, for kernels that run in 3-10 us on one environment. A
# gradient step launches ~25 kernels, so this was most of the time of a one-env backward.
#
# `install_fast_launch` keeps Taichi's own call for the first launch of every (kernel, template
# arguments) pair and for everything unusual, and remembers the compiled kernel it used. Later
# launches with the same template arguments (the same objects, checked through weak references, or
# equal ints / floats / bools / strings) and only scalar run-time arguments set those scalars into a
# launch context and launch the same compiled kernel; a forward kernel launched while a `ti.ad.Tape`
# records is put on the Tape first, as Taichi's call puts it. They fall back to Taichi's call while a
# validating Tape records (it compiles other kernels), in forward-mode autodiff, for kernels with print or a
# return value other than one signed integer, when a field was created since (Taichi must place it
# first), and after `ti.reset()` (the kernel's compiled instances are gone). A kernel returning one
# signed integer (the rigid step's count of envs with a NaN, read after every step) has it read from
# the launch context as Taichi does, after Taichi's synchronisation on a GPU; on the CPU the launch has
# finished when it returns (~5 us less). GS_TAICHI_FAST_LAUNCH=0 keeps Taichi's call everywhere.


class _FastEntry:
    """What a fast launch reuses: weak references to the template arguments (position, ref), Taichi's
    key and compiled instance of the kernel, whether to synchronise after it, and the compiled kernel
    data (None until the first fast launch asks Taichi for it)."""
    __slots__ = ("refs", "key", "t_kernel", "sync", "data")

    def __init__(self, refs, key, t_kernel, sync=False):
        self.refs, self.key, self.t_kernel, self.sync, self.data = refs, key, t_kernel, sync, None


_VALUE_TYPES = (int, float, bool, str, type(None))


def install_fast_launch() -> bool:
    """Replace taichi's Kernel.__call__ with the cached launch above; True if installed (or already)."""
    if os.environ.get("GS_TAICHI_FAST_LAUNCH") == "0":
        return False
    try:
        import numpy as np
        from taichi.lang import impl
        from taichi.lang import kernel_impl as K
        from taichi.lang.enums import AutodiffMode
        from taichi.lang import runtime_ops
        from taichi.lang.exception import handle_exception_from_cpp
        from taichi.lang.util import cook_dtype
        from taichi.types import primitive_types as P
        from taichi.types import ndarray_type, template
        from taichi.types.utils import is_signed
    except ImportError:
        return False
    Kernel = getattr(K, "Kernel", None)
    if Kernel is None or getattr(Kernel.__call__, "_gs_fast", False):
        return Kernel is not None
    if not all(hasattr(Kernel, n) for n in ("ensure_compiled", "launch_kernel", "materialize")):
        return False  # another Taichi layout: leave it alone
    original = Kernel.__call__
    real_ids, int_ids = set(P.real_type_ids), set(P.integer_type_ids)
    plain_modes = (AutodiffMode.NONE, AutodiffMode.VALIDATION)
    fields_seen = [None]  # the program's field counts when the fast path last checked them
    numbers = (int, float, np.integer, np.floating)
    import taichi

    cpu_archs = tuple(a for a in (getattr(taichi, "x64", None), getattr(taichi, "arm64", None)) if a is not None)
    integers = (int, np.integer)

    def fields_state(rt):
        return (id(rt.prog), len(rt.global_vars), len(rt.grad_vars), len(rt.dual_vars), len(rt.matrix_fields))

    def plan_of(kernel):
        """(template positions, floats, ints, arrays) or None where the kernel's arguments are not all
        templates, scalars and external arrays of scalars. floats and arrays are (position, launch
        index) pairs, ints (setter name, position, launch index)."""
        temps, floats, ints, arrays, n_t = [], [], [], [], 0
        for i, a in enumerate(kernel.arguments):
            anno = a.annotation
            if isinstance(anno, template):
                temps.append(i)
                n_t += 1
            elif id(anno) in real_ids:
                floats.append((i, i - n_t))
            elif id(anno) in int_ids:
                ints.append(("set_arg_int" if is_signed(cook_dtype(anno)) else "set_arg_uint", i, i - n_t))
            elif (isinstance(anno, ndarray_type.NdarrayType) and anno.needs_grad is None
                  and (anno.dtype is None or id(anno.dtype) in P.type_ids)):
                arrays.append((i, i - n_t))
            else:
                return None
        return tuple(temps), tuple(floats), tuple(ints), tuple(arrays)

    def array_sig(v):
        """What Taichi's template key takes from an external array, for the arrays the fast path
        launches itself (C-contiguous numpy arrays, contiguous CPU torch tensors without grad), else None."""
        if type(v) is np.ndarray:
            return (np.ndarray, v.dtype, v.ndim) if v.flags.c_contiguous else None
        torch = sys.modules.get("torch")  # imported after the solvers
        if torch is not None and isinstance(v, torch.Tensor):
            if v.requires_grad or v.device.type != "cpu" or not v.is_contiguous():
                return None
            return (torch.Tensor, v.dtype, v.dim())
        return None

    def template_sig(args, temps):
        """The template arguments' part of a cache key: value arguments as they are, objects by id."""
        return tuple([a if type(a) in _VALUE_TYPES else id(a) for a in [args[i] for i in temps]])

    def reraise(err):
        """Taichi's exception for an error of its C++ launch, as Kernel.__call__ raises it."""
        err = handle_exception_from_cpp(err)
        if impl.get_runtime().print_full_traceback:
            raise err
        raise err from None

    def fast_call(self, *args, **kwargs):
        d = self.__dict__
        plan = d.get("_gs_plan", False)
        if plan is False:
            ret = self.return_type
            int_ret = (ret is not None and len(ret) == 1 and ret[0] in P.integer_types
                       and is_signed(cook_dtype(ret[0])))
            plan = d["_gs_plan"] = plan_of(self) if ret is None or int_ret else None
            d["_gs_ret"] = bool(int_ret)
            d["_gs_cache"] = {}
        rt = self.runtime
        # a forward kernel launched while a Tape records (outside a grad_replaced call) goes on the Tape, as
        # Taichi's own __call__ puts it there (Tape.insert), right before the fast launch below; a validating
        # Tape compiles another kernel, which Taichi's path does
        tape = rt.target_tape if (not rt.grad_replaced and self.autodiff_mode in plain_modes) else None
        if (plan is None or kwargs or len(args) != len(self.arguments) or rt.fwd_mode_manager
                or (tape is not None and tape.validation) or self.has_print):
            return original(self, *args, **kwargs)
        temps, floats, ints, arrays = plan
        # a kernel whose one template argument is an object (a data-oriented class's kernel) and that
        # takes no array: the entry of its last fast launch, if that object is the one passed again
        hit = d.get("_gs_last")
        if hit is not None:
            i, r = hit.refs[0]
            if r() is not args[i]:
                hit = None
        sig = None
        if hit is None:
            sig = template_sig(args, temps)
            if arrays:
                asig = tuple(array_sig(args[i]) for i, _ in arrays)
                if None in asig:
                    return original(self, *args)
                sig = (sig, asig)
            hit = d["_gs_cache"].get(sig)
            if hit is not None:
                for i, r in hit.refs:
                    if r() is not args[i]:
                        hit = None
                        break
            if hit is not None and len(temps) == 1 and len(hit.refs) == 1 and not arrays:
                d["_gs_last"] = hit
        if hit is None or self.compiled_kernels.get(hit.key) is not hit.t_kernel or fields_seen[0] != fields_state(rt):
            d["_gs_last"] = None
            cache = d["_gs_cache"]
            if sig is None:  # the last launch's entry, gone stale (such a kernel takes no array)
                sig = template_sig(args, temps)
            ret = original(self, *args)
            refs = []
            for i in temps:
                if type(args[i]) not in _VALUE_TYPES:
                    try:
                        refs.append((i, weakref.ref(args[i])))
                    except TypeError:  # not weakly referable: no fast path for these arguments
                        cache.pop(sig, None)
                        return ret
            key = self.ensure_compiled(*args)
            sync = impl.current_cfg().arch not in cpu_archs
            cache[sig] = _FastEntry(tuple(refs), key, self.compiled_kernels[key], sync)
            fields_seen[0] = fields_state(rt)
            return ret
        t_kernel = hit.t_kernel
        ctx = t_kernel.make_launch_context()
        for i, j in floats:
            v = args[i]
            if not isinstance(v, numbers):
                return original(self, *args)  # Taichi's own type error
            ctx.set_arg_float((j,), float(v))
        for setter, i, j in ints:
            v = args[i]
            if not isinstance(v, integers):
                return original(self, *args)
            getattr(ctx, setter)((j,), int(v))
        for i, j in arrays:
            v = args[i]
            if type(v) is np.ndarray:
                ctx.set_arg_external_array_with_shape((j,), int(v.ctypes.data), v.nbytes, v.shape, 0)
            else:
                ctx.set_arg_external_array_with_shape((j,), int(v.data_ptr()), v.element_size() * v.nelement(),
                                                      tuple(v.shape), 0)
        if tape is not None:
            tape.insert(self, args)
        prog = rt.prog
        try:
            data = hit.data
            if data is None:
                # Taichi's compiled data for this instance: compile_kernel looks it up by the key the
                # kernel got at its first compile (not by the config of the moment) and returns a
                # reference into its cache, stable while the program lives (fields_state checks it)
                data = hit.data = prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel)
            prog.launch_kernel(data, ctx)
        except Exception as e:
            reraise(e)
        if d["_gs_ret"]:
            if hit.sync:
                runtime_ops.sync()
            return ctx.get_struct_ret_int((0,))
        return None

    def hot(bound):
        """See hot_launcher."""
        kernel, owner = bound._primal, bound._kernel_owner
        ret_type = kernel.return_type
        ret_int = ret_type is not None
        if ret_int and not (len(ret_type) == 1 and ret_type[0] in P.integer_types
                            and is_signed(cook_dtype(ret_type[0]))):
            return bound  # a return the direct launch does not read
        rt = kernel.runtime
        # (compiled instance, Taichi's key, compiled data, fields_state, argument count) of the last fast launch
        entry = [None]

        def launch(*args):
            e = entry[0]
            if (e is not None and len(args) == e[4] and Kernel.__call__ is fast_call and rt.target_tape is None
                    and not rt.fwd_mode_manager and kernel.compiled_kernels.get(e[1]) is e[0]
                    and fields_state(rt) == e[3]):
                ctx = e[0].make_launch_context()
                for j, v in enumerate(args):
                    if type(v) is not int:
                        break
                    ctx.set_arg_int((j,), v)
                else:
                    try:
                        rt.prog.launch_kernel(e[2], ctx)
                    except Exception as err:
                        reraise(err)
                    return ctx.get_struct_ret_int((0,)) if ret_int else None
            ret = bound(*args)
            d = kernel.__dict__
            hit, plan = d.get("_gs_last"), d.get("_gs_plan")
            if (hit is not None and hit.data is not None and not hit.sync and hit.refs[0][1]() is owner and plan
                    and plan[0] == (0,) and not plan[1] and not plan[3] and len(plan[2]) == len(args)
                    and all(setter == "set_arg_int" for setter, _, _ in plan[2])):
                entry[0] = (hit.t_kernel, hit.key, hit.data, fields_state(rt), len(args))
            return ret

        launch._gs_entry = entry  # (tests look at it)
        return launch

    _HOT[0] = hot
    fast_call._gs_fast = True
    fast_call.__wrapped__ = original
    Kernel._taichi_call = original
    Kernel.__call__ = fast_call
    return True


_HOT = [None]  # install_fast_launch's hot(bound), once installed


def hot_launcher(bound):
    """A launcher for one data-oriented object's kernel whose only template argument is its owner and whose
    other arguments are ints, returning a signed int or nothing (the rigid solver's fused step, launched once
    a step: at 1 env its launch through Kernel.__call__ was three quarters of the step's time). After a
    launch through the fast path it launches Taichi's compiled data for that owner directly with a new
    launch context: ~2 us less a launch than the fast path's general checks. It checks what the fast
    path's reuse of an entry checks (the same compiled instance, no field created since, the fast path
    still installed) and that no Tape records and no forward-mode manager transforms the launch; any
    other case, and an argument that is not an int, goes through the kernel itself (Taichi's errors
    included). Without the fast launch (GS_TAICHI_SPEEDUPS=0, another Taichi): the bound kernel itself."""
    h = _HOT[0]
    return bound if h is None else h(bound)


def uninstall() -> None:
    """Put back every Taichi function that `install` and `install_fast_launch` replaced."""
    import importlib

    try:
        from taichi.lang import kernel_impl as K
        from taichi.lang import util
        from taichi.lang.ast import ast_transformer_utils as atu
    except ImportError:
        return
    if getattr(K._get_tree_and_ctx, "_gs_fast", False):
        K._inside_class, K._get_tree_and_ctx = K._taichi_inside_class, K._taichi_get_tree_and_ctx
    ctx_cls = getattr(atu, "ASTTransformerContext", None)
    if ctx_cls is not None and getattr(ctx_cls.get_pos_info, "_gs_fast", False):
        ctx_cls.get_pos_info = ctx_cls._taichi_get_pos_info
    original = getattr(util, "_taichi_get_traceback", None)
    if original is not None:
        for name in ("taichi.lang.util", "taichi.lang.impl", "taichi.lang.matrix", "taichi.lang.snode",
                     "taichi.lang._ndarray"):
            mod = importlib.import_module(name)
            if getattr(getattr(mod, "get_traceback", None), "_gs_fast", False):
                mod.get_traceback = original
    Kernel = getattr(K, "Kernel", None)
    if Kernel is not None and getattr(Kernel.__call__, "_gs_fast", False):
        Kernel.__call__ = Kernel._taichi_call


def installed() -> dict:
    """Which of the replacements are in place now."""
    from taichi.lang import kernel_impl as K

    return {"frontend": bool(getattr(K._get_tree_and_ctx, "_gs_fast", False)),
            "fast_launch": bool(getattr(K.Kernel.__call__, "_gs_fast", False))}
