"""Shared test set-up: one `gs.init` per session, and the robots of example-robot-data by short name.

example-robot-data ships no Python module: its pip wheel (a cmeel package) puts the robots under
`<site-packages>/cmeel.prefix/share/example-robot-data/robots`. `EXAMPLE_ROBOT_DATA_DIR` overrides it.
"""
from __future__ import annotations

import os
import shutil
import site
import sys
import sysconfig
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
ASSETS_DIR = REPO_ROOT / "assets"

# Short name -> URDF path relative to the robots directory. The first group is fixed-base arms
# (kinova and double_pendulum_continuous have continuous joints); the last group has floating bases.
FIXED_BASE_ROBOTS = {
    "panda": "panda_description/urdf/panda.urdf",
    "ur5": "ur_description/urdf/ur5_robot.urdf",
    "z1": "z1_description/urdf/z1.urdf",
    "kinova": "kinova_description/robots/kinova.urdf",
    "xarm7": "xarm_description/urdf/xarm7.urdf",
    "so101": "so_arm_description/urdf/so101.urdf",
    "double_pendulum_continuous": "double_pendulum_description/urdf/double_pendulum_continuous.urdf",
    "finger_edu": "finger_edu_description/robots/finger_edu.urdf",
}
FLOATING_BASE_ROBOTS = {
    "go2": "go2_description/urdf/go2.urdf",
    "anymal": "anymal_b_simple_description/robots/anymal.urdf",
    "anymal_c": "anymal_c_simple_description/urdf/anymal.urdf",
}
ROBOTS = {**FIXED_BASE_ROBOTS, **FLOATING_BASE_ROBOTS}


def find_robots_dir() -> Path | None:
    """The example-robot-data robots directory of this interpreter, or None when not installed."""
    env = os.environ.get("EXAMPLE_ROBOT_DATA_DIR")
    if env:
        return Path(env)
    candidates = []
    for getter in (site.getsitepackages, lambda: [site.getusersitepackages()]):
        try:
            candidates += list(getter())
        except Exception:
            pass
    candidates += [sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"], sys.prefix]
    for base in candidates:
        d = Path(base) / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
        if d.is_dir():
            return d
    return None


def robot_urdf(name: str) -> Path:
    """Path of the URDF of a robot given by short name (see ROBOTS); asserts that the file exists."""
    if name not in ROBOTS:
        raise KeyError(f"unknown robot {name!r}; known: {sorted(ROBOTS)}")
    robots_dir = find_robots_dir()
    if robots_dir is None:
        pytest.skip("example-robot-data is not installed (pip install example-robot-data)")
    path = robots_dir / ROBOTS[name]
    assert path.is_file(), f"{name}: {path} does not exist in this example-robot-data version"
    return path


# Every kernel of the suite runs against Taichi's runtime with bounds-checked autodiff stacks
# (solvers/taichi_compat/checked_runtime.py): an undersized stack aborts the run with a message
# instead of giving a wrong gradient that a test might not see. Subprocesses (examples) inherit it.
# GS_CHECK_AD_STACK=0 runs the suite on Taichi's own runtime.
os.environ.setdefault("GS_CHECK_AD_STACK", "1")

# One gs.init per process (DESIGN.md). The import is guarded so that this file, and the tests that do
# not need the simulator, still work while the package is incomplete; tests that need it import it
# themselves and fail there with the real error.
try:
    import genesis_lite as gs
except Exception as exc:  # pragma: no cover - only while the core is missing or broken
    gs = None
    _GS_IMPORT_ERROR = exc
else:
    _GS_IMPORT_ERROR = None


def pytest_configure(config):
    # hasattr: while the core is being written, `genesis_lite` may be a bare namespace package.
    if gs is not None and hasattr(gs, "init"):
        gs.init(backend=gs.cpu, precision="64")


def _has_gpu() -> bool:
    return shutil.which("nvidia-smi") is not None or os.environ.get("GS_TEST_GPU") == "1"


def pytest_collection_modifyitems(config, items):
    if _has_gpu():
        return
    skip_gpu = pytest.mark.skip(reason="needs a GPU (none found; set GS_TEST_GPU=1 to force)")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip_gpu)


@pytest.fixture(scope="session")
def robots_dir() -> Path:
    """The example-robot-data robots directory."""
    d = find_robots_dir()
    if d is None:
        pytest.skip("example-robot-data is not installed (pip install example-robot-data)")
    return d


@pytest.fixture(scope="session")
def urdf_path():
    """A function: short robot name (panda, ur5, z1, kinova, xarm7, so101, double_pendulum_continuous,
    finger_edu, go2, anymal, anymal_c) -> URDF path."""
    return robot_urdf


@pytest.fixture(scope="session")
def assets_dir() -> Path:
    """The repository's assets/ directory (URDFs written for the tests)."""
    return ASSETS_DIR


@pytest.fixture
def compiled(monkeypatch):
    """The names of the kernels Taichi compiles from now on (Taichi's Kernel.materialize wrapped: every
    kernel Taichi builds, ours and its own field-copy kernels, goes through it)."""
    from taichi.lang import kernel_impl

    names = []
    original = kernel_impl.Kernel.materialize

    def materialize(self, key=None, args=None, arg_features=None):
        if (key if key is not None else (self.func, 0, self.autodiff_mode)) not in self.compiled_kernels:
            names.append(self.func.__name__ + ("" if self.autodiff_mode == kernel_impl.AutodiffMode.NONE else ".grad"))
        return original(self, key, args, arg_features)

    monkeypatch.setattr(kernel_impl.Kernel, "materialize", materialize)
    return names
