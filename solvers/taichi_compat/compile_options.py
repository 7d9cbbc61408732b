"""Compiler switches set around kernel launches: Taichi's advanced IR optimisation on or off for the
kernels compiled inside (the option is read when a kernel compiles and is part of the offline cache's
key, so it must be set around the launch that compiles)."""
import os

from . import config


class ForwardCompile:
    """Compile the kernels launched inside it without Taichi's advanced IR optimisation.

    Its whole-kernel passes cost time superlinear in a kernel's size: the fused step of a scene with
    contacts (dynamics, the contact stages, the three contact solves with their passes, integration:
    one loop body) compiled in ~45 s with them and ~6 s without (benchmarks/bench_build.py), and steps
    ~10 % slower in float32 (ANYmal on the ground 61 -> 69 us, four stacked boxes 95 -> 105 us, the
    Panda over a plane unchanged; GS_FORWARD_ADVANCED_OPTIMIZATION=1 keeps gs.init's setting, for long
    runs where that matters more than the compile). float64 runs without them anyway (gs.init); float32
    keeps them for the kernels that Taichi differentiates, whose adjoints need them (see gs.init), hence
    this is set around forward launches only: the option is read when a kernel compiles (and is part
    of the offline cache's key), so an adjoint compiled later, outside, gets gs.init's setting."""

    def __enter__(self):
        cfg = config()
        self.was = cfg.advanced_optimization
        cfg.advanced_optimization = self.was and KEEP_FORWARD_ADVANCED_OPTIMIZATION

    def __exit__(self, *exc):
        config().advanced_optimization = self.was


KEEP_FORWARD_ADVANCED_OPTIMIZATION = os.environ.get("GS_FORWARD_ADVANCED_OPTIMIZATION") == "1"


class AdjointCompile:
    """Compile the adjoints launched inside it without Taichi's advanced IR optimisation when `plain`.

    float32 needs that optimisation for correct adjoints of some stages only (see gs.init). Measured on
    the Panda's 50-step rollout: without it the adjoints of func_dof_momentum, func_mass_matrix and
    func_project_forces + func_generalized_force came out wrong by 30-500 %, while those of the stages
    in PLAIN_ADJOINT matched the optimised ones to float32 rounding (gradients within 1e-7), and the
    cold first backward took 4.2-4.7 s instead of 6.2-7.6 s (their compile is ~40 % of it).
    tests/test_precision.py compares float32 gradients with float64 ones (a ball landing on a plane:
    free joint and contacts; the arm and the box stack under -m slow). GS_ADJOINT_ADVANCED_OPTIMIZATION=1
    keeps the optimisation for every adjoint."""

    def __init__(self, plain: bool):
        self.plain = plain and not KEEP_ADJOINT_ADVANCED_OPTIMIZATION

    def __enter__(self):
        cfg = config()
        self.was = cfg.advanced_optimization
        cfg.advanced_optimization = self.was and not self.plain

    def __exit__(self, *exc):
        config().advanced_optimization = self.was


KEEP_ADJOINT_ADVANCED_OPTIMIZATION = os.environ.get("GS_ADJOINT_ADVANCED_OPTIMIZATION") == "1"
