"""Factorisations and solves of the contact system and their hand-written adjoints (not differentiated
by Taichi: forward and adjoint, as the tree factorisation in inertia.py). The solves of
func_contact_solve keep their factors (factor_candidates, factor_normal); these variants of inertia.func_solve and
func_dense_solve take the factor's field as an argument.

(inertia.py has the core's tree factor and solve; func_tree_solve here is inertia.func_solve on a
factor field given as an argument, and func_factor_to is inertia's: the two could share one
implementation once a bitwise comparison shows the inlined code is the same.)"""
import taichi as ti

from ..inertia import func_factor_to, func_fold_vec, func_unfold_vec

# which envelope (ContactSolver.env_first / env_last, dense scenes) goes with which factor: the solves'
# k argument (a tree factor has none and ignores it); the gradient path keeps the final factor's
# envelope before bound round r at ENV_BOUND + r
ENV_CANDIDATES, ENV_NORMAL, ENV_FINAL = 0, 1, 2
N_ENV = ENV_BOUND = 3


# ------------------------------------------------------------------------------------------------
# Solves (not differentiated by Taichi: forward and hand-written adjoint, as the tree factorisation in
# inertia.py). The solves of func_contact_solve reuse the first factor, kept in factor_candidates; these variants
# of inertia.func_solve and func_dense_solve take the factor's field as an argument.
# ------------------------------------------------------------------------------------------------
@ti.func
def func_tree_solve(s: ti.template(), Fc: ti.template(), i_b, x: ti.template(), e):
    """x[e, i_b, :] <- A^-1 x[e, i_b, :] with the tree L^T D L factor of A in Fc (inertia.func_solve).
    Read-modify-writes spelled out: `-=` on a field in the env loop compiles to an atomic (a
    compare-and-swap loop), and these solves are never differentiated by Taichi."""
    n = s.n_dofs
    func_fold_vec(s, i_b, x, e)
    for kk in range(n):
        i = n - 1 - kk
        j = s.dof_parent[i]
        while j >= 0:
            x[e, i_b, j] = x[e, i_b, j] - Fc[i_b, i, j] * x[e, i_b, i]
            j = s.dof_parent[j]
    for i in range(n):
        x[e, i_b, i] = x[e, i_b, i] / Fc[i_b, i, i]
    for i in range(n):
        j = s.dof_parent[i]
        while j >= 0:
            x[e, i_b, i] = x[e, i_b, i] - Fc[i_b, i, j] * x[e, i_b, j]
            j = s.dof_parent[j]
    func_unfold_vec(s, i_b, x, e)


@ti.func
def func_dense_solve(s: ti.template(), Fc: ti.template(), k, i_b, x: ti.template(), e):
    """x[e, i_b, :] <- A^-1 x[e, i_b, :] with A = L D L^T in Fc (unit lower L, D on the diagonal), in the
    factorisation's order (dense_perm) and over its envelope k (func_factor_dense_to): the terms outside
    it are exact zeros."""
    c = s.contact
    n = s.n_dofs
    y = ti.static(c.perm_tmp)
    func_fold_vec(s, i_b, x, e)
    for i in range(n):
        y[i_b, i] = x[e, i_b, c.dense_perm[i]]
    for i in range(n):
        acc = y[i_b, i]
        for kk in range(c.env_first[i_b, k, i], i):
            acc -= Fc[i_b, i, kk] * y[i_b, kk]
        y[i_b, i] = acc
    for i in range(n):
        y[i_b, i] = y[i_b, i] / Fc[i_b, i, i]
    for ii in range(n):
        i = n - 1 - ii
        acc = y[i_b, i]
        for kk in range(i + 1, c.env_last[i_b, k, i] + 1):
            acc -= Fc[i_b, kk, i] * y[i_b, kk]
        y[i_b, i] = acc
    for i in range(n):
        x[e, i_b, c.dense_perm[i]] = y[i_b, i]
    func_unfold_vec(s, i_b, x, e)


@ti.func
def func_factor_dense(s: ti.template(), i_b):
    """mass_fac <- L D L^T of A = M (tree entries) + mass_cross, dense."""
    func_factor_dense_to(s, i_b, s.mass_fac, ENV_FINAL)


