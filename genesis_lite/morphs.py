"""Morphs: what an entity looks like (its shape or source file) and where it starts."""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from typing import Optional, Sequence, Tuple

import numpy as np


def _vec(name, owner, v, n):
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ValueError(f"gs.morphs.{owner}({name}={v!r}): expected {n} finite numbers")
    return a


def _positive(name, owner, v):
    if not (isinstance(v, (int, float, np.floating)) and np.isfinite(v) and v > 0):
        raise ValueError(f"gs.morphs.{owner}({name}={v!r}): must be a positive number (m)")
    return float(v)


def euler_to_quat(euler_deg) -> np.ndarray:
    """(w, x, y, z) of Genesis's `euler` (degrees): roll about x, then pitch about the fixed y, then yaw
    about the fixed z (R = Rz Ry Rx, URDF's rpy)."""
    from .utils.geom import xyz_to_quat

    return xyz_to_quat(np.asarray(euler_deg, dtype=float), rpy=True, degrees=True)


@dataclass
class Morph:
    """pos (m) and quat (w, x, y, z) of the entity's base in the world, or instead of quat Genesis's
    euler (degrees, roll-pitch-yaw about the fixed x, y, z axes); fixed welds the base to the world,
    otherwise it is a free floating base."""

    pos: Sequence[float] = (0.0, 0.0, 0.0)
    quat: Optional[Sequence[float]] = None
    fixed: bool = False
    euler: Optional[Sequence[float]] = None

    def __post_init__(self):
        owner = type(self).__name__
        self.pos = _vec("pos", owner, self.pos, 3)
        if self.euler is not None:
            if self.quat is not None:
                raise ValueError(f"gs.morphs.{owner}(quat={self.quat!r}, euler={self.euler!r}): give one orientation, "
                                 "not both")
            self.euler = _vec("euler", owner, self.euler, 3)
            self.quat = euler_to_quat(self.euler)
        q = _vec("quat", owner, self.quat if self.quat is not None else (1.0, 0.0, 0.0, 0.0), 4)
        n = np.linalg.norm(q)
        if n < 1e-9:
            raise ValueError(f"gs.morphs.{owner}(quat={self.quat!r}): a zero quaternion is no orientation")
        self.quat = q / n
        self._check()

    def _check(self):
        pass


@dataclass
class FileMorph(Morph):
    """A body or robot from a file. `align` is Genesis's: a free-floating root link's frame moved to its
    centre of mass and turned to its principal axes of inertia, so that its pose (get_pos, get_quat,
    get_qpos, get_dofs_position) is that frame's. None (Genesis's default) aligns a basic rigid object (a
    free root with nothing below it on a hinge or slide joint: a mesh, a one-body URDF or MJCF); True any
    free root; False keeps the file's frame (as MuJoCo and Pinocchio report it). See loaders/align.py.

    Collision meshes, by Genesis's rules and options: a convex mesh collides as itself, a non-convex one as
    its convex hull or, split by CoACD (pip install coacd), as the hulls of its parts: an object's (a Mesh, or a
    URDF / MJCF body with no hinge or slide joint at or below it) when its hull's volume is more than
    decompose_object_error_threshold (0.15) over its own, a robot's only past decompose_robot_error_threshold
    (infinite by default: the hull, as Genesis and MuJoCo collide a robot's meshes), any with convexify=False
    (Genesis: the raw mesh; parts are how genesis_lite collides a non-convex surface). decompose_nonconvex
    (Genesis's older switch): True splits every non-convex mesh, False none, None leaves it to the thresholds.
    coacd_options: gs.options.CoacdOptions or a dict of its fields (Genesis's defaults); CoACD's parts are
    cached on disk by mesh and options. recompute_inertia=True: each moving link's mass, centre of mass and inertia from its
    collision shapes at the material's density, not the file's. decimate, decimate_face_num,
    decimate_aggressiveness and batch_fixed_verts are Genesis's and change nothing here (_check_file_options);
    file_meshes_are_zup=False reads a Mesh's or a URDF's mesh files as y-up (Genesis's turn, (x, y, z) -> (x, -z, y))."""

    file: str = ""
    scale: float = 1.0
    align: Optional[bool] = None
    # Genesis's FileMorph options (see _check_file_options): collision meshes are convex hulls or CoACD's
    # parts of the whole mesh, never decimated; recompute_inertia takes the moving links' mass properties from
    # their collision shapes at the material's density
    convexify: bool = True
    decompose_nonconvex: Optional[bool] = None
    decompose_object_error_threshold: float = 0.15
    decompose_robot_error_threshold: float = float("inf")
    coacd_options: Optional[object] = None
    decimate: bool = True
    decimate_face_num: int = 500
    decimate_aggressiveness: int = 2
    recompute_inertia: bool = False
    file_meshes_are_zup: bool = True
    batch_fixed_verts: bool = False

    def _check(self):
        owner = type(self).__name__
        if not self.file:
            raise ValueError(f"gs.morphs.{owner}: `file` is required")
        _check_file_options(self)
        _check_decomposition(self)
        if self.align not in (None, True, False):
            raise ValueError(f"gs.morphs.{owner}(align={self.align!r}): use None (Genesis's default: align a free "
                             "rigid object's frame to its centre of mass and principal axes), True or False")
        from .loaders.assets import resolve

        # Genesis's relative asset paths ("urdf/panda_bullet/panda.urdf") resolve against the asset folders
        self.file = resolve(os.fspath(self.file), owner)
        _positive("scale", owner, self.scale)


