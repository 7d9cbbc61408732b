"""Genesis's own example scripts, run on genesis_lite and on real Genesis: how many run, how their answers compare.

Takes 27 scripts (28 runs: water_wheel also with its --solver mpm) from `examples/` of a Genesis checkout (a git
tag of a mirror, or a work tree), makes a transformed copy of each with ONLY the edits listed below, runs it in a
fresh process on each side, and records exit status, wall time, the last error line and the `GS_RESULT <name>
<value>` lines.

The edits, each a regular expression applied to the script's text (see `IMPORT_EDITS`, `VIEWER_EDITS`,
`BACKEND_EDITS` and each script's `loops` in `SCRIPTS`):
  import   `import genesis as gs` -> `import genesis_lite as gs`, `from genesis.x import` ->
           `from genesis_lite.x import` (our run only; Genesis's run keeps the import)
  viewer   `show_viewer=True` -> `show_viewer=False`, a camera's `GUI=True` -> `GUI=False`
  backend  `gs.gpu` / `gs.cuda` / `gs.metal` / `gs.vulkan` -> `gs.cpu`; a `gs.init(...)` that names no
           backend gets `backend=gs.cpu` (Genesis's default would be the GPU)
  loops    a script's own loop lengths (`range(N)`, `horizon = N if ...`) and large `n_envs` are capped
           at the small values given per script; every listed edit must match, else the run is refused
Asset paths are not rewritten: our side runs with GS_ASSETS_DIR=<Genesis's genesis/assets folder>.
Argparse defaults of these scripts already leave the viewer off (`-v` is store_true), so none is changed.

Harness-only additions, identical on both sides and not touching the simulation:
  * before `if __name__ == "__main__":` (scripts with a main()), a `sys.setprofile` hook that keeps main's
    frame on its first call and removes itself at once, so the probe can read main's locals afterwards;
  * at the end, the probe: `GS_RESULT <name> <v1,v2,...>` lines computed from the script's variables
    (e.g. the Franka's joint positions, the mean z of a body's particles, the loss).
The go2 "script" is a driver: Genesis's locomotion/go2_env.py (import-edited like any script), the
`get_cfgs()` function taken verbatim from locomotion/go2_train.py of the same checkout (that script itself
needs rsl-rl and a training run), and a tiny loop: `gs.init(backend=gs.cpu)`, `Go2Env(num_envs=4, ...)`,
`reset()`, 100 `step()`s of zero actions.

    python benchmarks/genesis_scripts.py --help
    python benchmarks/genesis_scripts.py --side ours                      # our side, all 27
    python benchmarks/genesis_scripts.py --side genesis --genesis-python /work/genesis_venv/bin/python
    python benchmarks/genesis_scripts.py --scripts pyramid,tower --side both --genesis-python ...

Results accumulate in <out>/results.json (one entry per side and script; a run replaces its entries) and
<out>/table.md is rewritten from it after every script. Logs and transformed scripts: <out>/<side>/.

Without Genesis installed, `--genesis-recorded FILE` fills the Genesis column from a recorded run (a JSON file written
by `--save-genesis FILE` after a Genesis-side run, or once by `--extract-recorded MD` from an older results
markdown); the table then says the Genesis column is that recorded run (version, date, source) and ours is today's:

    python benchmarks/genesis_scripts.py --side ours --rev v0.4.5 --assets <genesis/assets>
        --genesis-recorded benchmarks/results/genesis_scripts_genesis045.json       (one command line)
"""
from __future__ import annotations

import argparse
import ast
import json
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MIRROR = "/work/.mirror/Genesis-Embodied-AI+Genesis/repo"
DEFAULT_OUT = "/tmp/genesis_scripts_out"
RECORDED_DEFAULT = REPO_ROOT / "benchmarks" / "results" / "genesis_scripts_genesis045.json"

