"""Issue #10 item 4, the Python side of build time: the lighter Taichi front-end helpers
(solvers/taichi_compat/frontend.py) must return exactly what Taichi's own return, and the on-disk model
cache (genesis_lite/loaders/cache.py) must give the model a fresh load gives, and notice every change
of what the loader read."""
import ast
import os
import pickle
import sys
import warnings

import numpy as np
import pytest
import taichi as ti
import trimesh
from scipy.spatial import ConvexHull
from taichi.lang import kernel_impl as K

import genesis_lite as gs
from genesis_lite import materials, morphs
from genesis_lite.loaders import cache as model_cache
from genesis_lite.loaders import load_morph
from genesis_lite.loaders import urdf as urdf_loader

from conftest import ASSETS_DIR, robot_urdf

RIGID = materials.Rigid(rho=700.0)


# --------------------------------------------------------------------------------------------
# Taichi front end
# --------------------------------------------------------------------------------------------
def test_frontend_helpers_are_installed():
    assert getattr(K._inside_class, "_gs_fast", False) and getattr(K._get_tree_and_ctx, "_gs_fast", False)


def test_inside_class_answers_as_taichi_does(monkeypatch):
    """Every decoration of the cases Taichi distinguishes (module function, class with kernels, a
    data_oriented class, nested function, one-line def) gets the answer Taichi's own function gives."""
    answers = []
    fast, original = K._inside_class, K._taichi_inside_class

    def both(level_of_class_stackframe):
        # one frame deeper than the real call: both helpers look one level further up
        a, b = fast(level_of_class_stackframe + 1), original(level_of_class_stackframe + 1)
        answers.append((a, b))
        return b

    monkeypatch.setattr(K, "_inside_class", both)

    @ti.func
    def f(x):
        return x + 1

    class Plain:
        @ti.kernel
        def k(self) -> ti.i32:
            return 1

        @ti.func
        def g(self, x):
            return x

    @ti.data_oriented
    class Oriented:
        def __init__(self):
            self.x = ti.field(ti.f32, shape=())

        @ti.kernel
        def k(self) -> ti.f32:
            return self.x[None] + 2.0

    def outer():
        @ti.func
        def inner(x):
            return 2 * x

        return inner

    outer()
    assert len(answers) >= 5
    assert all(a == b for a, b in answers), answers
    assert {b for _, b in answers} == {True, False}  # both outcomes were exercised
    assert Oriented().k() == pytest.approx(2.0)


@ti.func
def _poly(x, c: ti.template()):
    return c * x * x + 1


@ti.kernel
def _kernel_templated(a: ti.template(), s: ti.f32) -> ti.f32:
    acc = 0.0
    for i in range(a.shape[0]):
        acc += _poly(a[i], 3) * s
    return acc