@ti.func
def func_factor_dense_to(s: ti.template(), i_b, F: ti.template(), k):
    """func_factor_dense into F (lower triangle only), an envelope (skyline) L D L^T of A in the order
    dense_perm (plan._dense_order; F[i, j] = A[perm[i], perm[j]]): row i of that A is zero
    left of its first nonzero column first[i], and so is row i of L (fill-in stays inside the envelope),
    so each sum runs from the later of the two rows' first columns, and column j's rows stop at
    last[j] = max{i : first[i] <= j}. The skipped terms are exact zeros, so this is the dense factor
    at the envelope's cost (the 100-box tower, its boxes stacked in dof order: a band of ~24 of its 606
    dofs; 174 -> 65 ms a step), up to the sums' rounding: Taichi's fast math lets LLVM split a
    reduction into partial sums by position in the loop, and the loops now start elsewhere (the tower's
    state after 60 steps in float64: 1e-14 m apart). first and last go to envelope k (ENV_*) for the
    solves with this factor."""
    c = s.contact
    n = s.n_dofs
    for i in range(n):
        f = i
        pi = c.dense_perm[i]
        for j in range(i + 1):
            pj = c.dense_perm[j]
            a = ti.max(pi, pj)  # A is stored in its lower triangle
            b = ti.min(pi, pj)
            v = s.mass_mat[i_b, a, b] * s.dof_anc[a, b] + c.mass_cross[i_b, a, b]
            F[i_b, i, j] = v
            if f == i and v != 0.0:
                f = j
        c.env_first[i_b, k, i] = f
    if func_fold_dense(s, i_b, F) > 0:
        # the rows' first columns again, of the folded matrix
        for i in range(n):
            f = i
            for j in range(i + 1):
                if f == i and F[i_b, i, j] != 0.0:
                    f = j
            c.env_first[i_b, k, i] = f
    # last[j], sweeping j down with the minimum of first over the rows from i on (>= i's, so last[j] >= j)
    i = n - 1
    lowest = c.env_first[i_b, k, i]
    for jj in range(n):
        j = n - 1 - jj
        while lowest > j:
            i -= 1
            lowest = ti.min(lowest, c.env_first[i_b, k, i])
        c.env_last[i_b, k, j] = i
    for j in range(n):
        fj = c.env_first[i_b, k, j]
        dj = F[i_b, j, j]
        for kk in range(fj, j):
            dj -= F[i_b, j, kk] * F[i_b, j, kk] * F[i_b, kk, kk]
        F[i_b, j, j] = dj
        for i2 in range(j + 1, c.env_last[i_b, k, j] + 1):
            fi = c.env_first[i_b, k, i2]
            if fi <= j:
                v = F[i_b, i2, j]
                for kk in range(ti.max(fi, fj), j):
                    v -= F[i_b, i2, kk] * F[i_b, j, kk] * F[i_b, kk, kk]
                F[i_b, i2, j] = v / dj


@ti.func
def func_dense_position(s: ti.template(), d):
    """The position of dof d in the dense factorisation's order (dense_perm's inverse)."""
    at = 0
    for k in range(s.n_dofs):
        if s.contact.dense_perm[k] == d:
            at = k
    return at


@ti.func
def func_fold_dense(s: ti.template(), i_b, F: ti.template()):
    """inertia.func_fold_matrix on the dense copy F (lower triangle, in dense_perm's order), where the
    leader and the follower may be coupled (mass_cross) and any entry of theirs may be nonzero. Returns
    how many followers it folded."""
    n = s.n_dofs
    count = 0
    for f in range(n):
        lead = s.dof_fold_leader[f]
        if lead >= 0:
            count += 1
            m = s.dof_mimic_mult[f]
            pf = func_dense_position(s, f)
            pl = func_dense_position(s, lead)
            a_ff = F[i_b, pf, pf]
            a_lf = F[i_b, ti.max(pl, pf), ti.min(pl, pf)]
            for k in range(n):
                if (k != pf) & (k != pl):
                    F[i_b, ti.max(pl, k), ti.min(pl, k)] = (F[i_b, ti.max(pl, k), ti.min(pl, k)]
                                                            + m * F[i_b, ti.max(pf, k), ti.min(pf, k)])
                    F[i_b, ti.max(pf, k), ti.min(pf, k)] = 0.0
            F[i_b, pl, pl] = F[i_b, pl, pl] + 2.0 * m * a_lf + m * m * a_ff
            F[i_b, ti.max(pl, pf), ti.min(pl, pf)] = 0.0
    return count


@ti.func
def func_factor_solve_dense(s: ti.template(), i_b, e):
    """qacc[e] = A^-1 force with A = M (tree entries) + mass_cross, by a dense L D L^T."""
    func_factor_dense(s, i_b)
    for i in range(s.n_dofs):
        s.qacc[e, i_b, i] = s.force[i_b, i]
    func_dense_solve(s, s.mass_fac, ENV_FINAL, i_b, s.qacc, e)


