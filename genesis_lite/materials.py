"""Materials: physical properties an entity is made of."""
from __future__ import annotations

import numbers
from dataclasses import dataclass, field
from typing import Optional

import numpy as np


# Genesis 0.4.5's densities for Rigid(rho=None) (its rigid_link.py): objects, and articulated robots' links
RHO_OBJECT = 600.0
RHO_ROBOT = 1500.0


@dataclass
class Rigid:
    """rho: density (kg/m^3) used for links without a URDF <inertial> and for primitive and mesh shapes;
    None (the default) takes Genesis's: RHO_OBJECT (600) for a body that is not part of an articulated
    robot (primitives, meshes, a URDF with no hinge or slide joint), RHO_ROBOT (1,500) for the links of a
    URDF robot that has one (MJCF files carry their own densities: MuJoCo's compiler, 1,000 by default);
    friction: Coulomb coefficient (dimensionless, >= 0) against other rigid bodies. Coupling with MPM
    materials (Genesis's names): needs_coup (the body is a boundary for MPM particles), coup_friction
    (Coulomb coefficient against them), coup_softness (m: width of the band outside the surface over
    which the boundary fades in; None: half an MPM grid cell; 0: none, the boundary acts from the
    surface in). gravity_compensation: the fraction of gravity cancelled on the entity's links (0: none,
    1: it floats; Genesis's meaning: an upward force gc m g at each link's centre of mass); a 0-d torch
    tensor that requires grad makes it a differentiable parameter (entity.set_gravity_compensation
    changes it after build)."""

    rho: Optional[float] = None
    friction: float = 1.0
    needs_coup: bool = True
    coup_friction: float = 0.1
    coup_softness: Optional[float] = None
    gravity_compensation: float = 0.0

    def __post_init__(self):
        for name in ("rho", "friction", "coup_friction", "coup_softness"):
            v = getattr(self, name)
            real = isinstance(v, numbers.Real) or (isinstance(v, np.ndarray) and v.ndim == 0
                                                   and np.issubdtype(v.dtype, np.number))
            if not (real and not isinstance(v, bool) or (v is None and name in ("rho", "coup_softness"))):
                raise TypeError(f"gs.materials.Rigid({name}={v!r}): give a number, not a {type(v).__name__}")
        if self.rho is not None and not (np.isfinite(self.rho) and self.rho > 0):
            raise ValueError(f"gs.materials.Rigid(rho={self.rho!r}): density must be None (Genesis's defaults) or a "
                             "positive number (kg/m^3)")
        if not (np.isfinite(self.friction) and self.friction >= 0):
            raise ValueError(f"gs.materials.Rigid(friction={self.friction!r}): friction must be a finite number >= 0")
        if not (np.isfinite(self.coup_friction) and self.coup_friction >= 0):
            raise ValueError(f"gs.materials.Rigid(coup_friction={self.coup_friction!r}): must be a finite number >= 0")
        if self.coup_softness is not None and not (np.isfinite(self.coup_softness) and self.coup_softness >= 0):
            raise ValueError(f"gs.materials.Rigid(coup_softness={self.coup_softness!r}): must be None or a number "
                             ">= 0 (m; 0: a hard boundary, as in Genesis)")
        check_gravity_compensation(self.gravity_compensation, "gs.materials.Rigid(gravity_compensation=...)")

    def density(self, robot: bool) -> float:
        """The density (kg/m^3) that fills a shape with no mass of its own: rho when given, else Genesis's
        default for an articulated robot's links (robot=True) or for an object."""
        if self.rho is not None:
            return float(self.rho)
        return RHO_ROBOT if robot else RHO_OBJECT


def check_gravity_compensation(gc, who):
    """Raise unless gc is a finite number (or a one-element tensor) in [0, 1]."""
    import torch

    if torch.is_tensor(gc):
        if gc.numel() != 1 or not gc.is_floating_point():
            raise ValueError(f"{who}: a tensor must hold one floating-point number, got shape {tuple(gc.shape)} "
                             f"dtype {gc.dtype}")
        v = float(gc.detach().reshape(()))
    else:
        try:
            v = float(gc)
        except (TypeError, ValueError):
            raise ValueError(f"{who}: must be a number in [0, 1], got {gc!r}") from None
    if not (np.isfinite(v) and 0.0 <= v <= 1.0):
        raise ValueError(f"{who}: must be a number in [0, 1] (the fraction of gravity cancelled: 0 none, 1 all), "
                         f"got {v}")


