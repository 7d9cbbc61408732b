"""RigidSolver: owns the Taichi fields of every rigid entity of a scene and advances them.

Static model data lives in `*_info`-style fields set once at build (link_*, dof_* without an env
axis); parameters and controls have an env axis [i_b, ...]; state has a slot axis [t, i_b, ...]
holding the step's schedule of intermediate states (two slots for plain Euler, so memory does not grow
with the horizon); per-evaluation scratch (poses, inertias, forces) is written once per evaluation.

A step is a schedule of ops per substep (dynamics + factor-solve at a slot, integrate, copy-back).
Without gradients it runs as one fused kernel. With gradients each substep runs op by op
(`substep(i)`) so that the scene can record it on a `ti.ad.Tape` (genesis_lite/simulator.py): an
evaluation (dynamics + factor-solve) is one `ti.ad.grad_replaced` call whose adjoint, registered with
`ti.ad.grad_for`, recomputes the evaluation's scratch when a later one has overwritten it, runs the
hand-written adjoint of the factor-solve and then Taichi's adjoint of the dynamics kernel;
integration kernels are recorded as they are.
"""

from typing import List

import numpy as np
import taichi as ti

from .actuation import func_generalized_force
from .bias import BIAS
from .contact import func_factor_solve_dense, func_solve_grad_dense
from .inertia import INERTIA, func_factor_solve, func_solve_grad
from .integrate import INT_EULER, INT_RK_FINAL, INT_RK_STAGE, INTEGRATE
from .kinematics import (JOINT_FIXED, JOINT_FREE, JOINT_PRISMATIC, JOINT_REVOLUTE, KINEMATICS, LINK_STATE,
                         func_dof_subspace, func_forward_kinematics, func_world_inertia)
from .model import JOINT_NQ, JOINT_NV, EntityModel

OP_DYN, OP_SOLVE, OP_INT, OP_COPY = 0, 1, 2, 3
JTYPE = {"fixed": JOINT_FIXED, "free": JOINT_FREE, "revolute": JOINT_REVOLUTE, "prismatic": JOINT_PRISMATIC}
INTEGRATOR_EULER, INTEGRATOR_IMPLICITFAST, INTEGRATOR_RK4 = 0, 1, 2
# parallel dispatch of a Taichi CPU kernel costs ~70 us here against ~12 us serial: few envs run serially
SERIAL_MAX_ENVS = 16
DYNAMICS = KINEMATICS + INERTIA + BIAS + (func_generalized_force,)


