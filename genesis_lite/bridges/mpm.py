"""The scene's side of the MPM solver: torch mirrors of the particle state (x, v, C, F), of the
external forces and material parameters, their upload to the solver's fields, and the MPM part of the
scene's step node (simulator.py).

Material parameters are kept as the user sets them, per particle: E, nu, yield stress, friction angle
(degrees), viscosity, (B, P) each; the solver receives the packed (mu, lam, yield stress, alpha,
viscosity) computed from them by torch, so gradients reach E, nu and the friction angle through
ordinary autograd.
"""
from __future__ import annotations

import weakref

import numpy as np
import torch

from solvers.mpm.solver import POOL as SOLVER_POOL, acquire as acquire_solver

from ..errors import GenesisException
from ..grad.indexing import all_finite, index_put, raise_if_nan_grad
from ..grad.remake import recomposed
from ..materials import MPM as _MPM_MATERIALS, sand_alpha

Liquid = _MPM_MATERIALS.Liquid

MATERIAL_KEYS = ("E", "nu", "yield_stress", "friction_angle", "viscosity")
# A rollout's step nodes keep their substeps (substep_states) while the kept copies of the rollout take
# no more than this; the steps after recompute their substeps in their backward, as with checkpoints
KEEP_SUBSTEPS_BYTES = 2 << 30