# ----------------------------------------------------------------------------------------------- the edits
IMPORT_EDITS = [  # our side only
    (r"(?m)^(\s*)import genesis as gs\b", r"\1import genesis_lite as gs"),
    (r"(?m)^(\s*)from genesis((?:\.\w+)+) import\b", r"\1from genesis_lite\2 import"),
]
VIEWER_EDITS = [
    (r"\bshow_viewer\s*=\s*True\b", "show_viewer=False"),
    (r"\bGUI\s*=\s*True\b", "GUI=False"),
]
BACKEND_EDITS = [
    (r"\bgs\.(?:gpu|cuda|metal|vulkan)\b", "gs.cpu"),
    (r"\bgs\.init\(\s*\)", "gs.init(backend=gs.cpu)"),
    (r"\bgs\.init\((?![^)]*\bbackend\s*=)", "gs.init(backend=gs.cpu, "),
]


def cap_range(n: int, k: int):
    """`range(n)` -> `range(k)`."""
    return (rf"\brange\({n}\)", f"range({k})")


def cap_text(old: str, new: str):
    """The literal text `old` -> `new` (for a loop length written in an expression)."""
    return (re.escape(old), new.replace("\\", "\\\\"))


def cap_assign(name: str, n: int, k: int):
    """`name = n` (e.g. `horizon = 1000 if "PYTEST_VERSION" ...`, `B = 30000`) -> `name = k`."""
    return (rf"(?m)^(\s*{name}\s*=\s*){n}\b", rf"\g<1>{k}")


# Probe helpers: prepended to every probe, the same text on both sides.
PROBE_HELPERS = r'''
def _gsr_flat(x):
    import numpy as _np
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return _np.asarray(x, dtype=float).ravel()

def _gsr_pz(e):
    """Mean z of an MPM/particle entity's (active) particles."""
    import numpy as _np
    p = e.get_particles_pos()
    p = p.detach().cpu().numpy() if hasattr(p, "detach") else _np.asarray(p)
    z = p[..., 2]
    if hasattr(e, "get_particles_active"):
        try:
            a = e.get_particles_active()
            a = a.detach().cpu().numpy() if hasattr(a, "detach") else _np.asarray(a)
            if a.shape == z.shape and a.any():
                z = z[a.astype(bool)]
        except Exception:
            pass
    return float(_np.mean(z))

def _gsr_emitter_entity(em):
    return getattr(em, "entity", None) or getattr(em, "_entity")
'''

PROBE_TEMPLATE = '''
# ---------------- GS_RESULT probe (harness; the same text on both sides) ----------------
{helpers}
_gsr_ns = dict(globals())
if "_gsr_frames" in globals() and _gsr_frames:
    _gsr_ns.update(_gsr_frames[0].f_locals)
for _gsr_name, _gsr_expr in {probes!r}:
    try:
        _gsr_v = _gsr_flat(eval(_gsr_expr, _gsr_ns))
        print("GS_RESULT", _gsr_name, ",".join("%.6g" % _x for _x in _gsr_v), flush=True)
    except Exception as _gsr_e:
        print("GS_RESULT_ERROR", _gsr_name, type(_gsr_e).__name__, str(_gsr_e).splitlines()[0] if str(_gsr_e) else "", flush=True)
'''

MAIN_HOOK = '''# ---------------- harness: keep main()'s frame for the probe (removes itself on main's first call) ----
import sys as _gsr_sys
_gsr_frames = []
def _gsr_hook(frame, event, arg):
    if event == "call" and frame.f_code.co_name == "main" and frame.f_globals is globals():
        _gsr_frames.append(frame)
        _gsr_sys.setprofile(None)
_gsr_sys.setprofile(_gsr_hook)
'''

GO2_DRIVER = '''
# ---------------- harness: go2 driver (get_cfgs() from go2_train.py of the same checkout) ----------------
{get_cfgs}

gs.init(backend=gs.cpu)
env_cfg, obs_cfg, reward_cfg, command_cfg = get_cfgs()
env = Go2Env(num_envs=4, env_cfg=env_cfg, obs_cfg=obs_cfg, reward_cfg=reward_cfg, command_cfg=command_cfg,
             show_viewer=False)
obs = env.reset()
for _i in range(100):
    obs, rews, dones, infos = env.step(torch.zeros((env.num_envs, env.num_actions), dtype=gs.tc_float,
                                                   device=gs.device))
robot = env.robot
'''

