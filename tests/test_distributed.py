"""Issue #23: several processes. Data-parallel rollouts over torch.distributed ranks give the loss and
the gradients of one process over the same environments; each rank gets its share of the CPU threads;
processes starting at once on empty caches all work.

The distributed runs are started as a user starts them, `python -m torch.distributed.run` (torchrun),
on the worker tests/workers/distributed_rollout.py (a double pendulum, 4 environments, 12 steps,
float64, gloo). The reference is the same function over all environments in this process, with
every core (the suite's gs.init), so a rank's thread count cannot change a result unnoticed either.
"""
import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import genesis_lite as gs

REPO_ROOT = Path(__file__).resolve().parents[1]
WORKER = Path(__file__).parent / "workers" / "distributed_rollout.py"


def _worker_module():
    spec = importlib.util.spec_from_file_location("distributed_rollout", WORKER)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _reference():
    """Loss and gradient of the worker's problem over all its environments, in this process."""
    w = _worker_module()
    params = torch.tensor(w.PARAMS, dtype=torch.float64, requires_grad=True)
    loss = w.local_loss(list(range(w.N_ENVS)), w.N_ENVS, params)
    loss.backward()
    return loss.item(), params.grad.numpy().copy()


def _env(**extra):
    return {**os.environ, "PYTHONPATH": str(REPO_ROOT), **extra}


def _last_json(stdout):
    return json.loads([line for line in stdout.splitlines() if line.startswith("{")][-1])


def _cores():
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count()


# slow (suite time, ~33 s: two ranks each compiling in their own process), with the torchrun examples below
@pytest.mark.slow
def test_two_gloo_ranks_give_the_single_process_loss_and_gradients():
    gs.init(backend=gs.cpu, precision="64")
    loss, grad = _reference()
    t0 = time.time()
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                           str(WORKER)], cwd=REPO_ROOT, env=_env(), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"torchrun failed:\n{done.stdout[-2000:]}\n{done.stderr[-4000:]}"
    out = _last_json(done.stdout)
    print(f"2 ranks: {time.time() - t0:.1f} s; {out}")
    assert out["world"] == 2
    # each of the 2 ranks on this node gets half the cores (torchrun sets LOCAL_WORLD_SIZE=2)
    assert out["threads"] == max(1, _cores() // 2)
    assert abs(out["loss"] - loss) <= 1e-12 * abs(loss)
    g = np.array(out["grad"])
    assert np.all(np.abs(grad) > 1e-4)  # every shared parameter has a gradient to compare
    np.testing.assert_allclose(g, grad, rtol=1e-12, atol=0)


def test_default_threads_per_process(monkeypatch):
    """cores // LOCAL_WORLD_SIZE under torchrun, Taichi's and torch's own defaults alone,
    GS_NUM_THREADS above both; a value that is not a positive integer is refused."""
    cores = _cores()
    monkeypatch.delenv("GS_NUM_THREADS", raising=False)
    monkeypatch.delenv("LOCAL_WORLD_SIZE", raising=False)
    assert gs.default_num_threads() is None
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "1")
    assert gs.default_num_threads() is None
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    assert gs.default_num_threads() == max(1, cores // 2)
    monkeypatch.setenv("LOCAL_WORLD_SIZE", str(4 * cores))
    assert gs.default_num_threads() == 1
    monkeypatch.setenv("GS_NUM_THREADS", "3")
    assert gs.default_num_threads() == 3
    monkeypatch.setenv("GS_NUM_THREADS", "0")
    with pytest.raises(gs.GenesisException, match="GS_NUM_THREADS"):
        gs.default_num_threads()


def test_importing_genesis_lite_first_makes_torch_s_openmp_threads_sleep():
    """Imported before torch, genesis_lite sets OMP_WAIT_POLICY=PASSIVE for torch's OpenMP runtime (README,
    "Threads"), and a value the user set is kept. In fresh processes: the variable is read when torch loads."""
    code = "import os, genesis_lite, torch; print(os.environ.get('OMP_WAIT_POLICY'))"
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.stdout.split()[-1] == "PASSIVE", out.stderr[-2000:]
    out = subprocess.run([sys.executable, "-c", code], env={**env, "OMP_WAIT_POLICY": "ACTIVE"}, capture_output=True,
                         text=True, timeout=300)
    assert out.stdout.split()[-1] == "ACTIVE", out.stderr[-2000:]


@pytest.mark.slow  # four fresh processes building a scene of many envs (~15 s); a warning, not a number
def test_a_many_env_scene_warns_when_torch_was_imported_first():
    """torch imported before genesis_lite has read OMP_WAIT_POLICY already (unset: its threads spin), which
    slows scenes of many envs: their build warns once (ImportOrderWarning), naming the remedy. Not when
    genesis_lite came first, not when the user set the variable, not for a small scene. Fresh processes."""
    code = """
import sys, warnings
first = sys.argv[1]
if first == "torch":
    import torch, genesis_lite as gs
else:
    import genesis_lite as gs, torch
torch.set_num_threads(2)
gs.init(backend=gs.cpu, precision="64")
with warnings.catch_warnings(record=True) as w:
    warnings.simplefilter("always")
    for n in (int(a) for a in sys.argv[2:]):
        scene = gs.Scene(show_viewer=False)
        scene.add_entity(gs.morphs.Plane())
        scene.build(n_envs=n)
print("WARNED", [str(x.message) for x in w if issubclass(x.category, gs.errors.ImportOrderWarning)])
"""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}

    def warned(first, envs, extra=None):
        out = subprocess.run([sys.executable, "-c", code, first] + [str(n) for n in envs], env={**env, **(extra or {})},
                             capture_output=True, text=True, timeout=600)
        line = [ln for ln in out.stdout.splitlines() if ln.startswith("WARNED")]
        assert line, out.stderr[-3000:]
        return eval(line[-1][len("WARNED "):])

    msgs = warned("torch", [1, 256, 512])
    assert len(msgs) == 1 and "Import genesis_lite before torch" in msgs[0] and "OMP_WAIT_POLICY=PASSIVE" in msgs[0]
    assert warned("genesis_lite", [256]) == []
    assert warned("torch", [256], {"OMP_WAIT_POLICY": "ACTIVE"}) == []
    assert warned("torch", [64]) == []


