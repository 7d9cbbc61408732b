"""RigidSolver: the rigid entities of one scene, on a pooled core, and the entry points of their step.

The model is flattened (flatten.py) and loaded into a RigidCore of its capacity class, taken from the
pool (pool.py, core.py). A step is a schedule of ops per substep (schedule.py: dynamics + factor-solve
at a slot, integrate, copy-back). Without gradients it runs as one fused kernel (in a scene built for
gradients, op by op: see _fused). With gradients each
substep runs op by op (`substep(i)`) so that the scene can record it on a `ti.ad.Tape`
(genesis_lite/simulator.py): an evaluation (dynamics + factor-solve) is one `ti.ad.grad_replaced` call,
whose forward runs each env's stages in turn in one loop over the envs (core.kernel_evaluate) and whose
adjoint, registered with `ti.ad.grad_for`, recomputes the evaluation's scratch when a later one
has overwritten it, runs the hand-written adjoint of the factor-solve and then the adjoint of the
dynamics' stages, last first: written out for the core's stages (HAND_ADJOINTS), Taichi's for a scene's own
(kernel_dynamics_part, in the kernels of adjoint_groups); integration kernels are recorded as they are.

A scene with collision pairs (or with external wrenches, external.py) runs its dynamics on a SceneCore
(core.py) that adds those stages to the core's. The contact solver's fields are sized by a contact
class too (capacities of geoms, pairs, slots; static flags: slot kinds, SDF types, dense
factorisation, the model's constants) and read the scene's sizes at run time, so SceneCores with a
contact solver are pooled as well, each keeping its core: a later scene whose contacts fit one compiles
nothing (a robot over a plane after another), and so do scenes with external wrenches of the same sizes.

Arrays cross in caller-made buffers (numpy, or torch tensors the scene's side makes): this package
imports taichi and numpy only.
"""

import weakref
from typing import List

import numpy as np
import taichi as ti

from ..taichi_compat.adstack import require as require_ad_stack
from ..taichi_compat.compile_options import AdjointCompile, ForwardCompile
from ..taichi_compat.frontend import hot_launcher
from . import state_io
from .actuation import (LIMITS_CONSTRAINT, LIMITS_OFF, LIMITS_SPRING, func_free_rot_errors, func_generalized_force,
                        limit_gains)
from .collision import NO_ADJOINT
from .contact import ContactPlan
from .bias import BIAS
from .core import (DYNAMICS, LINK_STATE_ADJOINT, F_IMPLICIT_KV_ONLY, F_IMPLICIT_ON, F_LIMIT_D, F_LIMIT_K, I_ANC,
                   I_DOFS, I_FREE, I_ELEMS, I_ENVS, I_LIMITS_ON,
                   I_LINKS, I_QPOS_LEN, I_QS, I_QVEL_LEN, N_CFG_F, N_CFG_I, NO_NAN, PLAIN_ADJOINT,
                   HandAdjoint, elem_capacity, env_capacity, with_applied)
from .external import ExternalWrench
from .flatten import FlatModel
from .inertia import INERTIA, TreeSchedule
from .kinematics import JOINT_FREE, KINEMATICS, LINK_STATE
from .model import EntityModel
from .pool import POOL
from .schedule import OP_DYN, OP_INT, Integrator, StepSchedule, pack_span

# scenes of at least this many envs get specialised kernels by default (RigidOptions.specialize_kernels).
# Specialising costs a compile of its own: a Panda (MJCF) on a plane at 64 envs took 79.9 s from import to
# its first step on an empty cache, specialised, against 19.7 s sharing its class's kernels; the ~25 %
# faster step repays ~60 s after ~170,000 steps there, after ~12,000 at 1,024 envs on a quadruped
SPECIALIZE_MIN_ENVS = 512

# stages whose adjoint runs in the kernel of the stage before them (RigidSolver._evaluation_unit): the generalised
# force, whose adjoint alone left ~1e-250 in an env outside the loss, and the free joints' rotation errors it reads
MERGED_STAGES = (func_free_rot_errors, func_generalized_force)
# runs of consecutive stages whose adjoint is written out (core.kernel_hand_adjoint: one loop over envs, the stages'
# adjoints in turn, plain adds) instead of Taichi's, which add with compare-and-swap loops in a parallel loop and cost
# ~3.4x their forward even serial (benchmarks/results/grad.md). tests/test_autodiff_rules.py holds each part against
# Taichi's adjoint of the same stages. The longest run that starts at a stage is taken: a scene's own stages
# (contacts, external wrenches) come after DYNAMICS and keep Taichi's adjoints; applied wrenches come between the
# gyroscopic moments and the accumulation, which splits the core's run in two.
HAND_ADJOINTS = {
    DYNAMICS: HandAdjoint(kinematics=True, inertia=True, forces=True, accumulate=True, project=True, generalized=True),
    KINEMATICS + INERTIA + BIAS[:2]: HandAdjoint(kinematics=True, inertia=True, forces=True),
    BIAS[2:] + MERGED_STAGES: HandAdjoint(accumulate=True, project=True, generalized=True),
}