# ----------------------------------------------------------------------------------------------- the scripts
# path: under examples/; loops: the loop/env caps (each must match); probes: (name, expression) over the
# script's variables (main's locals for scripts with a main()); argv: the script's command-line arguments (an
# option of Genesis's own script, as its user would pass it).
FRANKA_Q = ("franka_q", "franka.get_dofs_position()")
FRANKA_Q0 = ("franka_q_env0", "franka.get_dofs_position()[0]")
SCRIPTS = {
    "hello_genesis": dict(path="tutorials/hello_genesis.py", loops=[cap_range(1000, 200)], probes=[FRANKA_Q]),
    "control_your_robot": dict(path="tutorials/control_your_robot.py", loops=[cap_assign("horizon", 1250, 300)],
                               probes=[FRANKA_Q]),
    "parallel_simulation": dict(path="tutorials/parallel_simulation.py", loops=[cap_range(1000, 200)],
                                probes=[FRANKA_Q0]),
    "entity_name": dict(path="tutorials/entity_name.py", loops=[],
                        probes=[("n_entities", "len(scene.entities)"), ("go2_n_dofs", "robot.n_dofs")]),
    "position_control_comparison": dict(
        path="tutorials/position_control_comparison.py", loops=[],
        probes=[("mean_abs_err_pos", "__import__('numpy').mean(abs(__import__('numpy').subtract("
                                     "pos_simulation_result[1], pos_simulation_result[2])))"),
                ("mean_abs_err_posvel", "__import__('numpy').mean(abs(__import__('numpy').subtract("
                                        "pos_vel_simulation_result[1], pos_vel_simulation_result[2])))")]),
    "mpm": dict(path="tutorials/mpm.py", loops=[cap_assign("horizon", 1000, 100)],
                probes=[("z_elastic_liquid_plastic", "[_gsr_pz(obj_elastic), _gsr_pz(obj_sand), _gsr_pz(obj_plastic)]")]),
    "single_franka": dict(path="rigid/single_franka.py", loops=[cap_range(1000, 200)], probes=[FRANKA_Q]),
    "single_franka_envs": dict(path="rigid/single_franka_envs.py", loops=[], probes=[FRANKA_Q]),
    "control_franka": dict(path="rigid/control_franka.py", loops=[cap_range(1250, 300)], probes=[FRANKA_Q]),
    "franka_cube": dict(path="rigid/franka_cube.py", loops=[], probes=[("cube_pos", "cube.get_pos()")]),
    "apply_external_force_torque": dict(path="rigid/apply_external_force_torque.py", loops=[cap_range(1000, 200)],
                                        probes=[("cube_pos", "cube.get_pos()")]),
    "gravity_compensation": dict(path="rigid/gravity_compensation.py", loops=[cap_range(1000, 200)],
                                 probes=[("joint2_comp0_0.5_1", "[e.get_dofs_position()[1] for e in scene.entities[1:4]]")]),
    "domain_randomization": dict(path="rigid/domain_randomization.py", loops=[],
                                 probes=[("base_z_mean", "robot.get_pos()[:, 2].mean()")]),
    "set_phys_attr": dict(path="rigid/set_phys_attr.py", loops=[cap_range(1250, 300)],
                          probes=[("franka_q_2envs", "franka.get_dofs_position()")]),
    "nonconvex_mesh": dict(path="rigid/nonconvex_mesh.py", loops=[cap_range(1000, 200)],
                           probes=[("ball_pos", "ball.get_pos()")]),
    "control_mesh": dict(path="rigid/control_mesh.py", loops=[cap_range(1000, 200)],
                         probes=[("duck_dofs", "duck.get_dofs_position()")]),
    "pyramid": dict(path="collision/pyramid.py", loops=[],
                    probes=[("boxes_mean_z", "sum(float(e.get_pos()[2]) for e in scene.entities[1:]) / (len(scene.entities) - 1)"),
                            ("top_box_z", "scene.entities[-1].get_pos()[2]")]),
    "tower": dict(path="collision/tower.py", loops=[cap_text('horizon = 50 if "PYTEST_VERSION" in os.environ else 1000',
                                                            'horizon = 50 if "PYTEST_VERSION" in os.environ else 400')],
                  probes=[("top_box_z", "scene.entities[-2].get_pos()[2]"),
                          ("cylinder_z", "scene.entities[-1].get_pos()[2]")]),
    "speed_franka": dict(path="speed_benchmark/franka.py", loops=[cap_assign("B", 30000, 64), cap_range(1000, 100)],
                         probes=[FRANKA_Q0]),
    "speed_anymal_c": dict(path="speed_benchmark/anymal_c.py", loops=[cap_assign("n_envs", 30000, 64), cap_range(1000, 100)],
                           probes=[("base_z_mean", "robot.get_pos()[:, 2].mean()")]),
    "go2": dict(path="locomotion/go2_env.py", loops=[], driver="go2",
                probes=[("base_z_mean", "robot.get_pos()[:, 2].mean()"), ("base_x_mean", "robot.get_pos()[:, 0].mean()")]),
    "flush_cubes": dict(path="coupling/flush_cubes.py", loops=[cap_assign("horizon", 100, 30)],
                        probes=[("z_elastic_3", "[_gsr_pz(e) for e in scene.entities[1:4]]"),
                                ("z_liquid", "[_gsr_pz(_gsr_emitter_entity(emitter1)), _gsr_pz(_gsr_emitter_entity(emitter2))]")]),
    "sand_wheel": dict(path="coupling/sand_wheel.py", loops=[cap_assign("horizon", 1000, 50)],
                       probes=[("z_sand", "_gsr_pz(_gsr_emitter_entity(emitter))")]),
    "water_wheel": dict(path="coupling/water_wheel.py", loops=[cap_assign("horizon", 500, 50)],
                        probes=[("z_liquid", "_gsr_pz(_gsr_emitter_entity(emitter))")]),
    # the same script with its MPM liquid (its --solver option; the default above is SPH, out of our scope)
    "water_wheel_mpm": dict(path="coupling/water_wheel.py", loops=[cap_assign("horizon", 500, 50)],
                            probes=[("z_liquid", "_gsr_pz(_gsr_emitter_entity(emitter))")], argv=["--solver", "mpm"]),
    "grasp_soft_cube": dict(path="coupling/grasp_soft_cube.py", loops=[cap_range(100, 50), cap_range(300, 150)],
                            probes=[("cube_particles_z", "_gsr_pz(cube)")]),
    "rigid_mpm_attachment": dict(path="coupling/rigid_mpm_attachment.py", loops=[cap_assign("n_steps", 500, 100)],
                                 probes=[("mpm_cube_z", "_gsr_pz(mpm_cube)"), ("rigid_box_z", "rigid_box.get_pos()[2]")]),
    "differentiable_push": dict(path="differentiable_push.py", loops=[cap_assign("horizon", 150, 50)],
                                probes=[("loss", "loss.item()")]),
}


