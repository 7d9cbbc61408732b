"""Shared pieces of the benchmarks: the robot files, the MuJoCo peer's model, timing and tables.

Every engine simulates the same file: example-robot-data's Panda with all <visual> and <collision>
elements removed (no meshes to load, no contacts), so what is timed is articulated-body dynamics.
"""
from __future__ import annotations

import json
import os
import site
import statistics
import subprocess
import sys
import sysconfig
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
DT = 0.01  # s
# Where real Genesis (genesis-world) lives: its own venv, never the project's (it brings its own Taichi fork).
GENESIS_VENV_DEFAULTS = ("/work/genesis_venv/bin/python", "/tmp/gvenv/bin/python")
# Panda's "ready" pose (7 arm joints, 2 fingers): inside every joint's limits.
PANDA_HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785, 0.04, 0.04])


def find_robots_dir() -> Path:
    """example-robot-data's robots directory (its pip wheel has no Python module, only files)."""
    env = os.environ.get("EXAMPLE_ROBOT_DATA_DIR")
    if env:
        return Path(env)
    bases = []
    try:
        bases += list(site.getsitepackages())
    except Exception:
        pass
    bases += [sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]]
    for base in bases:
        d = Path(base) / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
        if d.is_dir():
            return d
    raise FileNotFoundError("example-robot-data is not installed: pip install example-robot-data "
                            "(or set EXAMPLE_ROBOT_DATA_DIR to its robots/ directory)")


def panda_urdf() -> Path:
    """The full Panda URDF of example-robot-data (with its meshes)."""
    return find_robots_dir() / "panda_description" / "urdf" / "panda.urdf"


def write_stripped_panda(out_dir: str | os.PathLike | None = None, fusestatic: bool = True) -> Path:
    """Write panda.urdf without <visual>/<collision> elements to out_dir (a new temp dir by default).

    A <mujoco><compiler .../></mujoco> element is added for MuJoCo's URDF importer (other parsers ignore
    it). fusestatic=True lets MuJoCo merge bodies welded by fixed joints, as genesis_lite merges fixed
    links, so both engines see the same 9-dof tree of moving bodies.
    """
    tree = ET.parse(panda_urdf())
    root = tree.getroot()
    for link in root.findall("link"):
        for tag in ("visual", "collision"):
            for e in link.findall(tag):
                link.remove(e)
    mj = ET.SubElement(root, "mujoco")
    ET.SubElement(mj, "compiler", {"discardvisual": "true", "fusestatic": "true" if fusestatic else "false"})
    out_dir = Path(out_dir) if out_dir is not None else Path(tempfile.mkdtemp(prefix="bench_panda_"))
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "panda_stripped.urdf"
    tree.write(path, encoding="unicode")
    return path


def mujoco_model(urdf: str | os.PathLike, mimic: bool = False):
    """MuJoCo's model of a URDF set up like genesis_lite's benchmark scene.

    Semi-implicit Euler, dt = 0.01 s, gravity -9.81 z, joint damping, armature and friction loss 0,
    joint limits on. The Panda's finger mimic joint becomes an equality constraint in MuJoCo; genesis_lite
    (and Pinocchio by default) treat both fingers as independent joints, so mimic=False disables it.
    """
    import mujoco

    m = mujoco.MjModel.from_xml_path(str(urdf))
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    m.opt.timestep = DT
    m.opt.gravity[:] = (0.0, 0.0, -9.81)
    m.dof_damping[:] = 0.0
    m.dof_armature[:] = 0.0
    m.dof_frictionloss[:] = 0.0
    if not mimic and m.neq:
        m.eq_active0[:] = 0
    return m


def median_rate(fn: Callable[[], float], count: float, repeats: int = 5) -> float:
    """Median over repeats of count / seconds, where fn() runs once and returns the seconds it took."""
    return statistics.median(count / fn() for _ in range(repeats))


class Timer:
    def __enter__(self):
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self.t0


