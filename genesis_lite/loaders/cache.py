"""On-disk cache of loaded URDF and mesh models, so that a warm start skips yourdfpy and trimesh altogether.

Parsing a URDF takes milliseconds; importing yourdfpy, which imports trimesh and scipy, takes ~0.8 s
of every fresh process that loads a robot, and reading and processing its collision meshes more. The
loaded `EntityModel` is plain numpy data, so it is pickled under ~/.cache/genesis_lite/models (or
$GS_CACHE_DIR/models) keyed by everything the loader reads:
- the file's bytes and absolute path, the entity's name, the morph's fields, the material's density and
  ROS_PACKAGE_PATH;
- the source of the loader modules, of the model dataclasses and of the collision geoms module (a mesh's
  hull is stored with its SDF planes), and the versions of yourdfpy, trimesh, scipy and numpy (a change in
  any of them makes new keys);
- every mesh file the loader opened or found (path, mtime, size) and every candidate path it found
  missing, checked again on each hit, so an edited, added or removed mesh file is re-read.
Warnings the loader emitted are stored and emitted again on a hit. A failed load is never cached.
GS_MODEL_CACHE=0 turns the cache off; an unreadable or corrupt entry is ignored and rewritten; past
MAX_ENTRIES entries the least recently used half is removed.
"""
from __future__ import annotations

import hashlib
import os
import pickle
import stat
import tempfile
import warnings
from typing import Callable, List, Optional

FORMAT = 1
# entries kept; past it the least recently used half goes (tests load hundreds of throw-away files)
MAX_ENTRIES = 400
_SOURCES = ("cache.py", "urdf.py", "primitives.py", "__init__.py")
_fingerprint: Optional[str] = None
_recorder: Optional[List[tuple]] = None


def enabled() -> bool:
    return os.environ.get("GS_MODEL_CACHE", "1") != "0"


def cache_root() -> str:
    """genesis_lite's on-disk caches: $GS_CACHE_DIR, else ~/.cache/genesis_lite ($XDG_CACHE_HOME honoured)."""
    from solvers.taichi_compat import cache_root as root

    return root()


def cache_dir() -> str:
    return os.path.join(cache_root(), "models")


def _file_state(path: str):
    """(mtime, size) of a regular file, None for anything else (missing, a folder)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size) if stat.S_ISREG(st.st_mode) else None


def note_file(path: str) -> bool:
    """os.path.isfile for the loader, recording the answer (with mtime and size) as a dependency of the
    model being loaded."""
    state = _file_state(path)
    if _recorder is not None:
        _recorder.append((os.path.abspath(path), state))
    return state is not None


def _code_fingerprint() -> str:
    global _fingerprint
    if _fingerprint is None:
        from importlib import metadata

        import numpy as np

        from solvers.rigid import model
        from solvers.rigid.collision import geoms  # hull_planes: a mesh's SDF planes, stored with its hull

        h = hashlib.sha256(f"format {FORMAT} numpy {np.__version__}".encode())
        here = os.path.dirname(os.path.abspath(__file__))
        for p in [os.path.join(here, n) for n in _SOURCES] + [os.path.abspath(m.__file__) for m in (model, geoms)]:
            with open(p, "rb") as f:
                h.update(f.read())
        for dist in ("yourdfpy", "trimesh", "scipy", "coacd"):
            try:
                h.update(f"{dist} {metadata.version(dist)}".encode())
            except metadata.PackageNotFoundError:
                h.update(f"{dist} none".encode())
        _fingerprint = h.hexdigest()
    return _fingerprint


def _morph_key(morph) -> str:
    import dataclasses

    import numpy as np

    items = []
    for f in dataclasses.fields(morph):
        v = getattr(morph, f.name)
        if isinstance(v, np.ndarray):
            v = (str(v.dtype), v.shape, v.tobytes().hex())
        items.append((f.name, repr(v)))
    return repr((type(morph).__name__, items))


def cached(path: str, morph, material, name: str, load: Callable):
    """load() (the EntityModel of the URDF or mesh file at `path`), through the on-disk cache when enabled."""
    global _recorder
    if not enabled() or _recorder is not None:
        return load()
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError:
        return load()  # the loader raises the error that names the file
    h = hashlib.sha256(_code_fingerprint().encode())
    densities = repr((material.density(robot=False), material.density(robot=True)))
    for part in (os.path.abspath(path), name, _morph_key(morph), densities, os.environ.get("ROS_PACKAGE_PATH", "")):
        h.update(part.encode())
        h.update(b"\0")
    h.update(data)
    entry = os.path.join(cache_dir(), h.hexdigest() + ".pkl")
    hit = _read(entry)
    if hit is not None:
        deps, model, caught = hit
        if all(_file_state(p) == state for p, state in deps):
            try:
                os.utime(entry)  # recently used: kept by _prune
            except OSError:
                pass
            for message, category in caught:
                warnings.warn(message, category, stacklevel=4)
            return model
    _recorder = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            model = load()
        deps = list(dict.fromkeys(_recorder))
    finally:
        _recorder = None
    for w in caught:  # pass them on to whatever filters the caller has
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)
    _write(entry, (deps, model, [(str(w.message), w.category) for w in caught]))
    return model


def coacd_parts(V, F, options: dict, run: Callable):
    """run() (CoACD's parts of the mesh (V, F) with these coacd.run_coacd options: a list of (vertices, faces)),
    through an on-disk cache keyed by the mesh's numbers, the options and CoACD's version
    (cache_root()/coacd): CoACD takes seconds to minutes a mesh, and a mesh morph placed elsewhere, or an MJCF
    file (which has no model cache), would run it again. Off with the model cache (GS_MODEL_CACHE=0)."""
    from importlib import metadata

    import numpy as np

    if not enabled():
        return run()
    try:
        version = metadata.version("coacd")
    except metadata.PackageNotFoundError:
        version = "none"
    h = hashlib.sha256(f"{FORMAT} coacd {version} {sorted(options.items())!r}".encode())
    for a in (np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64)):
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    entry = os.path.join(cache_root(), "coacd", h.hexdigest() + ".pkl")
    hit = _read(entry)
    if hit is not None:
        try:
            os.utime(entry)
        except OSError:
            pass
        return hit
    parts = [(np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)) for v, f in run()]
    _write(entry, parts)
    return parts


def _read(entry: str):
    try:
        with open(entry, "rb") as f:
            return pickle.load(f)
    except FileNotFoundError:
        return None
    except Exception:  # a corrupt or incompatible entry: load from the file and write it anew
        return None


def _write(entry: str, value) -> None:
    try:
        os.makedirs(os.path.dirname(entry), exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=os.path.dirname(entry), suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            pickle.dump(value, f, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(tmp, entry)  # atomic: a concurrent reader sees the old entry or the new one
    except Exception:
        try:
            os.unlink(tmp)
        except Exception:
            pass
        return
    _prune(os.path.dirname(entry))


def _prune(folder: str) -> None:
    try:
        names = [n for n in os.listdir(folder) if n.endswith(".pkl")]
        if len(names) <= MAX_ENTRIES:
            return
        paths = sorted((os.path.join(folder, n) for n in names), key=lambda p: os.stat(p).st_mtime_ns)
        for p in paths[: len(paths) - MAX_ENTRIES // 2]:
            os.unlink(p)
    except OSError:  # another process pruned first
        pass
