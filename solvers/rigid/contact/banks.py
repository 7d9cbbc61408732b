"""Force banks: per-link sums of one set of contact forces and of their implicit blocks J^T W J,
summed up the kinematic tree and projected onto the dofs (force += J^T f, M += J^T W J), like
composite inertia; contacts between two moving links also sum per link pair into mass_cross (the
coupling outside the tree sparsity, see the package docstring)."""
import taichi as ti

from ..kinematics import func_link_origin
from ..layout import FieldTree
from ..math3d import func_add, func_add2, func_mm, func_mtv, func_mv, func_skew


@ti.data_oriented
class AccBank:
    """Per-link sums of one set of contact forces (wrench about the link's tree's origin,
    kinematics.func_link_origin) and, with `matrices`, of their implicit blocks J^T W J (6x6 per link: Sww,
    Swv, Svv), per link pair for contacts between two moving links (the coupling outside the tree
    sparsity: -J_2^T W J_1, its two off-diagonal 3x3 blocks apart, lp_Swv and lp_Svw, since the two links'
    trees may have different origins), and the per-dof vectors S(link(i)) cdof_i the projection onto M dots
    with the ancestors' cdofs."""

    def __init__(self, B, L, D, n_lp, dtype, grad, matrices):
        t = FieldTree(dtype, grad, B)
        V3, M3 = t.V3, t.M3
        self.matrices = matrices
        self.pairs = matrices and n_lp > 0
        self.link_fn, self.link_ff = V3((B, L)), V3((B, L))
        self.link_touch = t.I((B, L))
        self.grad_fields = [self.link_fn, self.link_ff]
        if matrices:
            self.link_Sww, self.link_Swv, self.link_Svv = M3((B, L)), M3((B, L)), M3((B, L))
            self.dof_Sw, self.dof_Sv = V3((B, D)), V3((B, D))
            self.grad_fields += [self.link_Sww, self.link_Swv, self.link_Svv, self.dof_Sw, self.dof_Sv]
        if self.pairs:
            self.lp_Sww, self.lp_Swv, self.lp_Svv = M3((B, n_lp)), M3((B, n_lp)), M3((B, n_lp))
            self.lp_Svw = M3((B, n_lp))
            self.lp_touch = t.I((B, n_lp))  # a slot of the pair added to it (func_bank_cross skips the others)
            self.grad_fields += [self.lp_Sww, self.lp_Swv, self.lp_Svv, self.lp_Svw]
        self.tree = t.finalize()


@ti.func
def func_bank_clear(s: ti.template(), b: ti.template(), i_b):
    for i_l in range(s.n_links):
        b.link_fn[i_b, i_l] = ti.Vector([0.0, 0.0, 0.0])
        b.link_ff[i_b, i_l] = ti.Vector([0.0, 0.0, 0.0])
        if ti.static(b.matrices):
            b.link_Sww[i_b, i_l] = ti.Matrix.zero(s.dtype, 3, 3)
            b.link_Swv[i_b, i_l] = ti.Matrix.zero(s.dtype, 3, 3)
            b.link_Svv[i_b, i_l] = ti.Matrix.zero(s.dtype, 3, 3)
        b.link_touch[i_b, i_l] = 0


@ti.func
def func_bank_clear_pairs(s: ti.template(), b: ti.template(), i_b):
    """The link pairs' sums <- 0: every pair's with gradients; without, the pairs a slot touched since the
    last clear (lp_touch; every other pair's sums are zeros already: the fields start at zero and only
    func_bank_add writes them, marking the pair): a robot with self-collision has ~50 pairs of moving links,
    27 numbers each, a few of them touching."""
    c = s.contact
    for lp in range(c.n_lp):
        if ti.static(s.requires_grad):
            func_zero_pair(s, b, i_b, lp)
        else:
            if b.lp_touch[i_b, lp] == 1:
                func_zero_pair(s, b, i_b, lp)
                b.lp_touch[i_b, lp] = 0


@ti.func
def func_zero_pair(s: ti.template(), b: ti.template(), i_b, lp):
    b.lp_Sww[i_b, lp] = ti.Matrix.zero(s.dtype, 3, 3)
    b.lp_Swv[i_b, lp] = ti.Matrix.zero(s.dtype, 3, 3)
    b.lp_Svv[i_b, lp] = ti.Matrix.zero(s.dtype, 3, 3)
    b.lp_Svw[i_b, lp] = ti.Matrix.zero(s.dtype, 3, 3)