# ----------------------------------------------------------------------------------------------- transform
def apply(text: str, edits, what: str, must_match: bool):
    for pat, rep in edits:
        text, n = re.subn(pat, rep, text)
        if must_match and n == 0:
            raise ValueError(f"{what} edit {pat!r} matched nothing")
    return text


def read_example(repo: str, rev: str | None, rel: str) -> str:
    if rev:
        return subprocess.run(["git", "-C", repo, "show", f"{rev}:examples/{rel}"], check=True,
                              capture_output=True, text=True).stdout
    return (Path(repo) / "examples" / rel).read_text()


def transform(name: str, side: str, repo: str, rev: str | None) -> str:
    spec = SCRIPTS[name]
    text = read_example(repo, rev, spec["path"])
    if side == "ours":
        text = apply(text, IMPORT_EDITS, "import", must_match=False)
    text = apply(text, VIEWER_EDITS, "viewer", must_match=False)
    text = apply(text, BACKEND_EDITS, "backend", must_match=False)
    text = apply(text, spec["loops"], "loop", must_match=True)
    if spec.get("driver") == "go2":
        train = read_example(repo, rev, "locomotion/go2_train.py")
        fn = next(n for n in ast.parse(train).body if isinstance(n, ast.FunctionDef) and n.name == "get_cfgs")
        text += GO2_DRIVER.format(get_cfgs=ast.get_source_segment(train, fn))
    m = re.search(r'(?m)^if __name__ == ["\']__main__["\']:', text)
    if m:
        text = text[:m.start()] + MAIN_HOOK + "\n" + text[m.start():]
    text += PROBE_TEMPLATE.format(helpers=PROBE_HELPERS, probes=spec["probes"])
    return text


