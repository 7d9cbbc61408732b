"""The size of Taichi's autodiff stacks: always fixed, never Taichi's adaptive sizing, and large enough.

Taichi's reverse mode keeps the successive values of a local variable that the forward code overwrites
(in a loop, or in a branch) on a per-thread "adstack" and pops them in the backward sweep. The compile
option `ad_stack_size` sets its capacity; its default, 0, asks Taichi to size each stack from the
kernel's control-flow graph (and to use 32 entries where a loop makes that impossible).

Two facts of Taichi 1.7.4 shape this module (measured with probe scripts; tests/test_adstack.py checks
what follows from them: no adaptive sizing, the checked runtime stops an overflow, and the free box's
gradient is exact in a fresh process on Taichi's own runtime):
- Its adaptive sizing gives wrong gradients: a free box in flight, 5 steps, d(pos)/d(initial pos) came
  out as 236 or 1e129 instead of 1, while any fixed size, even 4 entries, gives the exact value. The
  stacks adaptive sizing made were never pushed past their capacity (checked with the checked runtime
  below), so the fault is elsewhere in that mode; it is simply never used here.
- It checks no stack bound in any mode, debug included: an overflow is a silent wrong gradient or a
  crash. `checked_runtime` adds the check, and the test suite runs every kernel with it.

So `gs.init` fixes the size at `FLOOR` entries before any kernel compiles, and each solver that
records reverse-mode kernels declares at build, before its kernels compile, the longest loop over
scene-sized data that carries a local from one iteration to the next (`require`): a walk up the
kinematic tree, at most the rigid core's element capacity. Loops whose body starts afresh each iteration
(over contact slots, pairs, cross terms) push nothing across iterations and must not be declared: the
stacks live on the native stack of the thread running the kernel, and sized to the contact tables (4096
entries for five boxes on a plane) they overflowed it, a segfault in the backward, checked runtime or not
(tests/test_adstack.py runs six boxes in a fresh process against central differences). The deepest stacks measured with the checked
runtime: 11 entries for every rigid scene tried (a box, a double pendulum, a 30-link chain, the
Panda, ANYmal on the ground, a stack of boxes), 29 for MPM and rigid-MPM coupling (the unrolled
3x3x3 stencil), whatever the scene's size; FLOOR leaves twice that.

The size only grows within a process: a kernel compiled later for an earlier scene (a gradient kernel
compiles at its first backward) still gets a stack that covers that scene, and kernels compiled
before a raise keep the size that covered every scene built until then. Sizes come in a few steps
(64, 256, 1024, ...) because the option is part of the kernel cache's key. Run time does not depend
on the size (a push writes one entry): measured on the Panda's 50-step backward, no difference
between Taichi's default and 512 entries.
"""

from taichi.lang import impl

FLOOR = 64
STEP = 4


def current() -> int:
    """The number of entries every adstack gets in kernels compiled from now on (0: Taichi's adaptive sizing)."""
    return int(impl.current_cfg().ad_stack_size)


def init_size(requested) -> int:
    """The `ad_stack_size` to give `ti.init`: the user's request if any, at least FLOOR, never 0 (adaptive)."""
    size = FLOOR if requested in (None, 0) else int(requested)
    if size < 0:
        raise ValueError(f"gs.init(ad_stack_size={requested!r}): use a positive number of entries, or leave it out")
    return max(size, FLOOR)


def require(longest_loop: int) -> int:
    """Make every reverse-mode kernel compiled from now on hold a loop of `longest_loop` iterations
    (plus the variable's initial value and one spare entry); returns the size in force."""
    need = int(longest_loop) + 2
    size = current()
    if size == 0:  # gs.init fixes the size; this only happens when Taichi was initialised without it
        size = FLOOR
    grown = size
    while grown < need:
        grown *= STEP
    if grown != current():
        impl.current_cfg().ad_stack_size = grown
    return grown
