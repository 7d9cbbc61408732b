"""Stage 8, integration: semi-implicit Euler (also used by implicitfast) and the stages of RK4.

A step is a fixed schedule of evaluations e (dynamics at a state slot) and integrations between
state slots; every slot and every qacc[e] is written once per step, so a step can be replayed
backwards by Taichi's autodiff.
"""
import taichi as ti

from .kinematics import JOINT_FREE, JOINT_PRISMATIC, JOINT_REVOLUTE
from .math3d import func_quat_mul, func_rotvec_quat

INT_EULER, INT_RK_STAGE, INT_RK_FINAL = 0, 1, 2


@ti.func
def func_integrate_qpos(s: ti.template(), i_b, kind, e, base, src, dst, h):
    """qpos[dst] = qpos[base] advanced by velocity veff[e] over time h (quaternions on the sphere)."""
    for i_l in range(s.n_links):
        jt = s.link_jtype[i_l]
        qs = s.link_q_start[i_l]
        d0 = s.link_dof_start[i_l]
        if jt == JOINT_REVOLUTE or jt == JOINT_PRISMATIC:
            s.qpos[dst, i_b, qs] = s.qpos[base, i_b, qs] + h * s.veff[e, i_b, d0]
        elif jt == JOINT_FREE:
            for k in ti.static(range(3)):
                s.qpos[dst, i_b, qs + k] = s.qpos[base, i_b, qs + k] + h * s.veff[e, i_b, d0 + k]
            w = ti.Vector([s.veff[e, i_b, d0 + 3], s.veff[e, i_b, d0 + 4], s.veff[e, i_b, d0 + 5]])
            q0 = ti.Vector([s.qpos[base, i_b, qs + 3], s.qpos[base, i_b, qs + 4], s.qpos[base, i_b, qs + 5], s.qpos[base, i_b, qs + 6]])
            q1 = func_quat_mul(func_rotvec_quat(w, h), q0)
            qn = q1 / ti.sqrt(q1.dot(q1))
            for k in ti.static(range(4)):
                s.qpos[dst, i_b, qs + 3 + k] = qn[k]


@ti.func
def func_integrate_qvel(s: ti.template(), i_b, kind, e, base, src, dst, h):
    """kind INT_EULER: v' = v + h a, q' = q + h v'. INT_RK_STAGE: the RK4 trial state at h from the
    derivative at slot src. INT_RK_FINAL: combine the 4 stage derivatives e-3..e over h."""
    if kind == INT_EULER:
        for i_d in range(s.n_dofs):
            s.qvel[dst, i_b, i_d] = s.qvel[base, i_b, i_d] + h * s.qacc[e, i_b, i_d]
            s.veff[e, i_b, i_d] = s.qvel[dst, i_b, i_d]
    elif kind == INT_RK_STAGE:
        for i_d in range(s.n_dofs):
            s.qvel[dst, i_b, i_d] = s.qvel[base, i_b, i_d] + h * s.qacc[e, i_b, i_d]
            s.veff[e, i_b, i_d] = s.qvel[src, i_b, i_d]
    else:
        for i_d in range(s.n_dofs):
            s.qvel[dst, i_b, i_d] = s.qvel[base, i_b, i_d] + h / 6.0 * (
                s.qacc[e - 3, i_b, i_d] + 2.0 * s.qacc[e - 2, i_b, i_d] + 2.0 * s.qacc[e - 1, i_b, i_d] + s.qacc[e, i_b, i_d])
            s.veff[e, i_b, i_d] = (s.qvel[base, i_b, i_d] + 2.0 * s.qvel[base + 1, i_b, i_d]
                                   + 2.0 * s.qvel[base + 2, i_b, i_d] + s.qvel[base + 3, i_b, i_d]) / 6.0


INTEGRATE = (func_integrate_qvel, func_integrate_qpos)
