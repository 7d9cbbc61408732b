"""Validated option dataclasses: SimOptions, RigidOptions, MPMOptions (the Genesis names and defaults)."""
from __future__ import annotations

import enum
from dataclasses import dataclass, fields
from typing import Optional, Tuple, Union

import numpy as np

from solvers.rigid.schedule import Integrator


# time integrators of the rigid solver: the solver's one enum (Euler, implicitfast, RK4, approximate_implicitfast)
integrator = Integrator


class constraint_solver(enum.IntEnum):
    """Genesis's constraint solvers (RigidOptions(constraint_solver=...)). genesis_lite has one contact
    model, a smooth penalty law solved implicitly with the dynamics (solvers/rigid/contact.py): either
    value is accepted and gives that model."""

    CG = 0
    Newton = 1


def _finite_vec(opts, name, n):
    v = getattr(opts, name)
    if v is None:
        return
    a = np.asarray(v, dtype=float) if np.ndim(v) else None
    if a is None or a.shape != (n,) or not np.all(np.isfinite(a)):
        opts._err(name, v, f"must be {n} finite numbers")
    setattr(opts, name, tuple(float(x) for x in a))


class _Options:
    def __post_init__(self):
        self._validate()

    def _validate(self):
        pass

    def _err(self, name, value, what):
        raise ValueError(f"{type(self).__name__}.{name}={value!r}: {what}")

    def copy(self, **kw):
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d.update(kw)
        return type(self)(**d)


@dataclass
class SimOptions(_Options):
    """dt (s) per scene.step(); substeps split each step; gravity (m/s^2, world frame);
    requires_grad keeps per-step state so torch can backpropagate through the rollout;
    checkpoint_every is how many steps the gradient buffer keeps in memory before it checkpoints
    (memory stays bounded for any horizon; None keeps every step).

    nan_policy says what a NaN or inf in the state does. The state of every env is checked after every
    step (rigid and MPM, with and without gradients; measured in benchmarks/results/nan_check.md):
    "raise" (default) raises gs.errors.SimulationNaNError at the step where it appears, naming the
    env(s), the entity and the quantity; "mask" (Genesis's way, for batched training) logs the failed
    envs once and lets the others go on: scene.get_error_envs_mask() (alias
    scene.rigid_solver.get_error_envs_mask()) marks them and scene.reset(envs_idx=mask) restores
    them; backward through such a rollout gives the other envs their gradients and raises if the loss
    depends on a failed env; "off" checks nothing after the steps (get_error_envs_mask() then checks
    the current state)."""

    dt: float = 0.01
    substeps: int = 1
    gravity: Tuple[float, float, float] = (0.0, 0.0, -9.81)
    requires_grad: bool = False
    checkpoint_every: Optional[int] = None
    nan_policy: str = "raise"

    def _validate(self):
        if self.nan_policy not in ("raise", "mask", "off"):
            self._err("nan_policy", self.nan_policy, "must be 'raise', 'mask' or 'off'")
        if not (isinstance(self.dt, (int, float)) and np.isfinite(self.dt) and self.dt > 0):
            self._err("dt", self.dt, "the time step must be a positive finite number of seconds")
        if not (isinstance(self.substeps, int) and self.substeps >= 1):
            self._err("substeps", self.substeps, "must be an integer >= 1")
        g = np.asarray(self.gravity, dtype=float)
        if g.shape != (3,) or not np.all(np.isfinite(g)):
            self._err("gravity", self.gravity, "must be three finite numbers (m/s^2)")
        self.gravity = tuple(float(x) for x in g)
        if self.checkpoint_every is not None and not (isinstance(self.checkpoint_every, int) and self.checkpoint_every >= 1):
            self._err("checkpoint_every", self.checkpoint_every, "must be None or an integer >= 1")

    @property
    def substep_dt(self) -> float:
        return self.dt / self.substeps