def adjoint_groups(stages):
    """The kernels that run the adjoint of a dynamics' stages, last first, as (k0, k1, plain, hand). A run of
    HAND_ADJOINTS is one group whose `hand` is its HandAdjoint (core.kernel_hand_adjoint); the core's stages are one
    such run (a scene with applied wrenches: two), so a robot without contacts takes one adjoint kernel an
    evaluation. The others (`hand` None) are each the adjoint of kernel_dynamics_part(k0, k1), stages k0..k1-1 as
    separate loops in one kernel, for a run of consecutive stages with an adjoint (NO_ADJOINT stages are left out)
    and the same PLAIN_ADJOINT flag (the compile option differs); a MERGED_STAGES stage stays with the stage before
    it. One kernel per group, not per stage: each launch costs ~10 us of Python and Taichi. (The stages in one loop
    body instead, one env at a time, as the forward runs them, gave wrong adjoints in Taichi 1.7.4: it runs the
    adjoints of sibling loops of one loop body in their forward order, so a stage's adjoint reads its outputs'
    adjoints before the later stages have added to them (tests/sibling_loops.py).)"""
    def hand_at(k):
        runs = [(len(run), spec) for run, spec in HAND_ADJOINTS.items() if tuple(stages[k:k + len(run)]) == run]
        return max(runs, key=lambda r: r[0], default=(0, None))

    groups, k, n = [], 0, len(stages)
    while k < n:
        if stages[k] in NO_ADJOINT:
            k += 1
            continue
        m, spec = hand_at(k)
        if spec is not None:
            groups.append((k, k + m, True, spec))
            k += m
            continue
        plain = stages[k] in PLAIN_ADJOINT
        j = k + 1
        while (j < n and stages[j] not in NO_ADJOINT and hand_at(j)[1] is None
               and ((stages[j] in PLAIN_ADJOINT) == plain or stages[j] in MERGED_STAGES)):
            j += 1
        groups.append((k, j, all(f in PLAIN_ADJOINT for f in stages[k:j]), None))
        k = j
    return groups[::-1]


def _core_field(name, doc):
    """A field of the solver's core, read as the solver's (a property: the core is the scene's for life)."""
    return property(lambda self: getattr(self.core, name), doc=doc)


