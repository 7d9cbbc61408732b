"""RigidCore: the rigid solver's pooled fields of one capacity class and the kernels compiled on them.

Static model data lives in `*_info`-style fields set once at build (link_*, dof_* without an env
axis); parameters and controls have an env axis [i_b, ...]; state has a slot axis [t, i_b, ...]
holding the step's schedule of intermediate states (two slots for plain Euler, so memory does not grow
with the horizon); per-evaluation scratch (poses, inertias, forces) is written once per evaluation.

One compile serves every robot. Taichi bakes the fields a kernel touches, and every Python value it
reads while compiling, into the compiled kernel, keyed by the object that owns the kernel. So the
fields and kernels live in a RigidCore whose fields are sized by a capacity class (envs, elements:
links/dofs/qs, state slots) rather than by the scene, and the scene's sizes (n_envs, n_links, n_dofs,
n_qs) and options (the joint-limit model and its gains, implicit terms) are read at run time from its small `cfg`
fields (see `_runtime`). A scene takes a core of its class from the pool (pool.py) and gives it back
when it dies, so a second scene of that class, any robot, compiles nothing.

A scene with stages of its own (a contact solver, external wrenches) runs its dynamics on a SceneCore:
a RigidCore over the same fields (the very field objects, not copies) whose dynamics stages include
those, so the kernels that run them compile on it and not on the pooled core. Either way every stage
function's first argument `s` is a RigidCore: the fields, the run-time sizes, and `s.contact` /
`s.external` (None on a plain core). The kernels through which arrays enter and leave the core are in
state_io.py.
"""
import typing

import taichi as ti

from .. import taichi_compat
from .actuation import (LIMIT_ROUNDS, LIMITS_CONSTRAINT, func_free_rot_errors, func_generalized_force,
                        func_generalized_force_adjoint, func_limit_release, func_limit_release_grad,
                        func_limit_rounds_next)
from .bias import BIAS, func_bias_adjoint, func_free_gyro
from .contact import func_contact_solve, func_factor_solve_dense, func_solve_grad_dense, func_tree_env
from .external import AppliedWrench, func_applied_wrench
from .inertia import INERTIA, TreeSchedule, func_factor_solve, func_inertia_adjoint, func_solve_grad
from .integrate import INTEGRATE
from .kinematics import (KINEMATICS, LINK_STATE, func_dof_subspace, func_forward_kinematics, func_free_pose,
                         func_kinematics_adjoint, func_world_inertia)
from .layout import ZeroPlan, func_zero_plan, place_env_major
from .schedule import OP_DYN, OP_SOLVE, SPAN_BITS, SPAN_MASK

# parallel dispatch of a Taichi CPU kernel costs ~70 us here against ~12 us serial: few envs run serially
SERIAL_MAX_ENVS = 16
# on the CPU with at most two threads, up to this many (a core's env capacity): see runs_serially
SERIAL_MAX_ENVS_TWO_THREADS = 512
# the same for the light kernels (RigidCore.serial_light): state and control copies, the vjp, the integration
SERIAL_MAX_ENVS_LIGHT = 2048


