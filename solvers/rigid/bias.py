"""Stage 3, bias forces: Coriolis, centrifugal and gravity by recursive Newton-Euler (qacc = 0)."""
import taichi as ti

from .kinematics import func_link_joint_velocity, func_parent_slot
from .math3d import func_add, func_cross_force, func_inertia_mul


@ti.func
def func_link_forces(s: ti.template(), i_b, e, src, h):
    """Link accelerations with qacc = 0 (gravity as an upward world acceleration) and the forces they
    need. A free joint contributes sum_k cdofd_k qd_k = (0, vb x wb)."""
    for i_l in range(s.n_links):
        p = s.link_parent[i_l]
        has_p = p >= 0
        pp = func_parent_slot(s, p)
        d0, qd, free, vb, wb = func_link_joint_velocity(s, i_b, src, i_l)
        aw = ti.select(has_p, s.cacc_w[i_b, pp], ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)) + s.cdofd_w[i_b, d0] * qd
        av = ti.select(has_p, s.cacc_v[i_b, pp], -s.gravity[i_b]) + s.cdofd_v[i_b, d0] * qd + free * vb.cross(wb)
        s.cacc_w[i_b, i_l] = aw
        s.cacc_v[i_b, i_l] = av
        m, mc, J = s.link_mass[i_b, i_l], s.link_h[i_b, i_l], s.link_J[i_b, i_l]
        n, f = func_inertia_mul(m, mc, J, aw, av)
        wv, vv = s.cvel_w[i_b, i_l], s.cvel_v[i_b, i_l]
        hn, hf = func_inertia_mul(m, mc, J, wv, vv)
        cn, cf = func_cross_force(wv, vv, hn, hf)
        s.cfrc_n[i_b, i_l] = n + cn
        s.cfrc_f[i_b, i_l] = f + cf


@ti.func
def func_accumulate_forces(s: ti.template(), i_b, e, src, h):
    for k in range(s.n_links):
        i_l = s.n_links - 1 - k
        p = s.link_parent[i_l]
        if p >= 0:
            func_add(s, s.cfrc_n, i_b, p, s.cfrc_n[i_b, i_l])
            func_add(s, s.cfrc_f, i_b, p, s.cfrc_f[i_b, i_l])


@ti.func
def func_project_forces(s: ti.template(), i_b, e, src, h):
    for i_d in range(s.n_dofs):
        i_l = s.dof_link[i_d]
        s.bias[i_b, i_d] = s.cdof_w[i_b, i_d].dot(s.cfrc_n[i_b, i_l]) + s.cdof_v[i_b, i_d].dot(s.cfrc_f[i_b, i_l])


BIAS = (func_link_forces, func_accumulate_forces, func_project_forces)