def test_a_stale_kernel_cache_lock_is_removed_and_a_live_one_kept(tmp_path):
    """A Taichi cache lock (ticache.lock) left by a killed process would keep every later process from
    the kernel cache; one a running process holds (recent) must stay."""
    from genesis_lite import STALE_CACHE_LOCK_S, _remove_stale_cache_lock

    lock = tmp_path / "ticache.lock"
    lock.write_bytes(b"")
    _remove_stale_cache_lock(str(tmp_path))
    assert lock.exists(), "a lock held now was removed"
    old = time.time() - STALE_CACHE_LOCK_S - 60
    os.utime(lock, (old, old))
    _remove_stale_cache_lock(str(tmp_path))
    assert not lock.exists(), "a lock left two minutes ago was kept"
    _remove_stale_cache_lock(str(tmp_path / "missing"))  # no cache folder yet: nothing to do


@pytest.mark.slow
def test_four_processes_start_at_once_on_empty_caches(tmp_path):
    """Four processes started together on an empty GS_CACHE_DIR (models, Taichi function sources, the
    checked runtime) and an empty TI_OFFLINE_CACHE_FILE_PATH, with the checked autodiff-stack runtime
    (GS_CHECK_AD_STACK=1), each build the scene, step it and backpropagate: all exit 0 with the numbers
    of this process and leave a kernel cache (its metadata written) that four more processes started
    together read back to the same numbers. A stale lock left in the kernel cache by a killed process
    is cleared first: kept, it would stop every process from writing the cache, silently (gs.init
    sets Taichi's log level to errors; measured: no .tic file, no metadata, no message)."""
    from solvers.taichi_compat import checked_runtime

    gs.init(backend=gs.cpu, precision="64")
    loss, grad = _reference()
    gs_cache, ti_cache = tmp_path / "gs", tmp_path / "ti"
    # where the checked-runtime kernels of these processes go (checked_runtime.install): a lock file
    # there, two hours old, as a rank killed while writing the cache leaves it
    kernel_dir = ti_cache / ("checked-" + os.path.basename(checked_runtime.build()))
    kernel_dir.mkdir(parents=True)
    stale = kernel_dir / "ticache.lock"
    stale.write_bytes(b"")
    os.utime(stale, (time.time() - 7200, time.time() - 7200))
    env = _env(GS_CACHE_DIR=str(gs_cache), TI_OFFLINE_CACHE_FILE_PATH=str(ti_cache), GS_CHECK_AD_STACK="1")
    env.pop("LOCAL_WORLD_SIZE", None)
    kernels = {}
    for wave in ("empty cache", "cache written by the first four"):
        t0 = time.time()
        procs = [subprocess.Popen([sys.executable, str(WORKER)], cwd=REPO_ROOT, env=env, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True) for _ in range(4)]
        results = [p.communicate(timeout=900) for p in procs]
        print(f"{wave}: 4 processes in {time.time() - t0:.1f} s")
        for p, (stdout, stderr) in zip(procs, results):
            assert p.returncode == 0, f"{wave}: a process failed (exit {p.returncode}):\n{stderr[-4000:]}"
            out = _last_json(stdout)
            assert abs(out["loss"] - loss) <= 1e-12 * abs(loss)
            np.testing.assert_allclose(out["grad"], grad, rtol=1e-12, atol=0)
        assert not stale.exists()
        assert (kernel_dir / "ticache.tcb").is_file(), f"{wave}: no kernel-cache metadata was written"
        assert (gs_cache / "models").is_dir() and any((gs_cache / "models").iterdir())
        assert not list(gs_cache.rglob("*.tmp")), "a temporary cache file was left behind"
        kernels[wave] = sorted(p.name for p in kernel_dir.glob("*.tic"))
    # the second four compiled nothing: every kernel came from the cache the first four wrote together
    assert kernels["cache written by the first four"] == kernels["empty cache"]


@pytest.mark.slow
@pytest.mark.parametrize("example", ["distributed_identification", "distributed_policy"])
def test_example_under_torchrun_matches_one_process(example, tmp_path):
    """Each distributed example with --quick under torchrun (2 ranks) prints the summary numbers of
    its single-process run (the same environments, split over two ranks)."""
    def run(cmd, out):
        done = subprocess.run(cmd + [str(REPO_ROOT / "examples" / f"{example}.py"), "--quick", "--out", str(out)],
                              cwd=REPO_ROOT, env=_env(), capture_output=True, text=True, timeout=900)
        assert done.returncode == 0, f"{cmd}: {done.stderr[-4000:]}"
        return [line for line in done.stdout.splitlines() if line.startswith(("loss", "|"))]

    one = run([sys.executable], tmp_path / "one")
    two = run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"], tmp_path / "two")
    assert one and one == two
