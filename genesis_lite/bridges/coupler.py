"""The scene's side of the rigid-MPM coupler (solvers/coupling.py): which rigid geoms are boundaries
for the MPM material, with what friction and softness, and the coupling stage of the step
(simulator.py). The coupler has no state, controls or parameters of its own: its gradients flow
through the MPM and rigid bridges' inputs.
"""
from __future__ import annotations

import logging
import weakref

import numpy as np

from ..errors import GenesisException

logger = logging.getLogger("genesis_lite")


class CouplerBridge:
    """Rigid collision geoms of the entities whose material couples (`needs_coup`) as moving boundaries
    of the MPM grid, and (with CouplerOptions(mpm_reaction=True)) the material's reaction on their links.
    Made by `create`, which returns None when no geom couples."""

    def __init__(self, coupler, names=(), floor=0.0):
        self.coupler = coupler
        self.names = list(names)  # entity name of each coupled geom
        self.floor = floor  # the MPM domain's lower z

    @classmethod
    def create(cls, rigid_entities, rigid, mpm, rigid_options, mpm_options, coupler_options):
        """rigid, mpm: the scene's RigidSim and MPMSim bridges (the rigid one built with external wrenches)."""
        from solvers.coupling import POOL
        from solvers.rigid.collision import build_geoms
        from solvers.rigid.port import RigidPort

        geoms = build_geoms([e.model for e in rigid_entities], int(rigid_options.max_mesh_contact_points))
        keep = np.array([rigid_entities[int(i)].material.needs_coup for i in geoms.entity], dtype=bool)
        for e in rigid_entities:
            if e.material.needs_coup and e.n_geoms == 0:
                logger.warning(f"scene: rigid entity '{e.name}' has no collision geometry, so MPM material passes "
                               "through it (give its links <collision> shapes to couple it)")
        idx = np.nonzero(keep)[0]
        if len(idx) == 0:
            logger.info("scene: no rigid entity has collision geometry to couple with the MPM material")
            return None
        dx = mpm_options.dx
        mats = [rigid_entities[int(geoms.entity[i])].material for i in idx]
        softness = min(m.coup_softness if m.coup_softness is not None else 0.5 * dx for m in mats)
        softness = max(softness, 1e-6 * dx)  # 0 (Genesis's hard boundary): a band far below the grid's resolution
        # a coupler of the scene's class from the pool (its kernels compiled by an earlier scene, if any),
        # given back when this bridge dies
        # a tool (gs.materials.Tool) moves as it is told: the material does not push it back
        react = [getattr(rigid_entities[int(geoms.entity[i])], "tool_material", None) is None for i in idx]
        coupler, reused = POOL.acquire(mpm.solver, RigidPort(rigid.solver), geoms, idx, [m.coup_friction for m in mats],
                                       softness, coupler_options.mpm_reaction, react)
        bridge = cls(coupler, [rigid_entities[int(geoms.entity[i])].name for i in idx], float(mpm.solver.np_lower[2]))
        bridge.reused = reused
        weakref.finalize(bridge, POOL.release, coupler)
        return bridge

    def couple(self, i, grad, replay=False):
        """The coupling stage of substep i (see solvers/coupling.py)."""
        self.coupler.couple(i, grad, replay)

    @property
    def attached(self):
        """Whether particles are attached to links (MPMEntity.set_particle_constraints)."""
        return self.coupler.attached

    def g2p_attached(self, i, grad):
        """Grid-to-particle of substep i with the attachments (see solvers/coupling.py)."""
        self.coupler.g2p_attached(i, grad)

    def reset(self):
        """A new rollout, or some envs restored: the floor watch starts again (CouplerBridge.check)."""
        self.coupler.clear_through()

    def check(self, step, batched):
        """After a step: raise when a coupled body went below the MPM domain's floor within its footprint.
        The domain's walls stop particles only; a body the material cannot bear (or no floor at all) would
        otherwise leave the material behind and fall on without a word."""
        hit = self.coupler.through_floor()
        if hit is None:
            return
        envs, geoms = hit
        self.coupler.clear_through()
        names = sorted({self.names[int(g)] for g in geoms})
        env_txt = f" in env{'s' if len(set(envs.tolist())) > 1 else ''} {sorted(set(envs.tolist()))[:8]}" if batched else ""
        raise GenesisException(
            f"rigid entit{'ies' if len(names) > 1 else 'y'} {', '.join(repr(n) for n in names)} went through the floor of the "
            f"MPM domain (z = {self.floor:g} m) at step {step}{env_txt}: the domain's walls stop particles, not rigid "
            "bodies. Give the scene a floor for them (gs.morphs.Plane() at or above the domain's lower_bound), or "
            "lower MPMOptions.lower_bound.")
