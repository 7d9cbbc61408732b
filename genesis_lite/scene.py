"""Scene: holds entities, decides which solvers exist, and advances them together."""
from __future__ import annotations

import logging
import os
import warnings
import weakref
from dataclasses import dataclass
from typing import List, Optional

import numpy as np
import torch

from . import materials as gmat
from . import morphs as gm
from . import surfaces as gs_surfaces
from .errors import GenesisException, GenesisWarning, ImportOrderWarning
from .nan_watch import NaNWatch
from .options import CouplerOptions, MPMOptions, RigidOptions, SimOptions, ViewerOptions, VisOptions
from .validation import validate_model
from solvers.rigid.schedule import Integrator, rk4_combine

logger = logging.getLogger("genesis_lite")
# envs from which a scene warns that torch was imported first (ImportOrderWarning): below it the simulator's
# kernels are short and the spinning threads' cost was not measurable (1 env: the same times)
IMPORT_ORDER_ENVS = 256
_import_order_warned = False


def _warn_import_order(n_envs):
    """Once a process, at the build of a scene of IMPORT_ORDER_ENVS or more envs: torch was imported before
    genesis_lite (OMP_WAIT_POLICY unset then) and runs more than one thread."""
    global _import_order_warned
    from . import TORCH_IMPORTED_FIRST

    if _import_order_warned or not TORCH_IMPORTED_FIRST or n_envs < IMPORT_ORDER_ENVS or torch.get_num_threads() < 2:
        return
    _import_order_warned = True
    warnings.warn(ImportOrderWarning(
        "torch was imported before genesis_lite, so its OpenMP threads keep spinning after each torch op "
        "(OMP_WAIT_POLICY was unset when torch loaded) on the cores this scene's kernels need: a 1,024-env "
        "Panda's forward with gradients took ~1.5x as long on 2 cores. Import genesis_lite before torch, or "
        "start Python with OMP_WAIT_POLICY=PASSIVE (or ACTIVE, to keep torch's threads spinning and silence "
        "this)."), stacklevel=3)


class SolverState(tuple):
    """One solver's state tensors (a tuple, as scene.reset takes them back), also by Genesis's names: an MPM
    solver's pos, vel, C, F ((n_envs, n_particles, ...)) and active ((n_envs, n_particles) bool: the particles
    in the simulation, all but an emitter's not yet emitted); a rigid solver's qpos and dofs_vel."""

    def __new__(cls, tensors, names=(), **extra):  # (names default: copy and pickle rebuild from the tuple alone)
        obj = super().__new__(cls, tensors)
        obj._names = tuple(names)
        obj.__dict__.update(extra)
        return obj

    def __getattr__(self, k):
        names = self.__dict__.get("_names", ())
        if k in names:
            return self[names.index(k)]
        raise AttributeError(f"a solver state has {', '.join(names + tuple(self.__dict__.keys() - {'_names'}))}, "
                             f"not {k!r}")


@dataclass
class SimState:
    """A snapshot of the scene's state, for scene.reset(state): `solvers` holds each solver's state
    tensors (SolverState); `qpos`/`qvel` are the rigid solver's (None without rigid entities). Detached
    copies, except in a scene built with requires_grad=True, where they are in torch's graph like every
    getter's value (a loss on them has gradients, as in Genesis); scene.reset(state) starts from their values."""

    solvers: tuple
    step: int
    qpos: Optional[torch.Tensor] = None
    qvel: Optional[torch.Tensor] = None
    emitted: tuple = ()  # per emitter, how many of its particles had been emitted
    genesis_order: tuple = ()  # indices into `solvers` in the order of scene.solvers (rigid, then MPM)

    @property
    def solvers_state(self):
        """Genesis's name: the solvers' states in the order of scene.solvers (the rigid solver's, then the
        MPM solver's), so that solvers_state[scene.solvers.index(scene.mpm_solver)] is the MPM state."""
        order = self.genesis_order or range(len(self.solvers))
        return [self.solvers[i] for i in order]