@dataclass
class RigidOptions(_Options):
    """integrator: gs.integrator.approximate_implicitfast (the default, Genesis's: joint damping and the PD's kv
    implicit, saturated or not; kp explicit) | implicitfast (joint damping and the PD's kp and kv implicit,
    neither gain while the actuator is saturated) | Euler | RK4 (solvers/rigid/actuation.py). Like Genesis,
    the default relies on the armature of 0.1 that URDF and MJCF morphs add to their joints by default
    (gs.morphs.URDF / MJCF(default_armature=)): without it a stiff PD on light links can go unstable (Genesis's
    go2 driver tips over at landing).
    enable_collision / enable_joint_limit
    switch contacts and joint limits. Bodies collide with every other body, those of one entity included (an
    MJCF's free bodies, its worldbody's floor). A body's own links (one kinematic tree) collide with each
    other with enable_self_collision=True, as Genesis's do, except links adjacent to each other (one the
    other's parent, directly or through links attached by fixed joints; enable_adjacent_collision=True lets
    those too) and pairs of collision shapes that already overlap or touch with every joint at zero, as a
    robot's shapes often do where its parts meet (enable_neutral_collision=True keeps those; the test is a
    voxel-like grid of ~24 cells along each shape, collision.neutral_overlaps). Unlike Genesis, self-collision
    is off by default: it makes a robot scene's step longer (Genesis's MJCF Panda over a plane holding a bent
    pose: 1.3x at 1 env, 1.6-1.9x at 1,024 envs; with its hand pressed onto its forearm, 21-22 of its own
    pairs touching, 10-12x; benchmarks/results/self_collision.md), and with gradients its contact kernels and
    their adjoints compile as soon as any own pair can touch (the README's main example: 58 s cold, 15 s
    without). contact_stiffness (N/m per contact point, 1e5 by default) and the damping set the penalty
    model (the stiffness scaled up for pairs heavier than k (10 ms)^2, 10 kg at the default). By default each
    contact is critically damped for the mass it moves (see contact_damping_ratio); contact_damping (N s/m per
    contact point) gives
    a fixed damper instead (genesis_lite's default until 2026-12-05: 4e4 with a stiffness of 1e6), and
    giving both is an error. Joint limits are Genesis's (and MuJoCo's) soft constraint by default: past a limit
    by d, the constraint asks for the reference acceleration -b v - k imp d (b = 2 / (0.95 tc),
    k = 1 / (0.95 tc)^2, tc = max(constraint_timeconst, 2 substep dt), imp 0.9 -> 0.95 over the first mm or
    mrad; an MJCF joint's solreflimit / solimplimit where it has them) with an impedance that scales with the
    joint's inverse weight
    (M^-1)_jj at the initial configuration (recomputed when set_dofs_armature changes the armature), and lets go
    while the joint leaves the limit faster than that (tests/test_joint_limits.py: MuJoCo's trajectories to
    1e-14). joint_limit_stiffness / joint_limit_damping (N m/rad, N m s/rad; None by default) select penalty
    springs instead (either one given; the other then 1e4 / 1e2), genesis_lite's limits before 2026-11-29.
    contact_damping_ratio (None by default: 1, critical, unless contact_damping is given) sets each contact's
    damper relative to its mass: critical times the ratio, 2 ratio sqrt(k m_eff) with m_eff the
    mass the contact moves along its normal, each side's link weighed through its articulation at the
    initial configuration, armature included (MuJoCo's body_invweight0 along the normal: ANYmal's foot moves
    4-5 kg, its own mass is 0.35 kg; computed at build from the model's masses and armature, while a lone free
    body takes its own mass as it is set), and at least 4 k h (h the step). A landing then rebounds with
    exp(-2) of its speed whatever the mass behind the contact (tests/test_contact_damper.py). Since 2026-12-05
    this, with the stiffness of 1e5 N/m, is the default: the contact's time scales, sqrt(m_eff / k) and the
    damper's m_eff / c, are then those of the body (7 and 3 ms for ANYmal's foot), which practical steps resolve,
    so contact scenes converge as dt shrinks. The fixed damper of before (4e4 N s/m with 1e6 N/m) gave a foot a
    damping time m / c of 1e-4 s (1e-5 s without rotor inertia) that no practical step resolves: the quadruped's
    16 drops at 1.25 ms erred by 9.6e-4 m against the reference (2.7e-4 m now), and RK4 at 0.2 ms by 9.8e-5 m
    against RK4 at 0.1 ms (5.5e-6 m now; benchmarks/results/workprecision_quadruped_starts.md). Penetration
    under load is k-bound: a 4.5 kg box resting on four corners sinks 0.11 mm (0.011 mm at 1e6 N/m); a pair
    heavier than k (10 ms)^2 (10 kg at the default) has its stiffness scaled with its mass (a 400 t box sinks
    0.25 mm).
    friction_load ("coulomb" by default, since 2026-12-02) is the normal force Coulomb's bound mu f_n takes:
    the force the contact law gives with Coulomb's forces applied (at most twice the frictionless solve's, and
    in the bound rounds at most the law's force at the solution), which carries the load friction's own
    torque moves between a body's contacts (a box sliding on a face presses its leading edge; a standing
    robot's feet): a sliding box converges to Coulomb's slide at first order as dt shrinks (2.8e-4 m at
    0.3 ms) and a standing quadruped's posture converges (tests/test_contact.py). "frictionless" takes the
    frictionless solve's normal forces, the model before that day (3.2e-3 m at 0.3 ms, growing as dt shrank).

    Contact model (solvers/rigid/contact/): contact_smoothing (m) is the width over which the normal
    force softens near zero depth (softplus), friction_smoothing (m/s) the slip velocity below which
    Coulomb friction becomes viscous (smaller: less creep on slopes, stiffer gradients).
    friction_smoothing_accel (m/s^2, 0.25 by default since 2026-12-06; None: off): friction_smoothing at most
    this times the step (substep, or RK4 stage) h, so that the model converges at first order to exact Coulomb
    friction as dt shrinks. With a fixed slip speed a body resting on a slope creeps at about (tan / mu)
    friction_smoothing whatever the step, and steps finer than ~ friction_smoothing / (mu g) leave the coarser
    ones' limit (ANYmal standing sank 1.3e-5 m more per halving of dt below 25 us). At 0.25 the cap acts below
    h = 4 ms only (10 and 5 ms steps keep the fixed slip speed); a box on 15 degrees at mu = 0.5 creeps at
    0.54 mm/s at 10 and 5 ms, ~0.13 mm/s at 1 ms and half that at each halving (tests/test_contact.py).
    max_mesh_contact_points caps the hull points a collision mesh contacts with (more: smoother, slower).
    ignore_unsupported_pairs lets pairs the contact model cannot handle (a plane on a moving link)
    pass through each other instead of raising at build.

    specialize_kernels: True compiles the no-gradient step for this scene alone, with its contact sizes
    as constants and Taichi's full optimisation (~25 % faster batched contact steps, ~50 s more compile
    on a cold cache, nothing shared with other scenes); False shares compiled kernels with every scene
    of its size class (a second robot compiles nothing); None (default) specialises scenes of at least
    512 environments, where the step's run time outweighs its compile (a 64-env Panda on a plane: 20 s
    from import to first step on an empty cache shared, 80 s specialised).

    batch_links_info / batch_dofs_info / batch_joints_info (Genesis's; True or False): in Genesis they give
    each environment its own copy of the links' / dofs' / joints' parameters, so that scripts can set them
    per env (set_dofs_kp(..., envs_idx=), set_mass_shift(..., envs_idx=) and the like). genesis_lite
    keeps those parameters per environment always, so the flags are checked and change nothing: per-env
    setters work with them False as well, and the step is the same."""

    integrator: integrator = integrator.approximate_implicitfast
    enable_collision: bool = True
    enable_joint_limit: bool = True
    enable_self_collision: bool = False
    enable_adjacent_collision: bool = False
    enable_neutral_collision: bool = False
    contact_stiffness: float = 1e5
    contact_damping: Optional[float] = None
    contact_damping_ratio: Optional[float] = None
    friction_load: str = "coulomb"
    joint_limit_stiffness: Optional[float] = None
    joint_limit_damping: Optional[float] = None
    constraint_timeconst: float = 0.01
    enable_mimic: bool = True
    check_nan: bool = True
    contact_smoothing: float = 5e-6
    friction_smoothing: float = 1e-3
    friction_smoothing_accel: Optional[float] = 0.25
    max_mesh_contact_points: int = 32
    ignore_unsupported_pairs: bool = False
    specialize_kernels: Optional[bool] = None
    # Genesis's names (constraint_timeconst above: the joint-limit constraint's time constant, s). dt / gravity:
    # None takes SimOptions'; a value must agree with SimOptions' (one
    # scene steps every solver with one dt and one gravity: gs.Scene checks). The constraint solver's
    # settings (constraint_solver, iterations, tolerance, ls_iterations, ls_tolerance), the collision
    # pair budget (max_collision_pairs) and box_box_detection are accepted: genesis_lite's contact is a
    # penalty law solved with the dynamics, its contact pairs are sized from the scene at build, and
    # box-box contact is always its own (solvers/rigid/collision.py). batch_dofs_info /
    # batch_links_info / batch_joints_info: parameters are per environment in genesis_lite whatever they say.
    dt: Optional[float] = None
    gravity: Optional[Tuple[float, float, float]] = None
    constraint_solver: constraint_solver = constraint_solver.Newton
    iterations: int = 100
    tolerance: float = 1e-8
    ls_iterations: int = 50
    ls_tolerance: float = 1e-2
    max_collision_pairs: int = 300
    box_box_detection: bool = True
    batch_dofs_info: bool = False
    batch_links_info: bool = False
    batch_joints_info: bool = False
    use_contact_island: bool = False
    use_hibernation: bool = False

    def _validate(self):
        if self.dt is not None and not (isinstance(self.dt, (int, float)) and np.isfinite(self.dt) and self.dt > 0):
            self._err("dt", self.dt, "must be None (SimOptions' dt) or a positive number of seconds")
        _finite_vec(self, "gravity", 3)
        try:
            self.constraint_solver = constraint_solver(self.constraint_solver)
        except ValueError:
            self._err("constraint_solver", self.constraint_solver, "use gs.constraint_solver.CG or Newton")
        for name in ("iterations", "ls_iterations", "max_collision_pairs"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1):
                self._err(name, v, "must be a positive integer")
        for name in ("tolerance", "ls_tolerance"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                self._err(name, v, "must be a positive number")
        for name in ("box_box_detection", "batch_dofs_info", "batch_links_info", "batch_joints_info",
                     "use_contact_island", "use_hibernation", "enable_collision", "enable_joint_limit",
                     "enable_self_collision", "enable_adjacent_collision", "enable_neutral_collision"):
            if not isinstance(getattr(self, name), bool):
                self._err(name, getattr(self, name), "must be True or False")
        try:
            self.integrator = integrator(self.integrator)
        except ValueError:
            self._err("integrator", self.integrator,
                      "use gs.integrator.approximate_implicitfast, implicitfast, Euler or RK4")
        for name in ("contact_stiffness", "contact_damping", "joint_limit_stiffness", "joint_limit_damping"):
            v = getattr(self, name)
            if v is None and name != "contact_stiffness":
                continue
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0):
                self._err(name, v, "must be a finite number >= 0")
        for name in ("contact_smoothing", "friction_smoothing", "contact_damping_ratio", "constraint_timeconst",
                     "friction_smoothing_accel"):
            v = getattr(self, name)
            if name in ("contact_damping_ratio", "friction_smoothing_accel") and v is None:
                continue
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                self._err(name, v, "must be a finite number > 0")
        if self.contact_damping is not None and self.contact_damping_ratio is not None:
            self._err("contact_damping", self.contact_damping,
                      f"and contact_damping_ratio={self.contact_damping_ratio!r} both given: give one (a fixed "
                      "damper in N s/m, or a ratio of each contact's critical damping), or neither (critical)")
        if self.friction_load not in ("frictionless", "coulomb"):
            self._err("friction_load", self.friction_load, 'must be "coulomb" (the default) or "frictionless"')
        m = self.max_mesh_contact_points
        if not (isinstance(m, (int, np.integer)) and not isinstance(m, bool) and m >= 4):
            self._err("max_mesh_contact_points", m, "must be an integer >= 4")
        if self.specialize_kernels is not None and not isinstance(self.specialize_kernels, bool):
            self._err("specialize_kernels", self.specialize_kernels, "must be True, False or None (automatic)")


