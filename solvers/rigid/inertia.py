"""Stage 2, inertia: composite rigid bodies -> joint-space mass matrix M, and its tree-sparse
L^T D L factorisation (Featherstone) used to solve M qacc = force.

The factorisation and solve are not differentiated by Taichi (their loops are too deep for its
reverse mode); their adjoint is written out in `func_solve_grad`: for qacc = M^-1 f,
f_bar = M^-1 qacc_bar and M_bar = -f_bar qacc^T.
"""
import functools

import taichi as ti

from .layout import func_set_zero, func_take
from .math3d import func_add, func_inertia_mul, func_inertia_mul_adjoint

LOCAL_SOLVE_MAX = 16  # element capacity up to which the no-gradient factor-solve runs on local copies


class TreeSchedule:
    """The factorisation and solves of a mass matrix of one fixed dof tree as lists of index operations,
    for a kernel to unroll (a specialised core without gradients, see RigidCore): every entry of the
    factor and of the vector is then a local of its own, in registers, where the loops over the tree on
    fields chain a store and a load per operation (ANYmal's 18 dofs: factor + solve 3.2x faster,
    measured in one process). `create` gives None where unrolling would make the kernel too large."""

    MAX_OPS = 3000  # multiply-adds of one factorisation (ANYmal: 375; a 30-dof chain: ~4,500)

    def __init__(self, parent):
        self.n = n = len(parent)

        def ancestors(i):
            out = []
            j = int(parent[i])
            while j >= 0:
                out.append(j)
                j = int(parent[j])
            return tuple(out)

        self.anc = tuple(ancestors(i) for i in range(n))
        # the lower-triangle entries the tree fills, (i, j) with j an ancestor-or-self of i, packed: the
        # factor is a local vector of these only (fewer locals for the compiler than an n x n matrix)
        self.lower = tuple((i, j) for i in range(n) for j in (i,) + self.anc[i])
        at = {ij: k for k, ij in enumerate(self.lower)}
        self.diag = tuple(at[i, i] for i in range(n))
        # func_factor_to's steps, for k from the leaves up and each ancestor i of k: a = L[k, i] / L[k, k],
        # then L[i, j] -= a L[k, j] over i and its ancestors j, then L[k, i] = a (packed positions)
        self.fac = tuple((at[k, i], at[k, k], tuple((at[i, j], at[k, j]) for j in (i,) + self.anc[i]))
                         for k in reversed(range(n)) for i in self.anc[k])
        # func_solve's: (i, j, position of L[i, j]) for j an ancestor of i, i in the order of each pass
        self.down = tuple((i, j, at[i, j]) for i in reversed(range(n)) for j in self.anc[i])
        self.up = tuple((i, j, at[i, j]) for i in range(n) for j in self.anc[i])
        self.n_ops = sum(len(op[2]) for op in self.fac)
        self.n_lower = len(self.lower)

    @staticmethod
    @functools.lru_cache(maxsize=None)
    def create(parent: tuple):
        """The schedule of the tree given by its dof parents (a tuple), or None; kept per tree, as the
        solver asks when it builds its core's key and the core again when it is made."""
        t = TreeSchedule(parent)
        return t if 0 < t.n and t.n_ops <= TreeSchedule.MAX_OPS else None


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
def func_inertia_adjoint(s: ti.template(), i_b):
    """The adjoint of the four INERTIA stages of env i_b, written out (solver.HAND_ADJOINTS), with plain adds (an
    env is one thread's; Taichi's adjoints of these stages, compare-and-swap adds in a parallel loop, took 294 +
    410 + 409 + 410 us a step at 1,024 envs: benchmarks/results/grad.md). Each store's adjoint reads the stored
    field's adjoint and zeroes it, as Taichi's does, and adds into the adjoints of what the stage read:
    - func_mass_matrix, M[i, j] = cdof_w[j] . n[i] + cdof_v[j] . f[i]: n[i], f[i] and cdof[j] get g cdof[j] and
      g (n[i], f[i]), g = M's adjoint (the diagonal's too: func_generalized_force's adds to it are read, not
      stored, by its adjoint, which ran before);
    - func_dof_momentum, (n, f) = I (w, v) = (J w + h x v, m v + w x h) with I = crb of the dof's link: m gets
      f' . v, h gets f' x w + v x n', J gets n' w^T, w gets h x f' + J^T n', v gets m f' + n' x h;
    - func_composite_inertia and func_link_inertia: crb[l] is the sum of the links' own inertias over l's
      subtree, so link l's own (link_mass, link_h, link_J) gets G[l] = crb'[l] + G[parent], one pass in link
      order (parents come first), G kept in crb's adjoints for the children, which are zeroed after."""
    for t in range(s.n_anc):
        i = s.anc_i[t]
        j = s.anc_j[t]
        g = s.mass_mat.grad[i_b, i, j]
        func_set_zero(s.mass_mat.grad, (i_b, i, j))
        s.dof_n.grad[i_b, i] = s.dof_n.grad[i_b, i] + g * s.cdof_w[i_b, j]
        s.dof_f.grad[i_b, i] = s.dof_f.grad[i_b, i] + g * s.cdof_v[i_b, j]
        s.cdof_w.grad[i_b, j] = s.cdof_w.grad[i_b, j] + g * s.dof_n[i_b, i]
        s.cdof_v.grad[i_b, j] = s.cdof_v.grad[i_b, j] + g * s.dof_f[i_b, i]
    for i in range(s.n_dofs):
        i_l = s.dof_link[i]
        gm, gh, gJ, gw, gv = func_inertia_mul_adjoint(s.crb_m[i_b, i_l], s.crb_h[i_b, i_l], s.crb_J[i_b, i_l],
                                                      s.cdof_w[i_b, i], s.cdof_v[i_b, i], func_take(s.dof_n, i_b, i),
                                                      func_take(s.dof_f, i_b, i))
        s.crb_m.grad[i_b, i_l] = s.crb_m.grad[i_b, i_l] + gm
        s.crb_h.grad[i_b, i_l] = s.crb_h.grad[i_b, i_l] + gh
        s.crb_J.grad[i_b, i_l] = s.crb_J.grad[i_b, i_l] + gJ
        s.cdof_w.grad[i_b, i] = s.cdof_w.grad[i_b, i] + gw
        s.cdof_v.grad[i_b, i] = s.cdof_v.grad[i_b, i] + gv
    for i_l in range(s.n_links):
        p = s.link_parent[i_l]
        gm = s.crb_m.grad[i_b, i_l]
        gh = s.crb_h.grad[i_b, i_l]
        gJ = s.crb_J.grad[i_b, i_l]
        if p >= 0:
            gm += s.crb_m.grad[i_b, p]
            gh += s.crb_h.grad[i_b, p]
            gJ += s.crb_J.grad[i_b, p]
            s.crb_m.grad[i_b, i_l] = gm
            s.crb_h.grad[i_b, i_l] = gh
            s.crb_J.grad[i_b, i_l] = gJ
        s.link_mass.grad[i_b, i_l] = s.link_mass.grad[i_b, i_l] + gm
        s.link_h.grad[i_b, i_l] = s.link_h.grad[i_b, i_l] + gh
        s.link_J.grad[i_b, i_l] = s.link_J.grad[i_b, i_l] + gJ
    for i_l in range(s.n_links):
        for x in ti.static((s.crb_m.grad, s.crb_h.grad, s.crb_J.grad)):
            func_set_zero(x, (i_b, i_l))


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