def test_light_getframeinfo_answers_as_inspect_does(tmp_path, monkeypatch):
    """The getframeinfo Taichi's import runs under (frontend.import_taichi) gives inspect's answer for
    every frame a decoration looks at: a function's, a class body's, a module's while it is imported,
    and the import machinery's above it (a pseudo-file without source)."""
    import importlib
    import inspect

    from solvers.taichi_compat import frontend

    (tmp_path / "gl_frames_probe.py").write_text(
        "import sys\n"
        "FRAMES = [sys._getframe(k) for k in range(4)]\n"
        "class C:\n"
        "    FRAME = sys._getframe(0)\n"
        "def f():\n"
        "    return sys._getframe(0)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    probe = importlib.import_module("gl_frames_probe")
    frames = probe.FRAMES + [probe.C.FRAME, probe.f()]  # (finished frames: a running one moves on)
    files = {f.f_code.co_filename for f in frames}
    assert any(f.startswith("<frozen") for f in files) and str(tmp_path / "gl_frames_probe.py") in files
    for frame in frames:
        assert frontend.light_getframeinfo(frame) == inspect.getframeinfo(frame), frame.f_code.co_filename
        assert frontend.light_getframeinfo(frame).positions == inspect.getframeinfo(frame).positions
    assert inspect.getframeinfo is frontend._INSPECT_GETFRAMEINFO  # put back after Taichi's import


def test_tree_and_context_equal_taichi_s():
    """The cached source gives the same tree, source lines, file and line numbers as Taichi's helper,
    for a kernel with a template argument and for a function inside it."""
    gs.init(backend=gs.cpu, precision="64")
    a = ti.field(ti.f64, shape=4)
    kernel = _kernel_templated._primal
    func = _poly.func
    for obj, kw in ((kernel, dict(is_kernel=True, args=[a, 2.0])), (func, dict(is_kernel=False, args=[1.0, 3]))):
        for _ in range(2):  # the second call comes from the cache
            t1, c1 = K._get_tree_and_ctx(obj, **kw)
            t2, c2 = K._taichi_get_tree_and_ctx(obj, **kw)
            assert ast.dump(t1, include_attributes=True) == ast.dump(t2, include_attributes=True)
            assert c1.src == c2.src and c1.file == c2.file and c1.lineno_offset == c2.lineno_offset
            assert c1.indent == c2.indent and c1.is_kernel == c2.is_kernel
            assert c1.global_vars.keys() == c2.global_vars.keys()
            assert all(c1.global_vars[k] is c2.global_vars[k] for k in c1.global_vars)
    a.from_numpy(np.array([1.0, -2.0, 0.5, 3.0]))
    expected = sum(3 * x * x + 1 for x in (1.0, -2.0, 0.5, 3.0)) * 0.5
    assert _kernel_templated(a, 0.5) == pytest.approx(expected)


@ti.data_oriented
class _LaunchProbe:
    """A kernel with every argument kind the fast launch handles: the owner and a static int (templates),
    a float, an int, and an external array."""

    def __init__(self, n):
        self.out = ti.field(ti.f64, shape=n)
        self.x = ti.field(ti.f64, shape=n, needs_grad=True)
        self.loss = ti.field(ti.f64, shape=(), needs_grad=True)

    @ti.kernel
    def write(self, k: ti.template(), a: ti.f64, j: ti.i32, arr: ti.types.ndarray()):
        for i in self.out:
            self.out[i] = k * a * arr[i] + j

    @ti.kernel
    def square_sum(self, c: ti.f64):
        for i in self.x:
            self.loss[None] += c * self.x[i] ** 2

    @ti.kernel
    def scaled_square_sum(self, a: ti.i32):
        for i in self.x:
            self.loss[None] += a * self.x[i] ** 2

    @ti.kernel
    def count(self, a: ti.i32, b: ti.i32) -> ti.i32:
        """The owner as the only template (the fused step's shape): out += a * b, returns out[0]."""
        for i in self.out:
            self.out[i] += a * b
        return ti.cast(self.out[0], ti.i32)


def test_fast_launch_gives_taichi_s_results():
    """Repeated launches (the fast path) give what the formula gives, for every template argument, scalar
    and array kind, after a new field is created, with the same object id reused, and inside a Tape
    (whose gradient must see every launch); a wrong argument type still raises Taichi's error."""
    import torch

    gs.init(backend=gs.cpu, precision="64")
    assert getattr(K.Kernel.__call__, "_gs_fast", False)
    rng = np.random.default_rng(3)
    p = _LaunchProbe(5)
    for rep in range(3):
        for k in (1, 2, 1):  # a template value seen before comes back
            a, j = float(rng.normal()), int(rng.integers(-5, 5))
            arr = rng.normal(size=5)
            for given in (arr, torch.from_numpy(arr.copy())):
                p.write(k, a, j, given)
                np.testing.assert_allclose(p.out.to_numpy(), k * a * arr + j, rtol=1e-15, atol=1e-15)
        extra = ti.field(ti.f64, shape=3)  # a field created after the launches: Taichi must place it
        extra.fill(2.0 + rep)
        assert extra.to_numpy().tolist() == [2.0 + rep] * 3
    # a new owner at a freed one's address must get its own kernel: every object given one id here,
    # two live owners alternate
    del p
    from solvers.taichi_compat import frontend as F

    q, r = _LaunchProbe(5), _LaunchProbe(5)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(F, "id", lambda obj: 0, raising=False)
        for step in range(3):
            q.write(3, 1.0, step, np.ones(5))
            r.write(3, 2.0, step, np.ones(5))
            assert q.out.to_numpy().tolist() == [3.0 + step] * 5 and r.out.to_numpy().tolist() == [6.0 + step] * 5
    # a field declared but not placed is refused at the next launch, as Taichi does, until it is placed
    q.write(3, 1.0, 0, np.ones(5))  # the launch the next one repeats
    lonely = ti.field(ti.f64)
    with pytest.raises(RuntimeError, match="not placed"):
        q.write(3, 1.0, 0, np.ones(5))
    ti.root.dense(ti.i, 2).place(lonely)
    q.write(3, 2.0, 1, np.ones(5))
    assert q.out.to_numpy().tolist() == [7.0] * 5
    # a Tape records the launches it sees: d/dx sum(c x^2) = 2 c x, summed over two launches
    x = rng.normal(size=5)
    q.x.from_numpy(x)
    q.square_sum(1.0)  # a launch outside the tape first (the fast path's entry exists)
    q.loss[None] = 0.0
    with ti.ad.Tape(loss=q.loss):
        q.square_sum(1.5)
        q.square_sum(0.5)
    np.testing.assert_allclose(q.loss[None], 2.0 * (x ** 2).sum(), rtol=1e-14)
    np.testing.assert_allclose(q.x.grad.to_numpy(), 2 * 2.0 * x, rtol=1e-14)
    with pytest.raises(Exception) as fast_err:
        q.write(3, "one", 0, np.ones(5))
    with pytest.raises(Exception) as taichi_err:
        K.Kernel._taichi_call(q.write._primal, q, 3, "one", 0, np.ones(5))
    assert type(fast_err.value) is type(taichi_err.value) and "cannot be converted" in str(fast_err.value)


def test_fast_launch_of_an_owner_s_kernel_follows_the_owner():
    """A kernel whose only template is its owner (the fused step's shape) reuses its last launch's
    entry only for that same owner: two owners alternating, an owner freed and another made in its
    place (the same id), and fields created between launches each get their own results."""
    gs.init(backend=gs.cpu, precision="64")
    from solvers.taichi_compat import frontend as F

    q, r = _LaunchProbe(3), _LaunchProbe(3)
    for step in range(1, 5):  # two owners alternating: each launch's last entry is the other owner's
        assert q.count(step, 1) == sum(range(1, step + 1))
        assert r.count(step, 10) == 10 * sum(range(1, step + 1))
    for step in range(3):  # one owner again and again (the last entry reused), then the other
        assert q.count(1, 1) == 11 + step
    assert r.count(1, 1) == 101
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(F, "id", lambda obj: 0, raising=False)  # every owner gets one id: only the refs tell them apart
        for _ in range(2):
            q.count(0, 0)
        del q
        q = _LaunchProbe(3)  # fields created after the launches, an owner in the freed one's place
        assert q.count(2, 3) == 6 and q.count(1, 1) == 7
        assert r.count(1, 1) == 102
        assert q.out.to_numpy().tolist() == [7.0] * 3 and r.out.to_numpy().tolist() == [102.0] * 3


def test_hot_launcher_gives_the_kernel_s_results_and_steps_aside():
    """hot_launcher (the fused step's launch) gives the kernel's own results launch after launch, each owner
    its own, after a field is created (which Taichi must place first), for an argument that is not an int
    (the kernel's path, and Taichi's error for a wrong type), and inside a Tape, whose gradient must see every
    launch; without the fast launch it is the bound kernel itself."""
    gs.init(backend=gs.cpu, precision="64")
    from solvers.taichi_compat import frontend as F

    q, r = _LaunchProbe(3), _LaunchProbe(3)
    hq, hr = F.hot_launcher(q.count), F.hot_launcher(r.count)
    total_q = total_r = 0
    for step in range(1, 6):
        total_q += 2 * step
        total_r += 3 * step
        assert hq(step, 2) == total_q and hr(step, 3) == total_r
    assert hq._gs_entry[0] is not None and hr._gs_entry[0] is not None  # the direct launch was taken
    late = ti.field(ti.f64, shape=2)  # created after the launches
    late.fill(1.5)
    assert hq(1, 1) == total_q + 1 and late.to_numpy().tolist() == [1.5, 1.5]
    lonely = ti.field(ti.f64)  # declared, not placed: refused at the next launch, as Taichi does
    with pytest.raises(RuntimeError, match="not placed"):
        hq(1, 1)
    ti.root.dense(ti.i, 2).place(lonely)
    assert hq(np.int32(2), 1) == total_q + 3  # not a Python int: through the kernel
    with pytest.raises(Exception):
        hq(1)  # an argument missing: the kernel's own error
    with pytest.raises(Exception) as err:
        hq("one", 1)
    assert "cannot be converted" in str(err.value)
    assert q.out.to_numpy().tolist() == [total_q + 3] * 3 and r.out.to_numpy().tolist() == [total_r] * 3
    hs = F.hot_launcher(q.scaled_square_sum)
    x = np.random.default_rng(4).normal(size=3)
    q.x.from_numpy(x)
    for _ in range(3):
        hs(1)  # outside a Tape: the direct launch's entry exists
    q.loss[None] = 0.0
    with ti.ad.Tape(loss=q.loss):
        hs(2)
        hs(3)
    np.testing.assert_allclose(q.loss[None], 5.0 * (x ** 2).sum(), rtol=1e-14)
    np.testing.assert_allclose(q.x.grad.to_numpy(), 2 * 5.0 * x, rtol=1e-14)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(F, "_HOT", [None])
        bound = q.count
        assert F.hot_launcher(bound) is bound


def test_source_store_keeps_taichi_s_source_across_processes(tmp_path, monkeypatch):
    """The on-disk store gives back what Taichi's own helper computes, from a new store (a new process
    reads it from disk), and forgets a function whose file changed."""
    import importlib.util
    import textwrap

    from solvers.taichi_compat import frontend as F

    monkeypatch.setenv("GS_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("GS_MODEL_CACHE", raising=False)
    mod_file = tmp_path / "gl_store_probe.py"
    mod_file.write_text(textwrap.dedent('''
        import taichi as ti


        @ti.func
        def probe(x):
            y = x * 2  # a comment
            return y + 1
    '''))
    spec = importlib.util.spec_from_file_location("gl_store_probe", mod_file)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    fn = mod.probe.func.func
    tree, ctx = K._taichi_get_tree_and_ctx(mod.probe.func, is_kernel=False, args=[1.0])
    expected = (ctx.file, ctx.src, ctx.lineno_offset + 1, ast.dump(tree))

    def as_expected(value):
        file, src, start, text = value
        t = ast.parse(text)
        t.body[0].decorator_list = []
        return (file, src, start, ast.dump(t)) == expected

    assert F._SourceStore().get(fn) is None
    K._get_tree_and_ctx(mod.probe.func, is_kernel=False, args=[1.0])  # computes it, into the store
    F._STORE.flush()  # what the process does at exit
    reader = F._SourceStore()  # a new process' store reads it from disk
    got = reader.get(fn)
    assert got is not None and as_expected(got)
    monkeypatch.setenv("GS_MODEL_CACHE", "0")
    assert reader.get(fn) is None  # turned off
    monkeypatch.delenv("GS_MODEL_CACHE")
    # an edit of the file (another size) voids its entries
    mod_file.write_text(mod_file.read_text() + "\n# edited\n")
    assert F._SourceStore().get(fn) is None and reader.get(fn) is None


def _both_tracebacks(stacklevel):
    from taichi.lang import util

    return util._taichi_get_traceback(stacklevel), util.get_traceback(stacklevel)


def test_light_traceback_is_taichi_s_without_carets():
    from taichi.lang import impl, matrix, snode, util

    assert all(getattr(m.get_traceback, "_gs_fast", False) for m in (util, impl, matrix, snode))
    for level in (1, 2):
        original, light = _both_tracebacks(level)  # level >= 1 drops the helper, whose two calls differ
        kept = [ln for ln in original.splitlines() if ln.strip() and set(ln.strip()) - set("^~")]
        assert light.splitlines() == kept
        innermost = light.splitlines()[-2]  # the last frame kept: this test at level 1, its caller at 2
        assert ("in test_light_traceback_is_taichi_s_without_carets" in innermost) == (level == 1)
        assert "in _both_tracebacks" not in light
    # a field still records where it was declared
    gs.init(backend=gs.cpu, precision="64")
    x = ti.field(ti.f64, shape=3)
    tb = x.vars[0].declaration_tb
    assert "test_light_traceback_is_taichi_s_without_carets" in tb and "x = ti.field(ti.f64, shape=3)" in tb


def test_frontend_can_be_turned_off(monkeypatch):
    """GS_TAICHI_FAST_FRONTEND=0 keeps Taichi's helpers (checked in a fresh process: the switch acts at import)."""
    import subprocess

    code = ("import genesis_lite, taichi.lang.kernel_impl as K, taichi.lang.util as U; "
            "from taichi.lang.ast.ast_transformer_utils import ASTTransformerContext as C; "
            "print([getattr(f, '_gs_fast', False) for f in (K._get_tree_and_ctx, K._inside_class, "
            "U.get_traceback, C.get_pos_info)])")
    for switch, want in (("0", "[False, False, False, False]"), ("1", "[True, True, True, True]")):
        env = {**os.environ, "GS_TAICHI_FAST_FRONTEND": switch}
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300,
                             cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip().splitlines()[-1] == want, switch


def test_a_default_run_writes_the_kernel_cache(tmp_path):
    """A fresh process with an empty kernel cache leaves Taichi's cache metadata and kernels behind when
    it exits (Taichi writes them as its Program is destroyed at interpreter exit: anything that keeps
    that object alive, as a gc.freeze at gs.init once did, leaves every later run cold), and a second
    process finds them: it compiles nothing new (the cache's files are unchanged)."""
    import subprocess

    code = ("import genesis_lite as gs\n"
            "gs.init(backend=gs.cpu, precision='64', logging_level='warning')\n"
            "scene = gs.Scene()\n"
            "scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1), pos=(0, 0, 0.5)))\n"
            "scene.build()\n"
            "scene.step()\n")
    env = {**os.environ, "TI_OFFLINE_CACHE_FILE_PATH": str(tmp_path / "ti"), "GS_CACHE_DIR": str(tmp_path / "gs")}
    env.pop("GS_CHECK_AD_STACK", None)  # Taichi's own runtime: its cache folder is the one named above
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    listings = []
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600,
                             cwd=repo)
        assert out.returncode == 0, out.stderr
        files = sorted(p.name for p in (tmp_path / "ti").rglob("*.tic"))
        assert any((tmp_path / "ti").rglob("ticache.tcb")), "no kernel-cache metadata was written"
        assert files, "no compiled kernel was cached"
        listings.append(files)
    assert listings[0] == listings[1]


def test_objects_made_after_init_are_collected_and_flushed(tmp_path):
    """gs.init moves the objects alive before it to the collector's permanent generation (gc.freeze, so that
    later collections and the exit skip the libraries' ~10^6 objects); what a script makes after it is
    collected as before: a scene dropped in a reference cycle is freed by gc.collect(), and a file object
    left open in a cycle is flushed and closed when the process exits. With GS_GC_FREEZE=0 nothing is
    frozen; in either case the run ends with rc 0."""
    import subprocess

    code = ("import gc, sys, weakref\n"
            "import genesis_lite as gs\n"
            "gs.init(backend=gs.cpu, precision='64', logging_level='warning')\n"
            "frozen = gc.get_freeze_count()\n"
            "scene = gs.Scene()\n"
            "scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1), pos=(0, 0, 0.5)))\n"
            "scene.build()\n"
            "scene.step()\n"
            "scene.cycle = scene\n"
            "alive = weakref.ref(scene)\n"
            "del scene\n"
            "gc.collect()\n"
            "holder = [open(sys.argv[1], 'w')]\n"
            "holder.append(holder)\n"
            "holder[0].write('written after gs.init')\n"
            "print(frozen > 0, alive() is None)\n")
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    for switch, frozen in (("1", "True"), ("0", "False")):
        target = tmp_path / f"out{switch}.txt"
        env = {**os.environ, "GS_GC_FREEZE": switch}
        out = subprocess.run([sys.executable, "-c", code, str(target)], env=env, capture_output=True, text=True,
                             timeout=600, cwd=repo)
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip().splitlines()[-1] == f"{frozen} True", (switch, out.stdout)
        assert target.read_text() == "written after gs.init", switch


# --------------------------------------------------------------------------------------------
# Model cache
# --------------------------------------------------------------------------------------------
@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    d = tmp_path / "gs_cache"
    monkeypatch.setenv("GS_CACHE_DIR", str(d))
    monkeypatch.delenv("GS_MODEL_CACHE", raising=False)
    return d / "models"


def _entries(cache_dir):
    return sorted(os.listdir(cache_dir)) if cache_dir.is_dir() else []


def _same(a, b, path="model"):
    """Recursive equality of two models (dataclasses, lists, numpy arrays), naming the first difference."""
    if hasattr(a, "__dataclass_fields__"):
        assert type(a) is type(b), path
        for k in a.__dataclass_fields__:
            _same(getattr(a, k), getattr(b, k), f"{path}.{k}")
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            _same(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{path}[{i}]")
    elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=path)
    else:
        assert a == b or (a != a and b != b), f"{path}: {a!r} != {b!r}"


def _mesh_robot(tmp_path):
    """A 2-link URDF whose links collide through an STL box and an OBJ ball, next to its meshes; its
    visual mesh is missing and its joint mimics a joint that does not exist (a warning)."""
    (tmp_path / "meshes").mkdir(exist_ok=True)
    trimesh.creation.box(extents=(0.2, 0.3, 0.4)).export(tmp_path / "meshes" / "box.stl")
    trimesh.creation.icosphere(subdivisions=2, radius=0.1).export(tmp_path / "meshes" / "ball.obj")
    inertial = ('<inertial><mass value="1"/><inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/>'
                '</inertial>')
    p = tmp_path / "robot.urdf"
    p.write_text(f"""<robot name="r">
  <link name="base">{inertial}<collision><geometry><mesh filename="meshes/box.stl"/></geometry></collision></link>
  <link name="tip"><collision><origin xyz="0 0 0.3"/><geometry><mesh filename="meshes/ball.obj" scale="1 2 1"/>
    </geometry></collision><visual><geometry><mesh filename="meshes/missing.dae"/></geometry></visual></link>
  <joint name="j" type="revolute"><parent link="base"/><child link="tip"/><origin xyz="0 0 0.2" rpy="0.3 0 0"/>
    <axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="5" velocity="2"/><mimic joint="nobody"/></joint>
</robot>""")
    return p


def _load(path, **kw):
    return load_morph(morphs.URDF(file=str(path), fixed=True, **kw), RIGID, "robot")


def test_warm_load_equals_fresh_load_without_parsing(tmp_path, cache_dir, monkeypatch):
    p = _mesh_robot(tmp_path)
    with pytest.warns(UserWarning, match="mimics 'nobody'"):
        cold = _load(p)
    assert len(_entries(cache_dir)) == 1

    def no_parse(*a, **k):
        raise AssertionError("the URDF was parsed although the cache holds it")

    monkeypatch.setattr(urdf_loader, "_load_urdf", no_parse)
    with pytest.warns(UserWarning, match="mimics 'nobody'"):  # warnings come again from the cache
        warm = _load(p)
    _same(cold, warm)
    assert warm is not cold and warm.links[0].geoms[0].vertices is not cold.links[0].geoms[0].vertices
    monkeypatch.undo()
    monkeypatch.setenv("GS_MODEL_CACHE", "0")
    with pytest.warns(UserWarning, match="mimics 'nobody'"):
        fresh = _load(p)
    _same(cold, fresh)


def test_changes_of_what_the_loader_read_reload(tmp_path, cache_dir):
    p = _mesh_robot(tmp_path)
    warnings.simplefilter("ignore")
    first = _load(p)
    # a bigger mesh file: the geom's vertices follow it
    trimesh.creation.box(extents=(0.4, 0.3, 0.4)).export(tmp_path / "meshes" / "box.stl")
    second = _load(p)
    np.testing.assert_allclose(np.ptp(second.links[0].geoms[0].vertices, 0), [0.4, 0.3, 0.4], atol=1e-7)
    np.testing.assert_allclose(np.ptp(first.links[0].geoms[0].vertices, 0), [0.2, 0.3, 0.4], atol=1e-7)
    # a visual mesh that appears where the loader found none
    trimesh.creation.box().export(tmp_path / "meshes" / "missing.dae")
    third = _load(p)
    assert first.links[1].visuals[0].file is None
    assert third.links[1].visuals[0].file == str(tmp_path / "meshes" / "missing.dae")
    # the URDF itself and the morph's fields are part of the key
    p.write_text(p.read_text().replace('effort="5"', 'effort="7"'))
    assert _load(p).links[1].effort == 7.0
    assert _load(p, scale=2.0).links[1].joint_pos[2] == pytest.approx(0.4)
    assert _load(p).links[1].joint_pos[2] == pytest.approx(0.2)
    # the mesh edit and the visual found rewrote the first key's entry; effort and scale made new keys
    assert len(_entries(cache_dir)) == 3


def test_corrupt_entry_is_ignored_and_rewritten(tmp_path, cache_dir):
    p = _mesh_robot(tmp_path)
    warnings.simplefilter("ignore")
    cold = _load(p)
    (entry,) = _entries(cache_dir)
    (cache_dir / entry).write_bytes(b"not a pickle")
    again = _load(p)
    _same(cold, again)
    with open(cache_dir / entry, "rb") as f:
        pickle.load(f)  # rewritten


def test_cache_off_writes_nothing(tmp_path, cache_dir, monkeypatch):
    monkeypatch.setenv("GS_MODEL_CACHE", "0")
    warnings.simplefilter("ignore")
    _load(_mesh_robot(tmp_path))
    assert _entries(cache_dir) == []


def test_failed_load_is_not_cached(tmp_path, cache_dir):
    p = tmp_path / "bad.urdf"
    p.write_text('<robot name="r"><link name="a"/><joint name="j" type="revolute"><parent link="a"/></joint></robot>')
    for _ in range(2):
        with pytest.raises(ValueError, match="child"):
            _load(p)
    assert _entries(cache_dir) == []


def test_mesh_morph_is_cached(tmp_path, cache_dir, monkeypatch):
    trimesh.creation.icosphere(subdivisions=2, radius=0.2).export(tmp_path / "ball.stl")
    morph = morphs.Mesh(file=str(tmp_path / "ball.stl"), pos=(0.1, 0.2, 0.3))
    cold = load_morph(morph, RIGID, "ball")
    from genesis_lite.loaders import primitives

    monkeypatch.setattr(primitives, "_load_mesh", lambda *a, **k: pytest.fail("mesh re-read"))
    warm = load_morph(morph, RIGID, "ball")
    _same(cold, warm)
    # another entity name is another key (it names the link)
    monkeypatch.undo()
    assert load_morph(morph, RIGID, "ball2").links[0].name == "ball2"


def test_old_entries_are_pruned(tmp_path, cache_dir, monkeypatch):
    monkeypatch.setattr(model_cache, "MAX_ENTRIES", 4)
    warnings.simplefilter("ignore")
    p = _mesh_robot(tmp_path)
    for k in range(6):
        _load(p, pos=(0.0, 0.0, float(k)))
    assert 2 <= len(_entries(cache_dir)) <= 4


def test_collision_hull_is_the_convex_hull(tmp_path, cache_dir):
    """GeomDesc.hull (what the contact builder uses) against scipy's qhull of the geom's vertices."""
    warnings.simplefilter("ignore")
    m = _load(_mesh_robot(tmp_path))
    for g in (m.links[0].geoms[0], m.links[1].geoms[0]):
        h = g.hull
        ref = ConvexHull(g.vertices)
        assert h["is_volume"] and h["volume"] == pytest.approx(ref.volume, rel=1e-9)
        assert len(h["vertices"]) == len(ref.vertices)
        got = {tuple(np.round(v, 12)) for v in h["vertices"]}
        assert got == {tuple(np.round(v, 12)) for v in g.vertices[ref.vertices]}
    # the ball geom was scaled (1, 2, 1) in the file: its hull is the scaled one
    assert np.ptp(m.links[1].geoms[0].hull["vertices"], 0)[1] == pytest.approx(0.4, rel=1e-6)


def test_real_robot_from_cache_builds_and_steps_like_a_fresh_one(cache_dir, monkeypatch):
    """The Panda (meshes) over a plane, from a fresh load and from the cache: the same trajectory."""
    gs.init(backend=gs.cpu, precision="64")
    panda = str(robot_urdf("panda"))

    def run():
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
        scene.add_entity(gs.morphs.Plane())
        robot = scene.add_entity(gs.morphs.URDF(file=panda, fixed=True))
        scene.build()
        robot.control_dofs_force(np.linspace(-3, 3, robot.n_dofs))
        for _ in range(5):
            scene.step()
        return robot.get_dofs_position().numpy().copy()

    cold = run()
    assert len(_entries(cache_dir)) == 1
    monkeypatch.setattr(urdf_loader, "_load_urdf", lambda *a, **k: pytest.fail("parsed again"))
    warm = run()
    np.testing.assert_array_equal(cold, warm)
    assert np.abs(cold).max() > 1e-3  # it moved