class RigidSolver:
    """Generalised-coordinate rigid dynamics of all rigid entities of one scene.

    models: the entities' numpy descriptions; n_envs >= 1 parallel environments; dt the step (s);
    substeps per step; integrator a schedule.Integrator; requires_grad allocates adjoint storage.
    The fields live in `self.core` (a pooled RigidCore, core.py); the step's dynamics kernels run on
    `self.step_core`: that core, or a SceneCore over it that adds the scene's contact solver
    (`self.contact`) and external wrenches (`self.external`, written by the rigid-MPM coupler).
    Applied wrenches (`self.applied`: the user's link forces and gravity compensation, external.py) are
    added by `enable_applied()`, at build (`applied_wrench`) or at the first use: a scene that applies
    none runs, and compiles, exactly what it did without them.
    """

    NO_NAN = NO_NAN

    def __init__(self, models: List[EntityModel], n_envs: int, dt: float, substeps: int, integrator: int,
                 gravity, dtype, requires_grad: bool, enable_joint_limit: bool, limit_k, limit_d,
                 contact_options=None, mimic=False, external_wrench=False, specialize=None, applied_wrench=False,
                 limit_timeconst=0.01):
        self.models = models
        self.dtype = dtype
        self.np_dtype = np.float64 if dtype == ti.f64 else np.float32
        self.n_envs = n_envs
        self.dt = dt
        self.substeps = substeps
        self.integrator = integrator
        self.implicit = integrator in (Integrator.implicitfast, Integrator.approximate_implicitfast)
        self.implicit_on = 1.0 if self.implicit else 0.0
        self.implicit_kv_only = 1.0 if integrator == Integrator.approximate_implicitfast else 0.0
        self.requires_grad = requires_grad
        self.enable_joint_limit = enable_joint_limit
        # joint limits: penalty springs when limit_k / limit_d are numbers (their gains in the cfg), else Genesis's
        # constraint (actuation.func_limit_constraint; its parameters per dof, limit_constraint_params)
        self.limit_model = (LIMITS_OFF if not enable_joint_limit else
                            LIMITS_SPRING if limit_k is not None else LIMITS_CONSTRAINT)
        self.limits_on = self.limit_model != LIMITS_OFF
        # the constraint's default time constant (a joint without its own: limit_constraint_params)
        self.limit_timeconst = float(limit_timeconst)
        self.limit_k, self.limit_d = (limit_k, limit_d) if self.limit_model == LIMITS_SPRING else (0.0, 0.0)
        self.flat = FlatModel(models, bool(mimic))
        self.n_links, self.n_qs, self.n_dofs = self.flat.n_links, self.flat.n_qs, self.flat.n_dofs
        self._schedule()
        # n_links + 1: a root link reads its parent from a slot no link occupies (kinematics.func_parent_slot)
        self.specialized = bool(n_envs >= SPECIALIZE_MIN_ENVS if specialize is None else specialize)
        # (not with folded mimics: the unrolled factorisation does not fold them)
        tree = (tuple(int(p) for p in self.flat.np_dof_parent) if self.specialized and not requires_grad
                and not self.flat.has_fold else None)
        if tree is not None and TreeSchedule.create(tree) is None:
            tree = None
        key = (dtype, bool(requires_grad), env_capacity(n_envs),
               elem_capacity(max(self.n_links + 1, self.n_dofs, self.n_qs)),
               self.n_slots, self.n_evals, len(self.ops), self.specialized, tree)
        # Contacts plug in as extra dynamics stages after the generalised force (they add J^T f into
        # `force`); no plan when the scene has no collision pairs, so nothing is compiled for them.
        plan = None
        if contact_options is not None:
            plan = ContactPlan.create(self.flat, models, contact_options, self.specialized)
        self.contact = None
        self.external = None
        if plan is not None or external_wrench:
            # core + contact solver and / or external wrenches (per substep, written by the rigid-MPM
            # coupler, external.py) from the pool: a scene of the same class reuses the kernels compiled on them
            ext_key = ExternalWrench.make_key(self.n_envs, self.substeps, self.n_links, self.evals_per_substep,
                                              self.dtype, self.requires_grad) if external_wrench else None
            self.step_core, self.reused_core = POOL.acquire_scene_core(key, plan, ext_key)
            self.core = self.step_core.core
            self.contact = self.step_core.contact
            self.external = self.step_core.external
            if self.external is not None:
                self.external.load(self.flat.np_link_parent)
            weakref.finalize(self, POOL.release_scene_core, self.step_core)
        else:
            self.core, self.reused_core = POOL.acquire(key)
            weakref.finalize(self, POOL.release, self.core)
            self.step_core = self.core
        self.serial = self.core.serial
        # in place: a SceneCore shares the core's list
        self.core.scene_cfg[:] = self._cfg()
        if self.contact is not None:
            self.contact.load(plan, self.n_envs, self.np_dtype)
        if requires_grad:
            # the reverse-mode loops that carry a local from one iteration to the next walk the kinematic tree
            # (at most the core's element capacity); the contact stages' loops over slots, pairs and cross
            # terms carry none, so they must not size the stacks (taichi_compat/adstack.py: sized to them,
            # five boxes on a plane got 4096-entry stacks that overflowed the native stack: a segfault)
            loops = [self.core.cap_elems]
            if self.external is not None:
                loops.append(self.n_links * self.n_dofs)  # its dof x link double loop
            require_ad_stack(max(loops))
        self.dynamics_stages = self.step_core.dynamics_stages
        # contacts between two moving bodies couple dofs outside the tree sparsity: dense factorisation
        self.dense_solve = self.step_core.dense_solve
        self._fill_info(gravity)
        self._scratch = None  # the (e, src, h) whose evaluation the scratch fields hold, if any
        # whether every adjoint of the per-evaluation scratch is zero (see clear_grads); light_clear False: never
        # assumed (every clear zeroes them all)
        self._scratch_grads_zero = False
        self.light_clear = True
        self._light_clear_ok = self.external is None and not self.dense_solve
        self._fused_ready = False  # kernel_step_fused compiled (see taichi_compat.compile_options.ForwardCompile)
        self._fused_bound = (None, None)  # see _launch_fused
        self._watch_clock = self.contact.clock if self.contact is not None else None
        self.applied = None
        self.evaluate = self._evaluation_unit()
        self.kinematics = self._kinematics_unit()
        if applied_wrench:
            self.enable_applied()

    def enable_applied(self):
        """Run the dynamics with applied wrenches from now on (external.AppliedWrench, zero until written):
        the step core becomes its applied-wrench form (core.with_applied: the same fields, so the state,
        controls and parameters stay where they are; its kernels compile at their first launch unless an
        earlier scene on this core compiled them). Returns the AppliedWrench."""
        if self.applied is None:
            self.step_core = with_applied(self.step_core)
            self.applied = self.step_core.applied
            self.applied.clear()
            self.dynamics_stages = self.step_core.dynamics_stages
            self._scratch = None
            self._fused_ready = False
            self.evaluate = self._evaluation_unit()
        return self.applied

    # the core's fields that the scene's side and the coupler read (capacity-sized: the scene's block is
    # [.., :n_envs, :n_links or n_dofs]); with gradients, `.grad` is their adjoint
    qpos = _core_field("qpos", "[slot, env, q] generalised positions")
    qvel = _core_field("qvel", "[slot, env, dof] generalised velocities")
    qacc = _core_field("qacc", "[evaluation, env, dof] accelerations of the last step's evaluations")
    mass_mat = _core_field("mass_mat", "[env, dof, dof] mass matrix of the last evaluation (lower triangle)")
    dof_tau = _core_field("dof_tau", "[env, dof] actuator forces of the last evaluation")
    dof_qf = _core_field("dof_qf", "[env, dof] actuator + damping + spring - bias forces of the last evaluation")
    link_pos = _core_field("link_pos", "[env, link] link origins (world, m) of the last kinematics")
    link_quat = _core_field("link_quat", "[env, link] link orientations (w, x, y, z) of the last kinematics")
    link_R = _core_field("link_R", "[env, link] link rotation matrices of the last kinematics")
    cvel_w = _core_field("cvel_w", "[env, link] link angular velocities (world, rad/s)")
    cvel_v = _core_field("cvel_v", "[env, link] link linear velocities of the point at their kinematic tree's origin "
                         "(its root link's, kinematics.func_link_origin; m/s)")

    # ------------------------------------------------------------------ build
    def _schedule(self):
        """The step's ops and slots (schedule.StepSchedule) as attributes of the solver."""
        sched = StepSchedule(self.integrator, self.dt, self.substeps)
        for name in ("ops", "n_ops", "n_slots", "n_evals", "evals_per_substep", "substep_first_op", "substep_ops",
                     "substep_slot", "last_slot"):
            setattr(self, name, getattr(sched, name))

    def _cfg(self):
        cfg = [0] * N_CFG_I + [0.0] * N_CFG_F
        cfg[I_ENVS], cfg[I_LINKS], cfg[I_DOFS], cfg[I_QS] = self.n_envs, self.n_links, self.n_dofs, self.n_qs
        cfg[I_QPOS_LEN], cfg[I_QVEL_LEN], cfg[I_LIMITS_ON] = self.flat.qpos_len, self.flat.qvel_len, self.limit_model
        cfg[I_ELEMS] = max(self.n_links, self.n_dofs, self.n_qs, 1)
        cfg[I_ANC] = len(self.flat.np_anc_pairs)
        cfg[I_FREE] = len(self._free_links())
        cfg[N_CFG_I + F_LIMIT_K] = float(self.limit_k or 0.0)
        cfg[N_CFG_I + F_LIMIT_D] = float(self.limit_d or 0.0)
        cfg[N_CFG_I + F_IMPLICIT_ON] = float(self.implicit_on)
        cfg[N_CFG_I + F_IMPLICIT_KV_ONLY] = float(self.implicit_kv_only)
        return cfg

    def _free_links(self):
        """The links of free joints, in order (core.free_link): int32."""
        return np.flatnonzero(self.flat.np_link_jtype == JOINT_FREE).astype(np.int32)

    def limit_constraint_params(self):
        """(n_dofs, 7): each dof's limit constraint (k, b, dmin, dmax, width, mid, power), Genesis's reading of the
        joint's solref / solimp (rigid_solver.py _sanitize_sol_params): the time constant the joint's own or, where
        it has none (or a MuJoCo direct one, solref < 0), the scene's (limit_timeconst), at least twice the
        substep; dmin, dmax, mid clipped to [1e-4, 0.9999], width >= 0 (a small floor here: it divides), power >= 1."""
        sol = self.flat.np_dof_limit_sol.copy()
        tc = sol[:, 0]
        tc = np.where(np.isfinite(tc) & (tc > 0), tc, self.limit_timeconst)
        tc = np.maximum(tc, 2.0 * self.dt / self.substeps)
        dr = np.where(sol[:, 1] > 0, sol[:, 1], 1.0)
        imp = sol[:, 2:].copy()
        imp[:, [0, 1, 3]] = np.clip(imp[:, [0, 1, 3]], 1e-4, 0.9999)
        imp[:, 2] = np.maximum(imp[:, 2], 1e-9)
        imp[:, 4] = np.maximum(imp[:, 4], 1.0)
        k, b = limit_gains(tc, dr, imp[:, 1])
        return np.concatenate([k[:, None], b[:, None], imp], -1)

    def param_layout(self):
        """[(name, width per env)] of the packed parameter tensor of kernel_set_params, in order."""
        L, D = self.n_links, self.n_dofs
        return [("mass", L), ("com", 3 * L), ("inertia", 9 * L), ("damping", D), ("armature", D),
                ("frictionloss", D), ("kp", D), ("kv", D), ("stiffness", D), ("gravity", 3), ("force_lo", D),
                ("force_hi", D), ("invweight", D)]

    def initial_params(self, gravity):
        """numpy (n_envs, ...) arrays of every parameter of param_layout as built from the models."""
        m = self.flat
        B = self.n_envs
        tile = lambda a: np.ascontiguousarray(np.broadcast_to(a, (B,) + a.shape)).astype(self.np_dtype)  # noqa: E731
        big = np.finfo(self.np_dtype).max
        eff = np.clip(m.np_dof_effort, 0, big)
        zeros = np.zeros(self.n_dofs)
        return {"mass": tile(m.np_link_mass), "com": tile(m.np_link_com), "inertia": tile(m.np_link_inertia),
                "damping": tile(m.np_dof_damping), "armature": tile(m.np_dof_armature),
                "frictionloss": tile(m.np_dof_frictionloss), "kp": tile(zeros), "kv": tile(zeros),
                "stiffness": tile(m.np_dof_stiffness),
                "gravity": tile(np.asarray(gravity, dtype=float)), "force_lo": tile(-eff), "force_hi": tile(eff),
                "invweight": tile(np.ones(self.n_dofs))}

    def _fill_info(self, gravity):
        m = self.flat
        L, D = self.n_links, self.n_dofs
        pad = lambda a, n: a if len(a) else np.zeros((1,) + a.shape[1:], a.dtype)  # noqa: E731
        cfg = self.core.scene_cfg
        cfg_i = np.array(cfg[:N_CFG_I], dtype=np.int32)
        cfg_f = np.array(cfg[N_CFG_I:], dtype=self.np_dtype)
        link_i = [pad(a, L) for a in (m.np_link_parent, m.np_link_jtype, m.np_link_q_start, m.np_link_dof_start,
                                      m.np_link_ndof)]
        free = self._free_links()
        link_i = np.stack(link_i + [np.pad(free, (0, len(link_i[0]) - len(free)))], -1).astype(np.int32)
        link_f = np.concatenate([pad(m.np_link_jpos, L), pad(m.np_link_jquat, L), pad(m.np_link_jaxis, L)],
                                -1).astype(self.np_dtype)
        # "no limit" as a large finite number: infinities turn masked-out terms into NaN
        lim = np.clip(pad(m.np_dof_limit, D), -1e30, 1e30)
        dof_i = np.stack([pad(m.np_dof_link, D), pad(m.np_dof_q, D), pad(m.np_dof_parent, D),
                          m.np_mimic[:, 0].astype(np.int32), m.np_fold_leader], -1).astype(np.int32)
        dof_f = np.concatenate([lim, m.np_mimic[:, 1:], pad(m.np_dof_springref, D)[:, None],
                                pad(self.limit_constraint_params(), D)], -1).astype(self.np_dtype)
        sched = np.ascontiguousarray(np.array([op[:6] for op in self.ops], dtype=np.int32))
        sched_h = np.array([op[6] for op in self.ops], dtype=self.np_dtype)
        self.core.kernel_load(cfg_i, cfg_f, np.ascontiguousarray(link_i), np.ascontiguousarray(link_f),
                              np.ascontiguousarray(dof_i), np.ascontiguousarray(dof_f), m.np_dof_anc,
                              np.ascontiguousarray(pad(m.np_anc_pairs, 1)), sched, sched_h)
        p = self.initial_params(gravity)
        self.set_params(np.concatenate([p[k].reshape(self.n_envs, -1) for k, _ in self.param_layout()], -1))
        self.reset_state()

    def set_params(self, packed):
        """Every parameter from one (n_envs, sum of param_layout widths) array or tensor."""
        state_io.kernel_set_params(self.core, packed)

    def reset_state(self):
        """Initial state (URDF zero pose, free bases at their morph placement, zero velocity),
        zero controls in force mode."""
        m = self.flat
        self.core.kernel_reset_state(np.ascontiguousarray(np.pad(m.np_qpos0, (0, 1)).astype(self.np_dtype)))

    # ------------------------------------------------------------------ python entry points
    def _fused(self, step, k0, k1, finish):
        """Launch the fused step; returns the number of envs with a NaN record (see kernel_step_fused).
        A scene built for gradients runs its untracked steps op by op instead, with the kernels its
        tracked steps use (the same numbers): its fused kernel would hold the gradient path's forms of
        every stage and take seconds to compile (~10 s for the Panda over a plane) for steps such a scene
        rarely takes many of (finite-difference checks, evaluation rollouts). (self.requires_grad is
        the core's: cores are pooled by it; an attribute of a Taichi data-oriented object costs ~0.5 us.)"""
        if self.requires_grad:
            return self._unfused(step, k0, k1, finish)
        if self._fused_ready or self.specialized:
            return self._launch_fused(step, pack_span(k0, k1, finish))
        with ForwardCompile():
            n = self.step_core.kernel_step_fused(step, pack_span(k0, k1, finish))
        self._fused_ready = True
        return n

    @property
    def _launch_fused(self):
        """step_core.kernel_step_fused, bound once per step core (Taichi binds a data-oriented class's
        kernel anew at every attribute access: ~3 us, a tenth of a 1-env step) and launched through
        taichi_compat's hot_launcher (~2 us less a launch than Kernel.__call__'s fast path)."""
        core, bound = self._fused_bound
        if core is not self.step_core:
            bound = hot_launcher(self.step_core.kernel_step_fused)
            self._fused_bound = (self.step_core, bound)
        return bound

    def _unfused(self, step, k0, k1, finish):
        """Ops k0..k1-1 as the gradient path launches them (whole substeps), then kernel_finish."""
        for i in range(self.substeps):
            if k0 <= self.substep_first_op[i] < k1:
                self.substep(i)
        self._scratch = None
        return self.core.kernel_finish(step, finish)

    def step(self, step: int = 0):
        """One step without gradient bookkeeping: the state moves from slot 0 to slot 0."""
        self._scratch = None
        n = self._fused(step, 0, self.n_ops, 1)
        if self._watch_clock is not None and self._watch_clock.due():  # a contact deep inside a body warns (once a pair)
            self.contact.watch(step, self.n_evals, self.dt / self.substeps)
        return n

    def substep_fused(self, step: int, i: int):
        """Substep i without gradient bookkeeping (scenes where another solver steps between
        substeps); the last substep makes its result the current state (slot 0)."""
        self._scratch = None
        n = self._fused(step, self.substep_first_op[i], self.substep_first_op[i + 1], int(i == self.substeps - 1))
        if self._watch_clock is not None and i == self.substeps - 1 and self._watch_clock.due():
            self.contact.watch(step, self.n_evals, self.dt / self.substeps)
        return n

    def substep(self, i: int):
        """Substep i's ops one launch each, the form a ti.ad.Tape records (gradient path). The state
        moves from slot i (or the substep's first RK slot) to the substep's last slot."""
        with ForwardCompile():
            for kind_op, kind, e, base, src, dst, h in self.substep_ops[i]:
                if kind_op == OP_DYN:
                    self.evaluate(e, src, h)
                elif kind_op == OP_INT:
                    self.core.kernel_integrate(kind, e, base, src, dst, h)

    def _evaluation_unit(self):
        """Dynamics at slot src + factor-solve into qacc[e], as one call on the tape. Its adjoint
        recomputes the evaluation first when the scratch fields (poses, M, its factor) hold another
        one, then runs the adjoint of the solve (hand-written: for qacc = M^-1 f, f_bar = M^-1 qacc_bar
        and M_bar = -f_bar qacc^T) and the adjoints of the dynamics' stages in reverse order, in the kernels of
        adjoint_groups: the core's stages written out (HAND_ADJOINTS), a scene's own (contacts, external and
        applied wrenches) Taichi's (which compiles an adjoint in time superlinear in its size: the Panda's 13
        stages took 9 s as separate kernels, 24 s as one, before they were written out). In Taichi's, the
        generalised force shared the kernel of the stage before it (with the free joints' rotation errors,
        MERGED_STAGES): its adjoint alone left ~1e-250 (not 0) in the gradient of an env outside the loss
        (tests/test_gradients.py::test_batched_environments_each_get_their_own_gradient). A stage that
        writes no float (the broad phase: collision.NO_ADJOINT) has an empty adjoint, which is not run.

        Contacts only when some pair can touch: in a scene whose contact solver is its only addition to
        the core (no external or applied wrenches) and couples no two moving bodies (not dense), an
        evaluation at a state where the broad phase finds no pair active in any env runs the core's own
        kernels (those of the same robot without collision pairs), forward and backward. Its contact stages
        and passes would add exact zeros to the force and M, and the final solve is the core's, so the
        numbers are the same bit for bit (tests/test_contact.py: an arm over a plane it never reaches
        against the arm alone), while the contact kernels and their adjoints (the larger part of a contact
        scene's compile: ~20 s of the Panda over a plane's cold 40 s) compile only when a contact can
        happen. The check is one small kernel and a returned integer per evaluation."""
        step_core, core, contact = self.step_core, self.core, self.contact
        lazy = (contact is not None and not contact.dense and step_core.external is None
                and getattr(step_core, "applied", None) is None)

        runs = {True: (step_core, adjoint_groups(step_core.dynamics_stages)),
                False: (core, adjoint_groups(core.dynamics_stages))}
        used = {}  # (e, src, h) -> whether its last forward ran the contact kernels

        def with_contact(e, src, h):
            if not lazy:
                return True
            with ForwardCompile():
                use = contact.kernel_active_pairs(step_core, src, h) > 0
            used[(e, src, h)] = use
            return use

        def forward(target, e, src, h):
            with ForwardCompile():
                target.kernel_evaluate(e, src, h)  # with the final solve when there are no contacts
                if target.has_contact:
                    target.contact.factor_solve(target, e)
            self._scratch = (e, src, h, target)

        @ti.ad.grad_replaced
        def evaluate(e, src, h):
            forward(runs[with_contact(e, src, h)][0], e, src, h)

        @ti.ad.grad_for(evaluate)
        def evaluate_grad(e, src, h):
            use = used[(e, src, h)] if (e, src, h) in used else with_contact(e, src, h)
            target, parts = runs[use]
            if self._scratch != (e, src, h, target):
                forward(target, e, src, h)
            # the factor-solve's adjoint, in the first written-out adjoint's loop over envs where it can be
            fuse = not target.has_contact and parts and parts[0][3] is not None
            if not fuse:
                target.kernel_solve_grad(e)
            for i, (k0, k1, plain, hand) in enumerate(parts):
                if hand is not None:
                    with ForwardCompile():  # a primal kernel (nothing differentiates it)
                        target.hand_adjoint(hand._replace(solve=fuse and i == 0), e, src, h)
                    continue
                with AdjointCompile(plain):
                    target.kernel_dynamics_part.grad(k0, k1, e, src, h)
            self._scratch_grads_zero = self._light_clear_ok

        return evaluate

    def _kinematics_unit(self):
        """kernel_kinematics(src) as one call on a tape (the getters'), its adjoint the stages' as separate
        loops in one kernel (see adjoint_groups). The coupler launches the core's kernel itself: its calls
        run inside the MPM substep's own grad_replaced adjoint, where a nested one is not recorded."""
        core = self.core
        assert DYNAMICS[: len(LINK_STATE)] == LINK_STATE == KINEMATICS[: len(LINK_STATE)]

        @ti.ad.grad_replaced
        def kinematics(src):
            with ForwardCompile():
                core.kernel_kinematics(src)

        @ti.ad.grad_for(kinematics)
        def kinematics_grad(src):
            with ForwardCompile():  # written out (a primal kernel: nothing differentiates it)
                core.hand_adjoint(LINK_STATE_ADJOINT, 0, src, 0.0)
            self._scratch_grads_zero = self._light_clear_ok

        return kinematics

    def scratch_overwritten(self):
        """Called by every launch outside `evaluate` that writes the scratch fields (getters' kinematics,
        the mass matrix, the fused step, the coupler), so a pending adjoint recomputes its evaluation."""
        self._scratch = None

    def clear_grads(self):
        """Zero the adjoints of the scene's envs and seed the adjoint of the solver's vjp scalar. Those of the
        per-evaluation scratch (poses, inertias, forces, M: 3/4 of the numbers a full clear zeroes) only when
        they may not be zero. The core's stages come first in every dynamics, so their written-out adjoints
        (HAND_ADJOINTS) run last in an evaluation's backward, after those of a scene's own stages (contacts,
        applied wrenches) have added to the scratch's adjoints, and they read each scratch adjoint and zero it,
        as every store's adjoint does; the scene's own solvers' fields are cleared either way. So the scratch's
        adjoints are zero when the last launch that touched them before this clear was such an adjoint that
        ended (an evaluation's or the getters' kinematics'), with nothing that adds to them after it (the
        integration's and the vjp's adjoints touch the state's only). Not assumed: after a backward that stopped
        part-way, in a fresh solver, with the coupler's external wrenches (its kinematics run inside the MPM
        substep's adjoint) or a dense contact solve (its adjoints work on the full matrix, beyond the tree's
        entries that the mass matrix's adjoint zeroes: not checked, so not assumed). tests/test_gradients.py
        compares the two clears."""
        self.step_core.kernel_clear_grads(int(not (self.light_clear and self._scratch_grads_zero)))
        self._scratch_grads_zero = False

    def mass_matrix(self, src: int):
        """M (without armature or implicit terms) at qpos[src] into mass_mat (read it with read_mass_matrix)."""
        self.core.kernel_mass_matrix(src)

    def reset_nan(self, envs=None):
        """Forget the NaN record of the envs flagged in `envs` (numpy bool/int (n_envs,); None: all).
        Returns how many envs stay recorded."""
        mask = np.ones(self.n_envs, np.int32) if envs is None else np.ascontiguousarray(envs, dtype=np.int32)
        return int(self.core.kernel_reset_nan(mask))

    # ------------------------------------------------------------------ arrays in and out (state_io.py)
    # Each takes the caller's buffer (a numpy array or a contiguous CPU torch tensor of the solver's
    # dtype) and fills or reads it: the solver never makes a torch tensor itself.
    def write_state(self, slot: int, x):
        """qpos, qvel in `slot` from x = [qpos | qvel] (n_envs, n_qs + n_dofs)."""
        state_io.kernel_set_state(self.core, slot, x)

    def read_state(self, slot: int, x):
        """x = [qpos | qvel] (n_envs, n_qs + n_dofs) of `slot`, which also becomes slot 0."""
        state_io.kernel_get_state(self.core, slot, x)

    def write_ctrl(self, c):
        """The packed controls c = [force; pos; vel] (n_envs, 3, n_dofs)."""
        state_io.kernel_set_ctrl(self.core, c)

    def write_ctrl_mode(self, m):
        """The control mode of every dof, int32 (n_envs, n_dofs)."""
        state_io.kernel_set_ctrl_mode(self.core, m)

    def accumulate_vjp(self, slot: int, g):
        """The solver's vjp scalar += <g, state in `slot`> (g packed as read_state's x)."""
        state_io.kernel_vjp(self.core, slot, g)

    def read_grads(self, g):
        """g (n_envs, n_qs + 4 n_dofs): adjoints of the state in slot 0 and of the packed controls."""
        state_io.kernel_get_grads(self.core, g)

    def read_param_grads(self, g):
        """g: adjoints of the differentiable parameters, packed as param_layout without the force range."""
        state_io.kernel_get_param_grads(self.core, g)

    def read_param_grad(self, x, g):
        """Adjoint of a (B, n) parameter field outside the core (contact friction: its block object or
        the field) into g (n_envs, n)."""
        state_io.kernel_param_grad(self.core, getattr(x, "field", x), g)

    def read_link_outputs(self, pos, quat, vel, ang):
        """Link origin poses and velocities (world frame) of the last kinematics, each (n_envs, n_links, 3
        or 4)."""
        state_io.kernel_link_outputs(self.core, pos, quat, vel, ang, False)

    def accumulate_link_vjp(self, pos, quat, vel, ang):
        """The solver's vjp scalar += <output gradients, read_link_outputs's outputs>."""
        state_io.kernel_link_outputs(self.core, pos, quat, vel, ang, True)

    def write_applied(self, w):
        """The applied wrench of the next step from w (n_envs, n_links, 6) = [force | moment about the link
        origin] (N, N m, world axes); enable_applied() first."""
        if self.n_links:
            self.applied.kernel_set_wrench(w)

    def read_applied_grad(self, g):
        """Adjoint of the applied wrench into g (n_envs, n_links, 6)."""
        if self.n_links:
            self.applied.kernel_get_wrench_grad(g)

    @property
    def applied_gcomp(self):
        """The gravity compensation of every link as the scene's (n_envs, n_links) block (load / to_numpy /
        field, as the contact friction's)."""
        return _Block(self.applied.gcomp, (self.n_envs, self.n_links), self.applied.kernel_set_gcomp)

    RESULTS = ("mass_mat", "qacc", "dof_tau", "dof_qf")

    def read_result(self, name: str, out):
        """A per-env dof result of the last evaluation into out: "mass_mat" (n_envs, n_dofs, n_dofs) the
        mass matrix (of the last mass_matrix call, lower triangle), "qacc" (n_envs, n_evals, n_dofs) the
        accelerations of the last step's evaluations, "dof_tau" (n_envs, 1, n_dofs) the actuator forces,
        "dof_qf" (n_envs, 1, n_dofs) the actuator, damping and spring forces less the bias."""
        if self.n_envs * self.n_dofs:
            state_io.kernel_get_result(self.core, self.RESULTS.index(name), out)


class _Block:
    """A scene's (n_envs, n) block of a capacity-sized [env, element] parameter field."""

    def __init__(self, field, shape, setter):
        self.field, self.shape, self._setter = field, shape, setter

    @property
    def grad(self):
        return self.field.grad

    def to_numpy(self):
        B, n = self.shape
        return self.field.to_numpy()[:B, :n]

    def load(self, x):
        """The block from x (n_envs, n), a numpy array or a contiguous CPU tensor."""
        if tuple(x.shape) != self.shape:
            raise ValueError(f"expected shape {self.shape}, got {tuple(x.shape)}")
        if self.shape[1]:
            self._setter(x.contiguous() if hasattr(x, "contiguous") else np.ascontiguousarray(x))
