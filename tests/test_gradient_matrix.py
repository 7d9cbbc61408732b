"""The gradient matrix (table: tests/gradient_cases.py; how a case is checked: tests/gradient_check.py):
every case of the table, autograd against central finite differences in float64, with the options a
user gets by default (a scene that leaves one says why).

Each case builds its own scene (nothing is shared between tests, so any order and any subset runs
alike). Variations: integrators (the default approximate_implicitfast, Euler, implicitfast, RK4), n_envs
0 and 3, checkpointing off and on, the scene built in this process after other scenes or first in a fresh
process (a subprocess), and float32 (a subprocess with gs.init(precision="32")) against this process's
float64.

A case fails when a gradient differs from finite differences by more than 1e-6 of max(|g_fd|, scale),
when its finite differences do not converge (reported as FD-unreliable: the tolerance is never
loosened) or when its gradient is no larger than round-off (a case that could not fail). Cases under
`-m slow` complete the matrix; benchmarks/bench_gradient_matrix.py runs them all and writes a summary.
"""
from __future__ import annotations

import pytest

import gradient_cases as gc
from gradient_check import execute


def _params():
    for case in gc.CASES:
        marks = []
        if case.slow:
            marks.append(pytest.mark.slow)
        if case.xfail:
            marks.append(pytest.mark.xfail(strict=True, reason=case.xfail))
        yield pytest.param(case, id=case.id, marks=marks)


@pytest.mark.parametrize("case", list(_params()))
def test_gradient_case(case):
    out = execute(case)
    print(out.report)
    if out.status == "fd_unreliable":
        pytest.fail(f"FD-unreliable (finite differences at h, h/2, h/4 do not converge; not a verdict on the "
                    f"gradient):\n{out.report}")
    if out.status == "degenerate":
        pytest.fail(f"degenerate case: some input's gradient is no larger than round-off, so the check could not "
                    f"fail; change the case:\n{out.report}")
    assert out.status == "ok", out.report


def test_table_covers_every_input_and_output_kind_by_default():
    """Every input kind and every output kind appears in a case of the default (not slow) run, and every
    variation on several scenes of the whole table."""
    fast = [c for c in gc.CASES if not c.slow and not c.xfail]
    inputs = {i.split(".")[1] for c in fast for i in c.inputs}
    outputs = {o.split(".")[1] for c in fast for o in c.outputs}
    assert set(gc.INPUTS) == inputs, set(gc.INPUTS) - inputs
    assert set(gc.OUTPUTS) == outputs, set(gc.OUTPUTS) - outputs
    scenes_of = {}
    for c in gc.CASES:
        for t in c.var.tags():
            scenes_of.setdefault(t, set()).add(c.scene)
    for tag in ("integrator=Euler", "integrator=RK4", "integrator=implicitfast", "integrator=default", "n_envs=3", "checkpoint=on",
                "process=first", "process=after", "precision=32"):
        assert len(scenes_of.get(tag, ())) >= 3, (tag, scenes_of.get(tag))
    assert set(gc.SCENES) == {c.scene for c in gc.CASES}
