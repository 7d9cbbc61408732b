"""RigidSolver: the rigid entities of one scene, on a pooled set of Taichi fields, and their step.

Static model data lives in `*_info`-style fields set once at build (link_*, dof_* without an env
axis); parameters and controls have an env axis [i_b, ...]; state has a slot axis [t, i_b, ...]
holding the step's schedule of intermediate states (two slots for plain Euler, so memory does not grow
with the horizon); per-evaluation scratch (poses, inertias, forces) is written once per evaluation.

One compile serves every robot. Taichi bakes the fields a kernel touches, and every Python value it
reads while compiling, into the compiled kernel, keyed by the object that owns the kernel. So the
fields and kernels live in a `RigidCore` whose fields are sized by a capacity class (envs, elements:
links/dofs/qs, state slots) rather than by the scene, and the scene's sizes (n_envs, n_links, n_dofs,
n_qs) and options (joint-limit springs, implicit terms) are read at run time from its small `cfg`
fields (see `_runtime`). A scene takes a core of its class from a pool and gives it back when it dies,
so a second scene of that class, any robot, compiles nothing. Two scenes alive at once hold two
cores. A scene with collision pairs (or with external wrenches, external.py) runs its dynamics through a
`_SceneOwner`, a view of the core that also owns those stages. The contact solver's fields are sized by
a contact class too (capacities of geoms, pairs, slots; static flags: slot kinds, SDF types, dense
factorisation, the model's constants) and read the scene's sizes at run time, so owners with a contact
solver are pooled as well, each keeping its core: a later scene whose contacts fit one compiles nothing
(a robot over a plane after another). Owners with external wrenches stay per scene.

A step is a schedule of ops per substep (dynamics + factor-solve at a slot, integrate, copy-back).
Without gradients it runs as one fused kernel. With gradients each substep runs op by op
(`substep(i)`) so that the scene can record it on a `ti.ad.Tape` (genesis_lite/simulator.py): an
evaluation (dynamics + factor-solve) is one `ti.ad.grad_replaced` call whose adjoint, registered with
`ti.ad.grad_for`, recomputes the evaluation's scratch when a later one has overwritten it, runs the
hand-written adjoint of the factor-solve and then Taichi's adjoint of the dynamics kernel;
integration kernels are recorded as they are.
"""

import gc
import weakref
from typing import List

import numpy as np
import taichi as ti
from .. import taichi_compat
from ..taichi_compat.compile_options import AdjointCompile, ForwardCompile

from ..taichi_compat.adstack import require as require_ad_stack
from .actuation import func_generalized_force
from .bias import BIAS
from .contact import func_contact_solve, func_factor_solve_dense, func_solve_grad_dense
from .inertia import INERTIA, TreeSchedule, func_factor_solve, func_solve_grad
from .integrate import INTEGRATE
from .kinematics import (JOINT_FIXED, JOINT_FREE, JOINT_PRISMATIC, JOINT_REVOLUTE, KINEMATICS, LINK_STATE,
                         func_dof_subspace, func_forward_kinematics, func_world_inertia)
from .layout import place_env_major
from .model import JOINT_NQ, JOINT_NV, EntityModel
from .schedule import OP_DYN, OP_INT, OP_SOLVE, Integrator, StepSchedule

JTYPE = {"fixed": JOINT_FIXED, "free": JOINT_FREE, "revolute": JOINT_REVOLUTE, "prismatic": JOINT_PRISMATIC}
# parallel dispatch of a Taichi CPU kernel costs ~70 us here against ~12 us serial: few envs run serially
SERIAL_MAX_ENVS = 16
DYNAMICS = KINEMATICS + INERTIA + BIAS + (func_generalized_force,)
# stages whose float32 adjoints compile correctly without Taichi's advanced optimisation (taichi_compat.compile_options.AdjointCompile)
PLAIN_ADJOINT = KINEMATICS + INERTIA[:2] + BIAS[:2]
# smallest element capacity: the robots of one size class (Panda, UR5, arms up to 16 links/dofs/qs)
# share a core
MIN_ELEMS = 16
# run-time sizes and options, indices into RigidCore.cfg_i / cfg_f
I_ENVS, I_LINKS, I_DOFS, I_QS, I_QPOS_LEN, I_QVEL_LEN, I_LIMITS_ON, I_ELEMS, I_ANC, N_CFG_I = range(10)
F_LIMIT_K, F_LIMIT_D, F_IMPLICIT_ON, N_CFG_F = range(4)


def _runtime(index, floating=False):
    """A size or option of the scene a core holds. In Python scope it is that scene's number; inside a
    kernel being compiled it is a read of the core's cfg field, so the compiled kernel serves every
    scene the core will hold (stage code writes `range(s.n_links)` either way)."""

    def get(self):
        if taichi_compat.inside_kernel():
            return taichi_compat.subscript(self.cfg_f if floating else self.cfg_i, index)
        return self.scene_cfg[(N_CFG_I + index) if floating else index]

    return property(get)




# scenes of at least this many envs get specialised kernels by default (RigidOptions.specialize_kernels)
SPECIALIZE_MIN_ENVS = 64


def _cap_envs(n_envs: int) -> int:
    return SERIAL_MAX_ENVS if n_envs <= SERIAL_MAX_ENVS else 1 << (n_envs - 1).bit_length()


def _cap_elems(n: int) -> int:
    return max(MIN_ELEMS, 1 << (max(n, 1) - 1).bit_length())


@ti.func
def func_set_zero(x: ti.template(), I: ti.template()):
    """x[I] = 0 as a constant of x's element type (ti.zero would be x * 0, which keeps a NaN)."""
    if ti.static(not hasattr(x, "n")):
        x[I] = ti.cast(0, x.dtype)
    elif ti.static(x.m == 1):
        x[I] = ti.Vector.zero(x.dtype, x.n)
    else:
        x[I] = ti.Matrix.zero(x.dtype, x.n, x.m)


class _ZeroPlan:
    """Per-env fields grouped by the shape of their per-env part, so that one loop zeroes a whole group
    (one loop per field makes a kernel several times larger, and its size is what loading it costs).
    env0: core fields [B, ...]; env1: core fields [slot, B, ...]; other: fields of the scene's own
    (contact) solver, [B, ...]. For the core's fields a dimension equal to the element capacity runs to
    the scene's element count (a run-time bound); every other dimension runs to its full size."""

    def __init__(self, env0, env1, cap, other=()):
        self.cap = cap
        groups = {}
        for axis, fields, core in ((0, env0, True), (1, env1, True), (0, other, False)):
            for x in fields:
                rest = tuple(d if not core or d != cap else -1 for k, d in enumerate(x.shape) if k != axis)
                groups.setdefault((axis, rest), []).append(x)
        self.groups = [(axis, rest, tuple(fields)) for (axis, rest), fields in groups.items()]


@ti.func
def func_zero_group(fields: ti.template(), i_b, axis: ti.template(), rest: ti.template(), n):
    """One group of a _ZeroPlan (rest: the per-env shape, -1 where the scene's n elements apply)."""
    if ti.static(len(rest) == 0):
        for x in ti.static(fields):
            func_set_zero(x, i_b)
    elif ti.static(len(rest) == 1):
        for j in range(n if ti.static(rest[0] < 0) else rest[0]):
            for x in ti.static(fields):
                func_set_zero(x, (i_b, j))
    elif ti.static(axis == 0):
        for j, k in ti.ndrange(n if ti.static(rest[0] < 0) else rest[0], n if ti.static(rest[1] < 0) else rest[1]):
            for x in ti.static(fields):
                func_set_zero(x, (i_b, j, k))
    else:
        for j, k in ti.ndrange(rest[0], n if ti.static(rest[1] < 0) else rest[1]):
            for x in ti.static(fields):
                func_set_zero(x, (j, i_b, k))


