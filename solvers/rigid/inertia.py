"""Stage 2, inertia: composite rigid bodies -> joint-space mass matrix M, and its tree-sparse
L^T D L factorisation (Featherstone) used to solve M qacc = force.

The factorisation and solve are not differentiated by Taichi (their loops are too deep for its
reverse mode); their adjoint is written out in `func_solve_grad`: for qacc = M^-1 f,
f_bar = M^-1 qacc_bar and M_bar = -f_bar qacc^T.
"""
import taichi as ti

from .math3d import func_add, func_inertia_mul

LOCAL_SOLVE_MAX = 16  # element capacity up to which the no-gradient factor-solve runs on local copies


@ti.func
def func_link_inertia(s: ti.template(), i_b, e, src, h):
    """Composite inertias start as the links' own (without gradients kinematics.func_world_inertia
    writes them)."""
    for i_l in range(s.n_links if ti.static(s.requires_grad) else 0):
        s.crb_m[i_b, i_l] = s.link_mass[i_b, i_l]
        s.crb_h[i_b, i_l] = s.link_h[i_b, i_l]
        s.crb_J[i_b, i_l] = s.link_J[i_b, i_l]


@ti.func
def func_composite_inertia(s: ti.template(), i_b, e, src, h):
    for k in range(s.n_links):
        i_l = s.n_links - 1 - k
        p = s.link_parent[i_l]
        if p >= 0:
            func_add(s, s.crb_m, i_b, p, s.crb_m[i_b, i_l])
            func_add(s, s.crb_h, i_b, p, s.crb_h[i_b, i_l])
            func_add(s, s.crb_J, i_b, p, s.crb_J[i_b, i_l])


@ti.func
def func_dof_momentum(s: ti.template(), i_b, e, src, h):
    """The spatial force (n, f) = I_c cdof_i of each dof i, I_c the composite inertia of its link: the
    column of M below it is its dot product with the ancestors' cdofs (computed once per dof, not once
    per entry)."""
    for i in range(s.n_dofs):
        i_l = s.dof_link[i]
        n, f = func_inertia_mul(s.crb_m[i_b, i_l], s.crb_h[i_b, i_l], s.crb_J[i_b, i_l], s.cdof_w[i_b, i], s.cdof_v[i_b, i])
        s.dof_n[i_b, i] = n
        s.dof_f[i_b, i] = f


@ti.func
def func_mass_matrix(s: ti.template(), i_b, e, src, h):
    """Lower triangle M[i, j] (j an ancestor-or-self of i), over the static list of such pairs (a scan
    of all n^2 pairs would divide by the run-time n twice per pair); other entries are never read."""
    for t in range(s.n_anc):
        i = s.anc_i[t]
        j = s.anc_j[t]
        s.mass_mat[i_b, i, j] = s.cdof_w[i_b, j].dot(s.dof_n[i_b, i]) + s.cdof_v[i_b, j].dot(s.dof_f[i_b, i])


@ti.func
def func_factor(s: ti.template(), i_b):
    """In-place L^T D L of the (regularised) mass matrix into mass_fac; sparsity of the dof tree."""
    func_factor_to(s, i_b, s.mass_fac)


@ti.func
def func_factor_to(s: ti.template(), i_b, F: ti.template()):
    """func_factor into F (a [env, dof, dof] field; only its lower triangle is written): the contact
    solve keeps its intermediate factors in their own fields instead of copying mass_fac."""
    n = s.n_dofs
    for i in range(n):
        for j in range(i + 1):
            F[i_b, i, j] = s.mass_mat[i_b, i, j]
    for kk in range(n):
        k = n - 1 - kk
        i = s.dof_parent[k]
        while i >= 0:
            a = F[i_b, k, i] / F[i_b, k, k]
            j = i
            while j >= 0:
                F[i_b, i, j] = F[i_b, i, j] - a * F[i_b, k, j]
                j = s.dof_parent[j]
            F[i_b, k, i] = a
            i = s.dof_parent[i]