# ----------------------------------------------------------------------------------------------- run
ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")
EXC_LINE = re.compile(r"^([A-Za-z_][\w.]*(?:Error|Exception|Exit|Interrupt|Failure)|AssertionError|KeyError)\b(:.*)?$")


def last_error_line(stderr: str) -> str:
    lines = [ANSI.sub("", l).rstrip() for l in stderr.splitlines() if l.strip()]
    for l in reversed(lines):
        if EXC_LINE.match(l.strip()):
            return l.strip()
    return lines[-1].strip() if lines else ""


def category(err: str) -> str:
    """The missing name or feature an error line points at (a key to group blocking causes)."""
    pats = [
        (r"has no link '(\w+)'", lambda m: f"RigidEntity.get_link('{m[1]}') (a link on a fixed joint, merged away)"),
        (r"'int' object has no attribute 'short'", lambda m: "Entity.uid.short() (uid is an int)"),
        (r"gs\.materials\.(\w+)\((\w+)=([^)]*)\): must be", lambda m: f"{m[1]}({m[2]}={m[3]}) refused"),
        (r"module '([\w.]+)' has no attribute '(\w+)'", lambda m: f"{m[1].replace('genesis_lite', 'gs')}.{m[2]}"),
        (r"'(\w+)' object has no attribute '(\w+)'", lambda m: f"{m[1]}.{m[2]}"),
        (r"(\S+)\(\) got an unexpected keyword argument '(\w+)'", lambda m: f"{m[1]}({m[2]}=)"),
        (r"No module named '([\w.]+)'", lambda m: f"module {m[1]}"),
        (r"cannot import name '(\w+)' from '([\w.]+)'", lambda m: f"{m[2]}.{m[1]}"),
    ]
    for p, f in pats:
        m = re.search(p, err)
        if m:
            return f(m)
    return err.split(":", 1)[0] if err else ""


def run_one(name: str, side: str, python: str, script: Path, timeout: float, env_extra: dict, unset=()) -> dict:
    env = dict(os.environ)
    for k in unset:
        env.pop(k, None)
    env.update(env_extra)
    log_out, log_err = script.with_suffix(".stdout"), script.with_suffix(".stderr")
    t0 = time.perf_counter()
    try:
        with open(log_out, "w") as fo, open(log_err, "w") as fe:
            p = subprocess.run([python, str(script.name), *SCRIPTS[name].get("argv", ())], cwd=script.parent, env=env,
                               stdout=fo, stderr=fe, timeout=timeout, stdin=subprocess.DEVNULL)
        rc, timed_out = p.returncode, False
    except subprocess.TimeoutExpired:
        rc, timed_out = None, True
    wall = time.perf_counter() - t0
    out, err = log_out.read_text(errors="replace"), log_err.read_text(errors="replace")
    results, probe_errors = {}, {}
    for l in out.splitlines():
        if l.startswith("GS_RESULT "):
            _, k, v = (l.split(" ", 2) + [""])[:3]
            results[k] = [float(x) for x in v.split(",") if x]
        elif l.startswith("GS_RESULT_ERROR "):
            parts = l.split(" ", 2)
            probe_errors[parts[1]] = parts[2] if len(parts) > 2 else ""
    ok = (not timed_out) and rc == 0
    err_line = "" if ok else (f"timeout after {timeout:.0f} s" if timed_out else last_error_line(err + "\n" + out))
    return dict(script=name, side=side, ok=ok, rc=rc, timed_out=timed_out, wall_s=round(wall, 1), error=err_line,
                category=category(err_line) if not ok else "", results=results, probe_errors=probe_errors,
                log=str(log_err))


# ----------------------------------------------------------------------------------------------- report
def fmt_vals(v):
    return ", ".join(f"{x:.4g}" for x in v) if v else "-"


def compare(a: dict, b: dict) -> str:
    out = []
    for k in a:
        if k in b and len(a[k]) == len(b[k]) and a[k]:
            d = max(abs(x - y) for x, y in zip(a[k], b[k]))
            out.append(f"{k}: max abs diff {d:.3g}")
        elif k in b:
            out.append(f"{k}: shapes differ ({len(a[k])} vs {len(b[k])})")
    return "; ".join(out) if out else "-"