@ti.data_oriented
class RigidSolver:
    """Generalised-coordinate rigid dynamics of all rigid entities of one scene.

    models: the entities' numpy descriptions; n_envs >= 1 parallel environments; dt the step (s);
    substeps per step; integrator one of INTEGRATOR_*; requires_grad allocates adjoint storage.
    """

    def __init__(self, models: List[EntityModel], n_envs: int, dt: float, substeps: int, integrator: int,
                 gravity, dtype, requires_grad: bool, enable_joint_limit: bool, limit_k: float, limit_d: float,
                 contact_options=None, mimic=False, external_wrench=False):
        self.models = models
        self.dtype = dtype
        self.np_dtype = np.float64 if dtype == ti.f64 else np.float32
        self.n_envs = n_envs
        self.dt = dt
        self.substeps = substeps
        self.integrator = integrator
        self.implicit = integrator == INTEGRATOR_IMPLICITFAST
        self.implicit_on = 1.0 if self.implicit else 0.0
        self.requires_grad = requires_grad
        self.enable_joint_limit = enable_joint_limit
        self.limits_on = bool(enable_joint_limit)
        self.limit_k = limit_k
        self.limit_d = limit_d
        self.serial = n_envs <= SERIAL_MAX_ENVS
        self._layout(models, bool(mimic))
        self._schedule()
        self._allocate()
        # Contacts plug in as extra dynamics stages after the generalised force (they add J^T f into
        # `force` with +=); None when the scene has no collision pairs, so nothing is compiled for them.
        self.contact = None
        if contact_options is not None:
            from .contact import ContactSolver

            self.contact = ContactSolver.create(self, models, contact_options)
        self.dynamics_stages = DYNAMICS + (self.contact.stages if self.contact is not None else ())
        # external wrenches per substep (ext_f, ext_t: written by the rigid-MPM coupler)
        self.external = bool(external_wrench)
        if self.external:
            from .external import EXTERNAL_STAGES

            B, L, f, g = self.n_envs, max(self.n_links, 1), self.dtype, self.requires_grad
            self.ext_f = ti.Vector.field(3, f, shape=(self.substeps, B, L), needs_grad=g)
            self.ext_t = ti.Vector.field(3, f, shape=(self.substeps, B, L), needs_grad=g)
            self.ext_sum_f = ti.Vector.field(3, f, shape=(B, L), needs_grad=g)
            self.ext_sum_t = ti.Vector.field(3, f, shape=(B, L), needs_grad=g)
            self.dynamics_stages = self.dynamics_stages + EXTERNAL_STAGES
            if g:
                self.grad_fields = self.grad_fields + [self.ext_f, self.ext_t, self.ext_sum_f, self.ext_sum_t]
        # contacts between two moving bodies couple dofs outside the tree sparsity: dense factorisation
        self.dense_solve = self.contact is not None and self.contact.dense
        if self.contact is not None and requires_grad:
            self.grad_fields = self.grad_fields + list(self.contact.grad_fields)
        self._fill_info(gravity)
        self._scratch = None  # the (e, src, h) whose evaluation the scratch fields hold, if any
        self.evaluate = self._evaluation_unit()

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
        self.qpos_len, self.qvel_len = max(nq, 1), max(nd, 1)  # field lengths (never 0)
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

    def _schedule(self):
        """The ops of one step, (op, kind, e, base, src, dst, h), and where each substep's begin in
        that list (substep i moves the state from slot substep_slot[i] to substep_slot[i + 1])."""
        h = self.dt / self.substeps
        ops, first = [], []
        if self.integrator == INTEGRATOR_RK4:
            for i in range(self.substeps):
                first.append(len(ops))
                base = 4 * i
                for k, c in enumerate((0.5, 0.5, 1.0, 1.0)):
                    e = 4 * i + k
                    ops.append((OP_DYN, 0, e, base, base + k, 0, c * h))
                    ops.append((OP_SOLVE, 0, e, base, base + k, 0, 0.0))
                    if k < 3:
                        ops.append((OP_INT, INT_RK_STAGE, e, base, base + k, base + k + 1, c * h))
                    else:
                        ops.append((OP_INT, INT_RK_FINAL, e, base, base + k, base + 4, h))
            self.n_slots, self.n_evals = 4 * self.substeps + 1, 4 * self.substeps
            self.evals_per_substep = 4
        else:
            for i in range(self.substeps):
                first.append(len(ops))
                ops.append((OP_DYN, 0, i, i, i, 0, h))
                ops.append((OP_SOLVE, 0, i, i, i, 0, 0.0))
                ops.append((OP_INT, INT_EULER, i, i, i, i + 1, h))
            self.n_slots, self.n_evals = self.substeps + 1, self.substeps
            self.evals_per_substep = 1
        self.ops = ops
        self.substep_first_op = first + [len(ops)]
        self.substep_ops = [ops[first[i]:self.substep_first_op[i + 1]] for i in range(self.substeps)]
        per = (self.n_slots - 1) // self.substeps
        self.substep_slot = [per * i for i in range(self.substeps + 1)]
        self.last_slot = self.n_slots - 1

    def _allocate(self):
        B, L, D, Q = self.n_envs, max(self.n_links, 1), max(self.n_dofs, 1), max(self.n_qs, 1)
        S, E = self.n_slots, self.n_evals
        f, g = self.dtype, self.requires_grad
        V3 = lambda shape: ti.Vector.field(3, f, shape=shape, needs_grad=g)  # noqa: E731
        V4 = lambda shape: ti.Vector.field(4, f, shape=shape, needs_grad=g)  # noqa: E731
        M3 = lambda shape: ti.Matrix.field(3, 3, f, shape=shape, needs_grad=g)  # noqa: E731
        F = lambda shape, grad=g: ti.field(f, shape=shape, needs_grad=grad)  # noqa: E731
        I = lambda shape: ti.field(ti.i32, shape=shape)  # noqa: E731, E741
        # info
        self.link_parent, self.link_jtype, self.link_q_start = I(L), I(L), I(L)
        self.link_dof_start, self.link_ndof = I(L), I(L)
        self.link_jpos = ti.Vector.field(3, f, shape=L)
        self.link_jquat = ti.Vector.field(4, f, shape=L)
        self.link_jaxis = ti.Vector.field(3, f, shape=L)
        self.dof_link, self.dof_q, self.dof_parent = I(D), I(D), I(D)
        self.dof_anc = I((D, D))
        self.dof_limit_lo, self.dof_limit_hi = F(D, False), F(D, False)
        self.dof_mimic_leader, self.dof_mimic_mult, self.dof_mimic_off = I(D), F(D, False), F(D, False)
        # parameters
        self.link_mass, self.link_com, self.link_inertia = F((B, L)), V3((B, L)), M3((B, L))
        self.dof_damping, self.dof_armature, self.dof_frictionloss = F((B, D)), F((B, D)), F((B, D))
        self.dof_kp, self.dof_kv = F((B, D)), F((B, D))
        self.dof_force_lo, self.dof_force_hi = F((B, D), False), F((B, D), False)
        self.gravity = V3(B)
        # controls
        self.ctrl_force, self.ctrl_pos, self.ctrl_vel = F((B, D)), F((B, D)), F((B, D))
        self.ctrl_mode = I((B, D))
        # state
        self.qpos, self.qvel = F((S, B, Q)), F((S, B, D))
        self.qacc, self.veff = F((E, B, D)), F((E, B, D))
        # per-evaluation scratch
        self.link_pos, self.link_quat, self.link_R = V3((B, L)), V4((B, L)), M3((B, L))
        self.link_cpos, self.link_h, self.link_J = V3((B, L)), V3((B, L)), M3((B, L))
        self.cdof_w, self.cdof_v, self.cdofd_w, self.cdofd_v = V3((B, D)), V3((B, D)), V3((B, D)), V3((B, D))
        self.cvel_w, self.cvel_v, self.cacc_w, self.cacc_v = V3((B, L)), V3((B, L)), V3((B, L)), V3((B, L))
        self.crb_m, self.crb_h, self.crb_J = F((B, L)), V3((B, L)), M3((B, L))
        self.cfrc_n, self.cfrc_f = V3((B, L)), V3((B, L))
        self.mass_mat, self.bias, self.force = F((B, D, D)), F((B, D)), F((B, D))
        self.mass_fac = F((B, D, D), False)
        self.dof_tau = F((B, D), False)
        self.solve_tmp = F((1, B, D), False)
        self.energy = F((B, 2), False)
        self.bad_idx = ti.field(ti.i32, shape=())
        self.nan_step = ti.field(ti.i32, shape=())  # first step whose state was not finite (fused path)
        # schedule
        n_ops = len(self.ops)
        self.sched = ti.field(ti.i32, shape=(n_ops, 6))
        self.sched_h = ti.field(f, shape=n_ops)
        self.n_ops = n_ops
        self.grad_fields = [x for x in (
            self.link_mass, self.link_com, self.link_inertia, self.dof_damping, self.dof_armature,
            self.dof_frictionloss, self.dof_kp, self.dof_kv, self.gravity, self.ctrl_force, self.ctrl_pos,
            self.ctrl_vel, self.qpos, self.qvel, self.qacc, self.veff, self.link_pos, self.link_quat,
            self.link_R, self.link_cpos, self.link_h, self.link_J, self.cdof_w, self.cdof_v, self.cdofd_w,
            self.cdofd_v, self.cvel_w, self.cvel_v, self.cacc_w, self.cacc_v, self.crb_m, self.crb_h,
            self.crb_J, self.cfrc_n, self.cfrc_f, self.mass_mat, self.bias, self.force)] if g else []

    def _fill_info(self, gravity):
        L, D = self.n_links, self.n_dofs
        pad = lambda a, n: a if len(a) else np.zeros((1,) + a.shape[1:], a.dtype)  # noqa: E731
        self.link_parent.from_numpy(pad(self.np_link_parent, L))
        self.link_jtype.from_numpy(pad(self.np_link_jtype, L))
        self.link_q_start.from_numpy(pad(self.np_link_q_start, L))
        self.link_dof_start.from_numpy(pad(self.np_link_dof_start, L))
        self.link_ndof.from_numpy(pad(self.np_link_ndof, L))
        self.link_jpos.from_numpy(pad(self.np_link_jpos, L).astype(self.np_dtype))
        self.link_jquat.from_numpy(pad(self.np_link_jquat, L).astype(self.np_dtype))
        self.link_jaxis.from_numpy(pad(self.np_link_jaxis, L).astype(self.np_dtype))
        self.dof_link.from_numpy(pad(self.np_dof_link, D))
        self.dof_q.from_numpy(pad(self.np_dof_q, D))
        self.dof_parent.from_numpy(pad(self.np_dof_parent, D))
        self.dof_anc.from_numpy(self.np_dof_anc)
        self.dof_mimic_leader.from_numpy(self.np_mimic[:, 0].astype(np.int32))
        self.dof_mimic_mult.from_numpy(self.np_mimic[:, 1].astype(self.np_dtype))
        self.dof_mimic_off.from_numpy(self.np_mimic[:, 2].astype(self.np_dtype))
        big = np.finfo(self.np_dtype).max
        # "no limit" as a large finite number: infinities turn masked-out terms into NaN
        lim = np.clip(pad(self.np_dof_limit, D), -1e30, 1e30).astype(self.np_dtype)
        self.dof_limit_lo.from_numpy(lim[:, 0].copy())
        self.dof_limit_hi.from_numpy(lim[:, 1].copy())
        B = self.n_envs
        tile = lambda a: np.ascontiguousarray(np.broadcast_to(a, (B,) + a.shape)).astype(self.np_dtype)  # noqa: E731
        self.link_mass.from_numpy(tile(pad(self.np_link_mass, L)))
        self.link_com.from_numpy(tile(pad(self.np_link_com, L)))
        self.link_inertia.from_numpy(tile(pad(self.np_link_inertia, L)))
        self.dof_damping.from_numpy(tile(pad(self.np_dof_damping, D)))
        self.dof_armature.from_numpy(tile(pad(self.np_dof_armature, D)))
        self.dof_frictionloss.from_numpy(tile(pad(self.np_dof_frictionloss, D)))
        eff = np.clip(pad(self.np_dof_effort, D), 0, big)
        self.dof_force_lo.from_numpy(tile(-eff))
        self.dof_force_hi.from_numpy(tile(eff))
        self.gravity.from_numpy(tile(np.asarray(gravity, dtype=float)))
        sched = np.array([op[:6] for op in self.ops], dtype=np.int32)
        self.sched.from_numpy(sched)
        self.sched_h.from_numpy(np.array([op[6] for op in self.ops], dtype=self.np_dtype))
        self.reset_state()

    def reset_state(self):
        """Initial state (URDF zero pose, free bases at their morph placement, zero velocity),
        zero controls in force mode."""
        self.nan_step[None] = self.NO_NAN
        qpos = np.zeros((self.n_slots, self.n_envs, max(self.n_qs, 1)), self.np_dtype)
        qpos[:, :, : self.n_qs] = self.np_qpos0
        self.qpos.from_numpy(qpos)
        self.qvel.fill(0)
        self.ctrl_force.fill(0)
        self.ctrl_pos.fill(0)
        self.ctrl_vel.fill(0)
        self.ctrl_mode.fill(0)

    # ------------------------------------------------------------------ kernels
    # Every stage runs as its own top-level loop over envs (see kinematics.KINEMATICS).
    @ti.kernel
    def kernel_dynamics(self, e: ti.i32, src: ti.i32, h: float):
        for stage in ti.static(self.dynamics_stages):
            if ti.static(self.serial):
                ti.loop_config(serialize=True)
            for i_b in range(self.n_envs):
                stage(self, i_b, e, src, h)

    @ti.kernel
    def kernel_factor_solve(self, e: ti.i32):
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.n_envs):
            if ti.static(self.dense_solve):
                func_factor_solve_dense(self, i_b, e)
            else:
                func_factor_solve(self, i_b, e)

    @ti.kernel
    def kernel_solve_grad(self, e: ti.i32):
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.n_envs):
            if ti.static(self.dense_solve):
                func_solve_grad_dense(self, i_b, e)
            else:
                func_solve_grad(self, i_b, e)

    @ti.kernel
    def kernel_integrate(self, kind: ti.i32, e: ti.i32, base: ti.i32, src: ti.i32, dst: ti.i32, h: float):
        for stage in ti.static(INTEGRATE):
            if ti.static(self.serial):
                ti.loop_config(serialize=True)
            for i_b in range(self.n_envs):
                stage(self, i_b, kind, e, base, src, dst, h)

    @ti.kernel
    def kernel_step_fused(self, step: ti.i32, k0: ti.i32, k1: ti.i32, finish: ti.i32):
        """Ops k0..k1-1 of the schedule (the whole step, or one substep when another solver steps
        between substeps), all envs, one launch (no gradient bookkeeping). With `finish` the last slot
        becomes slot 0 and nan_step records the first `step` after which some state is not finite
        (checked for free here, read by the scene every few steps)."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.n_envs):
            for k in range(k0, k1):
                op = self.sched[k, 0]
                kind, e, base, src, dst = self.sched[k, 1], self.sched[k, 2], self.sched[k, 3], self.sched[k, 4], self.sched[k, 5]
                h = self.sched_h[k]
                if op == OP_DYN:
                    for stage in ti.static(self.dynamics_stages):
                        stage(self, i_b, e, src, h)
                elif op == OP_SOLVE:
                    if ti.static(self.dense_solve):
                        func_factor_solve_dense(self, i_b, e)
                    else:
                        func_factor_solve(self, i_b, e)
                else:
                    for stage in ti.static(INTEGRATE):
                        stage(self, i_b, kind, e, base, src, dst, h)
            if finish:
                for i_q in range(self.n_qs):
                    x = self.qpos[self.n_slots - 1, i_b, i_q]
                    self.qpos[0, i_b, i_q] = x
                    if ti.math.isnan(x) or ti.math.isinf(x):
                        ti.atomic_min(self.nan_step[None], step)
                for i_d in range(self.n_dofs):
                    x = self.qvel[self.n_slots - 1, i_b, i_d]
                    self.qvel[0, i_b, i_d] = x
                    if ti.math.isnan(x) or ti.math.isinf(x):
                        ti.atomic_min(self.nan_step[None], step)

    @ti.kernel
    def kernel_kinematics(self, src: ti.i32):
        """Link poses and velocities at qpos/qvel[src] (what the getters read)."""
        for stage in ti.static(LINK_STATE):
            if ti.static(self.serial):
                ti.loop_config(serialize=True)
            for i_b in range(self.n_envs):
                stage(self, i_b, 0, src, 0.0)

    @ti.kernel
    def kernel_mass_matrix(self, src: ti.i32):
        """M (without armature or implicit terms) at qpos[src]."""
        for stage in ti.static((func_forward_kinematics, func_dof_subspace, func_world_inertia) + INERTIA):
            if ti.static(self.serial):
                ti.loop_config(serialize=True)
            for i_b in range(self.n_envs):
                stage(self, i_b, 0, src, 0.0)

    @ti.kernel
    def kernel_energy(self, src: ti.i32):
        """energy[:, 0] kinetic 1/2 v^T M v (M from kernel_mass_matrix), energy[:, 1] potential -m g.c."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.n_envs):
            ke = 0.0
            for i in range(self.n_dofs):
                for j in range(self.n_dofs):
                    if self.dof_anc[i, j] == 1:
                        c = 1.0 if i == j else 2.0
                        ke += 0.5 * c * self.mass_mat[i_b, i, j] * self.qvel[src, i_b, i] * self.qvel[src, i_b, j]
            pe = 0.0
            for i_l in range(self.n_links):
                pe -= self.link_mass[i_b, i_l] * self.gravity[i_b].dot(self.link_cpos[i_b, i_l])
            self.energy[i_b, 0] = ke
            self.energy[i_b, 1] = pe

    @ti.kernel
    def kernel_clear_grads(self):
        """Zero every adjoint field in one launch (before each step's backward replay). Constants,
        not x * 0: a NaN left by an earlier failed backward must not survive."""
        for x in ti.static(self.grad_fields):
            if ti.static(self.serial):
                ti.loop_config(serialize=True)
            for I in ti.grouped(ti.ndrange(*x.shape)):
                if ti.static(not hasattr(x, "n")):
                    x.grad[I] = 0.0
                elif ti.static(x.m == 1):
                    x.grad[I] = ti.Vector.zero(self.dtype, x.n)
                else:
                    x.grad[I] = ti.Matrix.zero(self.dtype, x.n, x.m)

    # ------------------------------------------------------------------ python entry points
    NO_NAN = 2**31 - 1

    def step(self, step: int = 0):
        """One step without gradient bookkeeping: the state moves from slot 0 to slot 0."""
        self._scratch = None
        self.kernel_step_fused(step, 0, self.n_ops, 1)

    def substep_fused(self, step: int, i: int):
        """Substep i without gradient bookkeeping (scenes where another solver steps between
        substeps); the last substep makes its result the current state (slot 0)."""
        self._scratch = None
        self.kernel_step_fused(step, self.substep_first_op[i], self.substep_first_op[i + 1], int(i == self.substeps - 1))

    def substep(self, i: int):
        """Substep i's ops one launch each, the form a ti.ad.Tape records (gradient path). The state
        moves from slot i (or the substep's first RK slot) to the substep's last slot."""
        for kind_op, kind, e, base, src, dst, h in self.substep_ops[i]:
            if kind_op == OP_DYN:
                self.evaluate(e, src, h)
            elif kind_op == OP_INT:
                self.kernel_integrate(kind, e, base, src, dst, h)

    def _evaluation_unit(self):
        """Dynamics at slot src + factor-solve into qacc[e], as one call on the tape. Its adjoint
        recomputes the evaluation first when the scratch fields (poses, M, its factor) hold another
        one, then runs the adjoint of the solve (hand-written: for qacc = M^-1 f, f_bar = M^-1 qacc_bar
        and M_bar = -f_bar qacc^T) and Taichi's adjoint of the dynamics kernel."""

        @ti.ad.grad_replaced
        def evaluate(e, src, h):
            self.kernel_dynamics(e, src, h)
            self.kernel_factor_solve(e)
            self._scratch = (e, src, h)

        @ti.ad.grad_for(evaluate)
        def evaluate_grad(e, src, h):
            if self._scratch != (e, src, h):
                self.kernel_dynamics(e, src, h)
                self.kernel_factor_solve(e)
                self._scratch = (e, src, h)
            self.kernel_solve_grad(e)
            self.kernel_dynamics.grad(e, src, h)

        return evaluate

    def scratch_overwritten(self):
        """Called by every launch outside `evaluate` that writes the scratch fields (getters' kinematics,
        the mass matrix, the fused step, the coupler), so a pending adjoint recomputes its evaluation."""
        self._scratch = None

    # ------------------------------------------------------------------ state and gradient I/O
    # Every torch tensor passed to a kernel costs ~30 us here, so each crossing packs its data in one:
    # state x = [qpos | qvel] (B, n_qs + n_dofs), controls c = [force; pos; vel] (B, 3, n_dofs).
    @ti.kernel
    def kernel_set_state(self, slot: ti.i32, x: ti.types.ndarray()):
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.n_envs):
            for i_q in range(self.n_qs):
                self.qpos[slot, i_b, i_q] = x[i_b, i_q]
            for i_d in range(self.n_dofs):
                self.qvel[slot, i_b, i_d] = x[i_b, self.n_qs + i_d]

    @ti.kernel
    def kernel_get_state(self, slot: ti.i32, x: ti.types.ndarray()):
        """Read the state in `slot` and make it the current state (slot 0)."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.n_envs):
            for i_q in range(self.n_qs):
                x[i_b, i_q] = self.qpos[slot, i_b, i_q]
                self.qpos[0, i_b, i_q] = self.qpos[slot, i_b, i_q]
            for i_d in range(self.n_dofs):
                x[i_b, self.n_qs + i_d] = self.qvel[slot, i_b, i_d]
                self.qvel[0, i_b, i_d] = self.qvel[slot, i_b, i_d]

    @ti.kernel
    def kernel_vjp(self, slot: ti.i32, g: ti.types.ndarray(), loss: ti.template()):
        """loss += <g, state in `slot`>: the scalar whose adjoint a step's ti.ad.Tape propagates, g being
        the gradient torch hands the step's output state (packed like kernel_get_state)."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.n_envs):
            for i_q in range(self.n_qs):
                loss[None] += g[i_b, i_q] * self.qpos[slot, i_b, i_q]
            for i_d in range(self.n_dofs):
                loss[None] += g[i_b, self.n_qs + i_d] * self.qvel[slot, i_b, i_d]

    @ti.kernel
    def kernel_get_grads(self, g: ti.types.ndarray()):
        """g[:, :n_qs + n_dofs] <- adjoint of the state in slot 0, g[:, n_qs + n_dofs:] <- adjoint of
        the controls (force, pos, vel blocks of n_dofs)."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.n_envs):
            nx = self.n_qs + self.n_dofs
            for i_q in range(self.n_qs):
                g[i_b, i_q] = self.qpos.grad[0, i_b, i_q]
            for i_d in range(self.n_dofs):
                g[i_b, self.n_qs + i_d] = self.qvel.grad[0, i_b, i_d]
                g[i_b, nx + i_d] = self.ctrl_force.grad[i_b, i_d]
                g[i_b, nx + self.n_dofs + i_d] = self.ctrl_pos.grad[i_b, i_d]
                g[i_b, nx + 2 * self.n_dofs + i_d] = self.ctrl_vel.grad[i_b, i_d]

    @ti.kernel
    def kernel_set_ctrl(self, c: ti.types.ndarray()):
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.n_envs):
            for i_d in range(self.n_dofs):
                self.ctrl_force[i_b, i_d] = c[i_b, 0, i_d]
                self.ctrl_pos[i_b, i_d] = c[i_b, 1, i_d]
                self.ctrl_vel[i_b, i_d] = c[i_b, 2, i_d]

    @ti.kernel
    def kernel_set_ctrl_mode(self, m: ti.types.ndarray()):
        for i_b, i_d in ti.ndrange(self.n_envs, self.n_dofs):
            self.ctrl_mode[i_b, i_d] = m[i_b, i_d]

    def get_param_grad(self, x, g):
        """Adjoint of parameter field x into the tensor g (x's shape + element shape)."""
        if len(x.shape) == 1:
            self._kernel_grad_vec1(x, g)
        elif not hasattr(x, "n"):
            self._kernel_grad_scalar2(x, g)
        elif x.m == 1:
            self._kernel_grad_vec2(x, g)
        else:
            self._kernel_grad_mat2(x, g)

    @ti.kernel
    def _kernel_grad_scalar2(self, x: ti.template(), g: ti.types.ndarray()):
        for i, j in x:
            g[i, j] = x.grad[i, j]

    @ti.kernel
    def _kernel_grad_vec1(self, x: ti.template(), g: ti.types.ndarray()):
        for i in x:
            for k in ti.static(range(x.n)):
                g[i, k] = x.grad[i][k]

    @ti.kernel
    def _kernel_grad_vec2(self, x: ti.template(), g: ti.types.ndarray()):
        for i, j in x:
            for k in ti.static(range(x.n)):
                g[i, j, k] = x.grad[i, j][k]

    @ti.kernel
    def _kernel_grad_mat2(self, x: ti.template(), g: ti.types.ndarray()):
        for i, j in x:
            for k, l in ti.static(ti.ndrange(x.n, x.m)):
                g[i, j, k, l] = x.grad[i, j][k, l]

    @ti.kernel
    def kernel_link_outputs(self, pos: ti.types.ndarray(), quat: ti.types.ndarray(), vel: ti.types.ndarray(),
                            ang: ti.types.ndarray()):
        """Link origin poses and velocities (world frame) from the last kinematics evaluation."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b, i_l in ti.ndrange(self.n_envs, self.n_links):
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
                        ang: ti.types.ndarray(), loss: ti.template()):
        """loss += <output gradients, kernel_link_outputs's outputs>, for a getter's ti.ad.Tape."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b, i_l in ti.ndrange(self.n_envs, self.n_links):
            p = self.link_pos[i_b, i_l]
            w = self.cvel_w[i_b, i_l]
            v = self.cvel_v[i_b, i_l] + w.cross(p)
            q = self.link_quat[i_b, i_l]
            acc = 0.0
            for k in ti.static(range(3)):
                acc += pos[i_b, i_l, k] * p[k] + vel[i_b, i_l, k] * v[k] + ang[i_b, i_l, k] * w[k]
            for k in ti.static(range(4)):
                acc += quat[i_b, i_l, k] * q[k]
            loss[None] += acc

    @ti.kernel
    def kernel_check_finite(self, slot: ti.i32) -> ti.i32:
        """-1 if the state in `slot` is finite, else the first non-finite q index (or n_qs + dof)."""
        self.bad_idx[None] = self.n_qs + self.n_dofs
        for i_b, i_q in ti.ndrange(self.n_envs, self.n_qs):
            x = self.qpos[slot, i_b, i_q]
            if ti.math.isnan(x) or ti.math.isinf(x):
                ti.atomic_min(self.bad_idx[None], i_q)
        for i_b, i_d in ti.ndrange(self.n_envs, self.n_dofs):
            x = self.qvel[slot, i_b, i_d]
            if ti.math.isnan(x) or ti.math.isinf(x):
                ti.atomic_min(self.bad_idx[None], self.n_qs + i_d)
        r = self.bad_idx[None]
        if r == self.n_qs + self.n_dofs:
            r = -1
        return r