@ti.func
def func_zero_plan(plan: ti.template(), i_b, n):
    """Zero, for env i_b, every field of the plan (the scene's n elements of capacity dimensions)."""
    for g in ti.static(plan.groups):
        func_zero_group(g[2], i_b, g[0], g[1], n)


@ti.data_oriented
class _Kernels:
    """The kernels of the rigid solver and the run-time sizes they read. Owned by a RigidCore (shared by
    scenes over time) or by a scene's _SceneOwner (a view of the core plus its contact/external stages).

    Env loops run over the core's env capacity with a guard `if i_b < self.n_envs`, not over
    `range(self.n_envs)`: Taichi 1.7 evaluates a top-level loop bound read from a field in a task of its
    own, and the adjoint of a kernel with several such loops came out NaN (kernel_dynamics; each stage
    alone, or the debug build, was right)."""

    n_envs = _runtime(I_ENVS)
    n_links = _runtime(I_LINKS)
    n_dofs = _runtime(I_DOFS)
    n_qs = _runtime(I_QS)
    qpos_len = _runtime(I_QPOS_LEN)  # max(n_qs, 1): clamped reads stay inside the scene's entries
    qvel_len = _runtime(I_QVEL_LEN)
    limits_on = _runtime(I_LIMITS_ON)
    limit_k = _runtime(F_LIMIT_K, True)
    limit_d = _runtime(F_LIMIT_D, True)
    implicit_on = _runtime(F_IMPLICIT_ON, True)
    n_anc = _runtime(I_ANC)  # pairs (i, j) with dof j an ancestor-or-self of dof i (anc_i, anc_j)

    # ------------------------------------------------------------------ build and reset
    @ti.kernel
    def kernel_load(self, cfg_i: ti.types.ndarray(), cfg_f: ti.types.ndarray(), link_i: ti.types.ndarray(),
                    link_f: ti.types.ndarray(), dof_i: ti.types.ndarray(), dof_f: ti.types.ndarray(),
                    anc: ti.types.ndarray(), anc_pairs: ti.types.ndarray(), sched: ti.types.ndarray(),
                    sched_h: ti.types.ndarray()):
        """A scene's model into the core: sizes and options, link and dof info, the dof tree and the step
        schedule. The per-env entries that a masked-out term may read before the scene writes them are
        zeroed, so that no value of an earlier scene (a NaN of a diverged one, say) reaches it: M outside
        the tree pattern (the dense factorisation multiplies it by 0) and the dof subspaces read at a
        clamped index when the scene has no dofs; the state's are zeroed by kernel_reset_state."""
        for k in range(N_CFG_I):
            self.cfg_i[k] = cfg_i[k]
        for k in range(N_CFG_F):
            self.cfg_f[k] = cfg_f[k]
        for i_b in range(cfg_i[I_ENVS]):
            func_zero_plan(self.zero_plan, i_b, cfg_i[I_ELEMS])
        for i in range(link_i.shape[0]):
            self.link_parent[i] = link_i[i, 0]
            self.link_jtype[i] = link_i[i, 1]
            self.link_q_start[i] = link_i[i, 2]
            self.link_dof_start[i] = link_i[i, 3]
            self.link_ndof[i] = link_i[i, 4]
            for k in ti.static(range(3)):
                self.link_jpos[i][k] = link_f[i, k]
                self.link_jaxis[i][k] = link_f[i, 7 + k]
            for k in ti.static(range(4)):
                self.link_jquat[i][k] = link_f[i, 3 + k]
        for i in range(dof_i.shape[0]):
            self.dof_link[i] = dof_i[i, 0]
            self.dof_q[i] = dof_i[i, 1]
            self.dof_parent[i] = dof_i[i, 2]
            self.dof_mimic_leader[i] = dof_i[i, 3]
            self.dof_limit_lo[i] = dof_f[i, 0]
            self.dof_limit_hi[i] = dof_f[i, 1]
            self.dof_mimic_mult[i] = dof_f[i, 2]
            self.dof_mimic_off[i] = dof_f[i, 3]
        for i, j in ti.ndrange(anc.shape[0], anc.shape[1]):
            self.dof_anc[i, j] = anc[i, j]
        for t in range(anc_pairs.shape[0]):
            self.anc_i[t] = anc_pairs[t, 0]
            self.anc_j[t] = anc_pairs[t, 1]
        for k in range(sched.shape[0]):
            for c in ti.static(range(6)):
                self.sched[k, c] = sched[k, c]
            self.sched_h[k] = sched_h[k]

    @ti.kernel
    def kernel_reset_state(self, qpos0: ti.types.ndarray()):
        """Every state slot at qpos0 with zero velocity, zero controls in force mode, no NaN seen."""
        self.nan_count[None] = 0
        for i_b in range(self.cap_envs):
            self.nan_step[i_b] = NO_NAN
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                # the whole capacity: masked-out reads at clamped indices (a free joint's 7 qs and 6 dofs
                # read by a scene with fewer) must see zeros, not an earlier scene's values
                for t, i in ti.ndrange(self.n_slots, self.cap_elems):
                    self.qpos[t, i_b, i] = ti.select(i < self.n_qs, qpos0[ti.min(i, qpos0.shape[0] - 1)], 0.0)
                    self.qvel[t, i_b, i] = 0.0
                for i_d in range(self.n_dofs):
                    self.ctrl_force[i_b, i_d] = 0.0
                    self.ctrl_pos[i_b, i_d] = 0.0
                    self.ctrl_vel[i_b, i_d] = 0.0
                    self.ctrl_mode[i_b, i_d] = 0

    @ti.kernel
    def kernel_reset_nan(self, envs: ti.types.ndarray()) -> ti.i32:
        """Forget the NaN record of the envs with envs[i_b] != 0 (all of them: a full reset); returns
        how many envs stay recorded."""
        self.nan_count[None] = 0
        for i_b in range(self.cap_envs):
            keep = self.nan_step[i_b]
            if i_b < envs.shape[0]:
                if envs[i_b] != 0:
                    keep = NO_NAN
            self.nan_step[i_b] = keep
            if keep != NO_NAN:
                ti.atomic_add(self.nan_count[None], 1)
        return self.nan_count[None]

    # ------------------------------------------------------------------ kernels of the step
    # Every stage runs as its own top-level loop over envs (see kinematics.KINEMATICS).
    def kernel_dynamics(self, e: int, src: int, h: float):
        """Every dynamics stage of evaluation e at state slot src, substep length h."""
        self.kernel_dynamics_part(0, len(self.dynamics_stages), e, src, h)

    @ti.kernel
    def kernel_dynamics_part(self, k0: ti.template(), k1: ti.template(), e: ti.i32, src: ti.i32, h: float):
        """Stages k0..k1-1 of the dynamics (the gradient path's backward runs their adjoints as
        separate kernels: see _evaluation_unit)."""
        for stage in ti.static(self.dynamics_stages[k0:k1]):
            if ti.static(self.serial):
                ti.loop_config(serialize=True)
            for i_b in range(self.cap_envs):
                if i_b < self.n_envs:
                    stage(self, i_b, e, src, h)

    def kernel_kinematics(self, src: int):
        """Link poses and velocities at qpos/qvel[src] (what the getters read): the dynamics' first
        stages, so their adjoints (see RigidSolver._kinematics_unit) are the kernels the dynamics'
        backward compiles."""
        self.kernel_dynamics_part(0, len(LINK_STATE), 0, src, 0.0)

    has_contact = False
    static_tree = None  # a specialised core's dof tree (RigidCore)
    unrolled = False  # whether the no-gradient kernels unroll the factorisation over static_tree

    def kernel_factor_solve(self, e: int):
        """The solve op: qacc[e] (with contacts, the contact solver's passes around the final solve)."""
        if self.has_contact:
            self.contact.factor_solve(self, e)
        else:
            self._kernel_factor_solve(e)

    def kernel_solve_grad(self, e: int):
        if self.has_contact:
            self.contact.solve_grad(self, e)
        else:
            self._kernel_solve_grad(e)

    @ti.kernel
    def _kernel_factor_solve(self, e: ti.i32):
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                if ti.static(self.dense_solve):
                    func_factor_solve_dense(self, i_b, e)
                else:
                    func_factor_solve(self, i_b, e)

    @ti.kernel
    def _kernel_solve_grad(self, e: ti.i32):
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                if ti.static(self.dense_solve):
                    func_solve_grad_dense(self, i_b, e)
                else:
                    func_solve_grad(self, i_b, e)

    @ti.kernel
    def kernel_integrate(self, kind: ti.i32, e: ti.i32, base: ti.i32, src: ti.i32, dst: ti.i32, h: float):
        for stage in ti.static(INTEGRATE):
            if ti.static(self.serial):
                ti.loop_config(serialize=True)
            for i_b in range(self.cap_envs):
                if i_b < self.n_envs:
                    stage(self, i_b, kind, e, base, src, dst, h)

    @ti.kernel
    def kernel_step_fused(self, step: ti.i32, k0: ti.i32, k1: ti.i32, finish: ti.i32) -> ti.i32:
        """Ops k0..k1-1 of the schedule (the whole step, or one substep when another solver steps
        between substeps), all envs, one launch (no gradient bookkeeping). With `finish` the last slot
        becomes slot 0 and nan_step[i_b] records the first `step` after which env i_b's state is not
        finite (checked while copying, so nearly free). Returns how many envs have such a record: the
        scene reads that integer after every step and looks at the state only when it grew. (A
        return value, not an external array: an array argument costs ~6 us per launch to set, a
        returned integer ~0.5 us through taichi_compat's fast launch.)"""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                for k in range(k0, k1):
                    op = self.sched[k, 0]
                    kind, e, base, src, dst = self.sched[k, 1], self.sched[k, 2], self.sched[k, 3], self.sched[k, 4], self.sched[k, 5]
                    h = self.sched_h[k]
                    if op == OP_DYN:
                        for stage in ti.static(self.dynamics_stages):
                            stage(self, i_b, e, src, h)
                    elif op == OP_SOLVE:
                        if ti.static(self.has_contact):
                            func_contact_solve(self, i_b, e)
                        elif ti.static(self.dense_solve):
                            func_factor_solve_dense(self, i_b, e)
                        else:
                            func_factor_solve(self, i_b, e)
                    else:
                        for stage in ti.static(INTEGRATE):
                            stage(self, i_b, kind, e, base, src, dst, h)
                if finish:
                    bad = 0
                    for i_q in range(self.n_qs):
                        x = self.qpos[self.n_slots - 1, i_b, i_q]
                        self.qpos[0, i_b, i_q] = x
                        bad |= ti.math.isnan(x) or ti.math.isinf(x)
                    for i_d in range(self.n_dofs):
                        x = self.qvel[self.n_slots - 1, i_b, i_d]
                        self.qvel[0, i_b, i_d] = x
                        bad |= ti.math.isnan(x) or ti.math.isinf(x)
                    if bad:
                        if self.nan_step[i_b] == NO_NAN:
                            self.nan_step[i_b] = step
                            ti.atomic_add(self.nan_count[None], 1)
        return self.nan_count[None]

    @ti.kernel
    def kernel_mass_matrix(self, src: ti.i32):
        """M (without armature or implicit terms) at qpos[src]."""
        for stage in ti.static((func_forward_kinematics, func_dof_subspace, func_world_inertia) + INERTIA):
            if ti.static(self.serial):
                ti.loop_config(serialize=True)
            for i_b in range(self.cap_envs):
                if i_b < self.n_envs:
                    stage(self, i_b, 0, src, 0.0)

    @ti.kernel
    def kernel_clear_grads(self):
        """Zero every adjoint field of the scene's envs, and seed the adjoint of the solver's Tape
        scalar (see kernel_vjp). Constants, not x * 0: a NaN left by an earlier failed backward must not
        survive. One top-level loop: each costs a task to load."""
        self.vjp_loss.grad[None] = 1.0
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                func_zero_plan(self.grad_plan, i_b, self.cfg_i[I_ELEMS])

    # ------------------------------------------------------------------ state, controls, parameters I/O
    # Every torch tensor passed to a kernel costs ~30 us here, so each crossing packs its data in one:
    # state x = [qpos | qvel] (B, n_qs + n_dofs), controls c = [force; pos; vel] (B, 3, n_dofs),
    # parameters p = [mass | com | inertia | damping | armature | frictionloss | kp | kv | gravity |
    # force_lo | force_hi] (B, 13 n_links + 7 n_dofs + 3), see param_layout.
    @ti.kernel
    def kernel_set_state(self, slot: ti.i32, x: ti.types.ndarray()):
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                for i_q in range(self.n_qs):
                    self.qpos[slot, i_b, i_q] = x[i_b, i_q]
                for i_d in range(self.n_dofs):
                    self.qvel[slot, i_b, i_d] = x[i_b, self.n_qs + i_d]

    @ti.kernel
    def kernel_get_state(self, slot: ti.i32, x: ti.types.ndarray()):
        """Read the state in `slot` and make it the current state (slot 0)."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                for i_q in range(self.n_qs):
                    x[i_b, i_q] = self.qpos[slot, i_b, i_q]
                    self.qpos[0, i_b, i_q] = self.qpos[slot, i_b, i_q]
                for i_d in range(self.n_dofs):
                    x[i_b, self.n_qs + i_d] = self.qvel[slot, i_b, i_d]
                    self.qvel[0, i_b, i_d] = self.qvel[slot, i_b, i_d]

    @ti.kernel
    def kernel_vjp(self, slot: ti.i32, g: ti.types.ndarray()):
        """vjp_loss += <g, state in `slot`>: the scalar whose adjoint a step's ti.ad.Tape propagates, g
        being the gradient torch hands the step's output state (packed like kernel_get_state). The
        scalar is the core's own, its adjoint seeded to 1 by kernel_clear_grads, rather than the Tape's
        loss field: a kernel taking a field argument compiles once per field, the Tape's loss is one
        per scene, and d(Tape loss)/d(vjp_loss) = 1 either way."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                for i_q in range(self.n_qs):
                    self.vjp_loss[None] += g[i_b, i_q] * self.qpos[slot, i_b, i_q]
                for i_d in range(self.n_dofs):
                    self.vjp_loss[None] += g[i_b, self.n_qs + i_d] * self.qvel[slot, i_b, i_d]

    @ti.kernel
    def kernel_get_grads(self, g: ti.types.ndarray()):
        """g[:, :n_qs + n_dofs] <- adjoint of the state in slot 0, g[:, n_qs + n_dofs:] <- adjoint of
        the controls (force, pos, vel blocks of n_dofs)."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                nx = self.n_qs + self.n_dofs
                nd = self.n_dofs
                for i_q in range(self.n_qs):
                    g[i_b, i_q] = self.qpos.grad[0, i_b, i_q]
                for i_d in range(nd):
                    g[i_b, self.n_qs + i_d] = self.qvel.grad[0, i_b, i_d]
                    g[i_b, nx + i_d] = self.ctrl_force.grad[i_b, i_d]
                    g[i_b, nx + nd + i_d] = self.ctrl_pos.grad[i_b, i_d]
                    g[i_b, nx + 2 * nd + i_d] = self.ctrl_vel.grad[i_b, i_d]

    @ti.kernel
    def kernel_set_ctrl(self, c: ti.types.ndarray()):
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                for i_d in range(self.n_dofs):
                    self.ctrl_force[i_b, i_d] = c[i_b, 0, i_d]
                    self.ctrl_pos[i_b, i_d] = c[i_b, 1, i_d]
                    self.ctrl_vel[i_b, i_d] = c[i_b, 2, i_d]

    @ti.kernel
    def kernel_set_ctrl_mode(self, m: ti.types.ndarray()):
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                for i_d in range(self.n_dofs):
                    self.ctrl_mode[i_b, i_d] = m[i_b, i_d]

    @ti.kernel
    def kernel_set_params(self, p: ti.types.ndarray()):
        """All parameters of every env from the packed p (see param_layout)."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                L = self.n_links
                D = self.n_dofs
                for i in range(L):
                    self.link_mass[i_b, i] = p[i_b, i]
                    for k in ti.static(range(3)):
                        self.link_com[i_b, i][k] = p[i_b, L + 3 * i + k]
                    for k, l in ti.static(ti.ndrange(3, 3)):
                        self.link_inertia[i_b, i][k, l] = p[i_b, 4 * L + 9 * i + 3 * k + l]
                o = 13 * L
                for i in range(D):
                    self.dof_damping[i_b, i] = p[i_b, o + i]
                    self.dof_armature[i_b, i] = p[i_b, o + D + i]
                    self.dof_frictionloss[i_b, i] = p[i_b, o + 2 * D + i]
                    self.dof_kp[i_b, i] = p[i_b, o + 3 * D + i]
                    self.dof_kv[i_b, i] = p[i_b, o + 4 * D + i]
                    self.dof_force_lo[i_b, i] = p[i_b, o + 5 * D + 3 + i]
                    self.dof_force_hi[i_b, i] = p[i_b, o + 6 * D + 3 + i]
                for k in ti.static(range(3)):
                    self.gravity[i_b][k] = p[i_b, o + 5 * D + k]

    @ti.kernel
    def kernel_get_param_grads(self, g: ti.types.ndarray()):
        """Adjoints of the differentiable parameters into g, packed like kernel_set_params without the
        force range (B, 13 n_links + 5 n_dofs + 3)."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                L = self.n_links
                D = self.n_dofs
                for i in range(L):
                    g[i_b, i] = self.link_mass.grad[i_b, i]
                    for k in ti.static(range(3)):
                        g[i_b, L + 3 * i + k] = self.link_com.grad[i_b, i][k]
                    for k, l in ti.static(ti.ndrange(3, 3)):
                        g[i_b, 4 * L + 9 * i + 3 * k + l] = self.link_inertia.grad[i_b, i][k, l]
                o = 13 * L
                for i in range(D):
                    g[i_b, o + i] = self.dof_damping.grad[i_b, i]
                    g[i_b, o + D + i] = self.dof_armature.grad[i_b, i]
                    g[i_b, o + 2 * D + i] = self.dof_frictionloss.grad[i_b, i]
                    g[i_b, o + 3 * D + i] = self.dof_kp.grad[i_b, i]
                    g[i_b, o + 4 * D + i] = self.dof_kv.grad[i_b, i]
                for k in ti.static(range(3)):
                    g[i_b, o + 5 * D + k] = self.gravity.grad[i_b][k]

    @ti.kernel
    def kernel_get_matrix(self, which: ti.i32, out: ti.types.ndarray()):
        """The scene's block of a per-env (B, n, n) or (B, n) result: 0 the mass matrix, 1 the last
        evaluation's qacc (its slot in out[:, 0]), 2 the actuator forces."""
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                n = self.n_dofs
                if which == 0:
                    for i, j in ti.ndrange(n, n):
                        out[i_b, i, j] = self.mass_mat[i_b, i, j]
                elif which == 1:
                    for e, i in ti.ndrange(out.shape[1], n):
                        out[i_b, e, i] = self.qacc[e, i_b, i]
                else:
                    for i in range(n):
                        out[i_b, 0, i] = self.dof_tau[i_b, i]

    @ti.kernel
    def kernel_param_grad(self, x: ti.template(), g: ti.types.ndarray()):
        """Adjoint of a scalar parameter field that is not the core's (contact friction), the scene's
        (B, n) block of it (the field may be larger: pooled by capacity)."""
        for i, j in ti.ndrange(g.shape[0], g.shape[1]):
            g[i, j] = x.grad[i, j]

    # ------------------------------------------------------------------ getters
    @ti.kernel
    def kernel_link_outputs(self, pos: ti.types.ndarray(), quat: ti.types.ndarray(), vel: ti.types.ndarray(),
                            ang: ti.types.ndarray()):
        """Link origin poses and velocities (world frame) from the last kinematics evaluation."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                for i_l in range(self.n_links):
                    p = self.link_pos[i_b, i_l]
                    w = self.cvel_w[i_b, i_l]
                    v = self.cvel_v[i_b, i_l] + w.cross(p)
                    for k in ti.static(range(3)):
                        pos[i_b, i_l, k] = p[k]
                        vel[i_b, i_l, k] = v[k]
                        ang[i_b, i_l, k] = w[k]
                    for k in ti.static(range(4)):
                        quat[i_b, i_l, k] = self.link_quat[i_b, i_l][k]

    @ti.kernel
    def kernel_link_vjp(self, pos: ti.types.ndarray(), quat: ti.types.ndarray(), vel: ti.types.ndarray(),
                        ang: ti.types.ndarray()):
        """vjp_loss += <output gradients, kernel_link_outputs's outputs>, for a getter's ti.ad.Tape
        (see kernel_vjp)."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                for i_l in range(self.n_links):
                    p = self.link_pos[i_b, i_l]
                    w = self.cvel_w[i_b, i_l]
                    v = self.cvel_v[i_b, i_l] + w.cross(p)
                    q = self.link_quat[i_b, i_l]
                    acc = 0.0
                    for k in ti.static(range(3)):
                        acc += pos[i_b, i_l, k] * p[k] + vel[i_b, i_l, k] * v[k] + ang[i_b, i_l, k] * w[k]
                    for k in ti.static(range(4)):
                        acc += quat[i_b, i_l, k] * q[k]
                    self.vjp_loss[None] += acc