def run_python(args: Sequence[str], python: str | None = None, env: dict | None = None, timeout: float = 900):
    """Run a Python child (its own process: one gs.init per process, and a crash there cannot take the
    benchmark down). Returns (json of its last stdout line or None, error text or None)."""
    cmd = [python or sys.executable, *args]
    full_env = {**os.environ, **(env or {})}
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, env=full_env, timeout=timeout, cwd=REPO_ROOT)
    except subprocess.TimeoutExpired:
        return None, f"timed out after {timeout:.0f} s"
    lines = [ln for ln in p.stdout.strip().splitlines() if ln.strip()]
    if p.returncode == 0 and lines:
        try:
            return json.loads(lines[-1]), None
        except json.JSONDecodeError:
            pass
    tail = [ln.strip() for ln in (p.stderr or p.stdout).strip().splitlines() if ln.strip()]
    return None, f"exit {p.returncode}: " + (tail[-1] if tail else "no output")


def print_table(rows: list[dict], columns: Sequence[tuple[str, str, str]], title: str = "") -> str:
    """Print rows as a Markdown table; columns are (key, header, format). Returns the text."""
    def cell(row, key, fmt):
        v = row.get(key)
        if v is None:
            return "-"
        return format(v, fmt) if fmt and isinstance(v, (int, float)) else str(v)

    lines = []
    if title:
        lines.append(f"\n{title}")
    lines.append("| " + " | ".join(h for _, h, _ in columns) + " |")
    lines.append("| " + " | ".join("---" for _ in columns) + " |")
    for r in rows:
        lines.append("| " + " | ".join(cell(r, k, f) for k, _, f in columns) + " |")
    text = "\n".join(lines)
    print(text, flush=True)
    return text


def pyplot():
    """matplotlib.pyplot with a headless backend, or None (with a message) when it is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no plot", file=sys.stderr)
        return None
    return plt


def save_figure(fig, path: Path) -> None:
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def plot_rates(rows: list[dict], path: Path, title: str) -> None:
    """Horizontal bar chart of the rows' steps/s (log scale), one bar per engine and env count."""
    plt = pyplot()
    if plt is None:
        return
    ok = [r for r in rows if r.get("rate")]
    fig, ax = plt.subplots(figsize=(8, 0.6 * len(ok) + 1.5))
    ax.barh([f"{r['engine']}, {r['envs']} env" for r in ok], [r["rate"] for r in ok])
    ax.set_xscale("log")
    ax.set_xlabel("steps/s (env-steps/s), log scale")
    ax.set_title(title)
    save_figure(fig, path)


def genesis_python() -> str:
    """The interpreter of real Genesis's venv: $GENESIS_PYTHON, else the first default that exists (else the
    first default, which callers test with Path.exists() and then skip the peer, saying so)."""
    env = os.environ.get("GENESIS_PYTHON")
    if env:
        return env
    for p in GENESIS_VENV_DEFAULTS:
        if Path(p).exists():
            return p
    return GENESIS_VENV_DEFAULTS[0]


def progress(iterable=None, total=None, desc=None, disable=False):
    """tqdm progress bar on stderr, or the bare iterable when tqdm is not installed (benchmarks still run)."""
    try:
        from tqdm import tqdm
    except ImportError:
        return iterable if iterable is not None else range(total or 0)
    return tqdm(iterable, total=total, desc=desc, disable=disable, file=sys.stderr, dynamic_ncols=True,
                mininterval=1.0)


def machine_info() -> dict:
    """What the numbers were measured on: CPU model, cores, memory, load, OS and library versions."""
    import platform

    info = {"cores": os.cpu_count(), "python": platform.python_version(), "os": platform.platform()}
    try:
        with open("/proc/cpuinfo") as f:
            models = [ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")]
        info["cpu"] = models[0] if models else platform.processor()
    except OSError:
        info["cpu"] = platform.processor()
    try:
        with open("/proc/meminfo") as f:
            info["mem_gib"] = int(f.readline().split()[1]) / 2**20
    except (OSError, ValueError, IndexError):
        pass
    try:
        info["load"] = os.getloadavg()
    except OSError:
        pass
    for mod in ("numpy", "torch", "taichi", "mujoco", "pinocchio", "scipy"):
        try:
            m = __import__(mod)
            v = getattr(m, "__version__", None)
            info[mod] = ".".join(str(x) for x in v) if isinstance(v, tuple) else str(v)  # taichi's is a tuple
        except Exception:
            info[mod] = None
    return info