@dataclass
class URDF(FileMorph):
    """A robot from a URDF file. Links attached by fixed joints are merged into their parent (their mass,
    inertia and shapes added to it), except with merge_fixed_links=False (none merged) or for the links
    named in `links_to_keep` (Genesis's: e.g. a hand or a camera mount whose pose a script reads). A kept
    link moves with its parent; it has no dofs. `convexify` is Genesis's switch: by default a link's meshes
    collide as their convex hulls (Genesis does not decompose robot meshes by default either); with
    convexify=False (Genesis: collide the raw mesh) a non-convex collision mesh is split into convex parts
    by CoACD, as gs.morphs.Mesh does (parts are how genesis_lite collides a non-convex surface: the paddles
    of Genesis's water wheel, not the drum of their hull). Genesis's thresholds decide the rest, as its
    URDF morph does: a file with a hinge or slide joint is a robot, whose meshes are split only when their
    hull is off them by more than decompose_robot_error_threshold (infinite by default: never); a file
    without one is an object (a tank, a mug, a table), whose non-convex meshes are split when their hull
    is off them by more than decompose_object_error_threshold (0.15, as gs.morphs.Mesh). coacd_options:
    gs.options.CoacdOptions or a dict of its fields (Genesis's defaults)."""

    merge_fixed_links: bool = True
    requires_jac_and_IK: bool = False
    links_to_keep: Sequence[str] = ()
    default_armature: Optional[float] = 0.1

    def _check(self):
        super()._check()
        _check_default_armature(self)
        if isinstance(self.links_to_keep, str):
            raise ValueError(f"gs.morphs.URDF(links_to_keep={self.links_to_keep!r}): give a list of link names")
        self.links_to_keep = tuple(str(n) for n in self.links_to_keep)


@dataclass
class MJCF(FileMorph):
    """A robot from a MuJoCo MJCF (.xml) file, compiled by MuJoCo itself (pip install mujoco). pos (m) and
    quat / euler place the whole model (its worldbody) in the world; `scale` scales it uniformly (lengths
    times scale, masses scale^3). fixed: None (the default) keeps what the file says (a body with a
    <freejoint/> floats, one without joints is welded to the world); True welds free bodies too; False
    also frees the worldbody's bodies that have no joint. Its meshes collide by Genesis's rules (FileMorph):
    an object's non-convex mesh (a free body's with nothing articulated below it) as CoACD's parts, where
    MuJoCo would take its hull; a robot's as its hull, as MuJoCo's."""

    fixed: Optional[bool] = None
    requires_jac_and_IK: bool = False
    default_armature: Optional[float] = 0.1

    def _check(self):
        super()._check()
        _check_default_armature(self)


