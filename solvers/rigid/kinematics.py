"""Stage 1, kinematics: link poses, world-frame joint motion subspaces (cdof), link velocities."""
import taichi as ti

from .math3d import func_axis_angle_quat, func_cross_motion, func_normalize_quat, func_quat_mul, func_quat_to_R

JOINT_FIXED, JOINT_FREE, JOINT_REVOLUTE, JOINT_PRISMATIC = 0, 1, 2, 3


@ti.func
def func_forward_kinematics(s: ti.template(), i_b, e, src, h):
    """Link origin positions, orientations (quat and R), COM and world inertia from qpos[src]."""
    for i_l in range(s.n_links):
        p = s.link_parent[i_l]
        jt = s.link_jtype[i_l]
        qs = s.link_q_start[i_l]
        ppos = ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)
        pquat = ti.Vector([1.0, 0.0, 0.0, 0.0], dt=s.dtype)
        if p >= 0:
            ppos = s.link_pos[i_b, p]
            pquat = s.link_quat[i_b, p]
        jquat = func_quat_mul(pquat, s.link_jquat[i_l])
        pos = ppos + func_quat_to_R(pquat) @ s.link_jpos[i_l]
        quat = jquat
        if jt == JOINT_FREE:
            pos = ti.Vector([s.qpos[src, i_b, qs], s.qpos[src, i_b, qs + 1], s.qpos[src, i_b, qs + 2]])
            quat = func_normalize_quat(ti.Vector([s.qpos[src, i_b, qs + 3], s.qpos[src, i_b, qs + 4],
                                                  s.qpos[src, i_b, qs + 5], s.qpos[src, i_b, qs + 6]]))
        elif jt == JOINT_REVOLUTE:
            quat = func_quat_mul(jquat, func_axis_angle_quat(s.link_jaxis[i_l], s.qpos[src, i_b, qs]))
        elif jt == JOINT_PRISMATIC:
            pos = pos + func_quat_to_R(jquat) @ (s.link_jaxis[i_l] * s.qpos[src, i_b, qs])
        R = func_quat_to_R(quat)
        s.link_pos[i_b, i_l] = pos
        s.link_quat[i_b, i_l] = quat
        s.link_R[i_b, i_l] = R
        c = pos + R @ s.link_com[i_b, i_l]
        m = s.link_mass[i_b, i_l]
        s.link_cpos[i_b, i_l] = c
        # spatial inertia about the world origin: mass, first moment m c, J = I_c - m [c]x[c]x
        s.link_h[i_b, i_l] = m * c
        s.link_J[i_b, i_l] = R @ s.link_inertia[i_b, i_l] @ R.transpose() + m * (c.dot(c) * ti.Matrix.identity(s.dtype, 3) - c.outer_product(c))


@ti.func
def func_dof_subspace(s: ti.template(), i_b, e, src, h):
    """cdof: the spatial motion each dof produces per unit velocity, in world frame about the origin."""
    for i_d in range(s.n_dofs):
        i_l = s.dof_link[i_d]
        jt = s.link_jtype[i_l]
        k = i_d - s.link_dof_start[i_l]
        pos = s.link_pos[i_b, i_l]
        axis = s.link_R[i_b, i_l] @ s.link_jaxis[i_l]
        a = k % 3
        unit = ti.Vector([a == 0, a == 1, a == 2], dt=s.dtype)
        rev = ti.cast(jt == JOINT_REVOLUTE, s.dtype)
        pri = ti.cast(jt == JOINT_PRISMATIC, s.dtype)
        free_lin = ti.cast(jt == JOINT_FREE and k < 3, s.dtype)
        free_ang = ti.cast(jt == JOINT_FREE and k >= 3, s.dtype)
        w = rev * axis + free_ang * unit
        v = pri * axis + free_lin * unit + pos.cross(w)
        s.cdof_w[i_b, i_d] = w
        s.cdof_v[i_b, i_d] = v


@ti.func
def func_velocity(s: ti.template(), i_b, e, src, h):
    """Link spatial velocities (cvel)."""
    for i_l in range(s.n_links):
        p = s.link_parent[i_l]
        w = ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)
        v = ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)
        if p >= 0:
            w = s.cvel_w[i_b, p]
            v = s.cvel_v[i_b, p]
        d0 = s.link_dof_start[i_l]
        for k in ti.static(range(6)):
            if k < s.link_ndof[i_l]:
                qd = s.qvel[src, i_b, d0 + k]
                w = w + s.cdof_w[i_b, d0 + k] * qd
                v = v + s.cdof_v[i_b, d0 + k] * qd
        s.cvel_w[i_b, i_l] = w
        s.cvel_v[i_b, i_l] = v


@ti.func
def func_dof_subspace_dot(s: ti.template(), i_b, e, src, h):
    """Time derivative of cdof (cdofd)."""
    for i_d in range(s.n_dofs):
        i_l = s.dof_link[i_d]
        dw = ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)
        dv = ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)
        if s.link_jtype[i_l] == JOINT_FREE:
            # world-frame linear dofs are constant; angular ones move with the base origin
            if i_d - s.link_dof_start[i_l] >= 3:
                d0 = s.link_dof_start[i_l]
                vb = ti.Vector([s.qvel[src, i_b, d0], s.qvel[src, i_b, d0 + 1], s.qvel[src, i_b, d0 + 2]])
                dv = vb.cross(s.cdof_w[i_b, i_d])
        else:
            dw, dv = func_cross_motion(s.cvel_w[i_b, i_l], s.cvel_v[i_b, i_l], s.cdof_w[i_b, i_d], s.cdof_v[i_b, i_d])
        s.cdofd_w[i_b, i_d] = dw
        s.cdofd_v[i_b, i_d] = dv


# Each stage is one loop over elements for one env; kernels run every stage as its own top-level
# loop over envs, the shape Taichi's reverse mode differentiates correctly (several inner loops in
# one env loop lose gradients between them).
KINEMATICS = (func_forward_kinematics, func_dof_subspace, func_velocity, func_dof_subspace_dot)