class Scene:
    """A simulated world: add entities, build(), then step(). Options are validated dataclasses from
    gs.options; `requires_grad=True` in SimOptions makes every getter part of torch's graph."""

    def __init__(self, sim_options: Optional[SimOptions] = None, rigid_options: Optional[RigidOptions] = None,
                 mpm_options: Optional[MPMOptions] = None, coupler_options: Optional[CouplerOptions] = None,
                 viewer_options=None, show_viewer: bool = False, **kwargs):
        import genesis_lite as gs

        gs._assert_initialized()
        self.sim_options = sim_options if sim_options is not None else SimOptions()
        self.rigid_options = rigid_options if rigid_options is not None else RigidOptions()
        if not isinstance(self.sim_options, SimOptions):
            raise TypeError(f"sim_options must be gs.options.SimOptions, got {type(self.sim_options).__name__}")
        if not isinstance(self.rigid_options, RigidOptions):
            raise TypeError(f"rigid_options must be gs.options.RigidOptions, got {type(self.rigid_options).__name__}")
        if mpm_options is not None and not isinstance(mpm_options, MPMOptions):
            raise TypeError(f"mpm_options must be gs.options.MPMOptions, got {type(mpm_options).__name__}")
        self._mpm_options_given = mpm_options is not None
        self.mpm_options = mpm_options if mpm_options is not None else MPMOptions()
        if coupler_options is not None and not isinstance(coupler_options, CouplerOptions):
            raise TypeError(f"coupler_options must be gs.options.CouplerOptions, got {type(coupler_options).__name__}")
        self.coupler_options = coupler_options if coupler_options is not None else CouplerOptions()
        # Genesis's options of solvers genesis_lite does not have: accepted (their entities are refused)
        unknown = set(kwargs) - {"vis_options", "renderer", "profiling_options", "show_FPS", "sph_options",
                                 "pbd_options", "fem_options", "sf_options", "tool_options", "avatar_options"}
        if unknown:
            raise TypeError(f"gs.Scene got unexpected arguments {sorted(unknown)}")
        # Genesis's viewer and renderer options: checked, kept, not read (headless; see their docstrings)
        for name, value, cls in (("viewer_options", viewer_options, ViewerOptions),
                                 ("vis_options", kwargs.get("vis_options"), VisOptions)):
            if value is not None and not isinstance(value, cls):
                raise TypeError(f"{name} must be gs.options.{cls.__name__}, got {type(value).__name__}")
        self.viewer_options = viewer_options if viewer_options is not None else ViewerOptions()
        self.vis_options = kwargs.get("vis_options") or VisOptions()
        self._reconcile_rigid_options(sim_options is not None)
        self.entities: List = []
        self.rigid_entities: List = []
        self.mpm_entities: List = []
        self._emitters: List = []  # the simulated ones (add_emitter's stand-ins for SPH / PBD: _all_emitters)
        self._all_emitters: List = []
        self._cameras: List = []
        self._built = False
        self._rigid = None
        self._mpm = None
        self._coupler = None
        self._simulator = None
        self.n_envs = 0

    @property
    def entity_names(self):
        """The entities' names, in the order they were added (a tuple, as Genesis's `scene.entity_names`)."""
        return tuple(e.name for e in self.entities)

    def get_entity(self, name=None, *, uid=None):
        """The entity called `name`, or the one whose uid is `uid`, as Genesis's `scene.get_entity`: `uid`
        is the short string of `entity.uid.short()` (Genesis's), the uid's full string, or the gs.UID itself.
        Give one of the two; an entity that is not there raises, listing the scene's names."""
        from .utils.uid import UID

        if (name is None) == (uid is None):
            raise ValueError("scene.get_entity: give name= or uid=, one of them")
        if name is not None:
            if not isinstance(name, str):
                raise TypeError(f"scene.get_entity(name={name!r}): a name is a string (see scene.entity_names)")
            found = [e for e in self.entities if e.name == name]
            what = f"name {name!r}"
        else:
            if isinstance(uid, UID):
                uid = str(uid)
            if not isinstance(uid, str):
                raise TypeError(f"scene.get_entity(uid={uid!r}): a uid is a string, e.g. entity.uid.short(); the "
                                "entity at index i in the order of add_entity is scene.entities[i]")
            key = uid.replace("-", "")
            found = [e for e in self.entities if e.uid.match(key, short_only=len(key) == 7)]
            what = f"uid {uid!r}"
        if found:
            return found[0]
        raise GenesisException(f"scene.get_entity: no entity with {what}; the scene has "
                               f"{[f'{e.name} (uid {e.uid.short()})' for e in self.entities]}")

    def _reconcile_rigid_options(self, sim_given):
        """RigidOptions(dt=, gravity=) are Genesis's per-solver copies of SimOptions': one scene steps
        every solver with one dt and one gravity. Given without sim_options they set the scene's;
        given with it they must agree."""
        ro, so = self.rigid_options, self.sim_options
        for name in ("dt", "gravity"):
            v = getattr(ro, name)
            if v is None:
                continue
            if not sim_given:
                self.sim_options = so = so.copy(**{name: v})
            elif not np.allclose(np.atleast_1d(v), np.atleast_1d(getattr(so, name)), rtol=0, atol=0):
                raise GenesisException(
                    f"RigidOptions({name}={v!r}) differs from SimOptions({name}={getattr(so, name)!r}): genesis_lite "
                    f"steps every solver of a scene with one {name}. Set it in SimOptions only (or give both the "
                    "same value).")

    # ---------------------------------------------------------------- construction
    @property
    def is_built(self):
        return self._built

    @property
    def dt(self):
        return self.sim_options.dt

    @property
    def t(self):
        """Steps taken since the last reset."""
        return self._simulator.step_count if self._simulator is not None else 0

    @property
    def rigid_solver(self):
        return self._rigid.solver if self._rigid is not None else None

    @property
    def mpm_solver(self):
        return self._mpm.solver if self._mpm is not None else None

    @property
    def solvers(self):
        """The solvers this scene built (Genesis's scene.solvers): the rigid and/or the MPM solver."""
        return [x for x in (self.rigid_solver, self.mpm_solver) if x is not None]

    @property
    def sim(self):
        """Genesis's scene.sim: the scene's solvers (rigid_solver, mpm_solver, solvers), dt and substeps."""
        return _SimView(self)

    def add_entity(self, morph, material=None, surface=None, visualize_contact=False, vis_mode=None, name=None):
        """Add an entity described by `morph` (gs.morphs.*) made of `material`: gs.materials.Rigid (the
        default) makes a rigid body or robot, a gs.materials.MPM.* material fills the morph's volume
        with MPM particles, gs.materials.Tool makes a body that moves as it is told and pushes MPM
        material (entities/tool_entity.py). vis_mode (Genesis's: "visual", "collision", "particle", ...)
        is kept as the entity's `vis_mode` for the cameras."""
        from .entities.rigid_entity import RigidEntity
        from .entities.tool_entity import ToolEntity, make_tool_model
        from .loaders import load_morph
        from .utils.uid import UID

        if self._built:
            raise GenesisException("scene.add_entity() after scene.build(): add every entity before building")
        if not isinstance(morph, gm.Morph):
            raise TypeError(f"add_entity expects a gs.morphs.* instance, got {type(morph).__name__}")
        material = material if material is not None else gmat.Rigid()
        if not isinstance(material, (gmat.Rigid, gmat.MPM.Base, gmat.Tool, gmat._OutOfScopeMaterial)):
            raise TypeError(f"add_entity: material must be gs.materials.Rigid, gs.materials.MPM.* or "
                            f"gs.materials.Tool, got {type(material).__name__}")
        if vis_mode is not None and not isinstance(vis_mode, str):
            raise TypeError(f"add_entity(vis_mode={vis_mode!r}): a string (Genesis's 'visual', 'collision', 'particle', ...)")
        if surface is not None and not isinstance(surface, gs_surfaces.Surface):
            raise TypeError(f"add_entity: surface must be a gs.surfaces.* instance, got {type(surface).__name__}")
        taken = set(self.entity_names)
        if name is None:
            stem = os.path.splitext(os.path.basename(morph.file))[0] if isinstance(morph, gm.FileMorph) else type(morph).__name__.lower()
            k = len(self.entities)
            while f"{stem}_{k}" in taken:  # (a name the user gave an earlier entity)
                k += 1
            name = f"{stem}_{k}"
        elif not isinstance(name, str) or not name:
            raise TypeError(f"scene.add_entity(name={name!r}): a name is a non-empty string (or None for one made "
                            "from the morph)")
        elif name in taken:
            raise GenesisException(f"scene.add_entity(name={name!r}): the scene already has an entity of that name "
                                   "(scene.get_entity(name=) finds one entity per name): give another name")
        if isinstance(material, gmat._OutOfScopeMaterial):
            return self._add_out_of_scope("scene.add_entity", morph, material, name, surface, vis_mode)
        if isinstance(material, gmat.MPM.Base):
            ent = self._add_mpm_entity(morph, material, name)
        else:
            tool = material if isinstance(material, gmat.Tool) else None
            if tool is not None:
                material = tool.rigid()  # what the rigid solver and the coupler read (entity.tool_material: the Tool)
            model = load_morph(morph, material, name)
            if tool is not None:
                model = make_tool_model(model, name)
            model.validate()
            validate_model(model)
            ent = (ToolEntity if tool is not None else RigidEntity)(self, len(self.entities), model, morph, material)
            ent.tool_material = tool
            ent._solver_idx = len(self.rigid_entities)
            self.rigid_entities.append(ent)
        ent.surface = surface  # read by cameras (colour, vis_mode)
        ent.vis_mode = vis_mode
        ent._uid = UID.unique({e.uid.short() for e in self.entities})
        self.entities.append(ent)
        return ent

    def _add_out_of_scope(self, what, morph, material, name, surface, vis_mode=None):
        """An entity of an SPH / PBD / FEM material: kept in scene.entities (Genesis's indices, names and
        uids), left out of the simulation with a warning (entities/out_of_scope.py)."""
        from .entities.out_of_scope import OutOfScopeEntity, warn_left_out
        from .utils.uid import UID

        warn_left_out(what, material, name)
        ent = OutOfScopeEntity(self, len(self.entities), morph, material, name,
                               UID.unique({e.uid.short() for e in self.entities}), what)
        ent.surface, ent.vis_mode = surface, vis_mode
        self.entities.append(ent)
        return ent

    def _add_mpm_entity(self, morph, material, name):
        from .entities.mpm_entity import MPMEntity
        from .loaders.particles import sample_particles

        particles, vol = sample_particles(morph, self.mpm_options.particle_size, name)
        ent = MPMEntity(self, len(self.entities), morph, material, name, particles, vol)
        self.mpm_entities.append(ent)
        return ent

    def add_emitter(self, material, max_particles=20000, surface=None, name=None):
        """A source of MPM particles (Genesis's scene.add_emitter): `max_particles` particles of
        `material` (a gs.materials.MPM.* material) that take no part in the simulation until
        `emitter.emit(...)` / `emit_omni(...)` sends them out, recycled from the first once used up
        (genesis_lite/entities/emitter.py). surface: gs.surfaces.*, default Default(color=(0.6, 0.8, 1.0,
        1.0)) drawn as particles. Not available with SimOptions(requires_grad=True), as in Genesis."""
        from .entities.emitter import NOWHERE, Emitter
        from .entities.mpm_entity import MPMEntity
        from .utils.uid import UID

        if self._built:
            raise GenesisException("scene.add_emitter() after scene.build(): add emitters before building")
        if self.sim_options.requires_grad:
            raise GenesisException(
                "scene.add_emitter: emitters are not differentiable (as in Genesis, which refuses them in "
                "differentiable mode): emission changes which particles exist between steps, outside the step's "
                "gradient. Build this scene with SimOptions(requires_grad=False), or give the material its initial "
                "shape with scene.add_entity(morph, material=gs.materials.MPM.*) instead.")
        if not isinstance(material, (gmat.MPM.Base, gmat._OutOfScopeMaterial)):
            raise TypeError(f"scene.add_emitter: material must be a gs.materials.MPM.* material (Liquid, Sand, "
                            f"Elastic, ElastoPlastic), got {type(material).__name__}")
        if not (isinstance(max_particles, (int, np.integer)) and not isinstance(max_particles, bool)
                and max_particles >= 1):
            raise GenesisException(f"scene.add_emitter(max_particles={max_particles!r}): must be an integer >= 1 "
                                   "(the most particles alive at once; they are recycled after that)")
        if surface is None:
            surface = gs_surfaces.Default(color=(0.6, 0.8, 1.0, 1.0))
        if not isinstance(surface, gs_surfaces.Surface):
            raise TypeError(f"scene.add_emitter: surface must be a gs.surfaces.* instance, got {type(surface).__name__}")
        if surface.vis_mode is None:
            surface.vis_mode = "particle"
        if surface.vis_mode == "visual":
            raise GenesisException("scene.add_emitter: surface.vis_mode='visual' is not supported for emitters (they "
                                   "have no mesh); use 'particle'")
        taken = set(self.entity_names)
        if name is None:
            k = len(self.entities)
            while f"emitter_{k}" in taken:
                k += 1
            name = f"emitter_{k}"
        elif not isinstance(name, str) or not name or name in taken:
            raise GenesisException(f"scene.add_emitter(name={name!r}): give a new non-empty name (or None)")
        if isinstance(material, gmat._OutOfScopeMaterial):
            from .entities.out_of_scope import OutOfScopeEmitter

            emitter = OutOfScopeEmitter(self._add_out_of_scope("scene.add_emitter", None, material, name, surface),
                                        max_particles)
            self._all_emitters.append(emitter)
            return emitter
        n = int(max_particles)
        ent = MPMEntity(self, len(self.entities), None, material, name, np.tile(np.asarray(NOWHERE), (n, 1)),
                        float(self.mpm_options.particle_size) ** 3)  # Genesis's particle volume: p_size^3
        ent.is_emitter = True
        ent._vis_radius = 0.5 * float(self.mpm_options.particle_size)  # cameras (vis/drawables.py)
        ent.surface = surface
        ent._uid = UID.unique({e.uid.short() for e in self.entities})
        emitter = Emitter(self, ent, n)
        self.entities.append(ent)
        self.mpm_entities.append(ent)
        self._emitters.append(emitter)
        self._all_emitters.append(emitter)
        return emitter

    @property
    def emitters(self):
        """The scene's emitters (Genesis's scene.emitters), in the order they were added."""
        return list(self._all_emitters)

    def add_camera(self, res=(320, 320), pos=(0.5, 2.5, 3.5), lookat=(0.5, 0.5, 0.5), up=(0.0, 0.0, 1.0), fov=30,
                   GUI=False, **kwargs):
        """A headless camera (genesis_lite.vis.Camera) for render() and start/stop_recording(), before
        or after build(). res = (width, height) px, pos / lookat / up in metres (world), fov the
        vertical field of view in degrees; near, far (m) and env_idx as keywords."""
        from .vis.camera import Camera

        cam = Camera(self, len(self._cameras), res=res, pos=pos, lookat=lookat, up=up, fov=fov, GUI=GUI, **kwargs)
        self._cameras.append(cam)
        return cam

    def build(self, n_envs: int = 0, env_spacing=None, **kwargs):
        """Allocate the solvers' fields for `n_envs` parallel environments (0: unbatched) and compile.
        A solver is built only when the scene has entities for it."""
        from .simulator import Simulator

        if self._built:
            raise GenesisException("scene.build() called twice: a scene is built once; create a new gs.Scene")
        if not (isinstance(n_envs, (int, np.integer)) and n_envs >= 0):
            raise ValueError(f"scene.build(n_envs={n_envs!r}): n_envs must be an integer >= 0")
        self.n_envs = int(n_envs)
        _warn_import_order(self.n_envs)
        coupled = bool(self.rigid_entities and self.mpm_entities and self.coupler_options.rigid_mpm)
        if self.rigid_entities or not self.mpm_entities:
            from .bridges.rigid import RigidSim

            ls = qs = ds = 0
            for e in self.rigid_entities:
                e._on_build(ls, qs, ds)
                ls, qs, ds = ls + e.n_links, qs + e.n_qs, ds + e.n_dofs
            self._rigid = RigidSim(self, [e.model for e in self.rigid_entities], self.n_envs, self.sim_options,
                                   self.rigid_options, external_wrench=coupled)
        if self.mpm_entities:
            self._build_mpm()
            if coupled:
                from .bridges.coupler import CouplerBridge

                self._coupler = CouplerBridge.create(self.rigid_entities, self._rigid, self._mpm, self.rigid_options,
                                                     self.mpm_options, self.coupler_options)
            elif self.rigid_entities:
                logger.info("scene: rigid and MPM entities are simulated side by side but do not interact "
                            "(CouplerOptions(rigid_mpm=False))")
        elif self._mpm_options_given:  # Genesis takes them (water_wheel passes them on its SPH path too)
            warnings.warn("scene: mpm_options were given but the scene has no MPM entity, so they are unused (an "
                          "entity made of a gs.materials.MPM.* material uses them)", GenesisWarning, stacklevel=2)
        self._simulator = Simulator(self._rigid, self._mpm, self._coupler, self.sim_options)
        self._nan = NaNWatch(self, self.sim_options.nan_policy)
        self._simulator.nan_watch = self._nan
        if self._rigid is not None:
            from .entities.external_api import RigidSolverAPI

            # Genesis's names on the rigid solver: scene.rigid_solver.get_error_envs_mask() (held weakly: no
            # cycle), apply_links_external_force/torque and the link getters (entities/external_api.py)
            self._rigid.solver.get_error_envs_mask = _WeakCall(self, "get_error_envs_mask")
            self._rigid_api = RigidSolverAPI(self)
            for name in RigidSolverAPI.METHODS:
                setattr(self._rigid.solver, name, getattr(self._rigid_api, name))
        self._built = True
        if self._rigid is not None:
            self._rigid.after_build(self.rigid_entities)
        self._init_state = self.get_state()

    def _build_mpm(self):
        from .bridges.mpm import MPMSim, check_time_step, domain_inside

        opts = self.mpm_options
        lo, hi = domain_inside(opts)
        p = 0
        # emitters' particles after every other entity's: until emitted they lie beyond the solver's count
        self.mpm_entities = [e for e in self.mpm_entities if not e.is_emitter] + \
                            [e for e in self.mpm_entities if e.is_emitter]
        for e in self.mpm_entities:
            if e.is_emitter:
                e._on_build(p)
                p += e.n_particles
                continue
            below, above = e._x0.min(0) < lo, e._x0.max(0) > hi
            if below.any() or above.any():
                axis = "xyz"[int(np.argmax(below | above))]
                raise GenesisException(
                    f"MPM entity '{e.name}': its particles span {e._x0.min(0).round(4).tolist()} .. "
                    f"{e._x0.max(0).round(4).tolist()} m, partly outside the MPM domain along {axis} (particles must "
                    f"start within {lo.round(4).tolist()} .. {hi.round(4).tolist()} m: MPMOptions lower_bound/upper_bound "
                    "less 3 cells of wall). Move the entity or enlarge the domain.")
            e._on_build(p)
            p += e.n_particles
        check_time_step(self.mpm_entities, opts, self.sim_options)
        self._mpm = MPMSim(self, self.mpm_entities, self.n_envs, self.sim_options, opts)
        return self._mpm

    # ---------------------------------------------------------------- running
    def _link_owner(self, link_idx, what):
        """(rigid entity, local index) of the link with scene-wide index link_idx (RigidLink.idx)."""
        n = sum(e.n_links for e in self.rigid_entities)
        if isinstance(link_idx, bool) or not isinstance(link_idx, (int, np.integer)) or not 0 <= link_idx < n:
            raise GenesisException(f"{what}: link_idx must be a link's scene-wide index (entity.links[k].idx), an "
                                   f"int in [0, {n}), got {link_idx!r}")
        for e in self.rigid_entities:
            if e.link_start <= link_idx < e.link_end:
                return e, int(link_idx) - e.link_start

    def _sim(self, what):
        if not self._built:
            raise GenesisException(f"scene.{what}() before scene.build(): call scene.build() first")
        return self._simulator

    def step(self):
        """Advance every solver by sim_options.dt, then check every env's state for NaN / inf
        (SimOptions.nan_policy: raise, or record the failed envs and go on)."""
        sim = self._sim("step")
        sim.step()
        self._nan.after_step(sim.step_count)
        if self._coupler is not None:
            self._coupler.check(sim.step_count, self.n_envs > 0)

    def get_error_envs_mask(self):
        """Bool tensor (n_envs,) (a 0-d one when built with n_envs=0): True for the envs whose state
        became NaN or infinite since build or since they were last reset (SimOptions.nan_policy='mask'
        lets the others go on). Restore them with scene.reset(envs_idx=mask)."""
        sim = self._sim("get_error_envs_mask")
        m = self._nan.mask(sim.step_count)
        import genesis_lite as gs

        m = m.to(gs.device)
        return m if self.n_envs > 0 else m[0]

    def get_state(self) -> SimState:
        """The current state of every solver (detached copies) and the step count."""
        sim = self._sim("get_state")
        keep = (lambda x: x.clone()) if sim.requires_grad else (lambda x: x.detach().clone())  # noqa: E731
        states = []
        for b in sim.bridges:
            xs = tuple(keep(x) for x in b.state())
            if b is self._mpm:
                states.append(SolverState(xs, ("pos", "vel", "C", "F"), active=self._mpm.active_rows(xs[0].shape[0])))
            else:
                states.append(SolverState(xs, ("qpos", "dofs_vel")))
        q, v = self._rigid.get_state() if self._rigid is not None else (None, None)
        q, v = (keep(q), keep(v)) if q is not None else (None, None)
        order = tuple(i for kind in (self._rigid, self._mpm) for i, b in enumerate(sim.bridges) if b is kind)
        return SimState(tuple(states), sim.step_count, q, v, tuple(em.high_water for em in self._emitters), order)

    def reset(self, state: Optional[SimState] = None, envs_idx=None):
        """Return to the state right after build() (or to `state` from get_state()). Controls and
        external forces are cleared; parameters set with setters are kept. Starts a new rollout for
        gradients.

        envs_idx (env indices, or a bool mask of n_envs such as get_error_envs_mask()): restore the
        state (positions, velocities; MPM particles' x, v, C, F) of just those envs and forget their
        NaN record; every other env, the controls, the step count and the rollout go on untouched."""
        sim = self._sim("reset")
        state = state if state is not None else self._init_state
        if not isinstance(state, SimState):
            raise TypeError("scene.reset(state): state must come from scene.get_state()")
        if envs_idx is not None:
            self._reset_envs(state, envs_idx)
            return
        for em, n in zip(self._emitters, state.emitted):
            # the particles emitted when the state was taken, as Genesis restores their `active` flags; and
            # emission starts again from the first particle (Genesis's scene.reset calls emitter.reset())
            self._mpm.activate(em.entity, n)
            em.reset()
        sim.new_rollout([tuple(x.detach().clone() for x in s) for s in state.solvers])
        self._nan.clear(np.ones(self._nan.B, dtype=bool))
        if self._coupler is not None:
            self._coupler.reset()

    def _reset_envs(self, state, envs_idx):
        if self.n_envs == 0:
            raise GenesisException("scene.reset(envs_idx=...): the scene was built without n_envs; call "
                                   "scene.reset() (or build with scene.build(n_envs=N))")
        t = torch.as_tensor(envs_idx.detach().cpu() if isinstance(envs_idx, torch.Tensor) else envs_idx)
        if t.dtype == torch.bool:
            if t.shape != (self.n_envs,):
                raise GenesisException(f"scene.reset(envs_idx=mask): a bool mask must have shape ({self.n_envs},) "
                                       f"(one entry per env), got {tuple(t.shape)}")
            envs = torch.nonzero(t).reshape(-1)
        else:
            envs = _SceneParams(self)._envs(t) if t.numel() else t.reshape(-1).long()
        mask = np.zeros(self.n_envs, dtype=bool)
        mask[envs.cpu().numpy()] = True
        if not mask.any():
            return
        for em, n in zip(self._emitters, state.emitted):
            if em.high_water != n:
                raise GenesisException(
                    f"scene.reset(envs_idx=...): emitter '{em.entity.name}' has {em.high_water} particles emitted now "
                    f"and had {n} in this state; emission is the same in every env, so some envs alone cannot go "
                    "back to another emission. Call scene.reset(state) for all envs, or reset to a state taken with "
                    "the emission as it is now.")
        sim = self._simulator
        rows = torch.as_tensor(mask, device=envs.device)
        for b, saved in zip(sim.bridges, state.solvers):
            now = b.state()
            new = []
            for x, x0 in zip(now, saved):
                keep = rows.to(x.device).reshape((-1,) + (1,) * (x.dim() - 1))
                new.append(torch.where(keep, x0.detach().to(x.dtype), x))
            b.set_state(*new)
        self._nan.clear(mask)
        if self._rigid is not None:
            self._rigid.clear_applied(mask)
        if self._coupler is not None:
            self._coupler.reset()

    def set_gravity(self, gravity, envs_idx=None):
        """Gravity (m/s^2, world frame) of every solver; differentiable."""
        self._sim("set_gravity")
        ent = _SceneParams(self)
        envs = ent._envs(envs_idx)
        vals = ent._values(gravity, envs, 3, "gravity")
        if self._rigid is not None:
            self._rigid.set_param("gravity", vals, envs, torch.arange(3, device=vals.device))
        if self._mpm is not None:
            self._mpm.set_param("gravity", vals, envs, torch.arange(3, device=vals.device))

    # ---------------------------------------------------------------- solver-wide reads used by entities
    def _mass_matrix(self):
        sim = self._rigid
        sim._upload()
        s = sim.solver
        s.scratch_overwritten()
        s.mass_matrix(0)
        M = sim.read_mass_matrix()
        low = torch.tril(M)
        return low + low.transpose(-1, -2) - torch.diag_embed(torch.diagonal(M, dim1=-2, dim2=-1))

    def _dofs_acc(self):
        s = self._rigid.solver
        a = self._rigid.read_qacc()
        if s.integrator == Integrator.RK4:
            return rk4_combine(a[-4], a[-3], a[-2], a[-1])
        return a[-1]

    def _dofs_control_force(self):
        return self._rigid.read_dof_tau()

    def _dofs_force(self):
        return self._rigid.read_dof_qf()


