"""Stage 7, contact: smooth penalty forces with Coulomb friction, treated implicitly.

The model, per contact slot (see collision.py for where slots come from), with depth d > 0 meaning
penetration, n the normal from the SDF side towards the point side and u the velocity of the point
side relative to the other at the contact point:

    normal     f_n = k * delta * softplus(d / delta) - c * sigmoid(d / delta) * (u . n),  clipped at 0
    friction   f_t = -mu * f_n * u_t / sqrt(|u_t|^2 + eps^2)        mu = max(mu_a, mu_b)

Friction scales with the net normal force f_n of the step's start. Known limitation: on the step a
body lands (or is placed overlapping) f_n exceeds the impulse the implicit step delivers by orders of
magnitude (its damping is far above critical, its spring force is that of a penetration the step
undoes), so a body landing while sliding loses far more tangential speed than mu times its normal
impulse; bodies in steady contact (resting, sliding, rolling, standing) are not affected. Substeps
shrink the effect (~h^2).

Every term is differentiable in the state and in mu, k and c; the only kinks are the clip at f_n = 0
(fast separation) and the slot's on/off at the contact margin (where the force is below 1e-8 k delta).
Gradients are therefore the exact derivatives of this smoothed, time-discretised model (what
tests/test_contact.py checks against finite differences); they approach those of hard contact and
exact Coulomb friction only as delta, eps and dt go to 0.

Stiff contacts at dt = 0.01 are stable because they are integrated like the joint-limit springs:
linearly implicit (backward Euler on the linearised force). For each contact the 3x3 matrix
W = h D + h^2 K with K = k sigmoid n n^T (normal stiffness), D = c sigmoid n n^T + eta (I - n n^T)
(normal damping, and friction as a viscosity eta = mu f_n / sqrt(|u_t|^2 + eps^2): the secant of the
friction law, so an implicit step can stop a sliding contact but never reverse it) enters the
generalised mass matrix as J^T W J, and the force gets the explicit correction -h K u. The part of
J^T W J that lives on one kinematic tree (a contact against a static geom, and the two diagonal
blocks J_a^T W J_a, J_b^T W J_b of a contact between moving links a and b) is accumulated like
composite inertia (a 6x6 block per link, summed up the tree), so it fits the tree sparsity of M. The
coupling -(J_a^T W J_b + J_b^T W J_a) between two moving links does not: scenes with such contact
pairs (objects stacked or touching each other, self-collision) accumulate it per link pair into
`mass_cross` and factor M densely (func_factor_solve_dense); scenes whose contacts all involve a
static geom (robots on the ground) keep the tree factorisation. (Dropping the coupling is not an
option: stacked bodies then close the gap between them twice per step, or half of it when the blocks
are doubled, and with the force's clip at 0 a stack of boxes ends in a limit cycle.)

Stages (each one loop over elements, see solver.py): geom poses, broad phase, clear the per-link
(and per-link-pair) accumulators, slots (geometry + force, accumulated onto the two links), sum up the
tree, project onto the dofs (force += J^T f, M += J^T W J), and with moving pairs the cross terms.
"""

import numpy as np
import taichi as ti

from .collision import (SLOT_CYL_RIM, SLOT_SEGSEG, ContactBuildError, build_geoms, build_slots, candidate_pairs,
                        func_broad_phase, func_geom_pose, func_slot_geometry, geom_rotations, link_is_dynamic)

# slots whose depth is below -MARGIN_WIDTHS * delta carry no force (softplus(-20) ~ 2e-9)
MARGIN_WIDTHS = 20.0


@ti.func
def func_skew(p):
    return ti.Matrix([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])


@ti.func
def func_acc(s: ti.template(), x: ti.template(), i_b, i, v):
    """x[i_b, i] += v. Without gradients as a plain read-modify-write: one thread owns an env's
    elements, and `+=` on a field inside the parallel env loop compiles to an f64 atomic (a
    compare-and-swap loop, the main cost of these stages). With gradients `+=`, which Taichi's reverse
    mode needs."""
    if ti.static(s.requires_grad):
        x[i_b, i] += v
    else:
        x[i_b, i] = x[i_b, i] + v