NO_NAN = 2**31 - 1


def _place_env_major(B, N, elem, mats, ones, slots):
    """The core's per-env fields env-major (layout.place_env_major): elem [B, N] fields, mats [B, N, N],
    ones [B], slots [(n, fields [n, B, N])], each list a group of its own."""
    place_env_major(ti.root, B, [(0, (), ones), (0, (N,), elem), (0, (N, N), mats)]
                    + [(1, (n, N), xs) for n, xs in slots])


@ti.data_oriented
class RigidCore(_Kernels):
    """The fields of one capacity class (dtype, gradients, env capacity, element capacity, state slots,
    evaluations, schedule length) and the kernels compiled on them; held by one scene at a time."""

    dynamics_stages = DYNAMICS
    dense_solve = False

    def __init__(self, key):
        f, g, B, N, S, E, n_ops, specialized, tree = key
        self.key = key
        # a specialised core (RigidOptions.specialize_kernels) compiles its fused step with gs.init's
        # optimisation setting (see taichi_compat.compile_options.ForwardCompile). Its sizes stay run-time reads: as constants they
        # measured no faster (ANYmal 1.38x vs 1.40x MuJoCo's rollout, Panda 1.93x vs 1.92x). Without
        # gradients it is one scene's dof tree (`tree`, its dof parents), whose factorisation and
        # solves the fused step unrolls (inertia.TreeSchedule)
        self.specialized = specialized
        self.static_tree = TreeSchedule.create(tree) if tree is not None else None
        self.unrolled = self.static_tree is not None and not g
        self.dtype = f
        self.requires_grad = g
        self.serial = B <= SERIAL_MAX_ENVS
        self.cap_envs, self.cap_elems = B, N
        self.n_slots, self.n_evals = S, E
        self.scene_cfg = [0] * (N_CFG_I + N_CFG_F)
        V3 = lambda shape: ti.Vector.field(3, f, shape=shape, needs_grad=g)  # noqa: E731
        V4 = lambda shape: ti.Vector.field(4, f, shape=shape, needs_grad=g)  # noqa: E731
        M3 = lambda shape: ti.Matrix.field(3, 3, f, shape=shape, needs_grad=g)  # noqa: E731
        F = lambda shape, grad=g: ti.field(f, shape=shape, needs_grad=grad)  # noqa: E731
        I = lambda shape: ti.field(ti.i32, shape=shape)  # noqa: E731, E741
        self.cfg_i, self.cfg_f = I(N_CFG_I), F(N_CFG_F, False)
        # info
        self.link_parent, self.link_jtype, self.link_q_start = I(N), I(N), I(N)
        self.link_dof_start, self.link_ndof = I(N), I(N)
        self.link_jpos = ti.Vector.field(3, f, shape=N)
        self.link_jquat = ti.Vector.field(4, f, shape=N)
        self.link_jaxis = ti.Vector.field(3, f, shape=N)
        self.dof_link, self.dof_q, self.dof_parent = I(N), I(N), I(N)
        self.dof_anc = I((N, N))
        self.anc_i, self.anc_j = I(N * N), I(N * N)
        self.dof_limit_lo, self.dof_limit_hi = F(N, False), F(N, False)
        self.dof_mimic_leader, self.dof_mimic_mult, self.dof_mimic_off = I(N), F(N, False), F(N, False)
        # per-env fields: declared without a shape and placed env-major (_place_env_major)
        s3 = lambda grad=g: ti.field(f, needs_grad=grad)  # noqa: E731
        v3 = lambda: ti.Vector.field(3, f, needs_grad=g)  # noqa: E731
        m3 = lambda: ti.Matrix.field(3, 3, f, needs_grad=g)  # noqa: E731
        # parameters
        self.link_mass, self.link_com, self.link_inertia = s3(), v3(), m3()
        self.dof_damping, self.dof_armature, self.dof_frictionloss = s3(), s3(), s3()
        self.dof_kp, self.dof_kv = s3(), s3()
        self.dof_force_lo, self.dof_force_hi = s3(False), s3(False)
        self.gravity = v3()
        # controls
        self.ctrl_force, self.ctrl_pos, self.ctrl_vel = s3(), s3(), s3()
        self.ctrl_mode = ti.field(ti.i32)
        # state
        self.qpos, self.qvel = s3(), s3()
        self.qacc, self.qvel_move = s3(), s3()  # qvel_move[e]: the velocity integration e moves qpos with
        # per-evaluation scratch
        self.link_pos, self.link_quat, self.link_R = v3(), ti.Vector.field(4, f, needs_grad=g), m3()
        self.link_cpos, self.link_h, self.link_J = v3(), v3(), m3()
        self.cdof_w, self.cdof_v, self.cdofd_w, self.cdofd_v = v3(), v3(), v3(), v3()
        self.cvel_w, self.cvel_v, self.cacc_w, self.cacc_v = v3(), v3(), v3(), v3()
        self.crb_m, self.crb_h, self.crb_J = s3(), v3(), m3()
        self.cfrc_n, self.cfrc_f = v3(), v3()
        self.dof_n, self.dof_f = v3(), v3()
        self.mass_mat, self.bias, self.force = s3(), s3(), s3()
        self.mass_fac = s3(False)
        self.dof_tau = s3(False)
        self.solve_tmp = s3(False)
        elem = [self.link_mass, self.link_com, self.link_inertia, self.dof_damping, self.dof_armature,
                self.dof_frictionloss, self.dof_kp, self.dof_kv, self.dof_force_lo, self.dof_force_hi, self.ctrl_force,
                self.ctrl_pos, self.ctrl_vel, self.ctrl_mode, self.link_pos, self.link_quat, self.link_R,
                self.link_cpos, self.link_h, self.link_J, self.cdof_w, self.cdof_v, self.cdofd_w, self.cdofd_v,
                self.cvel_w, self.cvel_v, self.cacc_w, self.cacc_v, self.crb_m, self.crb_h, self.crb_J, self.cfrc_n,
                self.cfrc_f, self.dof_n, self.dof_f, self.bias, self.force, self.dof_tau]
        mats, ones = [self.mass_mat, self.mass_fac], [self.gravity]
        slots = [(S, [self.qpos, self.qvel]), (E, [self.qacc, self.qvel_move]), (1, [self.solve_tmp])]
        _place_env_major(B, N, elem, mats, ones, slots)
        if g:
            grads = lambda xs: [x.grad for x in xs if x.grad is not None]  # noqa: E731
            _place_env_major(B, N, grads(elem), grads(mats), grads(ones), [(n, grads(xs)) for n, xs in slots])
        # per env, the first step after which its state was not finite (fused path), and how many envs
        # have one
        self.nan_step = I(B)
        self.nan_count = I(())
        self.vjp_loss = F((), True) if g else None
        # schedule
        self.sched = I((n_ops, 6))
        self.sched_h = F(n_ops, False)
        self.n_ops = n_ops
        # per-env fields by position of their env axis (zeroed at load), and the differentiable ones
        state = [self.qpos, self.qvel, self.qacc, self.qvel_move]
        params = [self.link_mass, self.link_com, self.link_inertia, self.dof_damping, self.dof_armature,
                  self.dof_frictionloss, self.dof_kp, self.dof_kv, self.gravity, self.ctrl_force, self.ctrl_pos,
                  self.ctrl_vel]
        scratch = [self.link_pos, self.link_quat, self.link_R, self.link_cpos, self.link_h, self.link_J,
                   self.cdof_w, self.cdof_v, self.cdofd_w, self.cdofd_v, self.cvel_w, self.cvel_v, self.cacc_w,
                   self.cacc_v, self.crb_m, self.crb_h, self.crb_J, self.cfrc_n, self.cfrc_f, self.dof_n, self.dof_f,
                   self.mass_mat, self.bias, self.force]
        self.zero_plan = _ZeroPlan([self.mass_mat, self.cdof_w, self.cdof_v, self.cdofd_w, self.cdofd_v], [], N)
        self.grad_fields0 = [x.grad for x in params + scratch] if g else []
        self.grad_fields1 = [x.grad for x in state] if g else []
        self.grad_plan = _ZeroPlan(self.grad_fields0, self.grad_fields1, N)