class MPMSim:
    """Bridge of the MPM solver (the protocol is in bridges/__init__.py). Step inputs: x, v, C, F (its state),
    external forces (B, P, 3), packed parameters (B, 5, P) and gravity (B, 3); outputs: x, v, C, F."""

    n_state = 4
    n_outputs = 4

    def __init__(self, scene, entities, n_envs, sim_options, mpm_options):
        import genesis_lite as gs

        self.scene = scene
        self.entities = entities
        self.B = max(n_envs, 1)
        self.dtype = gs.tc_float
        self.device = gs.device
        self.requires_grad = sim_options.requires_grad
        self.sim = None
        self._kept_bytes = 0  # this rollout's kept substeps (substep_states)
        x0 = np.concatenate([e._x0 for e in entities])
        vol = np.concatenate([np.full(e.n_particles, e._vol) for e in entities])
        mass = np.concatenate([np.full(e.n_particles, e._vol * e.material.rho) for e in entities])
        mat = np.concatenate([np.full(e.n_particles, e.material.code) for e in entities])
        self.n_particles = len(x0)
        # emitters' particles (entities/emitter.py) come after every other entity's (scene._build_mpm);
        # until emitted they carry no mass or volume in the solver and lie beyond its count
        self.emitter_entities = [e for e in entities if e.is_emitter]
        emitting = np.concatenate([np.full(e.n_particles, e.is_emitter) for e in entities])
        self.n_fixed = int((~emitting).sum())
        if self.emitter_entities and (emitting[:self.n_fixed].any() or self.requires_grad):
            raise GenesisException("MPMSim: emitter particles must follow every other entity's, without gradients")
        self._park = domain_inside(mpm_options)[0]  # where unemitted particles inside the count wait (kernel_park)
        self.active = torch.as_tensor(~emitting)  # (P,) bool: emitted (or not an emitter's)
        # a solver of the scene's class from the pool (its kernels compiled by an earlier scene, if any),
        # given back when this bridge dies (solvers/mpm/solver.py)
        self.solver, self.reused_solver = acquire_solver(
            self.B, x0, vol, mass, mat, mpm_options.lower_bound, mpm_options.upper_bound, mpm_options.dx,
            sim_options.dt, sim_options.substeps, sim_options.gravity, gs.ti_float, self.requires_grad,
            mpm_options.wall_friction)
        weakref.finalize(self, SOLVER_POOL.release, self.solver)
        if self.requires_grad:
            from ..simulator import tape_loss

            self.solver.replay_loss = tape_loss()
        self._mass_np, self._vol_np = mass, vol
        if self.emitter_entities:
            self.solver.kernel_set_particle_mass(self.n_fixed, self.n_particles, 0.0, 0.0)
            self.solver.set_count(self.n_fixed)
            mass = np.where(emitting, 0.0, mass)
        # per particle (kg): what the entities' get_mass / get_pos weigh (an unemitted particle: 0)
        self.mass = torch.as_tensor(mass, dtype=self.dtype, device=self.device)
        self.inside = domain_inside(mpm_options)
        self._dx, self._h = mpm_options.dx, sim_options.dt / sim_options.substeps
        self._sim_options = sim_options
        # per particle: density (kg/m^3) and whether the wave speed has no shear part (liquids), for the
        # time-step check of material changes after build
        self._rho = torch.as_tensor(np.concatenate([np.full(e.n_particles, e.material.rho) for e in entities]),
                                    dtype=torch.float64)
        self._liquid = torch.as_tensor(np.concatenate([np.full(e.n_particles, isinstance(e.material, Liquid))
                                                       for e in entities]))
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
        if self.emitter_entities:
            self._fill_inactive(out)
        return tuple(out)

    # ---------------------------------------------------------------- emitters (entities/emitter.py)
    def _fill_inactive(self, state):
        """Unemitted particles read as Genesis reports them: at gu.nowhere(), at rest, C = 0, F = I."""
        from ..entities.emitter import NOWHERE

        off = ~self.active.to(self.device)
        if bool(off.any()):
            x, v, C, F = state
            x[:, off] = torch.as_tensor(NOWHERE, dtype=self.dtype, device=self.device)
            v[:, off] = 0.0
            C[:, off] = 0.0
            F[:, off] = torch.eye(3, dtype=self.dtype, device=self.device)

    def _parked_ranges(self):
        """[lo, hi) of the unemitted particles inside the solver's count (behind another emitter's emitted ones)."""
        n = self.solver.n_particles
        out = []
        for e in self.emitter_entities:
            lo, hi = e._p_start + e._emitter.high_water, min(e._p_start + e.n_particles, n)
            if lo < hi:
                out.append((lo, hi))
        return out

    def _park_inactive(self):
        for lo, hi in self._parked_ranges():
            self.solver.kernel_park(lo, hi, self._park.tolist())

    def emit(self, ent, start, pos, vel):
        """Emit the particles start..start+len(pos)-1 of emitter entity `ent` (local indices) in every env
        at positions pos (n, 3) m with velocity vel (3,) m/s, with C = 0 and F = I (fresh material): they
        get their mass and volume in the solver, which counts them from now on."""
        n = len(pos)
        lo, hi = ent._p_start + start, ent._p_start + start + n
        x, v, C, F = (t.clone() for t in self.state())
        x[:, lo:hi] = torch.as_tensor(pos, dtype=self.dtype, device=self.device)
        v[:, lo:hi] = torch.as_tensor(vel, dtype=self.dtype, device=self.device)
        C[:, lo:hi] = 0.0
        F[:, lo:hi] = torch.eye(3, dtype=self.dtype, device=self.device)
        self.activate(ent, max(ent._emitter.high_water, hi - ent._p_start))  # recycled ones stay emitted
        self.set_state(x, v, C, F)

    def activate(self, ent, high_water):
        """Emitter entity `ent` has its first `high_water` particles emitted (and no others): masses,
        volumes and the solver's count follow."""
        em = ent._emitter
        lo, old, hi = ent._p_start, ent._p_start + em.high_water, ent._p_start + high_water
        if hi > old:
            self.solver.kernel_set_particle_mass(old, hi, float(self._mass_np[lo]), float(self._vol_np[lo]))
            self.mass[old:hi] = float(self._mass_np[lo])
        elif hi < old:
            self.solver.kernel_set_particle_mass(hi, old, 0.0, 0.0)
            self.mass[hi:old] = 0.0
        self.active[old:hi] = True
        self.active[hi:old] = False
        em.high_water = high_water
        count = max([self.n_fixed] + [e._p_start + e._emitter.high_water for e in self.emitter_entities
                                      if e._emitter.high_water > 0])
        self.solver.set_count(count)
        self._state_on_device = False  # written (and parked) before the next step
        self._loaded = (None, None, None)  # the parameters and forces of the newly counted particles too

    def _c(self, t):
        return t.detach().to(self.dtype).contiguous()

    def _write_state(self, x, v, C, F):
        self.solver.kernel_set_state(0, self._c(x), self._c(v), self._c(C), self._c(F))
        if self.emitter_entities:
            self._park_inactive()

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
            self.values[key] = recomposed(self.param_base[key], ops, key)
        self._params = None
        if self.param_ops["E"] or self.param_ops["nu"]:
            self.check_time_step(self.values["E"], self.values["nu"], "the material parameters set")

    def check_time_step(self, E, nu, what):
        """Raise if per-particle E (Pa) and nu, (B, P) tensors, make the substep too long for the grid:
        the check build() does (check_time_step below), for values set after build."""
        E, nu = E.detach().to(torch.float64).cpu(), nu.detach().to(torch.float64).cpu()
        lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
        mu = E / (2.0 * (1.0 + nu))
        c = torch.sqrt(torch.where(self._liquid, lam, lam + 2.0 * mu) / self._rho)
        i_b, i_p = divmod(int(torch.argmax(c)), c.shape[1])
        ent = next(e for e in self.entities if e._p_start <= i_p < e._p_start + e.n_particles)
        msg = time_step_error(ent.name, float(c[i_b, i_p]), float(E[i_b, i_p]), float(nu[i_b, i_p]),
                              float(self._rho[i_p]), bool(self._liquid[i_p]), self._dx, self._sim_options)
        if msg is not None:
            where = f"particle {i_p - ent._p_start}" + (f" in env {i_b}" if self.scene.n_envs else "")
            raise GenesisException(f"{msg} (after {what}: {where}). A built scene keeps its substeps: keep E at "
                                   "or below the bound given, or build a new scene with more substeps.")

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

    # the stages of a substep, called in the simulator's order (simulator.py, solvers/mpm/solver.py)
    def substep_pre_coupling(self, i, grad, replay=False):
        self.solver.substep_pre_coupling(i, grad, replay)

    def grid_update(self, i, replay=False):
        self.solver.grid_update(i, replay)

    def substep_post_coupling(self, i, grad, replay=False):
        self.solver.substep_post_coupling(i, grad, replay)

    def active_rows(self, n_rows):
        """`active` for n_rows envs: a (n_rows, P) bool tensor on the scene's device (emission is the same
        in every env)."""
        return self.active.to(self.device).unsqueeze(0).expand(n_rows, -1).clone()

    def substep_uncoupled(self, i):
        """Substep i without gradients and without a coupler: the three stages above in one launch."""
        self.solver.substep_uncoupled(i)

    def record_substep(self, i, stages):
        """Substep i as one call on the scene's Tape; stages(i, grad, replay) runs its stages."""
        self.solver.record_substep(i, stages)

    def substep_states(self):
        """The step's substeps as its forward left them in the solver's slots (x, v, C, F after each substep,
        the stress of each), for its node to keep, so that its backward records them on its Tape without
        computing them again (load_substeps); None once the rollout's copies would pass KEEP_SUBSTEPS_BYTES."""
        B, P, S = self.B, self.n_particles, self.solver.n_slots - 1
        nbytes = S * B * P * 33 * torch.finfo(self.dtype).bits // 8
        if self._kept_bytes + nbytes > KEEP_SUBSTEPS_BYTES:
            return None
        e = lambda *s: torch.empty(S, B, P, *s, dtype=self.dtype, device=self.device)  # noqa: E731
        kept = (e(3), e(3), e(3, 3), e(3, 3), e(3, 3))
        self.solver.kernel_get_substeps(*kept)
        self._kept_bytes += nbytes
        return kept

    def load_substeps(self, kept):
        """A kept step's substeps back into the slots (after `load` has put its inputs in slot 0); the
        solver's record_substep then records without recomputing until substeps_done()."""
        self.solver.kernel_set_substeps(*kept)
        self.solver.substeps_loaded = True

    def substeps_done(self):
        self.solver.substeps_loaded = False

    def untracked_step_done(self):
        self._state = None
        self._state_on_device = True
        if self.emitter_entities:
            self._park_inactive()

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
        self.solver.kernel_vjp(self.solver.last_slot, *g)

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

    def check_finite(self):
        """{env: description} of the envs with a particle whose x or v is not finite now (the scene's
        NaN watch, genesis_lite/nan_watch.py, names the step and decides what to do)."""
        x, v = (t.detach() for t in self.state()[:2])
        if all_finite(x, v):
            return {}
        bad = ~(torch.isfinite(x).all(-1) & torch.isfinite(v).all(-1))
        out = {}
        if not bool(bad.any()):
            return out
        for i_b in torch.nonzero(bad.any(-1)).reshape(-1).tolist():
            i_p = int(torch.nonzero(bad[i_b])[0])
            ent = next(e for e in self.entities if e._p_start <= i_p < e._p_start + e.n_particles)
            n = int(bad[i_b].sum())
            out[i_b] = (f"MPM entity '{ent.name}': particle {i_p - ent._p_start} (x = {x[i_b, i_p].tolist()}, v = "
                        f"{v[i_b, i_p].tolist()}){f' and {n - 1} more' if n > 1 else ''}")
        return out

    def count_nonfinite(self, step, clear=None):
        """How many envs have a record of a non-finite particle state: after a step without gradients
        the solver checks the particles in one pass and records the envs at `step`; None when the state
        is a torch tensor (gradient path: check_finite looks at it). clear (numpy bool (B,)): forget
        those envs' records instead (scene.reset)."""
        if clear is not None:
            return int(self.solver.kernel_reset_nan(np.ascontiguousarray(clear, dtype=np.int32)))
        if self._state is not None:
            return None
        return self.solver.kernel_count_nonfinite(0, step)

    # ---------------------------------------------------------------- rollouts
    def new_rollout(self, state):
        self._kept_bytes = 0
        self.reset_controls()
        self.rebuild_params()
        self.set_state(*state)