def _check_positive(owner, name, v, unit):
    if not (isinstance(v, (int, float, np.floating)) and np.isfinite(v) and v > 0):
        raise ValueError(f"gs.materials.{owner}({name}={v!r}): must be a positive number ({unit})")


class MPM:
    """Materials of MPM entities (soft bodies, plasticine, sand, liquids), Genesis's names and defaults.

    All take E (Young's modulus, Pa), nu (Poisson's ratio, -1 < nu < 0.5) and rho (density, kg/m^3).
    Parameters can be changed per entity, per particle and differentiably after build with
    `entity.set_material(...)`."""

    @dataclass
    class Base:
        E: float = 1e6
        nu: float = 0.2
        rho: float = 1000.0
        # Genesis's particle sampler ('regular', 'random', 'pbs...'): accepted so its scripts run; genesis_lite
        # always fills a regular lattice (loaders/particles.py, entities/emitter.py). Keyword-only, so the
        # materials' own fields keep their positions.
        sampler: str = field(default="regular", kw_only=True)

        code = -1  # solvers/mpm/constitutive.py MAT_* (set by each material)

        def __post_init__(self):
            owner = f"MPM.{type(self).__name__}"
            if not (isinstance(self.sampler, str) and (self.sampler in ("regular", "random")
                                                       or self.sampler.startswith("pbs"))):
                raise ValueError(f"gs.materials.{owner}(sampler={self.sampler!r}): use 'regular', 'random' or 'pbs' "
                                 "(genesis_lite samples a regular lattice whatever the choice)")
            _check_positive(owner, "E", self.E, "Pa")
            _check_positive(owner, "rho", self.rho, "kg/m^3")
            if not (isinstance(self.nu, (int, float, np.floating)) and -1.0 < self.nu < 0.5):
                raise ValueError(f"gs.materials.{owner}(nu={self.nu!r}): Poisson's ratio must lie in (-1, 0.5); 0.5 "
                                 "would make the material incompressible, which explicit MPM cannot step")
            self._check()

        def _check(self):
            pass

        @property
        def mu(self) -> float:
            return self.E / (2.0 * (1.0 + self.nu))

        @property
        def lam(self) -> float:
            return self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))

        def wave_speed(self) -> float:
            """Speed of elastic pressure waves sqrt((lam + 2 mu) / rho), m/s: what limits the time step."""
            return float(np.sqrt((self.lam + 2.0 * self.mu) / self.rho))

    @dataclass
    class Elastic(Base):
        """A hyperelastic solid: model "corotation" (corotated linear elasticity) or "neohooken"
        (neo-Hookean, spelled as Genesis spells it)."""

        E: float = 3e5
        model: str = "corotation"

        def _check(self):
            if self.model not in ("corotation", "neohooken"):
                raise ValueError(f"gs.materials.MPM.Elastic(model={self.model!r}): use 'corotation' or 'neohooken'")

        @property
        def code(self):
            return 0 if self.model == "corotation" else 1

    @dataclass
    class ElastoPlastic(Base):
        """Plasticine: corotated elasticity with a von Mises yield surface (yield_stress, Pa; Genesis's
        `von_mises_yield_stress`)."""

        yield_stress: float = 1e4
        code = 2

        def _check(self):
            _check_positive("MPM.ElastoPlastic", "yield_stress", self.yield_stress, "Pa")

    @dataclass
    class Sand(Base):
        """Granular material: Drucker-Prager plasticity with the given friction_angle (degrees)."""

        friction_angle: float = 45.0
        code = 3

        def _check(self):
            if not (isinstance(self.friction_angle, (int, float, np.floating)) and 0 < self.friction_angle < 90):
                raise ValueError(f"gs.materials.MPM.Sand(friction_angle={self.friction_angle!r}): must lie in (0, 90) "
                                 "degrees")

    @dataclass
    class Liquid(Base):
        """A weakly compressible liquid (bulk modulus from E and nu) with optional viscosity (Pa s)."""

        viscosity: float = 0.0
        code = 4

        def _check(self):
            if not (isinstance(self.viscosity, (int, float, np.floating)) and np.isfinite(self.viscosity)
                    and self.viscosity >= 0):
                raise ValueError(f"gs.materials.MPM.Liquid(viscosity={self.viscosity!r}): must be a number >= 0 (Pa s)")

        def wave_speed(self) -> float:
            """Liquids have no shear stiffness: sqrt(lam / rho)."""
            return float(np.sqrt(self.lam / self.rho))