def runs_serially(cap_envs: int, light: bool = False) -> bool:
    """Whether a core of env capacity cap_envs runs its env loops serially (on the launching thread): up to
    SERIAL_MAX_ENVS envs anywhere; on the CPU with one Taichi thread (GS_NUM_THREADS=1, a torchrun rank's
    share of a 2-core machine) at any env count; with two, up to SERIAL_MAX_ENVS_TWO_THREADS. A serial loop
    compiles `+=` on fields (Taichi's adjoints are made of them) to plain adds, a parallel one to
    compare-and-swap loops even on one thread, and skips the pool's dispatch. Measured on this project's
    2-core machine (benchmarks/results/grad.md, 2026-12-05), float64, a process of two threads: the Panda's
    100-step rollout with gradients, forward + backward, serial against parallel: 182 against 354 ms at 64
    envs, 510 against 812 at 256, 915 against 1,230 at 512, but 1,715-1,721 against 1,397-1,421 at 1,024;
    without gradients, 165 against 206 ms at 256 envs (200 steps), 136 against 165 at 512 (100 steps), 496
    against 428 at 1,024 (200 steps) (ANYmal on the ground, 100 steps: 747 against 765 ms at 512, 1,906
    against 1,269 at 1,024); one thread, 1,024 envs, the
    rollout with gradients: 331-344 against 436-459 ms forward, 1,426-1,513 against 2,130-2,180 backward.
    The two compiled codes give the same numbers to rounding (a 32-env contact rollout's gradients within
    6.5e-14 of the largest, 12: tests/test_threads.py). More threads than two: not measured, the old
    threshold kept.

    `light`: for the kernels that copy an env's state or controls in or out, the vjp's scalar and the gradient
    path's integration (a few numbers per dof; RigidCore.serial_light), serial with two threads up to
    SERIAL_MAX_ENVS_LIGHT envs: a parallel loop's dispatch costs them more than their work. The Panda's rollout
    with gradients, 100 steps, these kernels serial against parallel (2026-12-05, fresh processes alternated,
    two sessions of two pairs, the same numbers to the bit): forward 256-275 against 277-321 ms at 1,024 envs,
    427-503 against 479-542 at 2,048; backward 1,033-1,174 against 1,036-1,261 at 1,024, 2,019-2,431 against
    2,109-2,401 at 2,048 (within the runs' spread); at 4,096 (one pair) 1,434 / 5,978 against 1,356 / 5,463 ms,
    hence the cap. The same rollout without gradients (200 steps, the state read every step): within the
    spread at 1,024 and 2,048 envs."""
    if cap_envs <= SERIAL_MAX_ENVS:
        return True
    cfg = taichi_compat.config()
    if cfg.arch not in (ti.x64, ti.arm64):
        return False
    cap = SERIAL_MAX_ENVS_LIGHT if light else SERIAL_MAX_ENVS_TWO_THREADS
    return cfg.cpu_max_num_threads == 1 or (cfg.cpu_max_num_threads == 2 and cap_envs <= cap)


class HandAdjoint(typing.NamedTuple):
    """Which written-out adjoints a run of stages takes (core.kernel_hand_adjoint; solver.HAND_ADJOINTS)."""

    kinematics: bool = False  # KINEMATICS (full) or LINK_STATE
    full: bool = True
    inertia: bool = False  # INERTIA
    forces: bool = False  # func_link_forces, func_free_gyro
    accumulate: bool = False  # func_accumulate_forces
    project: bool = False  # func_project_forces
    generalized: bool = False  # func_free_rot_errors, func_generalized_force
    solve: bool = False  # the factor-solve's adjoint first (kernel_mass_solve's, in the same loop over envs)


LINK_STATE_ADJOINT = HandAdjoint(kinematics=True, full=False)


DYNAMICS = KINEMATICS + INERTIA + BIAS + (func_free_rot_errors, func_generalized_force)
# stages whose float32 adjoints compile correctly without Taichi's advanced optimisation (taichi_compat.compile_options.AdjointCompile)
PLAIN_ADJOINT = KINEMATICS + INERTIA[:2] + BIAS[:3]
# smallest element capacity: the robots of one size class (Panda, UR5, arms up to 16 links/dofs/qs)
# share a core
MIN_ELEMS = 16
# run-time sizes and options, indices into RigidCore.cfg_i / cfg_f
I_ENVS, I_LINKS, I_DOFS, I_QS, I_QPOS_LEN, I_QVEL_LEN, I_LIMITS_ON, I_ELEMS, I_ANC, I_FREE, N_CFG_I = range(11)
F_LIMIT_K, F_LIMIT_D, F_IMPLICIT_ON, F_IMPLICIT_KV_ONLY, N_CFG_F = range(5)
NO_NAN = 2**31 - 1  # nan_step of an env whose state has stayed finite


def _runtime(index, floating=False):
    """A size or option of the scene a core holds. In Python scope it is that scene's number; inside a
    kernel being compiled it is a read of the core's cfg field, so the compiled kernel serves every
    scene the core will hold (stage code writes `range(s.n_links)` either way)."""

    def get(self):
        if taichi_compat.inside_kernel():
            return taichi_compat.subscript(self.cfg_f if floating else self.cfg_i, index)
        return self.scene_cfg[(N_CFG_I + index) if floating else index]

    return property(get)