@ti.data_oriented
class _SceneOwner(_Kernels):
    """A scene's view of its core that also owns the scene's own dynamics stages: its contact solver
    and/or its external wrenches. The kernels that include them compile on this object; every other
    field and size read goes to the core. With a contact solver alone it is pooled (_Pool.acquire_owner)
    and serves later scenes of its contact class; with external wrenches it is the scene's own."""

    dense_solve = False

    def __init__(self, core, contact, external):
        self.core = core
        self.contact = contact
        self.external = external
        extra = [x for x in (contact, external) if x is not None]
        self.dynamics_stages = DYNAMICS + sum((tuple(x.stages) for x in extra), ())
        self.dense_solve = bool(contact is not None and contact.dense)
        self.has_contact = contact is not None
        self.static_tree, self.unrolled = core.static_tree, core.unrolled
        if core.requires_grad:
            self.grad_plan = _ZeroPlan(core.grad_fields0, core.grad_fields1, core.cap_elems,
                                       [f.grad for x in extra for f in x.grad_fields])

    def __getattr__(self, name):
        return getattr(self.__dict__["core"], name)


class _Pool:
    """Free cores by capacity class. A scene takes one (or has one made) and a finaliser gives it
    back when the scene's solver dies."""

    def __init__(self):
        self.free = {}
        self.taken = {}  # key -> number of cores held by live scenes
        # scene owners with a contact solver, by core key: each keeps its core and its compiled kernels
        self.owners_free = {}
        self.owners_taken = 0

    def acquire(self, key):
        free = self.free.setdefault(key, [])
        if not free and self.taken.get(key, 0):
            # scenes that are only garbage still hold their cores: a collection is far cheaper than a compile
            gc.collect()
        self.taken[key] = self.taken.get(key, 0) + 1
        return (free.pop(), True) if free else (RigidCore(key), False)

    def release(self, core):
        self.taken[core.key] -= 1
        self.free.setdefault(core.key, []).append(core)

    def acquire_owner(self, key, plan):
        """(owner, reused) for a scene of core class `key` with a contact plan: a free _SceneOwner whose
        contact solver fits the plan (its kernels already compiled), else a new one on a core of the
        class. The owner keeps that core for good (its kernels are compiled on the core's fields)."""
        for attempt in range(2):
            free = self.owners_free.get(key, [])
            fit = [o for o in free if o.contact.fits(plan)]
            if fit:
                # the smallest that fits: a later, larger scene may still find the larger ones
                o = min(fit, key=lambda o: o.contact.caps)
                free.remove(o)
                self.owners_taken += 1
                return o, True
            if attempt == 0 and self.owners_taken:
                gc.collect()  # dead scenes still holding owners give them back
        from .contact import ContactSolver

        core, _ = self.acquire(key)
        self.owners_taken += 1
        return _SceneOwner(core, ContactSolver(core, plan), None), False

    def release_owner(self, owner):
        self.owners_taken -= 1
        self.owners_free.setdefault(owner.core.key, []).append(owner)

    def clear(self):
        """Forget the free cores and owners (their fields stay allocated until Taichi is reset): the next
        scene of every class allocates a new core."""
        self.free.clear()
        self.owners_free.clear()