@ti.func
def func_solve_adjoint(s: ti.template(), Fc: ti.template(), k, i_b, x: ti.template(), xg: ti.template(), e,
                       rhs_g: ti.template()):
    """Adjoint of x[e] = A^-1 rhs (A's factor in Fc): rhs_bar += A^-1 x_bar, A_bar = -rhs_bar x^T (lower
    triangle, symmetrised), onto the tree entries of mass_mat and, in dense scenes, mass_cross."""
    c = s.contact
    for i in range(s.n_dofs):
        c.solve_tmp[0, i_b, i] = xg[e, i_b, i]
    if ti.static(c.dense):
        func_dense_solve(s, Fc, k, i_b, c.solve_tmp, 0)
    else:
        func_tree_solve(s, Fc, i_b, c.solve_tmp, 0)
    for i in range(s.n_dofs):
        rhs_g[i_b, i] += c.solve_tmp[0, i_b, i]
    for ij in range(s.n_dofs * s.n_dofs):
        i = ij // s.n_dofs
        j = ij % s.n_dofs
        if j <= i:
            g = c.solve_tmp[0, i_b, i] * x[e, i_b, j]
            if i != j:
                g += c.solve_tmp[0, i_b, j] * x[e, i_b, i]
            if ti.static(c.dense):
                c.mass_cross.grad[i_b, i, j] -= g
            if s.dof_anc[i, j] == 1:
                s.mass_mat.grad[i_b, i, j] -= g


@ti.func
def func_solve_grad_dense(s: ti.template(), i_b, e):
    """Adjoint of qacc[e] = A^-1 force (func_factor_solve_dense), its factor still in mass_fac."""
    func_solve_adjoint(s, s.mass_fac, ENV_FINAL, i_b, s.qacc, s.qacc.grad, e, s.force.grad)


@ti.func
def func_tree_env(s: ti.template(), i_b):
    """Whether env i_b's system in this evaluation is M's tree plus the contacts' per-link blocks, with no
    coupling between moving links: in a dense scene stepped without gradients, when none of its listed slots
    couples two moving links (n_cross_on, slots.func_contact_slots), mass_cross is all zeros, and the
    evaluation factors and solves as a scene without such pairs does (the tree factorisation, unrolled in a
    specialised core), not over the dense envelope: a Panda beside a box it does not touch steps as the Panda
    alone does, to the bit. Every factor and solve of the evaluation takes the same branch (its listed
    slots are fixed after the slots stage). With gradients, always False (the recorded steps keep the dense
    factor, whose adjoint reads it)."""
    tree = True
    if ti.static(s.contact.dense and not s.requires_grad):
        tree = s.contact.n_cross_on[i_b] == 0
    elif ti.static(s.contact.dense):
        tree = False
    return tree


@ti.func
def func_if_coupled(s: ti.template(), i_b, stage: ti.template()):
    """stage(s, i_b), a pass's link-pair sums (clear or cross terms), in a dense scene where the evaluation
    couples moving links: not where func_tree_env says it does not (nothing reads them there)."""
    if ti.static(s.contact.dense):
        if not func_tree_env(s, i_b):
            stage(s, i_b)


@ti.func
def func_factor_into(s: ti.template(), i_b, Fc: ti.template(), k, x: ti.template()):
    """Factor the current system (mass_mat, and mass_cross in dense scenes) into Fc (kept for the later
    solves and the adjoints; the solves read its lower triangle only), and solve x[0] = A^-1 force
    with it."""
    c = s.contact
    if ti.static(c.dense and not s.requires_grad):
        if func_tree_env(s, i_b):
            func_factor_to(s, i_b, Fc)
        else:
            func_factor_dense_to(s, i_b, Fc, k)
    elif ti.static(c.dense):
        func_factor_dense_to(s, i_b, Fc, k)
    else:
        func_factor_to(s, i_b, Fc)
    n = s.n_dofs
    for i in range(n):
        x[0, i_b, i] = s.force[i_b, i]
    func_any_solve(s, Fc, k, i_b, x, 0)


@ti.func
def func_any_solve(s: ti.template(), Fc: ti.template(), k, i_b, x: ti.template(), e):
    if ti.static(s.contact.dense and not s.requires_grad):
        if func_tree_env(s, i_b):
            func_tree_solve(s, Fc, i_b, x, e)
        else:
            func_dense_solve(s, Fc, k, i_b, x, e)
    elif ti.static(s.contact.dense):
        func_dense_solve(s, Fc, k, i_b, x, e)
    else:
        func_tree_solve(s, Fc, i_b, x, e)