def domain_inside(mpm_options):
    """(lo, hi) numpy (3,) m: where particles may be, the MPM domain less 3 cells of wall at each face
    (build() refuses entities outside it, setters refuse positions outside it)."""
    lo = np.asarray(mpm_options.lower_bound, float) + 3 * mpm_options.dx
    hi = np.asarray(mpm_options.upper_bound, float) - 3 * mpm_options.dx
    return lo, hi


def time_step_error(name, c, E, nu, rho, liquid, dx, sim_options, cfl=0.9):
    """The message of a substep too long for a material of wave speed c (m/s) on cells of dx m, or
    None when it is short enough (see check_time_step). Gives the stable substep count and the
    largest E (Pa) the current substep allows at this nu and rho."""
    h = sim_options.dt / sim_options.substeps
    h_max = cfl * dx / c
    if h <= h_max:
        return None
    need = int(np.ceil(sim_options.dt / h_max))
    c_ok = cfl * dx / h
    # c^2 rho = E k(nu): k = (1 - nu) / ((1 + nu)(1 - 2 nu)) for solids (lam + 2 mu), nu / (...) for liquids
    k = (nu if liquid else 1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))
    e_max = c_ok ** 2 * rho / k if k > 0 else float("inf")
    return (f"MPM entity '{name}': the substep dt / substeps = {h:.3g} s is too long for its material on this "
            f"grid: elastic waves travel at {c:.3g} m/s (E={E:g} Pa, nu={nu:g}, rho={rho:g} kg/m^3) and must cross "
            f"at most {cfl:g} of a cell ({dx:.3g} m) per substep, i.e. a substep <= {h_max:.3g} s. Use "
            f"SimOptions(substeps={need}) or more (or a smaller dt, a softer material: E <= {e_max:.3g} Pa at this "
            "nu and rho, a coarser grid)")


def check_time_step(entities, mpm_options, sim_options, cfl=0.9):
    """Raise if the substep is too long for the stiffest material on this grid: an explicit MPM step
    must not let an elastic wave (speed c) cross more than `cfl` of a cell. The message gives the
    substep count that would be stable. (Measured here: a corotated cube, E = 1e6 Pa, nu = 0.3, dropped
    on the floor at dx = 1/64 m, is stable at c h / dx = 0.94 and diverges at 1.17.)"""
    worst = max(entities, key=lambda e: e.material.wave_speed())
    m = worst.material
    msg = time_step_error(worst.name, m.wave_speed(), m.E, m.nu, m.rho, isinstance(m, Liquid), mpm_options.dx,
                          sim_options, cfl)
    if msg is not None:
        raise GenesisException(msg + ".")
