"""Entities of Genesis's solvers that genesis_lite does not have (SPH, PBD, FEM).

A Genesis script that adds one (water_wheel's default SPH liquid) runs on: `scene.add_entity` /
`scene.add_emitter` warn that the entity is left out of the simulation and return a stand-in that keeps the
script's entity indices, names and uids Genesis's. The stand-in has no state: reading or setting anything on
it raises, naming it and why (`NotSimulatedError`, also an AttributeError so that `hasattr` probes say no);
its emitter emits nothing.
"""
from __future__ import annotations

import warnings

from ..errors import GenesisException, GenesisWarning


class NotSimulatedError(GenesisException, AttributeError):
    """What is asked of an entity that genesis_lite left out of the simulation (an out-of-scope solver's)."""


class OutOfScopeEntity:
    """An entity made of a gs.materials.SPH / PBD / FEM material: in scene.entities, not simulated."""

    def __init__(self, scene, idx, morph, material, name, uid, added_by):
        self._scene, self.idx, self.morph, self.material, self.name, self._uid = scene, idx, morph, material, name, uid
        self._added_by = added_by  # "scene.add_entity" or "scene.add_emitter"
        self.surface = None
        self.vis_mode = None

    @property
    def uid(self):
        return self._uid

    @property
    def solver_name(self):
        return self.material.solver

    @property
    def is_built(self):
        return self._scene._built

    def __getattr__(self, attr):
        if attr.startswith("__") or "material" not in self.__dict__:  # (dunders; an object not yet initialised)
            raise AttributeError(attr)
        raise NotSimulatedError(
            f"entity '{self.name}' ({self.material.describe()}) has no '{attr}': genesis_lite left it out of the "
            f"simulation (Genesis's {self.material.solver} solver is out of its scope; a warning said so at "
            f"{self._added_by}). {self.material.instead}")

    def __repr__(self):
        return f"<OutOfScopeEntity '{self.name}': {self.material.describe()}, not simulated>"


class OutOfScopeEmitter:
    """scene.add_emitter's stand-in for an out-of-scope material: emit() and emit_omni() add nothing."""

    def __init__(self, entity, max_particles):
        self._entity = entity
        self._max_particles = int(max_particles)

    @property
    def entity(self):
        return self._entity

    @property
    def uid(self):
        return self._entity.uid

    @property
    def max_particles(self):
        return self._max_particles

    @property
    def next_particle(self):
        return 0

    def emit(self, *args, **kwargs):
        """Adds nothing (the material's solver is not simulated; add_emitter warned)."""
        self._check_built()

    def emit_omni(self, *args, **kwargs):
        """Adds nothing (the material's solver is not simulated; add_emitter warned)."""
        self._check_built()

    def reset(self):
        pass

    def _check_built(self):
        if not self._entity._scene._built:
            raise GenesisException(f"emitter '{self._entity.name}': emit() before scene.build(): build the scene first")


def warn_left_out(what, material, name):
    """The warning add_entity / add_emitter give for an out-of-scope material."""
    warnings.warn(
        f"{what}: {material.describe()} needs Genesis's {material.solver} solver, which is out of genesis_lite's scope "
        f"(rigid bodies and MPM only): '{name}' is left out of the simulation (nothing of it is simulated, drawn or "
        "coupled; reading its state raises), and the rest of the scene runs. " + material.instead,
        GenesisWarning, stacklevel=4)