@ti.func
def func_bank_add(s: ti.template(), b: ti.template(), i_b, i_s, pos, F, W):
    """Force F at pos on the point side of slot i_s (-F on the other side) and, with matrices, the
    implicit block W (3x3, on the relative velocity at pos), added onto the slot's moving links, each about
    its tree's origin (the lever r = pos - o, P = [r]x: the point moves at v - P w)."""
    c = s.contact
    la = c.geom_link[c.slot_ga[i_s]]
    lb = c.geom_link[c.slot_gb[i_s]]
    ra = pos - func_link_origin(s, i_b, la)
    rb = pos - func_link_origin(s, i_b, lb)
    PWa, Swwa, PWb, Swwb = W, W, W, W
    Pa, Pb = W, W
    if ti.static(b.matrices):
        Pa = func_skew(ra)
        Pb = func_skew(rb)
        PWa = func_mm(Pa, W)
        Swwa = -func_mm(PWa, Pa)
        PWb = func_mm(Pb, W)
        Swwb = -func_mm(PWb, Pb)
    if c.link_dyn[la] == 1:
        b.link_touch[i_b, la] = 1
        func_add(s, b.link_ff, i_b, la, F)
        func_add(s, b.link_fn, i_b, la, ra.cross(F))
        if ti.static(b.matrices):
            func_add(s, b.link_Sww, i_b, la, Swwa)
            func_add(s, b.link_Swv, i_b, la, PWa)
            func_add(s, b.link_Svv, i_b, la, W)
    if c.link_dyn[lb] == 1:
        b.link_touch[i_b, lb] = 1
        func_add(s, b.link_ff, i_b, lb, -F)
        func_add(s, b.link_fn, i_b, lb, -rb.cross(F))
        if ti.static(b.matrices):
            func_add(s, b.link_Sww, i_b, lb, Swwb)
            func_add(s, b.link_Swv, i_b, lb, PWb)
            func_add(s, b.link_Svv, i_b, lb, W)
    if ti.static(b.pairs):
        lp = c.slot_lp[i_s]
        if lp >= 0:
            if ti.static(not s.requires_grad):
                b.lp_touch[i_b, lp] = 1
            # the pair's links in the cross list's order (plan.py: the lower link index first, its dofs i, the
            # other's j): u_j^T W u_i with u = v - P w on each side's own lever
            low_a = la < lb
            P1 = ti.select(low_a, Pa, Pb)
            PW2 = ti.select(low_a, PWb, PWa)
            func_add(s, b.lp_Sww, i_b, lp, -func_mm(PW2, P1))
            func_add(s, b.lp_Swv, i_b, lp, PW2)
            func_add(s, b.lp_Svw, i_b, lp, ti.select(low_a, PWa, PWb))
            func_add(s, b.lp_Svv, i_b, lp, W)


@ti.func
def func_bank_tree(s: ti.template(), b: ti.template(), i_b):
    """Per-link sums over the link's subtree (children after parents in link order)."""
    for k in range(s.n_links):
        i_l = s.n_links - 1 - k
        p = s.link_parent[i_l]
        if (p >= 0) & (b.link_touch[i_b, i_l] == 1):
            b.link_touch[i_b, p] = 1
            func_add(s, b.link_ff, i_b, p, b.link_ff[i_b, i_l])
            func_add(s, b.link_fn, i_b, p, b.link_fn[i_b, i_l])
            if ti.static(b.matrices):
                func_add(s, b.link_Sww, i_b, p, b.link_Sww[i_b, i_l])
                func_add(s, b.link_Swv, i_b, p, b.link_Swv[i_b, i_l])
                func_add(s, b.link_Svv, i_b, p, b.link_Svv[i_b, i_l])


@ti.func
def func_bank_dof(s: ti.template(), b: ti.template(), i_b):
    """Per dof i: force_i += cdof_i . wrench(subtree of link(i)) (J^T f), and the spatial vector
    S(link(i)) cdof_i that func_bank_project dots with the ancestors' cdofs. Without gradients that
    projection is done here, from the vector in registers, walking up the dof tree (the same terms:
    each M[i, j] gets one term per bank; 28 % less time for the two stages on ANYmal), and
    func_bank_project does nothing."""
    for i in range(s.n_dofs):
        i_l = s.dof_link[i]
        touch = b.link_touch[i_b, i_l] == 1
        wi = s.cdof_w[i_b, i]
        vi = s.cdof_v[i_b, i]
        Swv = b.link_Swv[i_b, i_l]
        if ti.static(s.requires_grad):
            zero = ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)
            b.dof_Sw[i_b, i] = ti.select(touch, func_mv(b.link_Sww[i_b, i_l], wi) + func_mv(Swv, vi), zero)
            b.dof_Sv[i_b, i] = ti.select(touch, func_mtv(Swv, wi) + func_mv(b.link_Svv[i_b, i_l], vi), zero)
        if touch:
            func_add(s, s.force, i_b, i, wi.dot(b.link_fn[i_b, i_l]) + vi.dot(b.link_ff[i_b, i_l]))
            if ti.static(not s.requires_grad):
                Sw = func_mv(b.link_Sww[i_b, i_l], wi) + func_mv(Swv, vi)
                Sv = func_mtv(Swv, wi) + func_mv(b.link_Svv[i_b, i_l], vi)
                j = i
                while j >= 0:
                    func_add2(s, s.mass_mat, i_b, i, j, s.cdof_w[i_b, j].dot(Sw) + s.cdof_v[i_b, j].dot(Sv))
                    j = s.dof_parent[j]


