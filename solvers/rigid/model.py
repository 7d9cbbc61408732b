"""Plain numpy description of a rigid articulated entity: the contract between loaders and solver.

A loader (URDF, primitive morph, mesh) turns a user's morph into an `EntityModel`; the rigid solver
concatenates the models of all entities of a scene into its `*_info` fields at build time. Nothing
here imports taichi or torch.

Conventions (SI units throughout):
- Quaternions are (w, x, y, z), unit norm.
- Links are listed parent-before-child in depth-first order of the kinematic tree, so joint/dof order
  matches Pinocchio's and Genesis's. Fixed joints are merged into their parent (their child's mass,
  inertia and geometry move into the parent link, expressed in the parent's frame) unless the user
  asks to keep the child (Genesis's links_to_keep, merge_fixed_links=False).
- Each link has exactly one joint connecting it to its parent (`parent == -1`: the world):
  'fixed' (0 dofs: a root welded to the world, or a link welded to its parent that a loader kept
  rather than merged), 'free' (7 qs: pos xyz + quat wxyz,
  6 dofs: world-frame linear velocity of the link origin, then world-frame angular velocity),
  'revolute' (1 dof; a URDF `continuous` joint is revolute with infinite limits) or 'prismatic' (1 dof).
- The joint frame sits at `joint_pos, joint_quat` in the parent link frame (for a root: in the world);
  the joint's motion happens about/along `joint_axis` expressed in the child link frame, and at
  q = 0 the child link frame coincides with the joint frame.
- Inertia: `mass` (kg), `com` (m, in the link frame) and `inertia` (3x3 kg m^2 about the COM, axes of
  the link frame).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Tuple

import numpy as np

JOINT_TYPES = ("fixed", "free", "revolute", "prismatic")
JOINT_NQ = {"fixed": 0, "free": 7, "revolute": 1, "prismatic": 1}
JOINT_NV = {"fixed": 0, "free": 6, "revolute": 1, "prismatic": 1}
GEOM_TYPES = ("plane", "sphere", "box", "capsule", "cylinder", "mesh")


@dataclass
class GeomDesc:
    """A collision shape attached to a link.

    size: plane () [normal is the geom's +z], sphere (radius,), box (half_x, half_y, half_z),
    capsule (radius, half_length) and cylinder (radius, half_length), both along the geom's z axis.
    mesh: `vertices` (n, 3) and `faces` (m, 3) in the geom frame (scale already applied), and `hull`,
    when a loader computed it: the convex hull of `vertices` as trimesh makes it, {"vertices": (k, 3),
    "centroid": (3,), "volume": m^3, "is_volume": bool}. The contact builder needs only that hull; a
    model that carries it (and comes from the loaders' on-disk cache) builds without importing trimesh.
    Whoever changes `vertices` afterwards sets `hull` to None.
    """

    type: str
    pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    quat: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    size: Tuple[float, ...] = ()
    vertices: Optional[np.ndarray] = None
    faces: Optional[np.ndarray] = None
    friction: Optional[float] = None  # None: the entity material's friction
    hull: Optional[dict] = None


@dataclass
class VisualDesc:
    """A shape drawn for a link but ignored by the physics (URDF <visual>, the full mesh of a
    gs.morphs.Mesh). Mesh files are only located here, never read: cameras load them when they first
    render, so build time does not pay for meshes nobody looks at.

    type: 'box' | 'sphere' | 'cylinder' | 'capsule' | 'mesh'; pos, quat in the link frame; size as in
    GeomDesc (m); for meshes `file` is the resolved path (None when the file was not found, and
    `filename` keeps what the URDF said) and `scale` the per-axis scale; rgba in [0, 1] or None.
    """

    type: str
    pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    quat: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    size: Tuple[float, ...] = ()
    file: Optional[str] = None
    filename: str = ""
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))
    rgba: Optional[Tuple[float, float, float, float]] = None


@dataclass
class MimicDesc:
    """q_follower = multiplier * q_leader + offset (URDF <mimic>)."""

    joint: str
    multiplier: float = 1.0
    offset: float = 0.0


@dataclass
class LinkDesc:
    name: str
    parent: int
    joint_name: str
    joint_type: str
    joint_pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    joint_quat: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    joint_axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    limit: Tuple[float, float] = (-np.inf, np.inf)
    effort: float = np.inf
    velocity: float = np.inf
    damping: float = 0.0
    frictionloss: float = 0.0
    armature: float = 0.0
    # joint spring of a 1-dof joint: force -stiffness (q - springref) (N/m or N m/rad; MJCF stiffness, springref)
    stiffness: float = 0.0
    springref: float = 0.0
    mimic: Optional[MimicDesc] = None
    # the limit constraint's MuJoCo solref (time constant s, damping ratio) and solimp (dmin, dmax, width, mid,
    # power) of a 1-dof joint, as an MJCF file gives them (solreflimit / solimplimit); None: Genesis's defaults
    # (time constant RigidOptions.constraint_timeconst, solimp (0.9, 0.95, 0.001, 0.5, 2))
    limit_solref: Optional[Tuple[float, float]] = None
    limit_solimp: Optional[Tuple[float, float, float, float, float]] = None
    kp: Optional[float] = None  # PD gains of a 1-dof joint as the file gives them; None: the scene's default
    kv: Optional[float] = None
    mass: float = 0.0
    com: np.ndarray = field(default_factory=lambda: np.zeros(3))
    inertia: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    geoms: List[GeomDesc] = field(default_factory=list)
    visuals: List[VisualDesc] = field(default_factory=list)


@dataclass
class EntityModel:
    """One entity: its links (parent before child) and where it came from (for error messages)."""

    name: str
    links: List[LinkDesc]
    source: str = ""
    rigid_contact: bool = True  # whether its geoms collide with other entities' (a gs.materials.Tool's do not)

    @property
    def n_links(self) -> int:
        return len(self.links)

    @property
    def n_qs(self) -> int:
        return sum(JOINT_NQ[l.joint_type] for l in self.links)

    @property
    def n_dofs(self) -> int:
        return sum(JOINT_NV[l.joint_type] for l in self.links)

    def validate(self) -> None:
        """Raise ValueError naming the entity and link for an inconsistent description."""
        for i, l in enumerate(self.links):
            where = f"entity '{self.name}' ({self.source}), link '{l.name}'"
            if l.joint_type not in JOINT_TYPES:
                raise ValueError(f"{where}: unknown joint type '{l.joint_type}'; expected one of {JOINT_TYPES}")
            if not (-1 <= l.parent < i):
                raise ValueError(f"{where}: parent index {l.parent} must name an earlier link (-1 for the world)")
            if l.joint_type == "free" and l.parent != -1:
                raise ValueError(f"{where}: a 'free' joint is only allowed on a root link")
            if not np.isfinite(l.mass) or l.mass < 0:
                raise ValueError(f"{where}: mass {l.mass} must be finite and >= 0")
            if l.joint_type in ("revolute", "prismatic") and abs(np.linalg.norm(l.joint_axis) - 1) > 1e-6:
                raise ValueError(f"{where}: joint axis {l.joint_axis} is not a unit vector")