@dataclass
class MPMOptions(_Options):
    """The MPM solver's background grid: grid_density cells per metre between lower_bound and
    upper_bound (m, world frame), whose faces are walls; particle_size (m) is the spacing of the
    particles sampled in an entity (default 0.01 * 64 / grid_density, Genesis's). The 3 outermost cells
    of each face belong to the walls: particles stay inside [lower_bound + 3 dx, upper_bound - 3 dx]
    (dx = 1 / grid_density), as in Genesis. The walls are frictionless by default, as Genesis's domain
    boundary (which only stops the velocity into it); wall_friction > 0 gives them Coulomb friction of
    that coefficient (a floor that holds a sand pile without a rigid plane inside the domain), or three
    coefficients, for the faces normal to x, y and z ((0, 0, 0.5): a rough floor between smooth side
    walls). A rigid Plane at lower_bound lies below the walls and never touches the material, in Genesis
    as here."""

    grid_density: float = 64.0
    lower_bound: Tuple[float, float, float] = (-1.0, -1.0, 0.0)
    upper_bound: Tuple[float, float, float] = (1.0, 1.0, 1.0)
    particle_size: Optional[float] = None
    wall_friction: Union[float, Tuple[float, float, float]] = 0.0
    enable_CPIC: bool = False

    def _validate(self):
        d = self.grid_density
        if not (isinstance(d, (int, float)) and np.isfinite(d) and d > 0):
            self._err("grid_density", d, "must be a positive number of cells per metre")
        lo = np.asarray(self.lower_bound, dtype=float)
        hi = np.asarray(self.upper_bound, dtype=float)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            self._err("lower_bound/upper_bound", (self.lower_bound, self.upper_bound), "must be three finite numbers each (m)")
        if not np.all(hi - lo >= 8.0 / d):
            self._err("upper_bound", self.upper_bound, f"must exceed lower_bound {tuple(lo)} by at least 8 cells "
                      f"({8.0 / d:g} m) on every axis: 3 cells of wall on each side and room for particles")
        self.lower_bound, self.upper_bound = tuple(float(x) for x in lo), tuple(float(x) for x in hi)
        if self.particle_size is None:
            self.particle_size = 0.01 * 64.0 / float(d)
        elif not (isinstance(self.particle_size, (int, float)) and np.isfinite(self.particle_size) and self.particle_size > 0):
            self._err("particle_size", self.particle_size, "must be a positive number (m) or None")
        mu = self.wall_friction
        one = isinstance(mu, (int, float, np.integer, np.floating)) and not isinstance(mu, bool)
        three = (isinstance(mu, (tuple, list, np.ndarray)) and len(mu) == 3
                 and all(isinstance(m, (int, float, np.integer, np.floating)) and not isinstance(m, bool) for m in mu))
        if not ((one or three) and np.all(np.isfinite(np.asarray(mu, float))) and np.all(np.asarray(mu, float) >= 0)):
            self._err("wall_friction", mu, "must be a finite number >= 0, or three of them (the faces normal to x, y, z)")
        self.wall_friction = float(mu) if one else tuple(float(m) for m in mu)
        if self.enable_CPIC:
            self._err("enable_CPIC", self.enable_CPIC, "CPIC (thin rigid shells in MPM) is not implemented; leave it False")

    @property
    def dx(self) -> float:
        return 1.0 / float(self.grid_density)