POOL = _Pool()


class _SceneBlock:
    """A per-env result field of the core seen as the scene's exact shape (what `to_torch` returns)."""

    def __init__(self, solver, field, which):
        self._solver, self._field, self._which = solver, field, which

    @property
    def grad(self):
        return self._field.grad

    @property
    def shape(self):
        s = self._solver
        return {0: (s.n_envs, s.n_dofs, s.n_dofs), 1: (s.n_evals, s.n_envs, s.n_dofs), 2: (s.n_envs, s.n_dofs)}[self._which]

    def to_numpy(self):
        return self.to_torch().numpy()

    def to_torch(self, device=None):
        import torch  # solvers never import torch at module level; this reader is for the scene's side

        s = self._solver
        B, D = s.n_envs, s.n_dofs
        dt = torch.float64 if s.np_dtype == np.float64 else torch.float32
        if self._which == 0:
            out = torch.empty(B, D, D, dtype=dt)
        else:
            out = torch.empty(B, s.n_evals if self._which == 1 else 1, D, dtype=dt)
        if B * D:
            s.core.kernel_get_matrix(self._which, out)
        if self._which == 1:
            out = out.transpose(0, 1).contiguous()
        elif self._which == 2:
            out = out[:, 0]
        return out.to(device) if device is not None else out