class _SimView:
    """What Genesis scripts read from scene.sim; the stepping itself stays in simulator.py."""

    def __init__(self, scene):
        self._scene = scene

    rigid_solver = property(lambda self: self._scene.rigid_solver)
    mpm_solver = property(lambda self: self._scene.mpm_solver)
    solvers = property(lambda self: self._scene.solvers)
    dt = property(lambda self: self._scene.sim_options.dt)
    substeps = property(lambda self: self._scene.sim_options.substeps)
    substep_dt = property(lambda self: self._scene.sim_options.dt / self._scene.sim_options.substeps)


class _SceneParams:
    """Index/value validation for scene-level setters, sharing RigidEntity's rules."""

    def __init__(self, scene):
        from .entities.rigid_entity import RigidEntity

        self._scene = scene
        self.name = "scene"
        self._label = "scene"
        self._envs = RigidEntity._envs.__get__(self)
        self._values = RigidEntity._values.__get__(self)
        self._idx = RigidEntity._idx.__get__(self)

    @property
    def _device(self):
        import genesis_lite as gs

        return gs.device


class _WeakCall:
    """obj.name(...) through a weak reference to obj (a method handed to an object obj owns)."""

    def __init__(self, obj, name):
        self._ref, self._name = weakref.ref(obj), name

    def __call__(self, *args, **kwargs):
        obj = self._ref()
        if obj is None:
            raise GenesisException("this solver's scene no longer exists")
        return getattr(obj, self._name)(*args, **kwargs)
