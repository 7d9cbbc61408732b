"""Where a morph's relative file name is looked for: Genesis's asset-path convention.

Genesis scripts name their robots relative to Genesis's asset folder
(`gs.morphs.MJCF(file="xml/franka_emika_panda/panda.xml")`, `urdf/panda_bullet/panda.urdf`). A path
that exists as given (absolute, or relative to the working directory) is used as it is; otherwise it
is looked up, in this order, in
1. the folders of the GS_ASSETS_DIR environment variable (os.pathsep-separated),
2. the folder given to `gs.init(assets_dir=...)`,
3. the `assets` folder of a Genesis installation importable from this interpreter (found without
   importing Genesis, which would start its own Taichi),
4. genesis_lite's own `assets` folder (the repository's).
The first folder holding the file wins. Nothing is copied or downloaded.
"""
from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from typing import List, Optional

_REPO_ASSETS = Path(__file__).resolve().parents[2] / "assets"
_init_dir: Optional[Path] = None


def set_init_dir(folder) -> None:
    """Record gs.init(assets_dir=folder); None forgets it. Raises if the folder does not exist."""
    global _init_dir
    if folder is None:
        _init_dir = None
        return
    p = Path(os.fspath(folder)).expanduser()
    if not p.is_dir():
        raise FileNotFoundError(f"gs.init(assets_dir={folder!r}): no such folder; give the folder that holds "
                                "your robots (e.g. Genesis's genesis/assets)")
    _init_dir = p.resolve()


def genesis_assets_dir() -> Optional[Path]:
    """The `assets` folder of an installed Genesis package (genesis-world), or None."""
    try:
        spec = importlib.util.find_spec("genesis")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    for loc in spec.submodule_search_locations:
        d = Path(loc) / "assets"
        if d.is_dir():
            return d
    return None


def search_dirs() -> List[Path]:
    """The folders a relative asset path is looked up in, in order (see the module docstring)."""
    dirs = [Path(p).expanduser() for p in os.environ.get("GS_ASSETS_DIR", "").split(os.pathsep) if p]
    if _init_dir is not None:
        dirs.append(_init_dir)
    g = genesis_assets_dir()
    if g is not None:
        dirs.append(g)
    dirs.append(_REPO_ASSETS)
    return dirs


def resolve(file: str, owner: str) -> str:
    """The path of `file`: as given when it exists, else the first match in `search_dirs()`. Raises
    FileNotFoundError naming every folder tried and how to add one."""
    if os.path.isfile(file):
        return file
    tried = []
    if not os.path.isabs(file):
        rel = file[2:] if file.startswith("./") else file
        for d in search_dirs():
            cand = d / rel
            tried.append(str(d))
            if cand.is_file():
                return str(cand)
    where = f"; also looked in the asset folders {tried}" if tried else ""
    raise FileNotFoundError(
        f"gs.morphs.{owner}(file={file!r}): no such file{where}. Give an existing path, or name the folder that "
        "holds it with the GS_ASSETS_DIR environment variable or gs.init(assets_dir=...)"
    )
