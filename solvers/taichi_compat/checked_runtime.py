"""Taichi's CPU runtime with bounds-checked autodiff stacks, for the tests and for `GS_CHECK_AD_STACK=1`.

Taichi 1.7.4 compiles every kernel against an LLVM bitcode runtime (`taichi/_lib/runtime/runtime_x64.bc`)
whose `stack_push`, `stack_pop` and `stack_top_primal` implement the autodiff stacks without any bound
check ("TODO: assert n <= max_elements" in its source), in debug mode too. This module writes a copy of
that runtime in which a push past the stack's capacity, a pop of an empty stack and a read of the top
of an empty stack print what happened and abort the process, and points Taichi at it before `ti.init`.
A wrong gradient from an undersized stack then cannot pass unnoticed: the run dies with

    genesis_lite: Taichi autodiff stack overflow (push 33 onto a stack of 32 entries) ...

The three functions are rewritten in LLVM IR with llvmlite (whose LLVM 15 reads and writes the
bitcode of Taichi's LLVM 15); the rest of the runtime is unchanged, and so are the values a kernel
computes. Kernels compiled against it go to their own offline cache (`offline_cache_dir`), never
mixed with the ones compiled against Taichi's own runtime. The checked runtime is written once per
Taichi runtime file, under $GS_CACHE_DIR/taichi_checked_runtime.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import tempfile

from . import TAICHI_VERSION, cache_root, installed_version, version_ok

LLVM_MAJOR = 15  # Taichi 1.7.4's
ENV = "GS_CHECK_AD_STACK"

_MESSAGES = {
    "overflow": "genesis_lite: Taichi autodiff stack overflow (push %lu onto a stack of %lu entries) in a "
                "reverse-mode kernel; its gradient would be wrong. Please report it; "
                "gs.init(ad_stack_size=...) with a larger size is a workaround.\n",
    "pop": "genesis_lite: Taichi autodiff stack underflow (pop of an empty stack) in a reverse-mode kernel.\n",
    "top": "genesis_lite: Taichi autodiff stack underflow (read of an empty stack) in a reverse-mode kernel.\n",
}


def requested() -> bool:
    """Whether this process asked for the checked runtime (GS_CHECK_AD_STACK=1)."""
    return os.environ.get(ENV, "0") not in ("", "0")


def _c_string(name: str, text: str) -> str:
    data = text.encode() + b"\0"
    body = "".join(chr(c) if 32 <= c < 127 and c not in (34, 92) else "\\%02X" % c for c in data)
    return f'@gs_adstack_msg_{name} = private unnamed_addr constant [{len(data)} x i8] c"{body}", align 1\n'


def _message_ptr(name: str) -> str:
    n = len(_MESSAGES[name].encode()) + 1
    return f"i8* getelementptr inbounds ([{n} x i8], [{n} x i8]* @gs_adstack_msg_{name}, i64 0, i64 0)"


def _replace_function(ir: str, head: str, body: str) -> str:
    start = ir.find(head)
    if start < 0:
        raise RuntimeError(f"Taichi's runtime has no function starting with {head!r}: not the runtime of Taichi "
                           f"{'.'.join(map(str, TAICHI_VERSION))}")
    end = ir.find("\n}\n", start) + 3
    return ir[:start] + body + ir[end:]


def _unless_empty(signature: str, message: str, body: str) -> str:
    """A runtime function that aborts with `message` when the stack is empty, else runs `body` (which
    sees %count_ptr and %count, the stack's entry count)."""
    return f"""\
define dso_local {signature} #0 {{
  %count_ptr = bitcast i8* %stack to i64*
  %count = load i64, i64* %count_ptr, align 8
  %empty = icmp eq i64 %count, 0
  br i1 %empty, label %fail, label %ok
fail:
  %r = call i32 (i32, i8*, ...) @dprintf(i32 2, {_message_ptr(message)})
  call void @abort()
  unreachable
ok:
{body}}}
"""


def _checked_ir(ir: str) -> str:
    """Taichi's runtime (LLVM IR text) with bounds-checked stack_push / stack_pop / stack_top_primal.
    The stack layout is Taichi's: a u64 count, then (primal, adjoint) pairs of `element_size` bytes."""
    ir = _replace_function(ir, "define dso_local void @stack_push(", f"""\
define dso_local void @stack_push(i8* noundef %stack, i64 noundef %max, i64 noundef %size) #0 {{
  %count_ptr = bitcast i8* %stack to i64*
  %count = load i64, i64* %count_ptr, align 8
  %next = add i64 %count, 1
  %over = icmp ugt i64 %next, %max
  br i1 %over, label %fail, label %ok
fail:
  %r = call i32 (i32, i8*, ...) @dprintf(i32 2, {_message_ptr("overflow")}, i64 %next, i64 %max)
  call void @abort()
  unreachable
ok:
  store i64 %next, i64* %count_ptr, align 8
  %top = call i8* @stack_top_primal(i8* noundef %stack, i64 noundef %size)
  %bytes = mul i64 %size, 2
  call void @llvm.memset.p0i8.i64(i8* align 1 %top, i8 0, i64 %bytes, i1 false)
  ret void
}}
""")
    ir = _replace_function(ir, "define dso_local void @stack_pop(", _unless_empty(
        "void @stack_pop(i8* noundef %stack)", "pop", """\
  %next = add i64 %count, -1
  store i64 %next, i64* %count_ptr, align 8
  ret void
"""))
    ir = _replace_function(ir, "define dso_local i8* @stack_top_primal(", _unless_empty(
        "i8* @stack_top_primal(i8* noundef %stack, i64 noundef %size)", "top", """\
  %data = getelementptr inbounds i8, i8* %stack, i64 8
  %index = sub i64 %count, 1
  %pairs = mul i64 %index, 2
  %offset = mul i64 %pairs, %size
  %top = getelementptr inbounds i8, i8* %data, i64 %offset
  ret i8* %top
"""))
    decls = "".join(_c_string(k, v) for k, v in _MESSAGES.items())
    if "@dprintf(" not in ir.split("define ", 1)[0]:
        decls += "declare i32 @dprintf(i32, i8*, ...)\n"
    first = ir.find("\ndefine ")
    return ir[:first] + "\n" + decls + ir[first:]


def _cache_root() -> str:
    return os.path.join(cache_root(), "taichi_checked_runtime")


def _stock_runtime_dir() -> str:
    import taichi

    return os.path.join(os.path.dirname(taichi.__file__), "_lib", "runtime")


def build(stock_dir: str | None = None) -> str:
    """Write (once) the checked copy of Taichi's runtime directory; returns its path."""
    if not version_ok():
        raise RuntimeError(f"{ENV}=1: the checked autodiff-stack runtime is written for Taichi "
                           f"{'.'.join(map(str, TAICHI_VERSION))}, this is {'.'.join(map(str, installed_version()))}; "
                           f"unset {ENV} or install taichi=={'.'.join(map(str, TAICHI_VERSION))}")
    try:
        import llvmlite.binding as llvm
    except ImportError as exc:
        raise RuntimeError(f"{ENV}=1 needs llvmlite (LLVM {LLVM_MAJOR}) to write the checked runtime: "
                           "pip install 'llvmlite==0.44.0' (it comes with genesis_lite's test extra)") from exc
    if llvm.llvm_version_info[0] != LLVM_MAJOR:
        raise RuntimeError(f"{ENV}=1: llvmlite's LLVM is {llvm.llvm_version_info}, Taichi's runtime needs LLVM "
                           f"{LLVM_MAJOR}: pip install 'llvmlite==0.44.0'")
    stock_dir = stock_dir or _stock_runtime_dir()
    stock = os.path.join(stock_dir, "runtime_x64.bc")
    with open(stock, "rb") as f:
        data = f.read()
    key = hashlib.sha256(data + repr(_MESSAGES).encode() + open(__file__, "rb").read()).hexdigest()[:24]
    out_dir = os.path.join(_cache_root(), key)
    if os.path.isfile(os.path.join(out_dir, "runtime_x64.bc")):
        return out_dir
    llvm.initialize()
    llvm.initialize_native_target()
    llvm.initialize_native_asmprinter()
    # each module in a fresh context: the runtime's named struct types must keep their names
    # (Taichi looks them up by name), which a context that has seen them once would rename
    module = llvm.parse_bitcode(data, context=llvm.create_context())
    checked = llvm.parse_assembly(_checked_ir(str(module)), context=llvm.create_context())
    checked.verify()
    os.makedirs(_cache_root(), exist_ok=True)
    tmp = tempfile.mkdtemp(dir=_cache_root())
    for name in os.listdir(stock_dir):
        if name != "runtime_x64.bc":
            shutil.copy(os.path.join(stock_dir, name), tmp)
    with open(os.path.join(tmp, "runtime_x64.bc"), "wb") as f:
        f.write(checked.as_bitcode())
    try:
        os.rename(tmp, out_dir)  # atomic: processes starting at once each write their own, one wins
    except OSError:
        shutil.rmtree(tmp, ignore_errors=True)
        if not os.path.isfile(os.path.join(out_dir, "runtime_x64.bc")):
            raise
    return out_dir


def install() -> str:
    """Point Taichi at the checked runtime (before `ti.init`); returns the offline-cache directory that
    kernels compiled against it must use."""
    from taichi._lib import core

    runtime_dir = build()
    core.set_lib_dir(runtime_dir.encode())
    base = os.environ.get("TI_OFFLINE_CACHE_FILE_PATH")  # a cache folder the user chose: beside it
    if base:
        return os.path.join(base, "checked-" + os.path.basename(runtime_dir))
    return os.path.join(runtime_dir, "kernel_cache")