@ti.func
def func_acc2(s: ti.template(), x: ti.template(), i_b, i, j, v):
    if ti.static(s.requires_grad):
        x[i_b, i, j] += v
    else:
        x[i_b, i, j] = x[i_b, i, j] + v


@ti.func
def func_contact_clear(s: ti.template(), i_b, e, src, h):
    c = s.contact
    for i_l in range(s.n_links):
        c.link_fn[i_b, i_l] = ti.Vector([0.0, 0.0, 0.0])
        c.link_ff[i_b, i_l] = ti.Vector([0.0, 0.0, 0.0])
        c.link_Sww[i_b, i_l] = ti.Matrix.zero(s.dtype, 3, 3)
        c.link_Swv[i_b, i_l] = ti.Matrix.zero(s.dtype, 3, 3)
        c.link_Svv[i_b, i_l] = ti.Matrix.zero(s.dtype, 3, 3)
        c.link_touch[i_b, i_l] = 0


@ti.func
def func_contact_force(s: ti.template(), i_b, i_s, h, pos, n, depth):
    """Force and implicit block of slot i_s (within the contact margin), added onto its two links."""
    c = s.contact
    ga = c.slot_ga[i_s]
    gb = c.slot_gb[i_s]
    la = c.geom_link[ga]
    lb = c.geom_link[gb]
    u = (s.cvel_v[i_b, la] + s.cvel_w[i_b, la].cross(pos)) - (s.cvel_v[i_b, lb] + s.cvel_w[i_b, lb].cross(pos))
    un = u.dot(n)
    z = depth / c.delta
    # clamped so that exp stays finite in the adjoint (the force is ~0 below -MARGIN_WIDTHS anyway)
    zc = ti.min(ti.max(z, -60.0), 60.0)
    sp = ti.max(z, 0.0) + ti.log(1.0 + ti.exp(-ti.abs(zc)))
    sg = 1.0 / (1.0 + ti.exp(-zc))
    fn_raw = c.k * c.delta * sp - c.d * sg * un
    on = ti.cast(fn_raw > 0, s.dtype)
    fn = fn_raw * on
    ut = u - un * n
    mu = ti.max(c.geom_friction[i_b, ga], c.geom_friction[i_b, gb])
    eta = mu * fn / ti.sqrt(ut.dot(ut) + c.eps * c.eps)
    F = (fn - on * h * c.k * sg * un) * n - eta * ut
    wn = on * (h * c.d * sg + h * h * c.k * sg)
    W = (wn - h * eta) * n.outer_product(n) + h * eta * ti.Matrix.identity(s.dtype, 3)
    P = func_skew(pos)
    PW = P @ W
    Sww = -(PW @ P)
    tq = pos.cross(F)
    c.c_fn[i_b, i_s] = fn
    if fn > 0:
        c.c_pos[i_b, i_s] = pos
        c.c_normal[i_b, i_s] = n
        c.c_force[i_b, i_s] = F
        c.c_depth[i_b, i_s] = depth
        if c.link_dyn[la] == 1:
            c.link_touch[i_b, la] = 1
            func_acc(s, c.link_ff, i_b, la, F)
            func_acc(s, c.link_fn, i_b, la, tq)
            func_acc(s, c.link_Sww, i_b, la, Sww)
            func_acc(s, c.link_Swv, i_b, la, PW)
            func_acc(s, c.link_Svv, i_b, la, W)
        if c.link_dyn[lb] == 1:
            c.link_touch[i_b, lb] = 1
            func_acc(s, c.link_ff, i_b, lb, -F)
            func_acc(s, c.link_fn, i_b, lb, -tq)
            func_acc(s, c.link_Sww, i_b, lb, Sww)
            func_acc(s, c.link_Swv, i_b, lb, PW)
            func_acc(s, c.link_Svv, i_b, lb, W)
        if ti.static(c.dense):
            lp = c.slot_lp[i_s]
            if lp >= 0:
                func_acc(s, c.lp_Sww, i_b, lp, Sww)
                func_acc(s, c.lp_Swv, i_b, lp, PW)
                func_acc(s, c.lp_Svv, i_b, lp, W)