# Folded mimics (flatten.np_fold_leader): a follower f of leader l with q_f = m q_l + offset, beside l in the dof
# tree and with no dof below it, is solved in reduced form: A' = T^T A T and b' = T^T b, T the identity
# with m at (f, l), the follower's row and column then left with its diagonal alone (its b' is 0, so its
# solution is 0) and set to m x_l after the solve. Beside l, f shares l's ancestors, so A' keeps the tree
# sparsity. Every factorisation folds its copy of the matrix and every solve its right-hand side, the
# adjoints included (their formulas hold with the full vectors: A_bar = -y x^T with y = T A'^-1 T^T x_bar).
@ti.func
def func_fold_matrix(s: ti.template(), i_b, F: ti.template()):
    """A <- T^T A T on a copy F of the tree entries of mass_mat (lower triangle; the leader and the
    follower are not each other's ancestors, so A[l, f] is not a tree entry)."""
    for f in range(s.n_dofs):
        lead = s.dof_fold_leader[f]
        if lead >= 0:
            m = s.dof_mimic_mult[f]
            F[i_b, lead, lead] = F[i_b, lead, lead] + m * m * F[i_b, f, f]
            j = s.dof_parent[f]
            while j >= 0:
                F[i_b, lead, j] = F[i_b, lead, j] + m * F[i_b, f, j]
                F[i_b, f, j] = 0.0
                j = s.dof_parent[j]


@ti.func
def func_fold_vec(s: ti.template(), i_b, x: ti.template(), e):
    """b <- T^T b on x[e, i_b, :] (before a solve)."""
    for f in range(s.n_dofs):
        lead = s.dof_fold_leader[f]
        if lead >= 0:
            x[e, i_b, lead] = x[e, i_b, lead] + s.dof_mimic_mult[f] * x[e, i_b, f]
            x[e, i_b, f] = 0.0


