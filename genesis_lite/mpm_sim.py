"""The scene's side of the MPM solver: torch mirrors of the particle state (x, v, C, F), of the
external forces and material parameters, their upload to the solver's fields, and the MPM part of the
scene's step node (simulator.py).

Material parameters are kept as the user sets them, per particle: E, nu, yield stress, friction angle
(degrees), viscosity, (B, P) each; the solver receives the packed (mu, lam, yield stress, alpha,
viscosity) computed from them by torch, so gradients reach E, nu and the friction angle through
ordinary autograd.
"""
from __future__ import annotations

import numpy as np
import torch

from solvers.mpm.solver import MPMSolver

from .errors import GenesisException, SimulationNaNError
from .grad.indexing import index_put, raise_if_nan_grad
from .materials import sand_alpha

MATERIAL_KEYS = ("E", "nu", "yield_stress", "friction_angle", "viscosity")


class MPMSim:
    """Bridge of the MPM solver (the protocol is in simulator.py). Step inputs: x, v, C, F (its state),
    external forces (B, P, 3), packed parameters (B, 5, P) and gravity (B, 3); outputs: x, v, C, F."""

    n_state = 4
    n_outputs = 4

    def __init__(self, scene, entities, n_envs, sim_options, mpm_options, coupler=None):
        import genesis_lite as gs

        self.scene = scene
        self.entities = entities
        self.B = max(n_envs, 1)
        self.dtype = gs.tc_float
        self.device = gs.device
        self.requires_grad = sim_options.requires_grad
        self.sim = None
        x0 = np.concatenate([e._x0 for e in entities])
        vol = np.concatenate([np.full(e.n_particles, e._vol) for e in entities])
        mass = np.concatenate([np.full(e.n_particles, e._vol * e.material.rho) for e in entities])
        mat = np.concatenate([np.full(e.n_particles, e.material.code) for e in entities])
        self.n_particles = len(x0)
        self.solver = MPMSolver(self.B, x0, vol, mass, mat, mpm_options.lower_bound, mpm_options.upper_bound,
                                mpm_options.dx, sim_options.dt, sim_options.substeps, sim_options.gravity, gs.ti_float,
                                self.requires_grad, mpm_options.wall_friction, coupler=coupler)
        self.mass = torch.as_tensor(mass, dtype=self.dtype, device=self.device)
        t = lambda a: torch.as_tensor(np.asarray(a, dtype=float), dtype=self.dtype, device=self.device)  # noqa: E731
        per = {k: np.concatenate([np.full(e.n_particles, float(getattr(e.material, k, 0.0))) for e in entities])
               for k in MATERIAL_KEYS}
        # parameters: base values, then the user's setter calls replayed on top (as RigidSim's)
        self.param_base = {k: t(v).reshape(1, -1).repeat(self.B, 1) for k, v in per.items()}
        self.param_base["gravity"] = t(sim_options.gravity).reshape(1, 3).repeat(self.B, 1)
        self.param_ops = {k: [] for k in self.param_base}
        self.values = dict(self.param_base)
        self._params = None
        self._loaded = (None, None, None)  # the (params, force, gravity) tensors whose values are in the fields
        self.reset_controls()
        P = self.n_particles
        eye = torch.eye(3, dtype=self.dtype, device=self.device)
        self.init_state = (t(x0).reshape(1, P, 3).repeat(self.B, 1, 1),
                           torch.zeros(self.B, P, 3, dtype=self.dtype, device=self.device),
                           torch.zeros(self.B, P, 3, 3, dtype=self.dtype, device=self.device),
                           eye.expand(self.B, P, 3, 3).clone())
        self.set_state(*self.init_state)

    # ---------------------------------------------------------------- state
    def set_state(self, x, v, C, F):
        self._state = (x, v, C, F)
        self._state_on_device = False

    def state(self):
        if self._state is None:
            self._state = self._read_state(0)
        return self._state

    def _read_state(self, slot):
        B, P = self.B, self.n_particles
        out = [torch.empty(B, P, 3, dtype=self.dtype, device=self.device) for _ in range(2)] + \
              [torch.empty(B, P, 3, 3, dtype=self.dtype, device=self.device) for _ in range(2)]
        self.solver.kernel_get_state(slot, *out)
        return tuple(out)

    def _c(self, t):
        return t.detach().to(self.dtype).contiguous()

    def _write_state(self, x, v, C, F):
        self.solver.kernel_set_state(0, self._c(x), self._c(v), self._c(C), self._c(F))

    # ---------------------------------------------------------------- parameters and forces
    def params(self):
        """(B, 5, P): mu, lam, yield stress, Drucker-Prager alpha, viscosity, from the materials."""
        if self._params is None:
            m = self.values
            E, nu = m["E"], m["nu"]
            mu = E / (2.0 * (1.0 + nu))
            lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
            self._params = torch.stack([mu, lam, m["yield_stress"], sand_alpha(m["friction_angle"]),
                                        m["viscosity"]], 1)
        return self._params

    @property
    def gravity(self):
        return self.values["gravity"]

    def set_param(self, key, values, envs, idx):
        """values[envs][:, idx] of a material parameter (MATERIAL_KEYS, per particle) or gravity."""
        self.param_ops[key] = [op for op in self.param_ops[key]
                               if not (torch.equal(op[1], envs) and torch.equal(op[2], idx))]
        self.param_ops[key].append((values, envs, idx))
        self.values[key] = index_put(self.values[key], envs, idx, values)
        self._params = None

    def rebuild_params(self):
        """A new rollout: parameter tensors are recomposed from the user's setter calls so a leaf keeps
        receiving gradients rollout after rollout (as RigidSim.rebuild_params)."""
        for key, ops in self.param_ops.items():
            if not ops:
                continue
            p = self.param_base[key]
            for values, envs, idx in ops:
                remake = getattr(values, "_gs_remake", None)
                p = index_put(p, envs, idx, remake() if remake is not None else values.detach())
            self.values[key] = p
        self._params = None

    def reset_controls(self):
        self.force = torch.zeros(self.B, self.n_particles, 3, dtype=self.dtype, device=self.device)

    def set_force(self, values, envs, idx):
        self.force = index_put(self.force, envs, idx, values)

    # ---------------------------------------------------------------- the MPM part of the step node
    def inputs(self):
        return list(self.state()) + [self.force, self.params(), self.gravity]

    def context(self):
        return None

    def _load_params(self, params, force, gravity):
        if self._loaded[0] is not params or self._loaded[1] is not force or self._loaded[2] is not gravity:
            self.solver.kernel_set_params(self._c(params), self._c(force), self._c(gravity))
            self._loaded = (params, force, gravity)

    def upload(self):
        if not self._state_on_device:
            self._write_state(*self.state())
            self._state_on_device = True
        self._load_params(self.params(), self.force, self.gravity)

    def load(self, values, context):
        x, v, C, F, force, params, gravity = values
        self._write_state(x, v, C, F)
        self._load_params(params, force, gravity)
        self._state_on_device = False

    def substep(self, i, grad, step):
        self.solver.substep(i, grad)

    def untracked_step_done(self):
        self._state = None
        self._state_on_device = True

    def read_outputs(self):
        return list(self._read_state(self.solver.last_slot))

    def state_from_outputs(self, outs):
        return tuple(outs)

    def clear_grads(self):
        self.solver.kernel_clear_grads()

    def vjp(self, grads, loss):
        if all(g is None for g in grads):
            return
        B, P = self.B, self.n_particles
        shapes = [(B, P, 3), (B, P, 3), (B, P, 3, 3), (B, P, 3, 3)]
        g = [self._c(x) if x is not None else torch.zeros(s, dtype=self.dtype, device=self.device)
             for x, s in zip(grads, shapes)]
        self.solver.kernel_vjp(self.solver.last_slot, *g, loss)

    def input_grads(self, needs, step):
        B, P = self.B, self.n_particles
        e = lambda *s: torch.empty(*s, dtype=self.dtype, device=self.device)  # noqa: E731
        gx, gv, gC, gF, gf = e(B, P, 3), e(B, P, 3), e(B, P, 3, 3), e(B, P, 3, 3), e(B, P, 3)
        self.solver.kernel_get_state_grads(gx, gv, gC, gF, gf)
        gp, gg = e(B, 5, P), e(B, 3)
        self.solver.kernel_get_param_grads(gp, gg)
        out = [x if n else None for x, n in zip((gx, gv, gC, gF, gf, gp, gg), needs)]
        raise_if_nan_grad(out, step)
        return out

    def check_finite(self, step):
        """Raise SimulationNaNError naming the entity and the step if a particle's state is not finite."""
        x, v = self.state()[:2]
        bad = ~(torch.isfinite(x.detach()).all(-1) & torch.isfinite(v.detach()).all(-1))
        if bad.any():
            i_b, i_p = [int(a) for a in torch.nonzero(bad)[0]]
            ent = next(e for e in self.entities if e._p_start <= i_p < e._p_start + e.n_particles)
            raise SimulationNaNError(
                f"MPM entity '{ent.name}': particle {i_p - ent._p_start} was non-finite at step {step}"
                f"{f' in env {i_b}' if self.scene.n_envs else ''}. The simulation diverged: raise substeps (the time "
                "step must resolve the material's wave speed), lower E, or check the forces and velocities set.")

    def count_nonfinite(self):
        return int(self.solver.kernel_count_nonfinite(0))

    # ---------------------------------------------------------------- rollouts
    def new_rollout(self, state):
        self.reset_controls()
        self.rebuild_params()
        self.set_state(*state)