@ti.func
def func_contact_slots(s: ti.template(), i_b, e, src, h):
    """Geometry and force of every slot of an active pair; the force (at the contact point, on the
    point side, its opposite on the other side) and the implicit block J^T W J are added onto the two
    links. Single-assignment form (see kinematics.py): the contact's on/off is a 0/1 mask."""
    c = s.contact
    for i_s in range(c.n_slots):
        if c.pair_active[i_b, c.slot_pair[i_s]] == 1:
            pos, n, depth = func_slot_geometry(s, i_b, i_s)
            if depth > -c.margin:
                func_contact_force(s, i_b, i_s, h, pos, n, depth)
            else:
                c.c_fn[i_b, i_s] = 0.0
        # slots of inactive pairs keep stale outputs: readers mask them with pair_active


@ti.func
def func_contact_tree(s: ti.template(), i_b, e, src, h):
    """Per-link sums over the link's subtree (children after parents in link order)."""
    c = s.contact
    for k in range(s.n_links):
        i_l = s.n_links - 1 - k
        p = s.link_parent[i_l]
        if (p >= 0) & (c.link_touch[i_b, i_l] == 1):
            c.link_touch[i_b, p] = 1
            func_acc(s, c.link_ff, i_b, p, c.link_ff[i_b, i_l])
            func_acc(s, c.link_fn, i_b, p, c.link_fn[i_b, i_l])
            func_acc(s, c.link_Sww, i_b, p, c.link_Sww[i_b, i_l])
            func_acc(s, c.link_Swv, i_b, p, c.link_Swv[i_b, i_l])
            func_acc(s, c.link_Svv, i_b, p, c.link_Svv[i_b, i_l])


@ti.func
def func_contact_dof(s: ti.template(), i_b, e, src, h):
    """Per dof i: force_i += cdof_i . wrench(subtree of link(i)) (J^T f), and the spatial vector
    S(link(i)) cdof_i that the next stage dots with the ancestors' cdofs."""
    c = s.contact
    for i in range(s.n_dofs):
        i_l = s.dof_link[i]
        touch = c.link_touch[i_b, i_l] == 1
        wi = s.cdof_w[i_b, i]
        vi = s.cdof_v[i_b, i]
        Swv = c.link_Swv[i_b, i_l]
        zero = ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)
        c.dof_Sw[i_b, i] = ti.select(touch, c.link_Sww[i_b, i_l] @ wi + Swv @ vi, zero)
        c.dof_Sv[i_b, i] = ti.select(touch, Swv.transpose() @ wi + c.link_Svv[i_b, i_l] @ vi, zero)
        if touch:
            func_acc(s, s.force, i_b, i, wi.dot(c.link_fn[i_b, i_l]) + vi.dot(c.link_ff[i_b, i_l]))


@ti.func
def func_contact_project(s: ti.template(), i_b, e, src, h):
    """M[i, j] += cdof_j^T S(link(i)) cdof_i for j an ancestor-or-self of i (the composite-inertia
    pattern of func_mass_matrix), over the static list of such (i, j), skipping links with no contact
    below them."""
    c = s.contact
    for t in range(c.n_anc):
        i = c.anc_i[t]
        j = c.anc_j[t]
        if c.link_touch[i_b, s.dof_link[i]] == 1:
            func_acc2(s, s.mass_mat, i_b, i, j, s.cdof_w[i_b, j].dot(c.dof_Sw[i_b, i]) + s.cdof_v[i_b, j].dot(c.dof_Sv[i_b, i]))


@ti.func
def func_contact_clear_pairs(s: ti.template(), i_b, e, src, h):
    c = s.contact
    for lp in range(c.n_lp):
        c.lp_Sww[i_b, lp] = ti.Matrix.zero(s.dtype, 3, 3)
        c.lp_Swv[i_b, lp] = ti.Matrix.zero(s.dtype, 3, 3)
        c.lp_Svv[i_b, lp] = ti.Matrix.zero(s.dtype, 3, 3)