def env_capacity(n_envs: int) -> int:
    """The env capacity of the core class a scene of n_envs envs takes."""
    return SERIAL_MAX_ENVS if n_envs <= SERIAL_MAX_ENVS else 1 << (n_envs - 1).bit_length()


def elem_capacity(n: int) -> int:
    """The element (links, dofs, qs) capacity of the core class a scene of n elements takes."""
    return max(MIN_ELEMS, 1 << (max(n, 1) - 1).bit_length())


def _place_env_major(B, N, elem, mats, ones, slots):
    """The core's per-env fields env-major (layout.place_env_major): elem [B, N] fields, mats [B, N, N],
    ones [B], slots [(n, fields [n, B, N])], each list a group of its own."""
    place_env_major(ti.root, B, [(0, (), ones), (0, (N,), elem), (0, (N, N), mats)]
                    + [(1, (n, N), xs) for n, xs in slots])


@ti.data_oriented
class RigidCore:
    """The fields of one capacity class (key: dtype, gradients, env capacity, element capacity, state
    slots, evaluations, schedule length, specialised, dof tree) and the kernels compiled on them; held
    by one scene at a time (pool.CorePool).

    Env loops run over the core's env capacity with a guard `if i_b < self.n_envs`, not over
    `range(self.n_envs)`: Taichi 1.7 evaluates a top-level loop bound read from a field in a task of its
    own, and the adjoint of a kernel with several such loops came out NaN (kernel_dynamics; each stage
    alone, or the debug build, was right)."""

    dynamics_stages = DYNAMICS
    dense_solve = False  # contacts between moving bodies: dense factorisation (SceneCore)
    has_contact = False
    contact = None  # the scene's contact solver (SceneCore)
    external = None  # the scene's external wrenches (SceneCore)
    applied = None  # the user's wrenches and gravity compensation (SceneCore)


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
    implicit_kv_only = _runtime(F_IMPLICIT_KV_ONLY, True)  # 1.0: approximate_implicitfast's terms
    n_anc = _runtime(I_ANC)  # pairs (i, j) with dof j an ancestor-or-self of dof i (anc_i, anc_j)
    n_free_links = _runtime(I_FREE)  # the links of free joints, listed in free_link (actuation.func_free_rot_errors)

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
        self.serial = runs_serially(B)
        self.serial_light = runs_serially(B, light=True)
        self.cap_envs, self.cap_elems = B, N
        self.n_slots, self.n_evals = S, E
        self.scene_cfg = [0] * (N_CFG_I + N_CFG_F)
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
        self.dof_fold_leader = I(N)  # a folded mimic follower's leader, else -1 (flatten.np_fold_leader)
        self.free_link = I(N)  # n_free_links entries
        # the root of each link's kinematic tree: the spatial algebra of a tree is about its root link's origin
        # (kinematics.func_link_origin), not the world's
        self.link_root = I(N)
        self.dof_springref = F(N, False)  # rest position of the joint spring (MJCF springref; else 0)
        # the limit constraint's k and b (actuation.limit_gains) and solimp (dmin, dmax, width, mid, power), then
        # the impedance curve's two scales 1 / mid^(power - 1), 1 / (1 - mid)^(power - 1) (func_limit_constraint)
        self.dof_lim_k, self.dof_lim_b = F(N, False), F(N, False)
        self.dof_imp = ti.Vector.field(7, f, shape=N)
        # per-env fields: declared without a shape and placed env-major (_place_env_major)
        s3 = lambda grad=g: ti.field(f, needs_grad=grad)  # noqa: E731
        v3 = lambda: ti.Vector.field(3, f, needs_grad=g)  # noqa: E731
        m3 = lambda: ti.Matrix.field(3, 3, f, needs_grad=g)  # noqa: E731
        # parameters
        self.link_mass, self.link_com, self.link_inertia = s3(), v3(), m3()
        self.dof_damping, self.dof_armature, self.dof_frictionloss = s3(), s3(), s3()
        self.dof_kp, self.dof_kv, self.dof_stiffness = s3(), s3(), s3()
        # the joint-limit constraint's inverse weight (M^-1)_jj at qpos0 (actuation.func_limit_constraint)
        self.dof_invweight = s3()
        # the limit constraint of the evaluation: its term on M's diagonal and in the force, its direction
        # (+1 lower limit, -1 upper), and whether the solve released it (actuation.func_limit_release)
        self.dof_lim_D, self.dof_lim_f = s3(), s3()
        self.dof_rot_err = s3()  # a free joint's rotational dofs' PD error, with gradients (func_free_rot_errors)
        self.dof_lim_j = s3(False)
        self.dof_lim_off = ti.field(ti.i32)
        # without gradients: the dofs whose limit is active, and how many (the release visits those only)
        self.dof_lim_list, self.dof_lim_n = ti.field(ti.i32), ti.field(ti.i32)
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
        self.dof_qf = s3(False)
        self.solve_tmp = s3(False)
        elem = [self.link_mass, self.link_com, self.link_inertia, self.dof_damping, self.dof_armature,
                self.dof_frictionloss, self.dof_kp, self.dof_kv, self.dof_stiffness, self.dof_force_lo,
                self.dof_force_hi, self.dof_invweight, self.dof_lim_D, self.dof_lim_f, self.dof_lim_j,
                self.dof_lim_off, self.dof_lim_list, self.ctrl_force, self.ctrl_pos, self.ctrl_vel, self.ctrl_mode,
                self.link_pos, self.link_quat, self.link_R, self.link_cpos, self.link_h, self.link_J, self.cdof_w, self.cdof_v,
                self.cdofd_w, self.cdofd_v, self.cvel_w, self.cvel_v, self.cacc_w, self.cacc_v, self.crb_m,
                self.crb_h, self.crb_J, self.cfrc_n, self.cfrc_f, self.dof_n, self.dof_f, self.bias, self.force,
                self.dof_tau, self.dof_qf, self.dof_rot_err]
        mats, ones = [self.mass_mat, self.mass_fac], [self.gravity, self.dof_lim_n]
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
                  self.dof_frictionloss, self.dof_kp, self.dof_kv, self.dof_stiffness, self.gravity, self.ctrl_force,
                  self.ctrl_pos, self.ctrl_vel, self.dof_invweight]
        scratch = [self.link_pos, self.link_quat, self.link_R, self.link_cpos, self.link_h, self.link_J,
                   self.cdof_w, self.cdof_v, self.cdofd_w, self.cdofd_v, self.cvel_w, self.cvel_v, self.cacc_w,
                   self.cacc_v, self.crb_m, self.crb_h, self.crb_J, self.cfrc_n, self.cfrc_f, self.dof_n, self.dof_f,
                   self.mass_mat, self.bias, self.force, self.dof_lim_D, self.dof_lim_f, self.dof_rot_err]
        self.zero_plan = ZeroPlan([self.mass_mat, self.cdof_w, self.cdof_v, self.cdofd_w, self.cdofd_v], [], N)
        # kernel_clear_grads': the parameters' and the state's, and the per-evaluation scratch's
        self.param_grads = [x.grad for x in params] if g else []
        self.state_grads = [x.grad for x in state] if g else []
        self.input_grad_plan = ZeroPlan(self.param_grads, self.state_grads, N)
        self.scratch_grads = [x.grad for x in scratch] if g else []
        self.scratch_grad_plan = ZeroPlan(self.scratch_grads, [], N)

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
            self.free_link[i] = link_i[i, 5]
            for k in ti.static(range(3)):
                self.link_jpos[i][k] = link_f[i, k]
                self.link_jaxis[i][k] = link_f[i, 7 + k]
            for k in ti.static(range(4)):
                self.link_jquat[i][k] = link_f[i, 3 + k]
        ti.loop_config(serialize=True)
        for i in range(link_i.shape[0]):  # parents come before their children
            p = link_i[i, 0]
            self.link_root[i] = ti.select(p >= 0, self.link_root[ti.max(p, 0)], i)
        for i in range(dof_i.shape[0]):
            self.dof_link[i] = dof_i[i, 0]
            self.dof_q[i] = dof_i[i, 1]
            self.dof_parent[i] = dof_i[i, 2]
            self.dof_mimic_leader[i] = dof_i[i, 3]
            self.dof_fold_leader[i] = dof_i[i, 4]
            self.dof_limit_lo[i] = dof_f[i, 0]
            self.dof_limit_hi[i] = dof_f[i, 1]
            self.dof_mimic_mult[i] = dof_f[i, 2]
            self.dof_mimic_off[i] = dof_f[i, 3]
            self.dof_springref[i] = dof_f[i, 4]
            self.dof_lim_k[i] = dof_f[i, 5]
            self.dof_lim_b[i] = dof_f[i, 6]
            for k in ti.static(range(5)):
                self.dof_imp[i][k] = dof_f[i, 7 + k]
            mid, power = dof_f[i, 10], dof_f[i, 11]
            self.dof_imp[i][5] = 1.0 / ti.pow(mid, power - 1.0)
            self.dof_imp[i][6] = 1.0 / ti.pow(1.0 - mid, power - 1.0)
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
    @ti.kernel
    def kernel_evaluate(self, e: ti.i32, src: ti.i32, h: float):
        """The gradient path's forward of evaluation e at state slot src, substep length h: every dynamics
        stage, one env at a time (one loop over envs, in which an env's links stay in cache from stage to
        stage), then without contacts the final solve and its limit rounds (func_final_solve; with
        contacts the contact solver's launches follow, contact.factor_solve). The numbers are those of
        kernel_dynamics (the stages as separate loops, whose adjoints the backward runs) to the bit
        (tests/test_joint_limits.py), at 1,024 envs in 1.5 ms where those loops took 3.2-4.7 (the Panda)."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                for stage in ti.static(self.dynamics_stages):
                    stage(self, i_b, e, src, h)
                if ti.static(not self.has_contact):
                    self.func_final_solve(i_b, e)

    @ti.func
    def func_final_solve(self, i_b, e):
        """qacc[e] of a scene without contacts: the solve, then again while it releases limit constraints
        that pull (actuation.func_limit_rounds_next; an env stops at its first round that changes nothing,
        which is where the gradient path's rounds over all envs, release_limits, leave it too)."""
        r = 0
        while r >= 0:
            func_factor_solve(self, i_b, e)  # (the dense factorisation is a contact scene's: contact.factor_solve)
            r = func_limit_rounds_next(self, i_b, e, r)

    # The adjoints' stages run as separate top-level loops over envs (see kinematics.KINEMATICS).
    def kernel_dynamics(self, e: int, src: int, h: float):
        """Every dynamics stage of evaluation e at state slot src, substep length h, as separate loops."""
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

    def release_limits(self, e: int):
        """The final solve again while it releases limit constraints that pull (actuation.func_limit_release),
        in every env while one does: the contact solver's form (contact.factor_solve) of func_final_solve."""
        if self.limits_on == LIMITS_CONSTRAINT:
            r = 0
            while r < LIMIT_ROUNDS and self.kernel_limit_release(e) > 0:
                self.kernel_mass_solve(e, False)
                r += 1

    @ti.kernel
    def kernel_limit_release(self, e: ti.i32) -> ti.i32:
        """One change of the limit constraint's active set in every env, at the gradient path's solution of
        stage e (func_limit_release: pulling limits released, pushing ones brought back); returns the number
        of limits changed (RigidCore.release_limits solves again while it is not 0)."""
        n = 0
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                n += func_limit_release(self, i_b, e)
        return n

    def kernel_solve_grad(self, e: int):
        if self.has_contact:
            self.contact.solve_grad(self, e)
        else:
            self.kernel_mass_solve(e, True)

    @ti.kernel
    def kernel_mass_solve(self, e: ti.i32, adjoint: ti.template()):
        """qacc[e] = M^-1 force (M factored first; dense where contacts couple moving bodies), or with
        `adjoint` its hand-written adjoint (inertia.func_solve_grad)."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                if ti.static(adjoint and self.dense_solve):
                    func_solve_grad_dense(self, i_b, e)
                    func_limit_release_grad(self, i_b, e, self.contact.solve_tmp)
                elif ti.static(adjoint):
                    func_solve_grad(self, i_b, e)
                    func_limit_release_grad(self, i_b, e, self.solve_tmp)
                elif ti.static(self.dense_solve and not self.requires_grad):
                    # (without gradients mass_cross is current only where a slot couples moving links)
                    if func_tree_env(self, i_b):
                        func_factor_solve(self, i_b, e)
                    else:
                        func_factor_solve_dense(self, i_b, e)
                elif ti.static(self.dense_solve):
                    func_factor_solve_dense(self, i_b, e)
                else:
                    func_factor_solve(self, i_b, e)

    @ti.kernel
    def kernel_integrate(self, kind: ti.i32, e: ti.i32, base: ti.i32, src: ti.i32, dst: ti.i32, h: float):
        for stage in ti.static(INTEGRATE):
            if ti.static(self.serial_light):
                ti.loop_config(serialize=True)
            for i_b in range(self.cap_envs):
                if i_b < self.n_envs:
                    stage(self, i_b, kind, e, base, src, dst, h)

    @ti.kernel
    def kernel_step_fused(self, step: ti.i32, span: ti.i32) -> ti.i32:
        """Ops k0..k1-1 of the schedule (the whole step, or one substep when another solver steps
        between substeps), all envs, one launch (no gradient bookkeeping), span = k0 | k1 << 15 |
        finish << 30 (schedule.pack_span: one argument, not three, as each costs ~0.6 us to set at a
        launch, a twentieth of a 1-env step). With `finish` the last slot
        becomes slot 0 and nan_step[i_b] records the first `step` after which env i_b's state is not
        finite (checked while copying, so nearly free). Returns how many envs have such a record: the
        scene reads that integer after every step and looks at the state only when it grew. (A
        return value, not an external array: an array argument costs ~6 us per launch to set, a
        returned integer ~0.5 us through taichi_compat's fast launch.)"""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                k0 = span & SPAN_MASK
                k1 = (span >> SPAN_BITS) & SPAN_MASK
                finish = span >> (2 * SPAN_BITS)
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
                        else:
                            self.func_final_solve(i_b, e)
                    else:
                        for stage in ti.static(INTEGRATE):
                            stage(self, i_b, kind, e, base, src, dst, h)
                if finish:
                    self.func_finish(i_b, step)
        return self.nan_count[None]

    @ti.func
    def func_finish(self, i_b, step):
        """The step's last slot becomes slot 0; nan_step[i_b] records `step` if that state is not finite
        (and none is recorded yet)."""
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

    @ti.kernel
    def kernel_finish(self, step: ti.i32, finish: ti.i32) -> ti.i32:
        """kernel_step_fused's end alone (with `finish`), after a step run op by op; returns the count
        of envs with a NaN record."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                if finish:
                    self.func_finish(i_b, step)
        return self.nan_count[None]

    @ti.kernel
    def kernel_mass_matrix(self, src: ti.i32):
        """M (without armature or implicit terms) at qpos[src]."""
        for stage in ti.static((func_free_pose, func_forward_kinematics, func_dof_subspace, func_world_inertia) + INERTIA):
            if ti.static(self.serial):
                ti.loop_config(serialize=True)
            for i_b in range(self.cap_envs):
                if i_b < self.n_envs:
                    stage(self, i_b, 0, src, 0.0)

    @ti.kernel
    def kernel_hand_adjoint(self, e: ti.i32, src: ti.i32, h: float, kinematics: ti.i32, full: ti.i32, inertia: ti.i32,
                            forces: ti.i32, accumulate: ti.i32, project: ti.i32, generalized: ti.i32, solve: ti.i32):
        """Written-out adjoints of a run of stages (a HandAdjoint: solver.HAND_ADJOINTS), in one loop over envs, last
        stage first, after the factor-solve's of evaluation e (`solve`; a core without contacts): the
        generalised force's and the free joints' rotation errors' (actuation.func_generalized_force_adjoint), the
        BIAS stages' (bias.func_bias_adjoint), the INERTIA stages' (inertia.func_inertia_adjoint), the KINEMATICS
        stages' or LINK_STATE's at state slot src (kinematics.func_kinematics_adjoint). The parts are chosen at run
        time: every run is this one compiled kernel (as template arguments, each run was a kernel of its own,
        and a warm process paid Taichi's front end for each: ~130 ms for the getters' LINK_STATE alone)."""
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                if solve:
                    func_solve_grad(self, i_b, e)
                    func_limit_release_grad(self, i_b, e, self.solve_tmp)
                if generalized:
                    func_generalized_force_adjoint(self, i_b, src, h)
                if forces or accumulate or project:
                    func_bias_adjoint(self, i_b, src, h, forces, accumulate, project)
                if inertia:
                    func_inertia_adjoint(self, i_b)
                if kinematics:
                    func_kinematics_adjoint(self, i_b, src, full)

    def hand_adjoint(self, spec, e: int, src: int, h: float):
        """The written-out adjoint `spec` (a HandAdjoint) of evaluation e at state slot src, substep h."""
        assert not (spec.solve and (self.has_contact or self.dense_solve))
        self.kernel_hand_adjoint(e, src, h, *[int(x) for x in spec])

    @ti.kernel
    def kernel_clear_grads(self, scratch: ti.i32):
        """Zero the adjoint fields of the scene's envs, and seed the adjoint of the solver's Tape
        scalar (see kernel_vjp): those of the parameters and the state (and of a SceneCore's own solvers), and
        those of the per-evaluation scratch where `scratch` (RigidSolver.clear_grads: they may not be zero).
        Constants, not x * 0: a NaN left by an earlier failed backward must not survive. One top-level loop: each
        costs a task to load."""
        self.vjp_loss.grad[None] = 1.0
        if ti.static(self.serial):
            ti.loop_config(serialize=True)
        for i_b in range(self.cap_envs):
            if i_b < self.n_envs:
                func_zero_plan(self.input_grad_plan, i_b, self.cfg_i[I_ELEMS])
                if scratch:
                    func_zero_plan(self.scratch_grad_plan, i_b, self.cfg_i[I_ELEMS])


@ti.data_oriented
class SceneCore(RigidCore):
    """A RigidCore's fields (the same field objects) with the scene's own dynamics stages: its contact
    solver, its external wrenches (the coupler's) and/or its applied wrenches (the user's forces and
    gravity compensation, external.AppliedWrench: a stage right after the bias's link forces). The
    kernels that include them compile on this object, not on the pooled core. It is pooled with its core
    (CorePool.acquire_scene_core) and serves later scenes of its contact class and external-wrench sizes;
    `with_applied(step_core)` is a core with applied wrenches added, made once and kept.
    `core` is the pooled RigidCore whose fields it shares."""

    def __init__(self, core: RigidCore, contact, external, applied=None):
        # the core's fields, sizes and plans as attributes of this object (references, nothing copied),
        # so that stage code reads them from `s` alike on either kind
        self.__dict__.update(core.__dict__)
        self.core = core
        self.contact = contact
        self.external = external
        self.applied = applied
        self._with_applied = None  # not the plain core's (copied above): this SceneCore's own
        extra = [x for x in (contact, external) if x is not None]
        stages = DYNAMICS
        if applied is not None:
            k = DYNAMICS.index(func_free_gyro) + 1  # after the link forces (and their gyroscopic moments)
            stages = DYNAMICS[:k] + (func_applied_wrench,) + DYNAMICS[k:]
        self.dynamics_stages = stages + sum((tuple(x.stages) for x in extra), ())
        self.dense_solve = bool(contact is not None and contact.dense)
        self.has_contact = contact is not None
        if core.requires_grad:
            own = [f.grad for x in extra + [applied] if x is not None for f in x.grad_fields]
            self.input_grad_plan = ZeroPlan(core.param_grads, core.state_grads, core.cap_elems, own)


def with_applied(step_core):
    """`step_core` (a RigidCore or a SceneCore) with applied wrenches added: a SceneCore over the same
    fields, stages and contact solver, made at the first request and kept on `step_core`, so that a later
    scene that takes `step_core` from the pool and applies forces compiles nothing new."""
    if step_core.applied is not None:
        return step_core
    if getattr(step_core, "_with_applied", None) is None:
        core = step_core.core if isinstance(step_core, SceneCore) else step_core
        step_core._with_applied = SceneCore(core, step_core.contact, step_core.external, AppliedWrench(core))
    return step_core._with_applied