@ti.func
def func_solve(s: ti.template(), i_b, x: ti.template(), e):
    """x[e, i_b, :] <- M^-1 x[e, i_b, :] using the factor in mass_fac."""
    n = s.n_dofs
    for kk in range(n):
        i = n - 1 - kk
        j = s.dof_parent[i]
        while j >= 0:
            x[e, i_b, j] = x[e, i_b, j] - s.mass_fac[i_b, i, j] * x[e, i_b, i]
            j = s.dof_parent[j]
    for i in range(n):
        x[e, i_b, i] = x[e, i_b, i] / s.mass_fac[i_b, i, i]
    for i in range(n):
        j = s.dof_parent[i]
        while j >= 0:
            x[e, i_b, i] = x[e, i_b, i] - s.mass_fac[i_b, i, j] * x[e, i_b, j]
            j = s.dof_parent[j]


@ti.func
def func_factor_solve(s: ti.template(), i_b, e):
    """qacc[e] = M^-1 force. With gradients the factor stays in mass_fac for func_solve_grad; without,
    and for up to LOCAL_SOLVE_MAX dofs, func_factor_solve_local (beyond, zeroing its local copy of
    the capacity's N x N costs more than it saves: ANYmal's class, N = 32, was slower)."""
    if ti.static(s.requires_grad or s.cap_elems > LOCAL_SOLVE_MAX):
        func_factor(s, i_b)
        for i in range(s.n_dofs):
            s.qacc[e, i_b, i] = s.force[i_b, i]
        func_solve(s, i_b, s.qacc, e)
    else:
        func_factor_solve_local(s, i_b, e)


@ti.func
def func_factor_solve_local(s: ti.template(), i_b, e):
    """func_factor + func_solve with the same operations in the same order, on a local copy of M's lower
    triangle and of the force. On the fields every store may alias Taichi's runtime struct, so each
    access reloads the root pointer, and the walks up the dof tree become chains of dependent loads
    (most of the factor-solve's time); a local array does not alias, and its factor is never stored
    (only the adjoint needs mass_fac)."""
    N = ti.static(s.cap_elems)
    n = s.n_dofs
    L = ti.Matrix.zero(s.dtype, N, N)
    x = ti.Vector.zero(s.dtype, N)
    par = ti.Vector.zero(ti.i32, N)
    for i in range(n):
        par[i] = s.dof_parent[i]
        x[i] = s.force[i_b, i]
        for j in range(i + 1):
            L[i, j] = s.mass_mat[i_b, i, j]
    for kk in range(n):
        k = n - 1 - kk
        i = par[k]
        while i >= 0:
            a = L[k, i] / L[k, k]
            j = i
            while j >= 0:
                L[i, j] = L[i, j] - a * L[k, j]
                j = par[j]
            L[k, i] = a
            i = par[i]
    for kk in range(n):
        i = n - 1 - kk
        j = par[i]
        while j >= 0:
            x[j] = x[j] - L[i, j] * x[i]
            j = par[j]
    for i in range(n):
        x[i] = x[i] / L[i, i]
    for i in range(n):
        j = par[i]
        while j >= 0:
            x[i] = x[i] - L[i, j] * x[j]
            j = par[j]
    for i in range(n):
        s.qacc[e, i_b, i] = x[i]


@ti.func
def func_solve_grad(s: ti.template(), i_b, e):
    """Adjoint of qacc[e] = M^-1 force, with the factor of that evaluation still in mass_fac."""
    for i in range(s.n_dofs):
        s.solve_tmp[0, i_b, i] = s.qacc.grad[e, i_b, i]
    func_solve(s, i_b, s.solve_tmp, 0)
    for i in range(s.n_dofs):
        s.force.grad[i_b, i] = s.force.grad[i_b, i] + s.solve_tmp[0, i_b, i]
    for t in range(s.n_anc):
        i = s.anc_i[t]
        j = s.anc_j[t]
        g = s.solve_tmp[0, i_b, i] * s.qacc[e, i_b, j]
        if i != j:
            g += s.solve_tmp[0, i_b, j] * s.qacc[e, i_b, i]
        s.mass_mat.grad[i_b, i, j] = s.mass_mat.grad[i_b, i, j] - g


INERTIA = (func_link_inertia, func_composite_inertia, func_dof_momentum, func_mass_matrix)