@ti.func
def func_unfold_vec(s: ti.template(), i_b, x: ti.template(), e):
    """x <- T x on x[e, i_b, :] (after a solve): each folded follower moves m times its leader."""
    for f in range(s.n_dofs):
        lead = s.dof_fold_leader[f]
        if lead >= 0:
            x[e, i_b, f] = s.dof_mimic_mult[f] * x[e, i_b, lead]


@ti.func
def func_factor_to(s: ti.template(), i_b, F: ti.template()):
    """func_factor into F (a [env, dof, dof] field; only its lower triangle is written): the contact
    solve keeps its intermediate factors in their own fields instead of copying mass_fac."""
    n = s.n_dofs
    for i in range(n):
        for j in range(i + 1):
            F[i_b, i, j] = s.mass_mat[i_b, i, j]
    func_fold_matrix(s, i_b, F)
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
    func_fold_vec(s, i_b, x, e)
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
    func_unfold_vec(s, i_b, x, e)


@ti.func
def func_static_factor(s: ti.template(), i_b):
    """The L^T D L factor of mass_mat[i_b] (func_factor_to's operations, unrolled over the core's
    static_tree) as a local vector of the tree's entries (TreeSchedule.lower)."""
    L = ti.Vector.zero(s.dtype, s.static_tree.n_lower)
    for k in ti.static(range(s.static_tree.n_lower)):
        L[k] = s.mass_mat[i_b, s.static_tree.lower[k][0], s.static_tree.lower[k][1]]
    for op in ti.static(s.static_tree.fac):
        a = L[op[0]] / L[op[1]]
        for ij_kj in ti.static(op[2]):
            L[ij_kj[0]] = L[ij_kj[0]] - a * L[ij_kj[1]]
        L[op[0]] = a
    return L


@ti.func
def func_static_solve(s: ti.template(), L, b):
    """A^-1 b (b a local vector) with A's factor L (func_static_factor) as a local vector: func_solve's
    operations, unrolled."""
    y = b
    for op in ti.static(s.static_tree.down):
        y[op[1]] = y[op[1]] - L[op[2]] * y[op[0]]
    for i in ti.static(range(s.static_tree.n)):
        y[i] = y[i] / L[s.static_tree.diag[i]]
    for op in ti.static(s.static_tree.up):
        y[op[0]] = y[op[0]] - L[op[2]] * y[op[1]]
    return y


@ti.func
def func_static_vec(s: ti.template(), x: ti.template(), i_b):
    """x[i_b, :n] (a [env, dof] field) as a local vector."""
    y = ti.Vector.zero(s.dtype, ti.static(s.static_tree.n))
    for i in ti.static(range(s.static_tree.n)):
        y[i] = x[i_b, i]
    return y


@ti.func
def func_static_store(s: ti.template(), y, x: ti.template(), e, i_b):
    """x[e, i_b, :n] (an [evaluation, env, dof] field) <- the local vector y."""
    for i in ti.static(range(s.static_tree.n)):
        x[e, i_b, i] = y[i]


@ti.func
def func_factor_solve(s: ti.template(), i_b, e):
    """qacc[e] = M^-1 force. With gradients the factor stays in mass_fac for func_solve_grad; without,
    unrolled over the core's static_tree where it has one (specialised cores), else for up to
    LOCAL_SOLVE_MAX dofs func_factor_solve_local (beyond, zeroing its local copy of the capacity's
    N x N costs more than it saves: ANYmal's class, N = 32, was slower)."""
    if ti.static(s.unrolled):
        func_static_store(s, func_static_solve(s, func_static_factor(s, i_b), func_static_vec(s, s.force, i_b)), s.qacc, e, i_b)
    elif ti.static(s.requires_grad or s.cap_elems > LOCAL_SOLVE_MAX):
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
    # the folded mimics (func_fold_matrix, func_fold_vec), on the local copies
    for f in range(n):
        lead = s.dof_fold_leader[f]
        if lead >= 0:
            m = s.dof_mimic_mult[f]
            L[lead, lead] = L[lead, lead] + m * m * L[f, f]
            x[lead] = x[lead] + m * x[f]
            x[f] = 0.0
            j = par[f]
            while j >= 0:
                L[lead, j] = L[lead, j] + m * L[f, j]
                L[f, j] = 0.0
                j = par[j]
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
    func_unfold_vec(s, i_b, s.qacc, e)


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
