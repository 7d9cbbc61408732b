"""The size of Taichi's autodiff stacks, raised to cover the longest loop a scene differentiates.

Taichi's reverse mode keeps the successive values of a local variable that a loop body overwrites on
a per-thread "adstack", one entry per iteration. Where it cannot bound a loop at compile time (every
loop over a scene's links, dofs or contact slots: their counts are read at run time, or the body has
branches), Taichi 1.7.4 gives the stack a fixed size of 32 entries and, outside debug mode, does not
check it: a loop of more iterations writes past the stack, and the gradient is silently wrong (NaN for
a chain of 40 links; values that depend on the previous backward pass for two boxes with 57 contact
slots). So each solver that records reverse-mode kernels declares its longest loop at build, before
any of its kernels compiles, and `require` raises the compile option `ad_stack_size` to cover it.

The size only grows within a process: a kernel compiled later for an earlier scene (a gradient kernel
compiles at its first backward) then still gets a stack that covers that scene. Sizes come in a few
steps (64, 256, 1024, ...) because the option is part of the kernel cache's key: scenes of similar
size share compiled kernels across processes. Kernels compiled before a raise keep their size, which
covered every scene built until then. Measured on the Panda's 50-step backward: no difference in
run time between the default and 512 entries.
"""

from taichi.lang import impl

# Taichi's own size for stacks whose depth its analysis cannot bound (compile option 0 = "adaptive")
TAICHI_DEFAULT = 32
STEP = 4


def current() -> int:
    """The number of entries an unbounded adstack gets in kernels compiled from now on."""
    size = int(impl.current_cfg().ad_stack_size)
    return size if size > 0 else TAICHI_DEFAULT


def require(longest_loop: int) -> int:
    """Make every reverse-mode kernel compiled from now on hold a loop of `longest_loop` iterations
    (plus the variable's initial value and one spare entry); returns the size in force."""
    need = int(longest_loop) + 2
    if need <= current():
        return current()
    size = 64
    while size < need:
        size *= STEP
    impl.current_cfg().ad_stack_size = size
    return size
