"""Every example runs headless with --quick (what CI runs) and writes the files it promises.

Each example runs in its own Python process from the repository root, as a user would start it,
with --out under pytest's tmp_path; the test checks the exit code, that every expected file exists
and is non-empty, and that the example printed its closing summary. The examples' own numbers
(losses that decrease, gradients that match finite differences) are asserted inside the examples,
which exit non-zero when they fail.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

# example -> files it writes under --out
EXAMPLES = {
    "quickstart": ["trajectory.csv", "gradients.csv", "quickstart.png"],
    "seed_quickstart": ["gradient.txt"],
    "trajectory_optimization": ["loss.csv", "controls.csv", "trajectory_optimization.png"],
    "contact_quadruped": ["quadruped_contacts.csv", "quadruped_contacts.png"],
    "record_video": ["first_frame.png", "rollout.mp4", "rollout.gif"],
    "parameter_identification": ["fit.md", "loss.csv", "parameter_identification.png"],
    "contact_friction_identification": ["fit.md", "loss.csv", "trajectories.csv", "friction_identification.png"],
    "ball_on_soft_block": ["ball_on_soft_block.gif", "ball.csv", "ball_on_soft_block.png"],
    "push_through_sand": ["push_through_sand.gif", "drag.csv", "push_through_sand.png"],
    "elastic_identification": ["fit.md", "loss.csv", "elastic_identification.png"],
    "ball_mass_identification": ["fit.md", "loss.csv", "ball_mass_identification.png"],
    "arm_press_plasticine": ["fitted_press.gif", "loss.csv", "knots.md", "arm_press_plasticine.png", "before_after.png"],
    # one process here; tests/test_distributed.py runs them under torchrun (2 ranks) against this
    "distributed_identification": ["fit.md", "loss.csv", "distributed_identification.png"],
    "distributed_policy": ["loss.csv", "policy.pt", "distributed_policy.png"],
}
SLOW = {  # examples whose --quick run takes longer than ~40 s on the project's 2-core machine, and:
    # the distributed examples, whose single-process --quick runs tests/test_distributed.py (slow) compares with
    # their torchrun runs; the default suite keeps its two-rank gloo test (suite time)
    "distributed_identification", "distributed_policy",
    # and, for the default suite's 15-minute budget on 2 cores, the six whose --quick runs took 27-84 s in a
    # cold CI run (their solvers' paths are covered by the default examples, the gradient matrix and
    # tests/test_vis.py's recordings)
    "arm_press_plasticine", "ball_mass_identification", "elastic_identification", "record_video",
    "contact_friction_identification", "contact_quadruped"}


def _run(name, tmp_path):
    out = tmp_path / name
    t0 = time.time()
    proc = subprocess.run([sys.executable, str(REPO_ROOT / "examples" / f"{name}.py"), "--quick", "--out", str(out)],
                          cwd=REPO_ROOT, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONPATH": str(REPO_ROOT)})
    print(f"{name} --quick: {time.time() - t0:.1f} s\n{proc.stdout[-3000:]}")
    assert proc.returncode == 0, f"{name} --quick failed (exit {proc.returncode}):\n{proc.stderr[-4000:]}"
    assert "summary =====" in proc.stdout, f"{name} printed no closing summary"
    return out, proc


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n for n in EXAMPLES])
def test_example_quick_run_writes_its_files(name, tmp_path):
    out, proc = _run(name, tmp_path)
    for f in EXAMPLES[name]:
        p = out / f
        assert p.is_file(), f"{name} did not write {f} (wrote {sorted(x.name for x in out.iterdir())})"
        assert p.stat().st_size > 0, f"{name} wrote an empty {f}"


def test_every_example_is_tested():
    """A new example in examples/ gets a line in EXAMPLES."""
    found = {p.stem for p in (REPO_ROOT / "examples").glob("*.py") if p.stem != "example_utils"}
    assert found == set(EXAMPLES), f"untested: {sorted(found - set(EXAMPLES))}, missing: {sorted(set(EXAMPLES) - found)}"
