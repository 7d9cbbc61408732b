"""External wrenches on links (the rigid-MPM coupler's reaction forces), one per substep, added to
the generalised force: a force f (N, world frame) and a torque t (N m, about the world origin) on
link l act on dof d through its motion subspace as cdof_w . T + cdof_v . F, with (T, F) the sum of
the wrenches on the links below d's link (summed up the tree like composite inertia).
"""
import taichi as ti

from .contact import func_acc


@ti.func
def func_external_copy(s: ti.template(), i_b, e, src, h):
    sub = e // s.evals_per_substep
    for i_l in range(s.n_links):
        s.ext_sum_f[i_b, i_l] = s.ext_f[sub, i_b, i_l]
        s.ext_sum_t[i_b, i_l] = s.ext_t[sub, i_b, i_l]


@ti.func
def func_external_tree(s: ti.template(), i_b, e, src, h):
    for k in range(s.n_links):
        i_l = s.n_links - 1 - k
        p = s.link_parent[i_l]
        if p >= 0:
            func_acc(s, s.ext_sum_f, i_b, p, s.ext_sum_f[i_b, i_l])
            func_acc(s, s.ext_sum_t, i_b, p, s.ext_sum_t[i_b, i_l])


@ti.func
def func_external_dof(s: ti.template(), i_b, e, src, h):
    for i_d in range(s.n_dofs):
        i_l = s.dof_link[i_d]
        func_acc(s, s.force, i_b, i_d, s.cdof_w[i_b, i_d].dot(s.ext_sum_t[i_b, i_l])
                 + s.cdof_v[i_b, i_d].dot(s.ext_sum_f[i_b, i_l]))


EXTERNAL_STAGES = (func_external_copy, func_external_tree, func_external_dof)