def sand_alpha(friction_angle_deg):
    """Drucker-Prager cone coefficient of a friction angle (degrees): sqrt(2/3) 2 sin(phi) / (3 - sin(phi)).
    Works on floats and torch tensors (differentiably)."""
    import torch

    if isinstance(friction_angle_deg, torch.Tensor):
        s = torch.sin(torch.deg2rad(friction_angle_deg))
        return (2.0 / 3.0) ** 0.5 * 2.0 * s / (3.0 - s)
    s = np.sin(np.deg2rad(friction_angle_deg))
    return float(np.sqrt(2.0 / 3.0) * 2.0 * s / (3.0 - s))


@dataclass
class Tool:
    """Genesis's tool material (gs.materials.Tool): a rigid body that moves only as it is told
    (entity.set_position / set_quat / set_velocity, differentiable) and acts on MPM material as a moving
    boundary, one-way: nothing pushes it back, gravity does not act on it, and it passes through other
    rigid bodies. friction: Coulomb coefficient against the material; coup_softness (m): the width of the
    band outside its surface over which its boundary fades in (Genesis's default 0.01); collision: whether
    it acts on the material at all; sdf_res: Genesis's SDF grid resolution, accepted and not used (the
    boundary is the shape's own signed distance, of its convex hull for a mesh)."""

    friction: float = 0.0
    coup_softness: float = 0.01
    collision: bool = True
    sdf_res: int = 128

    def __post_init__(self):
        if not isinstance(self.collision, bool):
            raise TypeError(f"gs.materials.Tool(collision={self.collision!r}): give True or False")
        if isinstance(self.sdf_res, bool) or not isinstance(self.sdf_res, (int, np.integer)) or self.sdf_res <= 0:
            raise ValueError(f"gs.materials.Tool(sdf_res={self.sdf_res!r}): must be a positive int")
        try:
            self.rigid()  # friction and coup_softness: Rigid's checks
        except (TypeError, ValueError) as e:
            raise type(e)(f"gs.materials.Tool(friction={self.friction!r}, coup_softness={self.coup_softness!r}): {e} "
                          "(a tool's friction is its coup_friction)") from None

    def rigid(self) -> Rigid:
        """The rigid material the tool's body is simulated with (always massive enough not to matter: no
        force acts on it)."""
        return Rigid(rho=1000.0, friction=0.0, needs_coup=self.collision, coup_friction=self.friction,
                     coup_softness=self.coup_softness, gravity_compensation=1.0)


class _OutOfScopeMaterial:
    """A material of a Genesis solver genesis_lite does not have: it can be created (so a script's set-up
    runs), and an entity or emitter made of it is left out of the simulation with a warning that says what
    to use instead (entities/out_of_scope.py)."""

    solver, instead = "", ""

    def __init__(self, **kwargs):
        self.__dict__.update(kwargs)

    def describe(self) -> str:
        return f"gs.materials.{self.solver}.{type(self).__name__}"


def _out_of_scope_family(solver, instead, names):
    family = type(solver, (), {"__doc__": f"Genesis's {solver} materials: out of scope (see _OutOfScopeMaterial)."})
    for n in names:
        setattr(family, n, type(n, (_OutOfScopeMaterial,), {"solver": solver, "instead": instead}))
    return family


SPH = _out_of_scope_family("SPH", "For a liquid use gs.materials.MPM.Liquid().", ("Liquid",))
PBD = _out_of_scope_family("PBD", "For cloth or ropes there is no substitute; for a soft body use gs.materials.MPM.Elastic().",
                           ("Cloth", "Elastic", "Liquid", "Particle"))
FEM = _out_of_scope_family("FEM", "For a soft body use gs.materials.MPM.Elastic().", ("Elastic", "Muscle"))
