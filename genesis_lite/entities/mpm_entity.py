"""MPMEntity: a thin view (a particle index range) over the MPM solver's state, with Genesis's API.

Getters return genesis_lite.grad.Tensor on gs.device in the scene precision, with a leading env axis
when the scene was built with n_envs > 0; setters take tensors, arrays or lists, and tensors that
require grad carry gradients into the rollout (scenes with requires_grad=True).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import GenesisException
from ..grad.indexing import index_put
from ..grad.remake import recipe
from ..grad.tensor import wrap
from ..utils.geom import inv_transform_by_trans_quat
from .rigid_entity import RigidEntity


@dataclass
class MPMEntityState:
    """Particle positions (m), velocities (m/s), affine velocities C (1/s) and deformation gradients F
    of one MPM entity at one step; tensors in the autograd graph of a requires_grad scene."""

    pos: torch.Tensor
    vel: torch.Tensor
    C: torch.Tensor
    F: torch.Tensor


class MPMEntity:
    """Particles sampled in a morph's volume, made of one gs.materials.MPM material (or reserved by an
    emitter, entities/emitter.py: `is_emitter`, morph None, particles at gu.nowhere() until emitted)."""

    is_emitter = False
    _emitter = None  # the Emitter that owns this entity's particles

    # index and value validation are the rigid entities' (same rules, same messages)
    _idx = RigidEntity._idx
    _envs = RigidEntity._envs
    _values = RigidEntity._values
    _device = RigidEntity._device

    uid = RigidEntity.uid  # (gs.UID, given by scene.add_entity)

    def __init__(self, scene, idx, morph, material, name, particles, vol):
        self._scene = scene
        self.idx = idx
        self.morph = morph
        self.material = material
        self.name = name
        self._x0 = particles
        self._vol = vol
        self.n_particles = len(particles)
        self._p_start = -1

    @property
    def _label(self):
        return f"MPM entity '{self.name}'"

    def _on_build(self, p_start):
        self._p_start = p_start

    @property
    def is_built(self):
        return self._scene.is_built

    @property
    def _sim(self):
        if not self._scene.is_built:
            raise GenesisException(f"MPM entity '{self.name}': call scene.build() before reading or setting its state")
        return self._scene._mpm

    @property
    def _range(self):
        return slice(self._p_start, self._p_start + self.n_particles)

    def _particles(self, idx=None):
        return self._idx(idx, self.n_particles, "particles_idx_local", self._p_start)

    def _out(self, t):
        return wrap(t if self._scene.n_envs > 0 else t[0])

    def _state_part(self, k, envs_idx):
        return self._out(self._sim.state()[k][self._envs(envs_idx)][:, self._range])

    # ---------------------------------------------------------------- getters
    def get_particles_pos(self, envs_idx=None):
        """Particle positions (m), (n_particles, 3)."""
        return self._state_part(0, envs_idx)

    def get_particles_active(self, envs_idx=None):
        """Which particles take part in the simulation (Genesis's name): a boolean tensor (n_particles,),
        batched (n_envs, n_particles). All of an entity's; an emitter's (scene.add_emitter) once emitted,
        the same in every env."""
        envs = self._envs(envs_idx)  # (checks envs_idx)
        return self._out(self._sim.active_rows(len(envs))[:, self._range])

    def get_particles_in_bbox(self, bbox_min, bbox_max, envs_idx=None):
        """Which particles lie in the axis-aligned box [bbox_min, bbox_max] (m) now: a boolean tensor
        (n_particles,), batched (n_envs, n_particles) (Genesis's name)."""
        lo, hi = (torch.as_tensor(np.asarray(b, dtype=np.float64)).reshape(3) for b in (bbox_min, bbox_max))
        if not bool((lo <= hi).all()):
            raise GenesisException(f"entity '{self.name}': get_particles_in_bbox needs bbox_min <= bbox_max, got "
                                   f"{lo.tolist()} and {hi.tolist()}")
        x = self.get_particles_pos(envs_idx).detach()
        lo, hi = lo.to(x), hi.to(x)
        return ((x >= lo) & (x <= hi)).all(-1)

    def set_particle_constraints(self, particles_mask, link_idx, stiffness):
        """Attach particles to a rigid link (Genesis's name): each particle where `particles_mask` is true
        ((n_particles,), or (n_envs, n_particles) in a batched scene) is pulled towards the point of link
        `link_idx` (its scene-wide index, `link.idx`) where it lies now, by a spring of `stiffness` (N/m)
        with critical damping against its velocity relative to that point (solvers/coupling.py). One-way, as
        Genesis's: the link drives the particles and does not feel them. Call it again to re-attach; the
        attachments are kept through scene.reset(), as Genesis's (remove_particle_constraints ends them)."""
        coupler = self._coupler("set_particle_constraints")
        mask = self._particle_mask(particles_mask, "set_particle_constraints")
        k = stiffness
        if isinstance(k, bool) or not isinstance(k, (int, float, np.integer, np.floating)) or not np.isfinite(k) or k <= 0:
            raise GenesisException(f"entity '{self.name}': set_particle_constraints needs a finite stiffness > 0 "
                                   f"(N/m), got {stiffness!r}")
        ent, local = self._scene._link_owner(link_idx, "set_particle_constraints")
        with torch.no_grad():
            p = ent.get_links_pos([local]).detach().reshape(-1, 1, 3).to(torch.float64).cpu()
            q = ent.get_links_quat([local]).detach().reshape(-1, 1, 4).to(torch.float64).cpu()
            x = self.get_particles_pos().detach().reshape(-1, self.n_particles, 3).to(torch.float64).cpu()
        local_x = inv_transform_by_trans_quat(x, p, q)  # (B, n, 3): each particle in the link's frame
        coupler.set_attachments(self._full(mask), int(link_idx), self._full(local_x.numpy()), float(k))

    def remove_particle_constraints(self, particles_mask=None):
        """Detach the particles where `particles_mask` is true (all of this entity's when None)."""
        coupler = self._coupler("remove_particle_constraints")
        if particles_mask is None:
            mask = np.ones((self._n_env_rows(), self.n_particles), dtype=bool)
        else:
            mask = self._particle_mask(particles_mask, "remove_particle_constraints")
        coupler.set_attachments(self._full(mask), -1, None, 0.0)

    def _coupler(self, what):
        self._sim  # (raises before build)
        bridge = self._scene._coupler
        if bridge is None:
            raise GenesisException(
                f"entity '{self.name}': {what} attaches particles to a rigid link through the rigid-MPM coupler, "
                "which this scene does not have: it needs a rigid entity whose material couples "
                "(gs.materials.Rigid(needs_coup=True), the default) and CouplerOptions(rigid_mpm=True)")
        return bridge.coupler

    def _n_env_rows(self):
        return max(self._scene.n_envs, 1)

    def _particle_mask(self, mask, what):
        """A boolean mask (n_particles,) or (n_envs, n_particles) as a numpy (n_env_rows, n_particles) array."""
        B = self._n_env_rows()
        m = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
        if m.dtype != bool:
            raise GenesisException(f"entity '{self.name}': {what} takes a boolean particles mask (as "
                                   f"get_particles_in_bbox returns), got dtype {m.dtype}")
        if m.shape == (self.n_particles,):
            m = np.broadcast_to(m, (B, self.n_particles))
        if m.shape != (B, self.n_particles):
            want = f"({self.n_particles},)" + (f" or ({B}, {self.n_particles})" if self._scene.n_envs > 0 else "")
            raise GenesisException(f"entity '{self.name}': {what}: particles mask of shape {tuple(m.shape)}; this "
                                   f"entity's is {want}")
        return m

    def _full(self, a):
        """An entity's (n_env_rows, n_particles, ...) array placed in the solver's (n_env_rows, capacity, ...)."""
        out = np.zeros((a.shape[0], self._sim.solver.cap_particles) + a.shape[2:], dtype=a.dtype)
        out[:, self._range] = a
        return out

    def get_particles_vel(self, envs_idx=None):
        """Particle velocities (m/s), (n_particles, 3)."""
        return self._state_part(1, envs_idx)

    def get_particles_C(self, envs_idx=None):
        """Particle affine velocities (APIC C, 1/s), (n_particles, 3, 3)."""
        return self._state_part(2, envs_idx)

    def get_particles_F(self, envs_idx=None):
        """Particle deformation gradients, (n_particles, 3, 3)."""
        return self._state_part(3, envs_idx)

    def _masses(self):
        return self._sim.mass[self._range]

    def get_mass(self):
        """Total mass (kg)."""
        return float(self._masses().sum())

    def get_pos(self, envs_idx=None):
        """Centre of mass (m)."""
        m = self._masses()
        x = self._sim.state()[0][self._envs(envs_idx)][:, self._range]
        return self._out((x * m[None, :, None]).sum(1) / m.sum())

    def get_vel(self, envs_idx=None):
        """Velocity of the centre of mass (m/s)."""
        m = self._masses()
        v = self._sim.state()[1][self._envs(envs_idx)][:, self._range]
        return self._out((v * m[None, :, None]).sum(1) / m.sum())

    def get_state(self, envs_idx=None) -> MPMEntityState:
        return MPMEntityState(*(self._state_part(k, envs_idx) for k in range(4)))

    # ---------------------------------------------------------------- state setters
    def _set_part(self, k, values, envs, idx, what=None):
        sim = self._sim
        if k == 0:
            self._check_in_domain(values, envs, idx, what or "set_particles_pos")
        state = list(sim.state())
        state[k] = index_put(state[k], envs, idx, values)
        sim.set_state(*state)

    def _check_in_domain(self, pos, envs, idx, what):
        """Refuse positions outside the region build() admits (MPMOptions' bounds less 3 cells of wall):
        the grid has no nodes for them, and the walls could not hold them."""
        lo, hi = self._sim.inside
        p = pos.detach()
        lo_t, hi_t = (torch.as_tensor(b, dtype=p.dtype, device=p.device) for b in (lo, hi))
        bad = (p < lo_t) | (p > hi_t)  # NaN was refused by _values already
        if not bool(bad.any()):
            return
        i_e, i_p, a = [int(i) for i in torch.nonzero(bad)[0]]
        n_bad = int(bad.any(-1).sum())
        env = f" in env {int(envs[i_e])}" if self._scene.n_envs > 0 else ""
        raise GenesisException(
            f"MPM entity '{self.name}': {what} would put particle {int(idx[i_p]) - self._p_start}{env} at "
            f"{[round(float(v), 4) for v in p[i_e, i_p]]} m ({n_bad} particle(s) in all), outside the MPM domain "
            f"along {'xyz'[a]}: particles must stay within {np.round(lo, 4).tolist()} .. {np.round(hi, 4).tolist()} m "
            "(MPMOptions lower_bound/upper_bound less 3 cells of wall). Move the entity inside, or build the scene "
            "with a larger domain.")

    def _per_particle(self, x, envs, idx, what, trailing):
        """x as (len(envs), len(idx), *trailing): one value for all particles (shape `trailing`, or
        (n_envs, *trailing) batched) or one per particle."""
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else np.shape(x)
        one = shape == tuple(trailing) or (self._scene.n_envs > 0 and shape == (len(envs),) + tuple(trailing))
        if not one:
            return self._values(x, envs, len(idx), what, trailing)
        t = x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x, dtype=np.float64))
        vals = self._values(t.reshape(shape[:-len(trailing) or None] + (1,) + tuple(trailing))
                            if shape != tuple(trailing) else t.reshape((1,) + tuple(trailing)),
                            envs, 1, what, trailing).expand((len(envs), len(idx)) + tuple(trailing))
        again = recipe(x)
        if again is not None:  # made again in a new rollout (grad/remake.py)
            vals._gs_remake = lambda: self._per_particle(again(), envs, idx, what, trailing)
        return vals

    def set_particles_pos(self, pos, particles_idx_local=None, envs_idx=None):
        """Set particle positions (m): (n, 3) for the particles chosen (all by default)."""
        envs, idx = self._envs(envs_idx), self._particles(particles_idx_local)
        self._set_part(0, self._values(pos, envs, len(idx), "pos", (3,)), envs, idx, "set_particles_pos")

    def set_particles_vel(self, vel, particles_idx_local=None, envs_idx=None):
        """Set particle velocities (m/s): (n, 3) for the particles chosen (all by default)."""
        envs, idx = self._envs(envs_idx), self._particles(particles_idx_local)
        self._set_part(1, self._values(vel, envs, len(idx), "vel", (3,)), envs, idx)

    def set_position(self, pos, envs_idx=None):
        """Move the entity: pos (3,) puts its centre of mass there (the shape is kept), (n_particles, 3)
        sets every particle."""
        envs, idx = self._envs(envs_idx), self._particles(None)
        t = pos if isinstance(pos, torch.Tensor) else torch.as_tensor(np.asarray(pos, dtype=np.float64))
        if t.shape[-2:] == (self.n_particles, 3):
            return self.set_particles_pos(pos, envs_idx=envs_idx)
        # (3,) or batched (n_envs, 3): one centre per env
        c = self._values(t.unsqueeze(-2), envs, 1, "pos", (3,))
        m = self._masses()
        x = self._sim.state()[0][envs][:, self._range]
        com = (x * m[None, :, None]).sum(1, keepdim=True) / m.sum()
        self._set_part(0, x - com + c, envs, idx, "set_position")

    def set_velocity(self, vel, envs_idx=None):
        """Velocity (m/s) of every particle: (3,) for all of them or (n_particles, 3)."""
        envs, idx = self._envs(envs_idx), self._particles(None)
        self._set_part(1, self._per_particle(vel, envs, idx, "velocity", (3,)), envs, idx)

    # ---------------------------------------------------------------- forces and materials
    def set_particles_force(self, force, particles_idx_local=None, envs_idx=None):
        """External force on each particle (N, world frame), from the next step on until changed: (3,)
        for every particle or (n, 3) one each. Differentiable."""
        envs, idx = self._envs(envs_idx), self._particles(particles_idx_local)
        self._sim.set_force(self._per_particle(force, envs, idx, "force", (3,)), envs, idx)

    def set_material(self, E=None, nu=None, yield_stress=None, friction_angle=None, viscosity=None, envs_idx=None):
        """Change material parameters: Young's modulus E (Pa), Poisson's ratio nu, yield stress (Pa,
        ElastoPlastic), friction angle (degrees, Sand), viscosity (Pa s, Liquid). Each a number, a
        tensor of shape () or (n_particles,) (batched scenes: also (n_envs, n_particles)); tensors that
        require grad receive gradients (real Genesis takes only floats here)."""
        envs, idx = self._envs(envs_idx), self._particles(None)
        checks = {"E": (0.0, None, "Pa, > 0"), "nu": (-1.0, 0.5, "in (-1, 0.5)"),
                  "yield_stress": (0.0, None, "Pa, > 0"), "friction_angle": (0.0, 90.0, "degrees, in (0, 90)"),
                  "viscosity": (None, None, "Pa s, >= 0")}
        new = {}
        for key, value in (("E", E), ("nu", nu), ("yield_stress", yield_stress), ("friction_angle", friction_angle),
                           ("viscosity", viscosity)):
            if value is None:
                continue
            vals = self._per_particle(value, envs, idx, key, ())
            lo, hi, what = checks[key]
            v = vals.detach()
            bad = (v < 0).any() if key == "viscosity" else ((v <= lo).any() or (hi is not None and (v >= hi).any()))
            if bad:
                raise GenesisException(f"MPM entity '{self.name}': {key} must be {what}; got values from "
                                       f"{v.min().item():g} to {v.max().item():g}")
            new[key] = vals
        sim = self._sim
        if "E" in new or "nu" in new:
            # the time-step check of build(), on the values these would make (before any is stored)
            E_nu = [index_put(sim.values[k], envs, idx, new[k]) if k in new else sim.values[k] for k in ("E", "nu")]
            sim.check_time_step(*E_nu, "set_material(" + ", ".join(f"{k}=..." for k in new if k in ("E", "nu")) + ")")
        for key, vals in new.items():
            sim.set_param(key, vals, envs, idx)

    def get_material(self, key, envs_idx=None):
        """Per-particle value of a material parameter ("E", "nu", "yield_stress", "friction_angle",
        "viscosity"), (n_particles,)."""
        from ..bridges.mpm import MATERIAL_KEYS

        if key not in MATERIAL_KEYS:
            raise GenesisException(f"MPM entity '{self.name}': unknown material parameter {key!r}; one of "
                                   f"{list(MATERIAL_KEYS)}")
        return self._out(self._sim.values[key][self._envs(envs_idx)][:, self._range])

    def __repr__(self):
        return f"<MPMEntity '{self.name}': {self.n_particles} particles of {type(self.material).__name__}>"