def _check_file_options(morph):
    """Genesis's FileMorph options. decimate / decimate_face_num / decimate_aggressiveness (Genesis simplifies a
    collision mesh to ~500 faces before taking its hull) are checked and change nothing: genesis_lite takes the
    hull (or CoACD's parts) of the whole mesh, as Genesis does with decimate=False, and samples it at most at
    RigidOptions.max_mesh_contact_points points; cameras draw the file itself. batch_fixed_verts (Genesis: a copy
    of fixed geoms' vertices per env) changes nothing either: every env sees the same fixed geoms. recompute_inertia
    (loaders.load_morph) and file_meshes_are_zup act: False turns a Mesh's or a URDF's mesh files from y-up to z-up,
    (x, y, z) -> (x, -z, y), before the morph's scale, as Genesis does (an MJCF's meshes are placed by MuJoCo's
    compiler, and Genesis ignores the option there too: a warning says so)."""
    owner = f"gs.morphs.{type(morph).__name__}"
    for name in ("decimate", "recompute_inertia", "file_meshes_are_zup", "batch_fixed_verts"):
        if not isinstance(getattr(morph, name), bool):
            raise ValueError(f"{owner}({name}={getattr(morph, name)!r}): use True or False")
    n = morph.decimate_face_num
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"{owner}(decimate_face_num={n!r}): give a positive number of faces")
    a = morph.decimate_aggressiveness
    if isinstance(a, bool) or not isinstance(a, (int, np.integer)) or not 0 <= a <= 8:
        raise ValueError(f"{owner}(decimate_aggressiveness={a!r}): give an integer from 0 to 8")
    if not morph.file_meshes_are_zup and isinstance(morph, MJCF):
        warnings.warn(f"{owner}(file_meshes_are_zup=False) changes nothing: an MJCF's meshes are placed as MuJoCo "
                      "compiles the file (its <mesh refquat>, each geom's pos and quat), as Genesis places them; "
                      "turn the whole model with the morph's quat or euler", stacklevel=4)


def _check_decomposition(morph):
    """decompose_nonconvex, coacd_options as gs.options.CoacdOptions (None: Genesis's defaults; a dict: some of
    its fields), convexify and the decomposition thresholds (relative volume errors >= 0; inf: never)."""
    from .options import CoacdOptions

    owner = f"gs.morphs.{type(morph).__name__}"
    if morph.decompose_nonconvex not in (None, True, False):
        raise ValueError(f"{owner}(decompose_nonconvex={morph.decompose_nonconvex!r}): use None, True or False")
    morph.coacd_options = CoacdOptions.of(morph.coacd_options, owner)
    if not isinstance(morph.convexify, bool):
        raise ValueError(f"{owner}(convexify={morph.convexify!r}): use True or False")
    for name in ("decompose_object_error_threshold", "decompose_robot_error_threshold"):
        t = getattr(morph, name)
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not t >= 0:
            raise ValueError(f"{owner}({name}={t!r}): give a relative volume error >= 0 (float('inf'): never "
                             "split)")
        setattr(morph, name, float(t))


def _check_default_armature(morph):
    """default_armature (kg m^2 or kg; Genesis's option and default, 0.1): a rotor inertia added to the joints
    of the file (URDF: every hinge and slide joint; MJCF: every <joint> element of the worldbody that names no
    armature, a default class's value overridden, as Genesis reads it). The default integrator,
    approximate_implicitfast, relies on it, as Genesis's does: a stiff PD on light links stays stable. None
    keeps the file's armature (0 in a URDF): the robot's own dynamics, as Pinocchio and MuJoCo compute them."""
    v = morph.default_armature
    if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0):
        raise ValueError(f"gs.morphs.{type(morph).__name__}(default_armature={v!r}): give a number >= 0 (kg m^2 for "
                         "a hinge, kg for a slide) or None")