def check_time_step(entities, mpm_options, sim_options, cfl=0.9):
    """Raise if the substep is too long for the stiffest material on this grid: an explicit MPM step
    must not let an elastic wave (speed c) cross more than `cfl` of a cell. The message gives the
    substep count that would be stable. (Measured here: a corotated cube, E = 1e6 Pa, nu = 0.3, dropped
    on the floor at dx = 1/64 m, is stable at c h / dx = 0.94 and diverges at 1.17.)"""
    dx = mpm_options.dx
    h = sim_options.dt / sim_options.substeps
    worst = max(entities, key=lambda e: e.material.wave_speed())
    c = worst.material.wave_speed()
    h_max = cfl * dx / c
    if h > h_max:
        need = int(np.ceil(sim_options.dt / h_max))
        raise GenesisException(
            f"MPM entity '{worst.name}': the substep dt / substeps = {h:.3g} s is too long for its material on this "
            f"grid: elastic waves travel at {c:.3g} m/s (E={worst.material.E:g} Pa, nu={worst.material.nu:g}, "
            f"rho={worst.material.rho:g} kg/m^3) and must cross at most {cfl:g} of a cell ({dx:.3g} m) per substep, "
            f"i.e. a substep <= {h_max:.3g} s. Use SimOptions(substeps={need}) or more (or a smaller dt, a softer "
            "material, a coarser grid).")