@ti.func
def func_bank_dof_vector(s: ti.template(), b: ti.template(), i_b, i):
    """The gradient path's spatial vector S(link(i)) cdof_i of dof i, zero where no contact lies below the
    dof's link: func_bank_dof's expressions, which that function keeps inline (calling this from there
    changed the order in which its adjoint adds into the dofs' motion adjoints: contact gradients moved by
    up to 1e-11 relative)."""
    i_l = s.dof_link[i]
    touch = b.link_touch[i_b, i_l] == 1
    wi = s.cdof_w[i_b, i]
    vi = s.cdof_v[i_b, i]
    Swv = b.link_Swv[i_b, i_l]
    zero = ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)
    b.dof_Sw[i_b, i] = ti.select(touch, func_mv(b.link_Sww[i_b, i_l], wi) + func_mv(Swv, vi), zero)
    b.dof_Sv[i_b, i] = ti.select(touch, func_mtv(Swv, wi) + func_mv(b.link_Svv[i_b, i_l], vi), zero)


@ti.func
def func_bank_dof_vectors(s: ti.template(), b: ti.template(), i_b):
    """func_bank_dof's spatial vectors alone (gradient path), without its forces: a bank rebuilt for an
    adjoint (rounds.toggle_rebuild) must not add its forces again."""
    for i in range(s.n_dofs):
        func_bank_dof_vector(s, b, i_b, i)


@ti.func
def func_bank_project(s: ti.template(), b: ti.template(), i_b):
    """M[i, j] += cdof_j^T S(link(i)) cdof_i for j an ancestor-or-self of i (the composite-inertia
    pattern of func_mass_matrix), over the static list of such (i, j), skipping links with no contact
    below them. Without gradients func_bank_dof has done it."""
    if ti.static(s.requires_grad):
        for t in range(s.n_anc):
            i = s.anc_i[t]
            j = s.anc_j[t]
            if b.link_touch[i_b, s.dof_link[i]] == 1:
                func_add2(s, s.mass_mat, i_b, i, j, s.cdof_w[i_b, j].dot(b.dof_Sw[i_b, i]) + s.cdof_v[i_b, j].dot(b.dof_Sv[i_b, i]))


@ti.func
def func_bank_cross(s: ti.template(), b: ti.template(), i_b):
    """mass_cross[row, col] -= fac * cdof_i^T S(link pair) cdof_j over the static list of (i, j) with i
    a dof moving one link of a touching pair and j one moving the other: the coupling
    -(J_a^T W J_b + J_b^T W J_a) of J^T W J with J = J_a - J_b. Without gradients only the pairs a slot
    touched (the others' S is zero and adds exact zeros: the 100-box tower lists 4,950 pairs, ~100
    touch)."""
    c = s.contact
    for t in range(c.n_cross):
        if ti.static(s.requires_grad):
            func_cross_term(s, b, i_b, t)
        else:
            if b.lp_touch[i_b, c.cross_lp[t]] == 1:
                func_cross_term(s, b, i_b, t)


@ti.func
def func_cross_term(s: ti.template(), b: ti.template(), i_b, t):
    """Entry t of func_bank_cross's list."""
    c = s.contact
    i = c.cross_i[t]
    j = c.cross_j[t]
    lp = c.cross_lp[t]
    Swv = b.lp_Swv[i_b, lp]
    wi = s.cdof_w[i_b, i]
    vi = s.cdof_v[i_b, i]
    wj = s.cdof_w[i_b, j]
    vj = s.cdof_v[i_b, j]
    m = (wj.dot(func_mv(b.lp_Sww[i_b, lp], wi) + func_mv(Swv, vi))
         + vj.dot(func_mtv(b.lp_Svw[i_b, lp], wi) + func_mv(b.lp_Svv[i_b, lp], vi)))
    func_add2(s, c.mass_cross, i_b, ti.max(i, j), ti.min(i, j), -c.cross_fac[t] * m)
