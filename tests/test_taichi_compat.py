"""Issue #22's first item: Taichi's private API in one module (solvers/taichi_compat), its speed-ups
behind one switch and a version check. Whether they change a value is checked elsewhere (the IR and
cache keys in test_build_overheads.py, bitwise gradients in test_determinism.py); here: the switch
and the version check do what they say, in fresh processes."""
import json
import os
import subprocess
import sys
import textwrap

from solvers import taichi_compat

PROBE = textwrap.dedent("""
    import json, sys
    import genesis_lite as gs
    from solvers.taichi_compat import frontend
    before = frontend.installed()
    gs.init(backend=gs.cpu, precision="64", **json.loads(sys.argv[1]))
    print(json.dumps([before, frontend.installed()]))
""")


def _installed(init_kwargs, **env):
    done = subprocess.run([sys.executable, "-c", PROBE, json.dumps(init_kwargs)], env=dict(os.environ, **env),
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_speedups_are_on_by_default_and_one_switch_turns_them_off():
    on = {"frontend": True, "fast_launch": True}
    off = {"frontend": False, "fast_launch": False}
    assert taichi_compat.version_ok()  # the pinned Taichi is the one they were written for
    assert _installed({}) == [on, on]
    assert _installed({"taichi_speedups": False}) == [on, off]
    assert _installed({}, GS_TAICHI_SPEEDUPS="0") == [off, off]


def test_another_taichi_version_runs_without_them(monkeypatch, caplog):
    from solvers.taichi_compat import frontend

    monkeypatch.setattr(taichi_compat, "version_ok", lambda: False)
    calls = []
    monkeypatch.setattr(frontend, "install", lambda: calls.append("install"))
    monkeypatch.setattr(frontend, "install_fast_launch", lambda: calls.append("launch"))
    with caplog.at_level("INFO", logger="genesis_lite"):
        assert taichi_compat.install_speedups() == {"frontend": False, "fast_launch": False}
    assert calls == [] and "running without them" in caplog.text