@dataclass
class CouplerOptions(_Options):
    """Coupling between solvers (Genesis's name): rigid_mpm couples rigid bodies and MPM materials in
    both directions (rigid collision geoms are moving boundaries on the MPM grid, and the impulses the
    grid gives them come back as forces); mpm_reaction=False makes it one-way (the rigid bodies move
    the material but do not feel it). Friction and softness are per rigid material
    (gs.materials.Rigid coup_friction, coup_softness)."""

    rigid_mpm: bool = True
    mpm_reaction: bool = True

    def _validate(self):
        for name in ("rigid_mpm", "mpm_reaction"):
            if not isinstance(getattr(self, name), bool):
                self._err(name, getattr(self, name), "must be True or False")


@dataclass
class ViewerOptions(_Options):
    """Genesis's interactive viewer's options. genesis_lite is headless (no viewer): they are accepted
    and checked so that Genesis's scripts run, and nothing reads them; recordings come from cameras
    (scene.add_camera(res=, pos=, lookat=, fov=), Genesis's own defaults)."""

    res: Optional[Tuple[int, int]] = None
    refresh_rate: int = 60
    max_FPS: Optional[int] = 60
    camera_pos: Tuple[float, float, float] = (3.5, 0.5, 2.5)
    camera_lookat: Tuple[float, float, float] = (0.0, 0.0, 0.5)
    camera_up: Tuple[float, float, float] = (0.0, 0.0, 1.0)
    camera_fov: float = 40.0
    enable_interaction: bool = False
    run_in_thread: Optional[bool] = None

    def _validate(self):
        for name in ("camera_pos", "camera_lookat", "camera_up"):
            _finite_vec(self, name, 3)
        if not (isinstance(self.camera_fov, (int, float)) and 0 < self.camera_fov < 180):
            self._err("camera_fov", self.camera_fov, "must be a vertical field of view in degrees, in (0, 180)")
        if self.res is not None:
            r = tuple(self.res) if np.ndim(self.res) == 1 else ()
            if len(r) != 2 or not all(isinstance(x, (int, np.integer)) and x > 0 for x in r):
                self._err("res", self.res, "must be (width, height) in pixels, or None")
            self.res = tuple(int(x) for x in r)
        for name in ("refresh_rate", "max_FPS"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                self._err(name, v, "must be a positive number (or None for max_FPS)")


@dataclass
class VisOptions(_Options):
    """Genesis's visualisation options (its renderer's frames, shadows, reflections, lights, which envs
    to draw), accepted and checked so that Genesis's scripts run. genesis_lite's cameras are its own
    numpy rasteriser (genesis_lite/vis) and do not read them."""

    show_world_frame: bool = False
    world_frame_size: float = 1.0
    show_link_frame: bool = False
    link_frame_size: float = 0.2
    show_cameras: bool = False
    shadow: bool = True
    plane_reflection: bool = False
    env_separate_rigid: bool = False
    background_color: Tuple[float, float, float] = (0.04, 0.08, 0.12)
    ambient_light: Tuple[float, float, float] = (0.1, 0.1, 0.1)
    visualize_mpm_boundary: bool = False
    segmentation_level: str = "link"
    render_particle_as: str = "sphere"
    particle_size_scale: float = 1.0
    n_rendered_envs: Optional[int] = None
    rendered_envs_idx: Optional[Tuple[int, ...]] = None
    lights: Optional[list] = None

    def _validate(self):
        for name in ("background_color", "ambient_light"):
            _finite_vec(self, name, 3)
        if self.segmentation_level not in ("entity", "link", "geom"):
            self._err("segmentation_level", self.segmentation_level, "must be 'entity', 'link' or 'geom'")


@dataclass
class CoacdOptions(_Options):
    """CoACD's convex decomposition (Genesis's gs.options.CoacdOptions: its fields and its defaults, which are
    coarser and faster than CoACD's own: threshold 0.1, preprocess_resolution 30, resolution 1000,
    mcts_iterations 100 against 0.05, 50, 2000, 150). gs.morphs.Mesh / URDF / MJCF(coacd_options=) take one, or
    a dict of some of its fields (the rest Genesis's defaults). threshold is the concavity each part may keep
    (halving it about doubles the parts); the others go to coacd.run_coacd as they are."""

    threshold: float = 0.1
    max_convex_hull: int = -1
    preprocess_mode: str = "auto"
    preprocess_resolution: int = 30
    resolution: int = 1000
    mcts_nodes: int = 20
    mcts_iterations: int = 100
    mcts_max_depth: int = 3
    pca: bool = False
    merge: bool = True
    decimate: bool = False
    max_ch_vertex: int = 256
    extrude: bool = False
    extrude_margin: float = 0.1
    apx_mode: str = "ch"
    seed: int = 0

    def _validate(self):
        for name in ("threshold", "extrude_margin"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= 0:
                self._err(name, v, "must be a positive number")
        for name, lo in (("max_convex_hull", -1), ("preprocess_resolution", 1), ("resolution", 1), ("mcts_nodes", 1),
                         ("mcts_iterations", 1), ("mcts_max_depth", 1), ("max_ch_vertex", 4), ("seed", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                self._err(name, v, f"must be an integer >= {lo}")
        for name in ("pca", "merge", "decimate", "extrude"):
            if not isinstance(getattr(self, name), bool):
                self._err(name, getattr(self, name), "must be True or False")
        if self.preprocess_mode not in ("on", "off", "auto"):
            self._err("preprocess_mode", self.preprocess_mode, "must be 'on', 'off' or 'auto'")
        if self.apx_mode not in ("ch", "box"):
            self._err("apx_mode", self.apx_mode, "must be 'ch' or 'box'")

    def kwargs(self) -> dict:
        """coacd.run_coacd's keyword arguments."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def of(cls, value, owner: str) -> "CoacdOptions":
        """A morph's coacd_options as CoacdOptions: None gives Genesis's defaults, a dict overrides some of them."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, dict):
            names = [f.name for f in fields(cls)]
            unknown = sorted(str(k) for k in value if k not in names)
            if unknown:
                raise ValueError(f"{owner}(coacd_options=...): {unknown} are not CoACD options; the options are "
                                 f"{names} (gs.options.CoacdOptions)")
            return cls(**value)
        raise ValueError(f"{owner}(coacd_options={value!r}): give gs.options.CoacdOptions(...) or a dict of its "
                         "fields")


class _OutOfScopeOptions:
    """Options of a Genesis solver genesis_lite does not have (SPH, PBD, FEM, SF): accepted with any fields,
    so a script that sets them up runs its in-scope part; an entity made of that solver's material
    (gs.materials.SPH / PBD / FEM) is left out of the simulation with a warning (entities/out_of_scope.py)."""

    solver = ""

    def __init__(self, **kwargs):
        self.__dict__.update(kwargs)

    def __repr__(self):
        return f"gs.options.{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in self.__dict__.items())})"


class SPHOptions(_OutOfScopeOptions):
    solver = "SPH"


class PBDOptions(_OutOfScopeOptions):
    solver = "PBD"


class FEMOptions(_OutOfScopeOptions):
    solver = "FEM"


class SFOptions(_OutOfScopeOptions):
    solver = "SF"