@dataclass
class Mesh(FileMorph):
    """A single rigid body from a mesh file (STL, OBJ, DAE, ...). Collision shapes are convex (as in
    Genesis): a convex mesh collides as itself; a non-convex one is split into convex parts by CoACD
    (pip install coacd) when its convex hull's volume exceeds the mesh's by more than
    `decompose_object_error_threshold` (relative, Genesis's name, default and measure, which takes an open but
    consistently wound surface's volume as trimesh closes it and splits a mesh whose winding stays inconsistent
    whatever the threshold; for a sheet without volume, how deep it lies inside its hull relative to the hull's
    half thinnest width), or always with
    decompose_nonconvex=True; with decompose_nonconvex=False it collides as its convex hull (and a
    warning says so). convexify=False (Genesis: collide the raw mesh) decomposes too: parts are how
    genesis_lite collides a non-convex surface. decompose_robot_error_threshold is accepted (Genesis's;
    a mesh is an object). decompose_error_threshold is genesis_lite's earlier name of the object threshold
    (given, it overrides it). coacd_options: gs.options.CoacdOptions or a dict of its fields (Genesis's
    defaults: threshold 0.1, the concavity each part may keep). Mass and inertia come from the mesh's own
    volume when it is closed, else from the parts (or the hull)."""

    decompose_error_threshold: Optional[float] = None

    def _check(self):
        t = self.decompose_error_threshold
        if t is not None:
            if isinstance(t, bool) or not isinstance(t, (int, float)) or not t >= 0:
                raise ValueError(f"gs.morphs.Mesh(decompose_error_threshold={t!r}): give a relative volume error >= 0")
            self.decompose_object_error_threshold = t
            self.decompose_error_threshold = None
        super()._check()


@dataclass
class Box(Morph):
    """size: full edge lengths (m); or Genesis's lower and upper corners (m, world frame, before any
    rotation), which give pos (their midpoint) and size (their difference)."""

    size: Optional[Sequence[float]] = None
    lower: Optional[Sequence[float]] = None
    upper: Optional[Sequence[float]] = None

    def _check(self):
        if (self.lower is None) != (self.upper is None):
            raise ValueError("gs.morphs.Box: give both lower and upper, or neither (then size and pos)")
        if self.lower is not None:
            lo, hi = _vec("lower", "Box", self.lower, 3), _vec("upper", "Box", self.upper, 3)
            if self.size is not None or np.any(self.pos != 0.0):
                raise ValueError(f"gs.morphs.Box(lower={self.lower!r}, upper={self.upper!r}): the corners set pos and "
                                 "size; do not give those too")
            if not np.all(hi > lo):
                raise ValueError(f"gs.morphs.Box(lower={self.lower!r}, upper={self.upper!r}): upper must exceed lower "
                                 "on every axis")
            self.pos, self.size = 0.5 * (lo + hi), hi - lo
        self.size = _vec("size", "Box", self.size if self.size is not None else (1.0, 1.0, 1.0), 3)
        for s in self.size:
            _positive("size", "Box", s)


@dataclass
class Sphere(Morph):
    radius: float = 0.5

    def _check(self):
        _positive("radius", "Sphere", self.radius)


@dataclass
class Capsule(Morph):
    """radius and height (m) of the cylindrical part, axis along the body's z."""

    radius: float = 0.1
    height: float = 0.5

    def _check(self):
        _positive("radius", "Capsule", self.radius)
        _positive("height", "Capsule", self.height)


@dataclass
class Cylinder(Morph):
    """radius and height (m), axis along the body's z."""

    radius: float = 0.1
    height: float = 0.5

    def _check(self):
        _positive("radius", "Cylinder", self.radius)
        _positive("height", "Cylinder", self.height)


@dataclass
class Plane(Morph):
    """An infinite static ground plane through pos with the given normal."""

    normal: Sequence[float] = (0.0, 0.0, 1.0)
    fixed: bool = True

    def _check(self):
        n = _vec("normal", "Plane", self.normal, 3)
        if np.linalg.norm(n) < 1e-9:
            raise ValueError("gs.morphs.Plane(normal=...): the normal must be non-zero")
        self.normal = n / np.linalg.norm(n)
        self.fixed = True