@ti.func
def func_contact_clear_cross(s: ti.template(), i_b, e, src, h):
    c = s.contact
    for ij in range(s.n_dofs * s.n_dofs):
        c.mass_cross[i_b, ij // s.n_dofs, ij % s.n_dofs] = 0.0


@ti.func
def func_contact_cross(s: ti.template(), i_b, e, src, h):
    """mass_cross[row, col] -= fac * cdof_i^T S(link pair) cdof_j over the static list of (i, j) with i
    a dof moving one link of a touching pair and j one moving the other: the coupling
    -(J_a^T W J_b + J_b^T W J_a) of J^T W J with J = J_a - J_b."""
    c = s.contact
    for t in range(c.n_cross):
        i = c.cross_i[t]
        j = c.cross_j[t]
        lp = c.cross_lp[t]
        Swv = c.lp_Swv[i_b, lp]
        wi = s.cdof_w[i_b, i]
        vi = s.cdof_v[i_b, i]
        wj = s.cdof_w[i_b, j]
        vj = s.cdof_v[i_b, j]
        m = wj.dot(c.lp_Sww[i_b, lp] @ wi + Swv @ vi) + vj.dot(Swv.transpose() @ wi + c.lp_Svv[i_b, lp] @ vi)
        func_acc2(s, c.mass_cross, i_b, ti.max(i, j), ti.min(i, j), -c.cross_fac[t] * m)


CONTACT_STAGES = (func_geom_pose, func_broad_phase, func_contact_clear, func_contact_slots, func_contact_tree,
                  func_contact_dof, func_contact_project)
CROSS_STAGES = (func_contact_clear_pairs, func_contact_clear_cross, func_geom_pose, func_broad_phase,
                func_contact_clear, func_contact_slots, func_contact_tree, func_contact_dof, func_contact_project,
                func_contact_cross)


# ------------------------------------------------------------------------------------------------
# Dense factorisation for scenes with contacts between moving bodies (not differentiated by Taichi:
# forward and hand-written adjoint, as the tree factorisation in inertia.py)
# ------------------------------------------------------------------------------------------------
@ti.func
def func_dense_solve(s: ti.template(), i_b, x: ti.template(), e):
    """x[e, i_b, :] <- A^-1 x[e, i_b, :] with A = L D L^T in mass_fac (unit lower L, D on the diagonal)."""
    n = s.n_dofs
    for i in range(n):
        acc = x[e, i_b, i]
        for k in range(i):
            acc -= s.mass_fac[i_b, i, k] * x[e, i_b, k]
        x[e, i_b, i] = acc
    for i in range(n):
        x[e, i_b, i] /= s.mass_fac[i_b, i, i]
    for ii in range(n):
        i = n - 1 - ii
        acc = x[e, i_b, i]
        for k in range(i + 1, n):
            acc -= s.mass_fac[i_b, k, i] * x[e, i_b, k]
        x[e, i_b, i] = acc


@ti.func
def func_factor_solve_dense(s: ti.template(), i_b, e):
    """qacc[e] = A^-1 force with A = M (tree entries) + mass_cross, by a dense L D L^T."""
    c = s.contact
    n = s.n_dofs
    for i in range(n):
        for j in range(i + 1):
            s.mass_fac[i_b, i, j] = s.mass_mat[i_b, i, j] * s.dof_anc[i, j] + c.mass_cross[i_b, i, j]
    for j in range(n):
        dj = s.mass_fac[i_b, j, j]
        for k in range(j):
            dj -= s.mass_fac[i_b, j, k] * s.mass_fac[i_b, j, k] * s.mass_fac[i_b, k, k]
        s.mass_fac[i_b, j, j] = dj
        for i in range(j + 1, n):
            v = s.mass_fac[i_b, i, j]
            for k in range(j):
                v -= s.mass_fac[i_b, i, k] * s.mass_fac[i_b, j, k] * s.mass_fac[i_b, k, k]
            s.mass_fac[i_b, i, j] = v / dj
    for i in range(n):
        s.qacc[e, i_b, i] = s.force[i_b, i]
    func_dense_solve(s, i_b, s.qacc, e)


@ti.func
def func_solve_grad_dense(s: ti.template(), i_b, e):
    """Adjoint of qacc[e] = A^-1 force: force_bar += A^-1 qacc_bar, A_bar = -force_bar qacc^T (lower
    triangle, symmetrised), split into the tree entries of mass_mat and mass_cross."""
    c = s.contact
    for i in range(s.n_dofs):
        s.solve_tmp[0, i_b, i] = s.qacc.grad[e, i_b, i]
    func_dense_solve(s, i_b, s.solve_tmp, 0)
    for i in range(s.n_dofs):
        s.force.grad[i_b, i] += s.solve_tmp[0, i_b, i]
    for ij in range(s.n_dofs * s.n_dofs):
        i = ij // s.n_dofs
        j = ij % s.n_dofs
        if j <= i:
            g = s.solve_tmp[0, i_b, i] * s.qacc[e, i_b, j]
            if i != j:
                g += s.solve_tmp[0, i_b, j] * s.qacc[e, i_b, i]
            c.mass_cross.grad[i_b, i, j] -= g
            if s.dof_anc[i, j] == 1:
                s.mass_mat.grad[i_b, i, j] -= g


@ti.data_oriented
class ContactSolver:
    """Fields and stages of the contact model of one RigidSolver (see the module docstring)."""

    @staticmethod
    def create(solver, models, options):
        """The contact solver of a scene, or None when no two geoms can touch (nothing is compiled or
        launched for contacts then). Raises ContactBuildError for geometry it cannot simulate."""
        geoms = build_geoms(models, int(options.max_mesh_contact_points))
        if geoms.n == 0:
            return None
        pairs = candidate_pairs(geoms, solver, bool(options.enable_self_collision),
                                bool(getattr(options, "ignore_unsupported_pairs", False)))
        if not pairs:
            return None
        return ContactSolver(solver, geoms, pairs, options)

    def __init__(self, solver, geoms, pairs, options):
        self.geoms = geoms
        self.pairs = pairs
        slots = build_slots(geoms, pairs)
        self.n_geoms, self.n_pairs, self.n_slots = geoms.n, len(pairs), len(slots)
        self.k = float(options.contact_stiffness)
        self.d = float(options.contact_damping)
        self.delta = float(options.contact_smoothing)
        self.eps = float(options.friction_smoothing)
        self.margin = MARGIN_WIDTHS * self.delta
        self.dtype = solver.dtype
        # static: code is generated only for the slot kinds and SDF types this scene uses
        self.has_rim = any(x[1] == SLOT_CYL_RIM for x in slots)
        self.has_segseg = any(x[1] == SLOT_SEGSEG for x in slots)
        self.sdf_types = tuple(sorted({int(geoms.type[x[3]]) for x in slots}))
        self.entity_geom_start = list(geoms.entity_start)
        self.entity_geom_count = list(geoms.entity_count)
        # static slot tables, kept in numpy for the readers
        self.np_slot_ga = np.array([x[2] for x in slots], dtype=np.int32)
        self.np_slot_gb = np.array([x[3] for x in slots], dtype=np.int32)
        self.np_slot_pair = np.array([x[0] for x in slots], dtype=np.int32)
        self.np_slot_link_a = geoms.link[self.np_slot_ga]
        self.np_slot_link_b = geoms.link[self.np_slot_gb]
        # contacts between two moving links couple their dofs outside the tree sparsity of M: such
        # link pairs get a 6x6 accumulator, and the dof pairs they couple a static list (see above)
        dyn_np = link_is_dynamic(solver)
        lp_index, slot_lp = {}, []
        for la, lb in zip(self.np_slot_link_a, self.np_slot_link_b):
            if dyn_np[la] and dyn_np[lb]:
                key = (min(la, lb), max(la, lb))
                slot_lp.append(lp_index.setdefault(key, len(lp_index)))
            else:
                slot_lp.append(-1)
        self.dense = len(lp_index) > 0
        self.n_lp = len(lp_index)
        cross = []
        for (la, lb), lp in lp_index.items():
            for i in _link_dofs(solver, la):
                for j in _link_dofs(solver, lb):
                    # (i, j) and (j, i) land on the same lower-triangle entry; on the diagonal (a common
                    # ancestor of a self-collision pair) both terms of J_a^T W J_b + J_b^T W J_a do
                    cross.append((i, j, lp, 2.0 if i == j else 1.0))
        self.n_cross = len(cross)

        B, G, Pn, S, L = solver.n_envs, geoms.n, len(pairs), len(slots), max(solver.n_links, 1)
        f, g = solver.dtype, solver.requires_grad
        I = lambda shape: ti.field(ti.i32, shape=shape)  # noqa: E731, E741
        V3 = lambda shape, grad=g: ti.Vector.field(3, f, shape=shape, needs_grad=grad)  # noqa: E731
        M3 = lambda shape, grad=g: ti.Matrix.field(3, 3, f, shape=shape, needs_grad=grad)  # noqa: E731
        # geoms
        self.geom_type, self.geom_link = I(G), I(G)
        self.geom_pos, self.geom_center, self.geom_size = V3(G, False), V3(G, False), V3(G, False)
        self.geom_R = M3(G, False)
        self.geom_rbound = ti.field(f, shape=G)
        self.geom_beta = ti.field(f, shape=G)
        self.geom_kdop = ti.field(f, shape=(G, geoms.kdop.shape[1]))
        self.geom_friction = ti.field(f, shape=(B, G), needs_grad=g)
        self.link_dyn = I(L)
        self.link_touch = I((B, L))  # a contact acts on the link or below it (this evaluation)
        self.dof_Sw, self.dof_Sv = V3((B, max(solver.n_dofs, 1))), V3((B, max(solver.n_dofs, 1)))
        anc = [(i, j) for i in range(solver.n_dofs) for j in range(i + 1) if solver.np_dof_anc[i, j]]
        self.n_anc = max(len(anc), 1)
        self.anc_i, self.anc_j = I(self.n_anc), I(self.n_anc)
        # pairs and slots
        self.pair_ga, self.pair_gb = I(Pn), I(Pn)
        self.pair_active = I((B, Pn))
        self.slot_pair, self.slot_kind, self.slot_ga, self.slot_gb = I(S), I(S), I(S), I(S)
        self.slot_p = V3(S, False)
        self.slot_r, self.slot_aux = ti.field(f, shape=S), ti.field(f, shape=S)
        # per evaluation
        self.geom_xpos, self.geom_xR = V3((B, G)), M3((B, G))
        self.link_fn, self.link_ff = V3((B, L)), V3((B, L))
        self.link_Sww, self.link_Swv, self.link_Svv = M3((B, L)), M3((B, L)), M3((B, L))
        if self.dense:
            D = max(solver.n_dofs, 1)
            self.slot_lp = I(S)
            self.lp_Sww, self.lp_Swv, self.lp_Svv = M3((B, self.n_lp)), M3((B, self.n_lp)), M3((B, self.n_lp))
            self.cross_i, self.cross_j, self.cross_lp = I(self.n_cross), I(self.n_cross), I(self.n_cross)
            self.cross_fac = ti.field(f, shape=self.n_cross)
            self.mass_cross = ti.field(f, shape=(B, D, D), needs_grad=g)
        # outputs of the last evaluation (read by the entity API; no gradient)
        self.c_pos, self.c_normal, self.c_force = V3((B, S), False), V3((B, S), False), V3((B, S), False)
        self.c_depth, self.c_fn = ti.field(f, shape=(B, S)), ti.field(f, shape=(B, S))

        npf = solver.np_dtype
        self.geom_type.from_numpy(geoms.type)
        self.geom_link.from_numpy(geoms.link)
        self.geom_pos.from_numpy(geoms.pos.astype(npf))
        self.geom_center.from_numpy(geoms.center.astype(npf))
        self.geom_size.from_numpy(geoms.size.astype(npf))
        self.geom_R.from_numpy(geom_rotations(geoms.quat / np.linalg.norm(geoms.quat, axis=1, keepdims=True)).astype(npf))
        self.geom_rbound.from_numpy(np.minimum(geoms.rbound, np.finfo(npf).max).astype(npf))
        self.geom_beta.from_numpy(geoms.beta.astype(npf))
        self.geom_kdop.from_numpy(geoms.kdop.astype(npf))
        self.geom_friction.from_numpy(np.ascontiguousarray(np.broadcast_to(geoms.friction, (B, G))).astype(npf))
        dyn = np.zeros(L, dtype=np.int32)
        dyn[: solver.n_links] = dyn_np
        self.link_dyn.from_numpy(dyn)
        anc_arr = np.array(anc if anc else [(0, 0)], dtype=np.int32).reshape(-1, 2)
        self.anc_i.from_numpy(np.ascontiguousarray(anc_arr[:, 0]))
        self.anc_j.from_numpy(np.ascontiguousarray(anc_arr[:, 1]))
        self.pair_ga.from_numpy(np.array([p[0] for p in pairs], dtype=np.int32))
        self.pair_gb.from_numpy(np.array([p[1] for p in pairs], dtype=np.int32))
        self.slot_pair.from_numpy(self.np_slot_pair)
        self.slot_kind.from_numpy(np.array([x[1] for x in slots], dtype=np.int32))
        self.slot_ga.from_numpy(self.np_slot_ga)
        self.slot_gb.from_numpy(self.np_slot_gb)
        self.slot_p.from_numpy(np.array([x[4] for x in slots], dtype=npf).reshape(S, 3))
        self.slot_r.from_numpy(np.array([x[5] for x in slots], dtype=npf))
        self.slot_aux.from_numpy(np.array([x[6] for x in slots], dtype=npf))

        self.stages = CONTACT_STAGES
        self.grad_fields = [self.geom_friction, self.geom_xpos, self.geom_xR, self.link_fn, self.link_ff,
                            self.link_Sww, self.link_Swv, self.link_Svv, self.dof_Sw, self.dof_Sv] if g else []
        if self.dense:
            self.slot_lp.from_numpy(np.array(slot_lp, dtype=np.int32))
            self.cross_i.from_numpy(np.array([x[0] for x in cross], dtype=np.int32))
            self.cross_j.from_numpy(np.array([x[1] for x in cross], dtype=np.int32))
            self.cross_lp.from_numpy(np.array([x[2] for x in cross], dtype=np.int32))
            self.cross_fac.from_numpy(np.array([x[3] for x in cross], dtype=npf))
            self.stages = CROSS_STAGES
            if g:
                self.grad_fields += [self.lp_Sww, self.lp_Swv, self.lp_Svv, self.mass_cross]

    def longest_loop(self) -> int:
        """Iterations of the longest loop in the contact stages (for the autodiff stack, adstack.py)."""
        return max(self.n_slots, self.n_pairs, self.n_geoms, self.n_anc, self.n_cross)

    # ------------------------------------------------------------------ readers
    def read(self):
        """numpy views of the last evaluation: dict of position, normal, force (on the point side),
        depth, fn (normal force magnitude, 0 when not touching), each (B, n_slots[, 3])."""
        active = self.pair_active.to_numpy()[:, self.np_slot_pair] == 1
        return {"position": self.c_pos.to_numpy(), "normal": self.c_normal.to_numpy(),
                "force": self.c_force.to_numpy(), "depth": self.c_depth.to_numpy(),
                "fn": np.where(active, self.c_fn.to_numpy(), 0.0)}


def _link_dofs(solver, l):
    """The dofs that move link l: its own and its ancestors'."""
    out = []
    while l >= 0:
        d0 = solver.np_link_dof_start[l]
        out.extend(range(d0, d0 + solver.np_link_ndof[l]))
        l = solver.np_link_parent[l]
    return out


__all__ = ["ContactSolver", "ContactBuildError", "CONTACT_STAGES", "func_factor_solve_dense", "func_solve_grad_dense"]