def write_table(data: dict, path: Path, meta: dict):
    ours, theirs = data.get("ours", {}), data.get("genesis", {})
    rec = meta.get("genesis_recorded")
    gver = meta.get("genesis_version") or (rec or {}).get("genesis_version", "?")
    lines = [f"Machine: {meta.get('machine')}; CPU only. Genesis: {gver}, scripts from "
             f"{meta.get('source', '?')}.", ""]
    if rec and any(r.get("recorded") for r in theirs.values()):
        lines += [f"**The Genesis column is a recorded run**, not today's: {rec.get('genesis_version', '?')}, "
                  f"{rec.get('date', 'date unknown')}, {rec.get('machine', '')}; read from `{rec.get('file', '?')}` "
                  f"({rec.get('note', '')}). The ours column is today's run"
                  f"{' (' + meta['ours_run'] + ')' if meta.get('ours_run') else ''}.", ""]
    lines += [
             "| script | ours | ours error (category: line) | s | Genesis | Genesis error | s | GS_RESULT ours | GS_RESULT Genesis | difference |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name in SCRIPTS:
        o, g = ours.get(name), theirs.get(name)

        def cell(r):
            if r is None:
                return "not run", "", ""
            return ("yes" if r["ok"] else ("timeout" if r["timed_out"] else "no"),
                    "" if r["ok"] else f"`{category(r['error'])}`: {r['error'][:200]}".replace("|", "\\|"), f"{r['wall_s']:.0f}")
        oc, gc = cell(o), cell(g)
        ores = "; ".join(f"{k}={fmt_vals(v)}" for k, v in (o or {}).get("results", {}).items()) or "-"
        gres = "; ".join(f"{k}={fmt_vals(v)}" for k, v in (g or {}).get("results", {}).items()) or "-"
        diff = compare(o["results"], g["results"]) if o and g else "-"
        lines.append(f"| {name} | {oc[0]} | {oc[1]} | {oc[2]} | {gc[0]} | {gc[1]} | {gc[2]} | {ores} | {gres} | {diff} |")
    n = len(SCRIPTS)
    for side, d in (("ours", ours), ("genesis", theirs)):
        if d:
            lines.append(f"\n{side}: {sum(r['ok'] for r in d.values())} of {len(d)} run (of {n} listed); "
                         f"total wall {sum(r['wall_s'] for r in d.values()):.0f} s")
    if ours:
        groups = {}
        for r in ours.values():
            if not r["ok"]:
                groups.setdefault(category(r["error"]), []).append(r["script"])
        lines.append("\nBlocking causes on ours (grouped by the missing name/feature of the first error):\n")
        for cat, names in sorted(groups.items(), key=lambda kv: -len(kv[1])):
            lines.append(f"- `{cat}` ({len(names)}): {', '.join(names)}")
    path.write_text("\n".join(lines) + "\n")


def split_md_row(line: str) -> list[str]:
    """The cells of a markdown table row (a `\\|` inside a cell is not a separator)."""
    cells = re.split(r"(?<!\\)\|", line.strip())
    return [c.strip().replace("\\|", "|") for c in cells[1:-1]]


def recorded_from_markdown(md: str) -> dict:
    """The Genesis side of the first results table of an older `genesis_scripts.md` (columns: script, ours, ours
    error, s, Genesis, Genesis error, s, GS_RESULT ours, GS_RESULT Genesis, difference): {script: result entry}.
    The values are as the table printed them (4 significant digits)."""
    out = {}
    for line in md.splitlines():
        if not line.startswith("| "):
            continue
        c = split_md_row(line)
        if len(c) != 10 or c[0] not in SCRIPTS:
            continue
        if c[0] in out:  # only the first table (later tables of the file are other runs)
            break
        ok = c[4] == "yes"
        results = {}
        if c[8] not in ("", "-"):
            for part in c[8].split("; "):
                k, v = part.split("=", 1)
                results[k] = [float(x) for x in v.split(", ")]
        out[c[0]] = dict(script=c[0], side="genesis", ok=ok, rc=0 if ok else None, timed_out=c[4] == "timeout",
                         wall_s=float(c[6]) if c[6] else 0.0, error=c[5], category=category(c[5]) if c[5] else "",
                         results=results, probe_errors={}, log="", recorded=True)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n", 2)[2],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scripts", default="", help="comma-separated subset of: " + ", ".join(SCRIPTS))
    ap.add_argument("--side", choices=("ours", "genesis", "both"), default="both")
    ap.add_argument("--genesis-python", default=None,
                    help="python of real Genesis's own venv (e.g. /work/genesis_venv/bin/python); "
                         "absent or missing: the Genesis side is skipped")
    ap.add_argument("--genesis-repo", default=DEFAULT_MIRROR, help="Genesis git dir (mirror) or work tree; default %(default)s")
    ap.add_argument("--rev", default="auto",
                    help="git revision to take examples/ from: 'auto' = the tag v<installed genesis-world version>, "
                         "else the nearest older tag; 'worktree' reads files from --genesis-repo/examples")
    ap.add_argument("--assets", default=None, help="Genesis's genesis/assets folder for our side's GS_ASSETS_DIR "
                                                   "(default: found from --genesis-python)")
    ap.add_argument("--ours-python", default=str(REPO_ROOT / ".venv" / "bin" / "python"))
    ap.add_argument("--ours-pythonpath", default="",
                    help="extra PYTHONPATH for our side, for the examples' own third-party needs the project's venv "
                         "lacks (e.g. a folder holding tensordict for go2_env)")
    ap.add_argument("--timeout-ours", type=float, default=300)
    ap.add_argument("--timeout-genesis", type=float, default=600)
    ap.add_argument("--genesis-recorded", default=None, metavar="FILE",
                    help=f"JSON of a recorded Genesis-side run (e.g. {RECORDED_DEFAULT.relative_to(REPO_ROOT)}): fills "
                         "the Genesis column for the scripts whose Genesis side is not run now; the table says so")
    ap.add_argument("--save-genesis", default=None, metavar="FILE",
                    help="after the run, write the Genesis side's results (with version, date, machine) to FILE, "
                         "for later --genesis-recorded use")
    ap.add_argument("--extract-recorded", default=None, metavar="MD",
                    help="one-off: parse the Genesis column of the first table of an older results markdown MD into "
                         "--genesis-recorded FILE (required), with --recorded-meta KEY=VALUE pairs, and exit")
    ap.add_argument("--recorded-meta", action="append", default=[], metavar="KEY=VALUE",
                    help="metadata for --extract-recorded: genesis_version, date, machine, note")
    ap.add_argument("--table-only", action="store_true",
                    help="rewrite <out>/table.md from <out>/results.json (and --genesis-recorded) without running")
    ap.add_argument("--out", default=DEFAULT_OUT, help="folder for results.json, table.md, logs (default %(default)s)")
    args = ap.parse_args()

    if args.extract_recorded:
        if not args.genesis_recorded:
            ap.error("--extract-recorded needs --genesis-recorded FILE to write")
        rmeta = dict(kv.split("=", 1) for kv in args.recorded_meta)
        rmeta.setdefault("note", f"parsed from {args.extract_recorded}; values at the 4 significant digits printed there")
        rec = recorded_from_markdown(Path(args.extract_recorded).read_text())
        if not rec:
            ap.error(f"no results table found in {args.extract_recorded}")
        Path(args.genesis_recorded).write_text(json.dumps(dict(meta=rmeta, genesis=rec), indent=1) + "\n")
        print(f"{len(rec)} recorded Genesis results -> {args.genesis_recorded}")
        return

    names = [s for s in args.scripts.split(",") if s] or list(SCRIPTS)
    bad = [s for s in names if s not in SCRIPTS]
    if bad:
        ap.error(f"unknown scripts {bad}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res_path = out / "results.json"
    data = json.loads(res_path.read_text()) if res_path.exists() else {}
    meta = data.setdefault("meta", {})
    meta["machine"] = f"{platform.node()} {platform.machine()}, {os.cpu_count()} cores, {platform.platform()}"

    gpy = args.genesis_python if args.genesis_python and Path(args.genesis_python).exists() else None
    gver, gassets = None, args.assets
    if gpy:
        q = subprocess.run([gpy, "-c", "import importlib.metadata as m, importlib.util as u, os; "
                                      "print(m.version('genesis-world')); "
                                      "print(os.path.join(u.find_spec('genesis').submodule_search_locations[0], 'assets'))"],
                           capture_output=True, text=True, check=True).stdout.split()
        gver, gassets = q[0], gassets or q[1]
        meta["genesis_version"] = f"genesis-world {gver}"
    rev = None
    if args.rev == "worktree":
        meta["source"] = f"{args.genesis_repo}/examples (work tree)"
    elif args.rev != "auto":
        rev = args.rev
    else:
        tags = subprocess.run(["git", "-C", args.genesis_repo, "tag"], capture_output=True, text=True, check=True).stdout.split()
        key = lambda t: tuple(int(x) for x in re.findall(r"\d+", t))
        vtags = sorted((t for t in tags if re.fullmatch(r"v\d+(\.\d+)*", t)), key=key)
        want = key("v" + gver) if gver else None
        older = [t for t in vtags if want is None or key(t) <= want]
        rev = older[-1]
        exact = want is not None and key(rev) == want
        meta["source"] = f"tag {rev} of {args.genesis_repo}" + ("" if exact else
                         f" (no tag matches {gver}; nearest older)" if gver else " (newest tag)")
    if rev:
        meta.setdefault("source", f"{rev} of {args.genesis_repo}")
    print(f"examples from: {meta.get('source')}; Genesis: {meta.get('genesis_version', 'not run')}", flush=True)

    sides = ["ours", "genesis"] if args.side == "both" else [args.side]
    if "genesis" in sides and not gpy:
        print("Genesis side skipped: no --genesis-python", flush=True)
        sides.remove("genesis")
    if args.genesis_recorded:
        rpath = Path(args.genesis_recorded).resolve()
        if not rpath.exists():
            ap.error(f"--genesis-recorded {rpath}: no such file")
        rec = json.loads(rpath.read_text())
        # every recorded script (ours' results accumulate over runs), except those Genesis runs now
        for name, r in rec.get("genesis", {}).items():
            if name in SCRIPTS and not ("genesis" in sides and name in names):
                data.setdefault("genesis", {})[name] = r
        shown = rpath.relative_to(REPO_ROOT) if rpath.is_relative_to(REPO_ROOT) else rpath
        meta["genesis_recorded"] = dict(rec.get("meta", {}), file=str(shown))
    if args.table_only:
        write_table(data, out / "table.md", meta)
        print(f"table: {out / 'table.md'} (from {res_path}; nothing run)")
        return
    if "ours" in sides:
        meta["ours_run"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    res_path.write_text(json.dumps(data, indent=1))
    write_table(data, out / "table.md", meta)
    for side in sides:
        d = out / side
        d.mkdir(exist_ok=True)
        for name in names:
            script = d / f"{name}.py"
            script.write_text(transform(name, side, args.genesis_repo, rev))
            if side == "ours":
                env = {"MPLBACKEND": "Agg"}
                if gassets:
                    env["GS_ASSETS_DIR"] = gassets
                if args.ours_pythonpath:
                    env["PYTHONPATH"] = args.ours_pythonpath
                r = run_one(name, side, args.ours_python, script, args.timeout_ours, env, unset=("GS_NUM_THREADS",))
            else:
                r = run_one(name, side, gpy, script, args.timeout_genesis, {"MPLBACKEND": "Agg"})
            data.setdefault(side, {})[name] = r
            res_path.write_text(json.dumps(data, indent=1))
            write_table(data, out / "table.md", meta)
            status = "ok" if r["ok"] else f"FAIL [{r['category']}] {r['error'][:160]}"
            print(f"{side:8s} {name:28s} {r['wall_s']:7.1f} s  {status}  {r['results']}", flush=True)
    if args.save_genesis and "genesis" in sides:
        gmeta = dict(genesis_version=meta.get("genesis_version"), machine=meta.get("machine"),
                     source=meta.get("source"), date=time.strftime("%Y-%m-%d", time.gmtime()))
        Path(args.save_genesis).write_text(json.dumps(dict(meta=gmeta, genesis=data["genesis"]), indent=1) + "\n")
        print(f"Genesis side saved: {args.save_genesis}")
    print(f"table: {out / 'table.md'}")


if __name__ == "__main__":
    main()
