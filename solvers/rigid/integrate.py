"""Stage 8, integration: semi-implicit Euler (also used by implicitfast) and the stages of RK4.

A step is a fixed schedule of evaluations e (dynamics at a state slot) and integrations between
state slots; every slot and every qacc[e] is written once per step, so a step can be replayed
backwards by Taichi's autodiff.
"""
import taichi as ti

from .kinematics import JOINT_FREE, JOINT_PRISMATIC, JOINT_REVOLUTE
from .math3d import func_quat_mul, func_rotvec_quat

from .schedule import INT_EULER, INT_RK_FINAL, INT_RK_STAGE, RK4_WEIGHT_SUM, RK4_WEIGHTS


@ti.func
def func_rk4_combine(k0, k1, k2, k3):
    """schedule.rk4_combine in Taichi: the weights are compile-time constants (the 1.0s fold away, so
    the sum is the one written out before the tableau had one home)."""
    w = ti.static(RK4_WEIGHTS)
    return (w[0] * k0 + w[1] * k1 + w[2] * k2 + w[3] * k3) / ti.static(RK4_WEIGHT_SUM)


@ti.func
def func_integrate_qpos(s: ti.template(), i_b, kind, e, base, src, dst, h):
    """qpos[dst] = qpos[base] advanced by velocity qvel_move[e] over time h (quaternions on the sphere)."""
    for i_l in range(s.n_links):
        jt = s.link_jtype[i_l]
        qs = s.link_q_start[i_l]
        d0 = s.link_dof_start[i_l]
        if jt == JOINT_REVOLUTE or jt == JOINT_PRISMATIC:
            s.qpos[dst, i_b, qs] = s.qpos[base, i_b, qs] + h * s.qvel_move[e, i_b, d0]
        elif jt == JOINT_FREE:
            for k in ti.static(range(3)):
                s.qpos[dst, i_b, qs + k] = s.qpos[base, i_b, qs + k] + h * s.qvel_move[e, i_b, d0 + k]
            w = ti.Vector([s.qvel_move[e, i_b, d0 + 3], s.qvel_move[e, i_b, d0 + 4], s.qvel_move[e, i_b, d0 + 5]])
            q0 = ti.Vector([s.qpos[base, i_b, qs + 3], s.qpos[base, i_b, qs + 4], s.qpos[base, i_b, qs + 5], s.qpos[base, i_b, qs + 6]])
            q1 = func_quat_mul(func_rotvec_quat(w, h), q0)
            qn = q1 / ti.sqrt(q1.dot(q1))
            for k in ti.static(range(4)):
                s.qpos[dst, i_b, qs + 3 + k] = qn[k]


@ti.func
def func_dof_update(s: ti.template(), i_b, kind, e, base, src, h, j):
    """(new velocity, velocity that moves qpos) of dof j. INT_EULER: v' = v + h a, q moves with v'.
    INT_RK_STAGE: the RK4 trial state at h from the derivative at slot src. INT_RK_FINAL: combine the
    4 stage derivatives e-3..e over h. Indices of the other kinds' slots are clamped (masked out)."""
    last = s.n_slots - 1
    a_rk = func_rk4_combine(s.qacc[ti.max(e - 3, 0), i_b, j], s.qacc[ti.max(e - 2, 0), i_b, j],
                            s.qacc[ti.max(e - 1, 0), i_b, j], s.qacc[e, i_b, j])
    final = kind == INT_RK_FINAL
    v_new = s.qvel[base, i_b, j] + h * ti.select(final, a_rk, s.qacc[e, i_b, j])
    # the RK stage slots base+1..3, read only by INT_RK_FINAL; the other kinds read slot base there
    # (for Euler base+1 is dst, which this kernel writes: a masked read of it would still break
    # Taichi's global data access rule)
    r1 = ti.select(final, ti.min(base + 1, last), base)
    r2 = ti.select(final, ti.min(base + 2, last), base)
    r3 = ti.select(final, ti.min(base + 3, last), base)
    v_rk = func_rk4_combine(s.qvel[base, i_b, j], s.qvel[r1, i_b, j], s.qvel[r2, i_b, j], s.qvel[r3, i_b, j])
    v_move = ti.select(final, v_rk, ti.select(kind == INT_RK_STAGE, s.qvel[src, i_b, j], v_new))
    return v_new, v_move


@ti.func
def func_integrate_qvel(s: ti.template(), i_b, kind, e, base, src, dst, h):
    """New velocities, and the velocities qvel_move[e] that func_integrate_qpos moves positions with.
    A URDF <mimic> follower copies its leader: v_f = m v_l, and its position is carried onto
    m q_l + offset within the step. For a follower beside its leader (inertia.func_fold_matrix) the solves
    already gave it m times the leader's acceleration, its inertia, forces and contacts acting on the
    leader, so the copy changes nothing but rounding; other followers are kinematic (no force back)."""
    for i_d in range(s.n_dofs):
        lead = s.dof_mimic_leader[i_d]
        follower = lead >= 0
        j = ti.max(lead, 0)
        m = s.dof_mimic_mult[i_d]
        if kind == INT_EULER:
            # Euler (and implicitfast), with or without gradients: a branch on the kernel's argument (the same
            # for every env; no local outlives it) that reads the dof's own slots, or the leader's for a
            # follower; the select form below also reads the RK slots and the leader's, and its adjoint adds
            # into every one of them
            if follower:
                v_lead = s.qvel[base, i_b, j] + h * s.qacc[e, i_b, j]
                s.qvel[dst, i_b, i_d] = m * v_lead
                s.qvel_move[e, i_b, i_d] = m * v_lead + func_mimic_gap(s, i_b, base, i_d, j, m) / h
            else:
                v_own = s.qvel[base, i_b, i_d] + h * s.qacc[e, i_b, i_d]
                s.qvel[dst, i_b, i_d] = v_own
                s.qvel_move[e, i_b, i_d] = v_own
        elif ti.static(s.requires_grad):
            v_own, move_own = func_dof_update(s, i_b, kind, e, base, src, h, i_d)
            v_lead, move_lead = func_dof_update(s, i_b, kind, e, base, src, h, j)
            gap = func_mimic_gap(s, i_b, base, i_d, j, m)
            s.qvel[dst, i_b, i_d] = ti.select(follower, m * v_lead, v_own)
            s.qvel_move[e, i_b, i_d] = ti.select(follower, m * move_lead + gap / h, move_own)
        else:
            # without gradients a branch: the leader's update only for followers (the same numbers as the
            # selects above)
            if follower:
                v_lead, move_lead = func_dof_update(s, i_b, kind, e, base, src, h, j)
                s.qvel[dst, i_b, i_d] = m * v_lead
                s.qvel_move[e, i_b, i_d] = m * move_lead + func_mimic_gap(s, i_b, base, i_d, j, m) / h
            else:
                v_own, move_own = func_dof_update(s, i_b, kind, e, base, src, h, i_d)
                s.qvel[dst, i_b, i_d] = v_own
                s.qvel_move[e, i_b, i_d] = move_own


@ti.func
def func_mimic_gap(s: ti.template(), i_b, base, i_d, j, m):
    """How far follower i_d's position is from m q_j + offset at slot base (its leader j), which its velocity
    closes within the step."""
    return m * s.qpos[base, i_b, ti.max(s.dof_q[j], 0)] + s.dof_mimic_off[i_d] - s.qpos[base, i_b, ti.max(s.dof_q[i_d], 0)]


INTEGRATE = (func_integrate_qvel, func_integrate_qpos)