class RigidSolver:
    """Generalised-coordinate rigid dynamics of all rigid entities of one scene.

    models: the entities' numpy descriptions; n_envs >= 1 parallel environments; dt the step (s);
    substeps per step; integrator a schedule.Integrator; requires_grad allocates adjoint storage.
    The fields live in `self.core` (a pooled RigidCore, see the module docstring).
    """

    NO_NAN = NO_NAN

    def __init__(self, models: List[EntityModel], n_envs: int, dt: float, substeps: int, integrator: int,
                 gravity, dtype, requires_grad: bool, enable_joint_limit: bool, limit_k: float, limit_d: float,
                 contact_options=None, mimic=False, external_wrench=False, specialize=None):
        self.models = models
        self.dtype = dtype
        self.np_dtype = np.float64 if dtype == ti.f64 else np.float32
        self.n_envs = n_envs
        self.dt = dt
        self.substeps = substeps
        self.integrator = integrator
        self.implicit = integrator == Integrator.implicitfast
        self.implicit_on = 1.0 if self.implicit else 0.0
        self.requires_grad = requires_grad
        self.enable_joint_limit = enable_joint_limit
        self.limits_on = bool(enable_joint_limit)
        self.limit_k = limit_k
        self.limit_d = limit_d
        self._layout(models, bool(mimic))
        self._schedule()
        # n_links + 1: a root link reads its parent from a slot no link occupies (kinematics.func_parent_slot)
        self.specialized = bool(n_envs >= SPECIALIZE_MIN_ENVS if specialize is None else specialize)
        tree = tuple(int(p) for p in self.np_dof_parent) if self.specialized and not requires_grad else None
        if tree is not None and TreeSchedule.create(tree) is None:
            tree = None
        key = (dtype, bool(requires_grad), _cap_envs(n_envs), _cap_elems(max(self.n_links + 1, self.n_dofs, self.n_qs)),
               self.n_slots, self.n_evals, len(self.ops), self.specialized, tree)
        # Contacts plug in as extra dynamics stages after the generalised force (they add J^T f into
        # `force`); no plan when the scene has no collision pairs, so nothing is compiled for them.
        plan = None
        if contact_options is not None:
            from .contact import ContactPlan

            plan = ContactPlan.create(self, models, contact_options, self.specialized)
        self.contact = None
        self.external = None
        if plan is not None and not external_wrench:
            # the scene's owner (core + contact solver) from the pool: a scene of the same contact class
            # reuses the kernels compiled on it
            self.owner, self.reused_core = POOL.acquire_owner(key, plan)
            self.core = self.owner.core
            self.contact = self.owner.contact
            weakref.finalize(self, POOL.release_owner, self.owner)
        else:
            self.core, self.reused_core = POOL.acquire(key)
            weakref.finalize(self, POOL.release, self.core)
            if plan is not None:
                from .contact import ContactSolver

                self.contact = ContactSolver(self.core, plan)
            # external wrenches per substep (written by the rigid-MPM coupler), see external.py
            if external_wrench:
                from .external import ExternalWrench

                self.external = ExternalWrench(self.n_envs, self.substeps, self.np_link_parent,
                                               self.evals_per_substep, self.dtype, self.requires_grad)
            if self.contact is None and self.external is None:
                self.owner = self.core
            else:
                self.owner = _SceneOwner(self.core, self.contact, self.external)
        self.serial = self.core.serial
        self.core.scene_cfg = self._cfg()
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
        self.dynamics_stages = self.owner.dynamics_stages
        # contacts between two moving bodies couple dofs outside the tree sparsity: dense factorisation
        self.dense_solve = self.owner.dense_solve
        self.mass_mat = _SceneBlock(self, self.core.mass_mat, 0)
        self.qacc = _SceneBlock(self, self.core.qacc, 1)
        self.dof_tau = _SceneBlock(self, self.core.dof_tau, 2)
        self._fill_info(gravity)
        self._scratch = None  # the (e, src, h) whose evaluation the scratch fields hold, if any
        self._fused_ready = False  # kernel_step_fused compiled (see taichi_compat.compile_options.ForwardCompile)
        self.evaluate = self._evaluation_unit()
        self.kernel_kinematics = self._kinematics_unit()

    def __getattr__(self, name):
        # the core's fields (qpos, qvel, link_pos, ...) read as the solver's, as before pooling
        if name != "core" and "core" in self.__dict__ and not name.startswith("__"):
            return getattr(self.__dict__["core"], name)
        raise AttributeError(name)

    # ------------------------------------------------------------------ build
    def _layout(self, models, use_mimic):
        parent, jtype, qstart, dstart, ndof, jpos, jquat, jaxis, ent = [], [], [], [], [], [], [], [], []
        self.entity_link_start, self.entity_q_start, self.entity_dof_start = [], [], []
        q0, lo, hi, eff, damp, fl, arm = [], [], [], [], [], [], []
        mass, com, inertia = [], [], []
        dof_link, dof_q = [], []
        nl = nq = nd = 0
        for i_e, m in enumerate(models):
            self.entity_link_start.append(nl)
            self.entity_q_start.append(nq)
            self.entity_dof_start.append(nd)
            for l in m.links:
                parent.append(l.parent + nl if l.parent >= 0 else -1)
                jtype.append(JTYPE[l.joint_type])
                qstart.append(nq)
                dstart.append(nd)
                ndof.append(JOINT_NV[l.joint_type])
                jpos.append(l.joint_pos if l.joint_type != "free" else np.zeros(3))
                jquat.append(l.joint_quat if l.joint_type != "free" else np.array([1.0, 0, 0, 0]))
                jaxis.append(l.joint_axis)
                ent.append(i_e)
                mass.append(l.mass)
                com.append(l.com)
                inertia.append(l.inertia)
                if l.joint_type == "free":
                    q0.extend(list(l.joint_pos) + list(l.joint_quat))
                    for k in range(6):
                        dof_link.append(len(parent) - 1)
                        dof_q.append(-1)
                        lo.append(-np.inf); hi.append(np.inf); eff.append(np.inf)
                        damp.append(0.0); fl.append(0.0); arm.append(0.0)
                elif l.joint_type in ("revolute", "prismatic"):
                    q0.append(0.0)
                    dof_link.append(len(parent) - 1)
                    dof_q.append(nq)
                    lo.append(l.limit[0]); hi.append(l.limit[1])
                    # URDFs write effort="0" for 'unspecified': no limit
                    eff.append(l.effort if l.effort > 0 else np.inf)
                    damp.append(l.damping); fl.append(l.frictionloss); arm.append(l.armature)
                nq += JOINT_NQ[l.joint_type]
                nd += JOINT_NV[l.joint_type]
            nl += m.n_links
        self.n_links, self.n_qs, self.n_dofs = nl, nq, nd
        self.qpos_len, self.qvel_len = max(nq, 1), max(nd, 1)  # clamp bounds of masked-out reads
        self.np_link_parent = np.array(parent, dtype=np.int32)
        self.np_link_jtype = np.array(jtype, dtype=np.int32)
        self.np_link_q_start = np.array(qstart, dtype=np.int32)
        self.np_link_dof_start = np.array(dstart, dtype=np.int32)
        self.np_link_ndof = np.array(ndof, dtype=np.int32)
        self.np_link_jpos = np.array(jpos, dtype=float).reshape(nl, 3)
        self.np_link_jquat = np.array(jquat, dtype=float).reshape(nl, 4)
        self.np_link_jaxis = np.array(jaxis, dtype=float).reshape(nl, 3)
        self.np_link_entity = np.array(ent, dtype=np.int32)
        self.np_link_mass = np.array(mass, dtype=float).reshape(nl)
        self.np_link_com = np.array(com, dtype=float).reshape(nl, 3)
        self.np_link_inertia = np.array(inertia, dtype=float).reshape(nl, 3, 3)
        self.np_qpos0 = np.array(q0, dtype=float).reshape(nq)
        self.np_dof_link = np.array(dof_link, dtype=np.int32)
        self.np_dof_q = np.array(dof_q, dtype=np.int32)
        self.np_dof_limit = np.stack([np.array(lo, float), np.array(hi, float)], -1).reshape(nd, 2)
        self.np_dof_effort = np.array(eff, dtype=float).reshape(nd)
        self.np_dof_damping = np.array(damp, dtype=float).reshape(nd)
        self.np_dof_frictionloss = np.array(fl, dtype=float).reshape(nd)
        self.np_dof_armature = np.array(arm, dtype=float).reshape(nd)
        # dof tree: a dof's parent is the previous dof of its link, else the last dof of the
        # nearest ancestor link that has dofs
        dof_parent = np.full(nd, -1, dtype=np.int32)
        for i_d in range(nd):
            i_l = dof_link[i_d]
            if i_d > dstart[i_l]:
                dof_parent[i_d] = i_d - 1
            else:
                p = parent[i_l]
                while p >= 0 and ndof[p] == 0:
                    p = parent[p]
                dof_parent[i_d] = dstart[p] + ndof[p] - 1 if p >= 0 else -1
        self.np_dof_parent = dof_parent
        # URDF <mimic>: follower dof -> leader dof of the same entity
        self.np_mimic = np.zeros((max(nd, 1), 3))
        self.np_mimic[:, 0] = -1
        if use_mimic:
            for i_e, m in enumerate(models):
                dof_of = {}
                d = self.entity_dof_start[i_e]
                for l in m.links:
                    if l.joint_type in ("revolute", "prismatic"):
                        dof_of[l.joint_name] = d
                    d += JOINT_NV[l.joint_type]
                for l in m.links:
                    if l.mimic is not None and l.joint_name in dof_of and l.mimic.joint in dof_of:
                        self.np_mimic[dof_of[l.joint_name]] = (dof_of[l.mimic.joint], l.mimic.multiplier, l.mimic.offset)
        self.has_mimic = bool((self.np_mimic[:, 0] >= 0).any())
        anc = np.zeros((max(nd, 1), max(nd, 1)), dtype=np.int32)
        for i in range(nd):
            j = i
            while j >= 0:
                anc[i, j] = 1
                j = dof_parent[j]
        self.np_dof_anc = anc
        pairs = [(i, j) for i in range(nd) for j in range(i + 1) if anc[i, j]]
        self.np_anc_pairs = np.array(pairs, dtype=np.int32).reshape(-1, 2)

    def _schedule(self):
        """The step's ops and slots (schedule.StepSchedule) as attributes of the solver."""
        sched = StepSchedule(self.integrator, self.dt, self.substeps)
        for name in ("ops", "n_ops", "n_slots", "n_evals", "evals_per_substep", "substep_first_op", "substep_ops",
                     "substep_slot", "last_slot"):
            setattr(self, name, getattr(sched, name))

    def _cfg(self):
        cfg = [0] * N_CFG_I + [0.0] * N_CFG_F
        cfg[I_ENVS], cfg[I_LINKS], cfg[I_DOFS], cfg[I_QS] = self.n_envs, self.n_links, self.n_dofs, self.n_qs
        cfg[I_QPOS_LEN], cfg[I_QVEL_LEN], cfg[I_LIMITS_ON] = self.qpos_len, self.qvel_len, int(self.limits_on)
        cfg[I_ELEMS] = max(self.n_links, self.n_dofs, self.n_qs, 1)
        cfg[I_ANC] = len(self.np_anc_pairs)
        cfg[N_CFG_I + F_LIMIT_K] = float(self.limit_k)
        cfg[N_CFG_I + F_LIMIT_D] = float(self.limit_d)
        cfg[N_CFG_I + F_IMPLICIT_ON] = float(self.implicit_on)
        return cfg

    def param_layout(self):
        """[(name, width per env)] of the packed parameter tensor of kernel_set_params, in order."""
        L, D = self.n_links, self.n_dofs
        return [("mass", L), ("com", 3 * L), ("inertia", 9 * L), ("damping", D), ("armature", D),
                ("frictionloss", D), ("kp", D), ("kv", D), ("gravity", 3), ("force_lo", D), ("force_hi", D)]

    def initial_params(self, gravity):
        """numpy (n_envs, ...) arrays of every parameter of param_layout as built from the models."""
        B = self.n_envs
        tile = lambda a: np.ascontiguousarray(np.broadcast_to(a, (B,) + a.shape)).astype(self.np_dtype)  # noqa: E731
        big = np.finfo(self.np_dtype).max
        eff = np.clip(self.np_dof_effort, 0, big)
        zeros = np.zeros(self.n_dofs)
        return {"mass": tile(self.np_link_mass), "com": tile(self.np_link_com), "inertia": tile(self.np_link_inertia),
                "damping": tile(self.np_dof_damping), "armature": tile(self.np_dof_armature),
                "frictionloss": tile(self.np_dof_frictionloss), "kp": tile(zeros), "kv": tile(zeros),
                "gravity": tile(np.asarray(gravity, dtype=float)), "force_lo": tile(-eff), "force_hi": tile(eff)}

    def _fill_info(self, gravity):
        L, D = self.n_links, self.n_dofs
        pad = lambda a, n: a if len(a) else np.zeros((1,) + a.shape[1:], a.dtype)  # noqa: E731
        cfg = self.core.scene_cfg
        cfg_i = np.array(cfg[:N_CFG_I], dtype=np.int32)
        cfg_f = np.array(cfg[N_CFG_I:], dtype=self.np_dtype)
        link_i = np.stack([pad(a, L) for a in (self.np_link_parent, self.np_link_jtype, self.np_link_q_start,
                                                 self.np_link_dof_start, self.np_link_ndof)], -1).astype(np.int32)
        link_f = np.concatenate([pad(self.np_link_jpos, L), pad(self.np_link_jquat, L), pad(self.np_link_jaxis, L)],
                                -1).astype(self.np_dtype)
        # "no limit" as a large finite number: infinities turn masked-out terms into NaN
        lim = np.clip(pad(self.np_dof_limit, D), -1e30, 1e30)
        dof_i = np.stack([pad(self.np_dof_link, D), pad(self.np_dof_q, D), pad(self.np_dof_parent, D),
                          self.np_mimic[:, 0].astype(np.int32)], -1).astype(np.int32)
        dof_f = np.concatenate([lim, self.np_mimic[:, 1:]], -1).astype(self.np_dtype)
        sched = np.ascontiguousarray(np.array([op[:6] for op in self.ops], dtype=np.int32))
        sched_h = np.array([op[6] for op in self.ops], dtype=self.np_dtype)
        self.core.kernel_load(cfg_i, cfg_f, np.ascontiguousarray(link_i), np.ascontiguousarray(link_f),
                              np.ascontiguousarray(dof_i), np.ascontiguousarray(dof_f), self.np_dof_anc,
                              np.ascontiguousarray(pad(self.np_anc_pairs, 1)), sched, sched_h)
        p = self.initial_params(gravity)
        self.set_params(np.concatenate([p[k].reshape(self.n_envs, -1) for k, _ in self.param_layout()], -1))
        self.reset_state()

    def set_params(self, packed):
        """Every parameter from one (n_envs, sum of param_layout widths) array or tensor."""
        self.core.kernel_set_params(packed)

    def reset_state(self):
        """Initial state (URDF zero pose, free bases at their morph placement, zero velocity),
        zero controls in force mode."""
        self.core.kernel_reset_state(np.ascontiguousarray(np.pad(self.np_qpos0, (0, 1)).astype(self.np_dtype)))

    # ------------------------------------------------------------------ python entry points
    def _fused(self, step, k0, k1, finish):
        """Launch the fused step; returns the number of envs with a NaN record (see kernel_step_fused)."""
        if self._fused_ready or self.specialized:
            return self.owner.kernel_step_fused(step, k0, k1, finish)
        with ForwardCompile():
            n = self.owner.kernel_step_fused(step, k0, k1, finish)
        self._fused_ready = True
        return n

    def step(self, step: int = 0):
        """One step without gradient bookkeeping: the state moves from slot 0 to slot 0."""
        self._scratch = None
        n = self._fused(step, 0, self.n_ops, 1)
        if self.contact is not None:  # a contact that ended the step deep inside a body warns once
            self.contact.watch(step, self.n_evals, self.dt / self.substeps)
        return n

    def substep_fused(self, step: int, i: int):
        """Substep i without gradient bookkeeping (scenes where another solver steps between
        substeps); the last substep makes its result the current state (slot 0)."""
        self._scratch = None
        n = self._fused(step, self.substep_first_op[i], self.substep_first_op[i + 1], int(i == self.substeps - 1))
        if self.contact is not None and i == self.substeps - 1:
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
        and M_bar = -f_bar qacc^T) and Taichi's adjoint of the dynamics kernel, stage by stage in reverse
        order: the same computation as the adjoint of one kernel of every stage, but Taichi
        compiles an adjoint in time superlinear in its size (the Panda's 13 stages: 9 s as separate
        kernels, 24 s as one). The generalised force shares the kernel of the stage before it: its
        adjoint alone left ~1e-250 (not 0) in the gradient of an env outside the loss
        (tests/test_gradients.py::test_batched_environments_each_get_their_own_gradient)."""
        owner = self.owner
        bounds = [k for k, f in enumerate(owner.dynamics_stages) if f is not func_generalized_force or k == 0]
        bounds.append(len(owner.dynamics_stages))
        parts = [(k0, k1, all(f in PLAIN_ADJOINT for f in owner.dynamics_stages[k0:k1]))
                 for k0, k1 in ((bounds[i], bounds[i + 1]) for i in range(len(bounds) - 2, -1, -1))]

        @ti.ad.grad_replaced
        def evaluate(e, src, h):
            owner.kernel_dynamics(e, src, h)
            owner.kernel_factor_solve(e)
            self._scratch = (e, src, h)

        @ti.ad.grad_for(evaluate)
        def evaluate_grad(e, src, h):
            if self._scratch != (e, src, h):
                owner.kernel_dynamics(e, src, h)
                owner.kernel_factor_solve(e)
                self._scratch = (e, src, h)
            owner.kernel_solve_grad(e)
            for k0, k1, plain in parts:
                with AdjointCompile(plain):
                    owner.kernel_dynamics_part.grad(k0, k1, e, src, h)

        return evaluate

    def _kinematics_unit(self):
        """kernel_kinematics(src) as one call on a tape (the getters'), its adjoint stage by stage in
        reverse order (see _evaluation_unit). The coupler launches the core's kernel itself: its calls
        run inside the MPM substep's own grad_replaced adjoint, where a nested one is not recorded."""
        core = self.core
        stages = range(len(LINK_STATE) - 1, -1, -1)
        assert DYNAMICS[: len(LINK_STATE)] == LINK_STATE and set(LINK_STATE) <= set(PLAIN_ADJOINT)

        @ti.ad.grad_replaced
        def kinematics(src):
            with ForwardCompile():
                core.kernel_kinematics(src)

        @ti.ad.grad_for(kinematics)
        def kinematics_grad(src):
            with AdjointCompile(True):  # LINK_STATE is in PLAIN_ADJOINT
                for k in stages:
                    core.kernel_dynamics_part.grad(k, k + 1, 0, src, 0.0)

        return kinematics

    def scratch_overwritten(self):
        """Called by every launch outside `evaluate` that writes the scratch fields (getters' kinematics,
        the mass matrix, the fused step, the coupler), so a pending adjoint recomputes its evaluation."""
        self._scratch = None

    def kernel_clear_grads(self):
        self.owner.kernel_clear_grads()

    def kernel_mass_matrix(self, src: int):
        self.core.kernel_mass_matrix(src)

    def reset_nan(self, envs=None):
        """Forget the NaN record of the envs flagged in `envs` (numpy bool/int (n_envs,); None: all).
        Returns how many envs stay recorded."""
        mask = np.ones(self.n_envs, np.int32) if envs is None else np.ascontiguousarray(envs, dtype=np.int32)
        return int(self.core.kernel_reset_nan(mask))

    def get_param_grad(self, x, g):
        """Adjoint of a (B, n) parameter field outside the core (contact friction) into the tensor g."""
        self.core.kernel_param_grad(getattr(x, "field", x), g)
