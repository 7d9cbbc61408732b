"""Stage 7, contact: smooth penalty forces with Coulomb friction, treated implicitly.

The model, per contact slot (see collision.py for where slots come from), with depth d > 0 meaning
penetration, n the normal from the SDF side towards the point side, u the velocity of the point side
relative to the other at the contact point, h the step and d' = d - h (u' . n) the depth at the end
of the step (u' the velocity after it):

    normal     f_n = k delta softplus(d' / delta) + (c / h) delta (softplus(d' / delta) - softplus(d / delta))
    friction   f_t = -mu f_n u_t' / sqrt(|v|^2 + eps^2)        mu = max(mu_a, mu_b)

The normal force is a spring on the end-of-step depth plus a damper on the overlap gained over the
step, (c / h)(d'+ - d+), which for a contact that stays in overlap is -c (u' . n) (the familiar
spring-damper) and for one that starts apart acts only on the part of the step spent in overlap.
Because the force is a function of the end-of-step depth, a pair whose gap closes within the step is in
contact in that step (a speculative contact): a body arriving at 20 m/s stops at the surface instead
of being caught one step deep (the broad phase widens its margin by the distance the pair can close in
h, and a slot counts while its current or its predicted depth is within the margin). The predicted
depth moves the two sides as the integrator does, each link turned by exactly h w about its origin
(func_rot_excess: the tangent h (w x r) plus Rodrigues' remainder), not along the tangent: with the
tangent alone, a box spinning at 1e3 rad/s 6 cm above the ground "reached" 1.7 m below it and the
ground threw it at 28.8 m/s; two boxes 1 m apart pushed each other (issue #21). Friction follows
Coulomb's law with the normal force the step actually applies, and is viscous below the slip speed eps.

Limits (issue #21). A penalty contact stops a body within a step only when (k + c / h) times the
depth it allows outweighs the body's momentum per step and its load: a box at 1e6 m/s (1e4 m per step)
or a 400 t box on four corners of 1e6 N/m goes through. The report pass records, per env, the first
contact that ends a step deeper than DEEP_FRACTION of the thinner geom's half thickness, and the scene
warns once (ContactPenetrationWarning, ContactSolver.watch: a read after each of the first 16 steps,
then every 16th), naming the geoms, the step and the remedy (smaller dt or more substeps for a fast
body, a larger contact_stiffness for a heavy one; with 1e10 N/m the 400 t box rests within 0.1 mm).
Known gap: a point of one box beside an edge of another box, level with its face (a box sliding over
the edge of the one below it), is tested against the side face (the nearest feature), and the step's
linear prediction along that face's normal closes a gap that never closes: a horizontal kick that
breaks Coulomb's bound (tests/test_faults_contact.py, xfail).

Time stepping. The forces are linearly implicit (backward Euler on the linearised force, as the
joint-limit springs): f_n is linearised about the predicted depth d - h (u . n), which makes it
linear in u' with slope B = (c + h k) sigmoid; each contact contributes J^T W J to the generalised mass
matrix (W the 3x3 block on the contact's relative velocity) and J^T f to the force. One evaluation's
solve runs in steps (func_contact_solve), because Coulomb's law ties the friction to a normal force that
only the solve determines (a stiff implicit contact is a velocity constraint: its force is whatever
stops the approach, far from the explicit penalty force of the state), and because a speculative
contact's linear force pulls where another contact stops the body first:

 1. every candidate normal contact: A1 = M + sum J^T (h B n n^T) J, qacc1 = A1^-1 force; each
    contact's normal force in it, f1 = f_n(u1), from the implicit law at the resulting velocity.
 2. without the contacts whose linear force at u1 pulls (a speculative contact that another contact
    stopped first, or one that separates), and with the candidates (below) linearised again about u1:
    A2, qacc2 (the normal solve), and its normal forces f2. (Dropping a contact whose force is 0 at the
    solution leaves the solution unchanged, so the removal is continuous.)
 3. Coulomb's forces -mu f2 g2 (g2 the smoothed slip direction of u2) applied to A2 (a back-substitution
    with its factor) predict each contact's slip speed at the end of the step, v = (u2 + h J A2^-1 J^T
    f_c)_t . g2, smoothly clipped at 0 (a slip that would reverse sticks).
 4. the final system adds friction as a viscosity eta = mu f2 / sqrt(v^2 + eps^2) (the secant of the
    law at the predicted slip, so the implicit step can stop a contact but never reverse it: while a
    contact slides, eta |u_t'| = mu f2 to the accuracy of the prediction, exact for a body whose contact
    points slip alike; a sticking contact gets eta = mu f2 / eps, the static friction of a stiff
    damper), and drops the speculative contacts whose f2 pulled: A3 = A2 + sum J^T dW J, qacc = A3^-1
    (force + sum J^T dF).
Steps 1, 2 and 4 factorise, 3 reuses the second factor. Candidates: the linearisation at the
start-of-step velocity misses a gap that closes only because the motion changes within the step (two
boxes falling together, the lower one stopped: their relative velocity is ~0 at the start). A slot whose
gap the two bodies' speeds could close within the step is in the system from step 1 with the ~0 force
and slope of that linearisation; between steps 1 and 2 its law is linearised again at the velocity of
the first solve (a Newton step), and it acts if the law pushes there. Contacts acting at the start keep
their first linearisation (linearising them again too left a 30-link chain on the ground swinging). The passes between the solves (link velocities
of a dof vector, per-slot forces, accumulation onto the dofs) are Taichi-differentiated kernels; the
solves have hand-written adjoints (ContactSolver.solve_grad runs them in reverse). Friction uses the
normal forces of a frictionless solve: where friction carries load (legs, chains), the final normal
forces differ from f2 and so does the friction bound.

Every term is differentiable in the state and in mu, k and c; the kinks are the contact's on/off (at
the margin, where the force is below 1e-8 k delta, and where the force of the current and of the
predicted state both stop pushing: fast separation), and the removals of steps 2 and 4 (continuous,
see above). Gradients are therefore the exact derivatives of this smoothed, time-discretised model (what
tests/test_contact.py checks against finite differences); they approach those of hard contact and
exact Coulomb friction only as delta, eps and dt go to 0.

The part of J^T W J that lives on one kinematic tree (a contact against a static geom, and the two
diagonal blocks J_a^T W J_a, J_b^T W J_b of a contact between moving links a and b) is accumulated like
composite inertia (a 6x6 block per link, summed up the tree: AccBank), so it fits the tree sparsity of
M. The coupling -(J_a^T W J_b + J_b^T W J_a) between two moving links does not: scenes with such contact
pairs (objects stacked or touching each other, self-collision) accumulate it per link pair into
`mass_cross` and factor M densely (func_factor_solve_dense); scenes whose contacts all involve a static
geom (robots on the ground) keep the tree factorisation. (Dropping the coupling is not an option:
stacked bodies then close the gap between them twice per step, or half of it when the blocks are
doubled, and with the force's clip at 0 a stack of boxes ends in a limit cycle.)

Dynamics stages (each one loop over elements, see solver.py): geom poses, broad phase, clear the
per-link (and per-link-pair) accumulators, slots (geometry + normal force, accumulated onto the two
links, and the slot's data for the passes), sum up the tree, project onto the dofs (force += J^T f,
M += J^T W J), and with moving pairs the cross terms. The passes of the solve repeat the accumulation
for their own forces.
"""

import warnings

import numpy as np
import taichi as ti

from .. import taichi_compat
from .inertia import func_factor_solve, func_factor_to, func_static_factor, func_static_solve, func_static_store, func_static_vec
from .collision import (GEOM_BOX, GEOM_CAPSULE, GEOM_CYLINDER, GEOM_MESH, GEOM_SPHERE, N_KDOP, SLOT_BOXEDGE, SLOT_CYL_RIM, SLOT_SEGSEG, TINY, ContactBuildError, build_geoms, build_slots, candidate_pairs,
                        func_broad_phase, func_geom_pose, func_slot_geometry, geom_rotations, link_is_dynamic)
from .layout import place_env_major

# slots whose depth is below -MARGIN_WIDTHS * delta carry no force (softplus(-20) ~ 2e-9)
MARGIN_WIDTHS = 20.0
# a contact whose depth at the end of a step exceeds this fraction of the thinner geom's half
# thickness has gone (or is going) through it: the scene warns (ContactSolver.watch). Half: the
# thinner body's middle has reached the other's surface, past which its normal can flip. (A quarter
# warned on ANYmal's ordinary 1.6 m/s foot landing at dt = 0.01 s: 5.6 mm into a 15 mm shank.)
DEEP_FRACTION = 0.5


class ContactPenetrationWarning(UserWarning):
    """A contact ended a step deeper than DEEP_FRACTION of the thinner geom's half thickness: the
    penalty contact could not stop the body within the step (too fast for dt, or too heavy for
    RigidOptions.contact_stiffness), so it sinks into or tunnels through the other body."""


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


class FieldTree:
    """Fields placed in an SNode tree of their own. Taichi caps the SNodes of one tree (1024; every
    component of a vector or matrix field and of its adjoint is one), and a scene's contact fields with
    their adjoints would take the rigid solver's tree past it: each AccBank and the rest of the contact
    solver get their own tree. finalize() after the last field, before any is used.

    Fields with an env axis of length `B` (first, or second after a leading axis of 1: shapes (B, ...)
    and (1, B, ...)) are placed env-major by finalize() (layout.place_env_major, as the core's), fields
    of the same shape side by side."""

    def __init__(self, dtype, grad, B=None):
        self.fb = ti.FieldsBuilder()
        self.dtype, self.grad = dtype, grad
        self.B = B
        self.groups = {}  # (env axis, other extents) -> fields, placed env-major by finalize()

    def _place(self, x, shape):
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        B = self.B
        if B is not None and shape[0] == B:
            self.groups.setdefault((0, shape[1:]), []).append(x)
        elif B is not None and len(shape) >= 2 and shape[0] == 1 and shape[1] == B:
            self.groups.setdefault((1, (1,) + shape[2:]), []).append(x)
        else:
            self.fb.dense(ti.axes(*range(len(shape))), shape).place(x)
        return x

    def F(self, shape, grad=None):
        return self._place(ti.field(self.dtype, needs_grad=self.grad if grad is None else grad), shape)

    def I(self, shape):  # noqa: E741, E743
        return self._place(ti.field(ti.i32), shape)

    def V3(self, shape, grad=None):
        return self._place(ti.Vector.field(3, self.dtype, needs_grad=self.grad if grad is None else grad), shape)

    def M3(self, shape, grad=None):
        return self._place(ti.Matrix.field(3, 3, self.dtype, needs_grad=self.grad if grad is None else grad), shape)

    def finalize(self):
        place_env_major(self.fb, self.B, [(axis, rest, xs) for (axis, rest), xs in self.groups.items()])
        if self.grad:
            self.fb.lazy_grad()
        return self.fb.finalize()


@ti.data_oriented
class AccBank:
    """Per-link sums of one set of contact forces (wrench about the world origin) and, with
    `matrices`, of their implicit blocks J^T W J (6x6 per link: Sww, Swv, Svv), per link pair for
    contacts between two moving links (the coupling outside the tree sparsity), and the per-dof
    vectors S(link(i)) cdof_i the projection onto M dots with the ancestors' cdofs."""

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
            self.grad_fields += [self.lp_Sww, self.lp_Swv, self.lp_Svv]
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
    c = s.contact
    for lp in range(c.n_lp):
        b.lp_Sww[i_b, lp] = ti.Matrix.zero(s.dtype, 3, 3)
        b.lp_Swv[i_b, lp] = ti.Matrix.zero(s.dtype, 3, 3)
        b.lp_Svv[i_b, lp] = ti.Matrix.zero(s.dtype, 3, 3)


@ti.func
def func_bank_add(s: ti.template(), b: ti.template(), i_b, i_s, pos, F, W):
    """Force F at pos on the point side of slot i_s (-F on the other side) and, with matrices, the
    implicit block W (3x3, on the relative velocity at pos), added onto the slot's moving links."""
    c = s.contact
    la = c.geom_link[c.slot_ga[i_s]]
    lb = c.geom_link[c.slot_gb[i_s]]
    P = func_skew(pos)
    PW = P @ W
    Sww = -(PW @ P)
    tq = pos.cross(F)
    if c.link_dyn[la] == 1:
        b.link_touch[i_b, la] = 1
        func_acc(s, b.link_ff, i_b, la, F)
        func_acc(s, b.link_fn, i_b, la, tq)
        if ti.static(b.matrices):
            func_acc(s, b.link_Sww, i_b, la, Sww)
            func_acc(s, b.link_Swv, i_b, la, PW)
            func_acc(s, b.link_Svv, i_b, la, W)
    if c.link_dyn[lb] == 1:
        b.link_touch[i_b, lb] = 1
        func_acc(s, b.link_ff, i_b, lb, -F)
        func_acc(s, b.link_fn, i_b, lb, -tq)
        if ti.static(b.matrices):
            func_acc(s, b.link_Sww, i_b, lb, Sww)
            func_acc(s, b.link_Swv, i_b, lb, PW)
            func_acc(s, b.link_Svv, i_b, lb, W)
    if ti.static(b.pairs):
        lp = c.slot_lp[i_s]
        if lp >= 0:
            func_acc(s, b.lp_Sww, i_b, lp, Sww)
            func_acc(s, b.lp_Swv, i_b, lp, PW)
            func_acc(s, b.lp_Svv, i_b, lp, W)


@ti.func
def func_bank_tree(s: ti.template(), b: ti.template(), i_b):
    """Per-link sums over the link's subtree (children after parents in link order)."""
    for k in range(s.n_links):
        i_l = s.n_links - 1 - k
        p = s.link_parent[i_l]
        if (p >= 0) & (b.link_touch[i_b, i_l] == 1):
            b.link_touch[i_b, p] = 1
            func_acc(s, b.link_ff, i_b, p, b.link_ff[i_b, i_l])
            func_acc(s, b.link_fn, i_b, p, b.link_fn[i_b, i_l])
            if ti.static(b.matrices):
                func_acc(s, b.link_Sww, i_b, p, b.link_Sww[i_b, i_l])
                func_acc(s, b.link_Swv, i_b, p, b.link_Swv[i_b, i_l])
                func_acc(s, b.link_Svv, i_b, p, b.link_Svv[i_b, i_l])


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
            b.dof_Sw[i_b, i] = ti.select(touch, b.link_Sww[i_b, i_l] @ wi + Swv @ vi, zero)
            b.dof_Sv[i_b, i] = ti.select(touch, Swv.transpose() @ wi + b.link_Svv[i_b, i_l] @ vi, zero)
        if touch:
            func_acc(s, s.force, i_b, i, wi.dot(b.link_fn[i_b, i_l]) + vi.dot(b.link_ff[i_b, i_l]))
            if ti.static(not s.requires_grad):
                Sw = b.link_Sww[i_b, i_l] @ wi + Swv @ vi
                Sv = Swv.transpose() @ wi + b.link_Svv[i_b, i_l] @ vi
                j = i
                while j >= 0:
                    func_acc2(s, s.mass_mat, i_b, i, j, s.cdof_w[i_b, j].dot(Sw) + s.cdof_v[i_b, j].dot(Sv))
                    j = s.dof_parent[j]


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
                func_acc2(s, s.mass_mat, i_b, i, j, s.cdof_w[i_b, j].dot(b.dof_Sw[i_b, i]) + s.cdof_v[i_b, j].dot(b.dof_Sv[i_b, i]))


@ti.func
def func_bank_cross(s: ti.template(), b: ti.template(), i_b):
    """mass_cross[row, col] -= fac * cdof_i^T S(link pair) cdof_j over the static list of (i, j) with i
    a dof moving one link of a touching pair and j one moving the other: the coupling
    -(J_a^T W J_b + J_b^T W J_a) of J^T W J with J = J_a - J_b."""
    c = s.contact
    for t in range(c.n_cross):
        i = c.cross_i[t]
        j = c.cross_j[t]
        lp = c.cross_lp[t]
        Swv = b.lp_Swv[i_b, lp]
        wi = s.cdof_w[i_b, i]
        vi = s.cdof_v[i_b, i]
        wj = s.cdof_w[i_b, j]
        vj = s.cdof_v[i_b, j]
        m = wj.dot(b.lp_Sww[i_b, lp] @ wi + Swv @ vi) + vj.dot(Swv.transpose() @ wi + b.lp_Svv[i_b, lp] @ vi)
        func_acc2(s, c.mass_cross, i_b, ti.max(i, j), ti.min(i, j), -c.cross_fac[t] * m)


# ------------------------------------------------------------------------------------------------
# Dynamics stages (inside the evaluation, before the solve): geometry, and the normal forces with their
# implicit blocks, which the first solve of func_contact_solve takes as they are
# ------------------------------------------------------------------------------------------------
@ti.func
def func_contact_clear(s: ti.template(), i_b, e, src, h):
    c = s.contact
    c.eval_h[i_b] = h
    func_bank_clear(s, c.bank_n, i_b)


@ti.func
def func_contact_clear_pairs(s: ti.template(), i_b, e, src, h):
    func_bank_clear_pairs(s, s.contact.bank_n, i_b)


@ti.func
def func_contact_clear_cross(s: ti.template(), i_b, e, src, h):
    c = s.contact
    for ij in range(s.n_dofs * s.n_dofs):
        c.mass_cross[i_b, ij // s.n_dofs, ij % s.n_dofs] = 0.0


@ti.func
def func_softplus(x, xc):
    """log(1 + e^x), with xc = x clamped to [-60, 60] (exp stays finite in the adjoint). Each branch is
    exact on its side (x + log(1 + e^-x) above 0, log(1 + e^x) at and below), so the derivative Taichi's
    reverse mode takes is the sigmoid everywhere, x = 0 included. Spelled max(x, 0) + log(1 + e^-|x|)
    (the same values) its adjoint at x == 0 was 0, not 1/2: Taichi sends max's adjoint to its second
    argument at a tie and takes abs's as sign(0) = 0. A body placed exactly on the ground starts its
    contacts at depth 0 with no normal velocity, so z = zp = 0 there, and the first step's gradient
    dropped the force's dependence on the depth."""
    return ti.select(x > 0, x + ti.log(1.0 + ti.exp(-xc)), ti.log(1.0 + ti.exp(xc)))


@ti.func
def func_normal_law(c: ti.template(), depth, depth_end, h):
    """(normal force, slope h * dF/d(approach speed)) of the implicit law for the depth now and the
    depth predicted for the end of the step, and the force of the current state alone (the spring on
    the current depth and the damper on the current approach)."""
    z = depth / c.delta
    zp = depth_end / c.delta
    # clamped so that exp stays finite in the adjoint (the force is ~0 below -MARGIN_WIDTHS anyway)
    zc = ti.min(ti.max(z, -60.0), 60.0)
    zpc = ti.min(ti.max(zp, -60.0), 60.0)
    sp = func_softplus(z, zc)
    spp = func_softplus(zp, zpc)
    sg = 1.0 / (1.0 + ti.exp(-zpc))
    ch = c.d / h
    fn = (c.k + ch) * c.delta * spp - ch * c.delta * sp
    return fn, h * (c.d + h * c.k) * sg, c.k * c.delta * sp - c.d / (1.0 + ti.exp(-zc)) * (depth - depth_end) / h


@ti.func
def func_rot_excess(s: ti.template(), i_b, l, p, h, axis, axial):
    """How far the rotation of link l over the step moves the material point at p beyond its linear
    prediction h w x r (r = p - link origin, w the link's angular velocity): (R(h w) - I) r - h w x r,
    by Rodrigues' formula (sinc(t) - 1) h w x r + (1 - cos t) / t^2 h^2 w x (w x r), t = h |w|. The
    integrator turns a free body by exactly R(h w) about its origin, so the linear prediction plus this
    is where the point ends; for a link turning many times in a step the linear prediction runs metres
    away (a box spinning at 1e3 rad/s above the ground: its corners "reach" 1.7 m below it) while this
    keeps the point on its circle. Series below t^2 = 1e-4 (no cancellation, no sqrt at 0: smooth in w).
    axial (0 or 1) drops the spin about `axis` (a cylinder's: turning about it moves its material but
    not its shape)."""
    w = s.cvel_w[i_b, l]
    w = w - (axial * w.dot(axis)) * axis
    r = p - s.link_pos[i_b, l]
    t2 = h * h * w.dot(w)
    small = t2 < 1e-4
    t = ti.sqrt(ti.max(t2, 1e-4))
    st = ti.sin(0.5 * t) / (0.5 * t)
    a = ti.select(small, t2 * (-1.0 / 6.0 + t2 / 120.0), ti.sin(t) / t - 1.0)
    b = ti.select(small, 0.5 + t2 * (-1.0 / 24.0 + t2 / 720.0), 0.5 * st * st)
    wr = w.cross(r)
    return (a * h) * wr + (b * h * h) * w.cross(wr)


@ti.func
def func_rot_corr(s: ti.template(), i_b, i_s, h, pos, n, depth):
    """How much further than h u.n the two sides of slot i_s approach along n over the step because
    they turn (func_rot_excess of each side's reference point): the point side's sample point (a
    box corner, a sphere's centre, a capsule's or cylinder cap's axis point: pos + n (radius) from its
    surface point) and the SDF side's surface point, or its core point for a sphere or capsule (the
    rounding radius in from the surface). Those are the points whose motion moves the surfaces: a ball
    rolling on the ground turns its contact point up and away, not its centre."""
    c = s.contact
    ga = c.slot_ga[i_s]
    gb = c.slot_gb[i_s]
    la = c.geom_link[ga]
    lb = c.geom_link[gb]
    # pos is midway between the two surfaces against a moving geom and for box edge pairs, else on the
    # point side's surface (func_slot_geometry)
    mid = (c.link_dyn[lb] == 1) | (c.slot_kind[i_s] == SLOT_BOXEDGE)
    sa = ti.select(mid, pos - (0.5 * depth) * n, pos)
    tb = c.geom_type[gb]
    rb = ti.select((tb == GEOM_SPHERE) | (tb == GEOM_CAPSULE), c.geom_size[gb][0], 0.0)
    Ra = c.geom_xR[i_b, ga]
    Rb = c.geom_xR[i_b, gb]
    za = ti.Vector([Ra[0, 2], Ra[1, 2], Ra[2, 2]])
    zb = ti.Vector([Rb[0, 2], Rb[1, 2], Rb[2, 2]])
    ca = ti.select(c.geom_type[ga] == GEOM_CYLINDER, 1.0, 0.0)
    cb = ti.select(tb == GEOM_CYLINDER, 1.0, 0.0)
    ea = func_rot_excess(s, i_b, la, sa + c.slot_r[i_s] * n, h, za, ca)
    eb = func_rot_excess(s, i_b, lb, sa + (depth - rb) * n, h, zb, cb)
    return (ea - eb).dot(n)


@ti.func
def func_contact_normal(s: ti.template(), i_b, i_s, h, pos, n, depth, u, cand, corr):
    """Normal force and its implicit block of slot i_s (within the contact margin, now or at the end
    of the step), added onto its two links; the slot's data for the friction passes."""
    c = s.contact
    # the normal force is linearised about the depth predicted for the end of the step, so a contact
    # that closes its gap within the step acts in it (speculative contact, see the module docstring)
    # (corr: how much further the rotations close the gap than the linear prediction h u.n says)
    fn_pred, wn, fn_now = func_normal_law(c, depth, depth - h * u.dot(n) - corr, h)
    # on while the force of the current state pushes (a contact creeping out of a deep overlap, whose
    # predicted force sits at ~0), the predicted one does (a gap closing within the step), or the pair
    # is a candidate (cand: its gap could close within the step if the bodies' motion changes; the
    # first pass linearises it again at the velocity the first solve gives)
    acting = (fn_now > 0) | (fn_pred > 0)
    on = acting | cand
    c.sl_on[i_b, i_s] = ti.select(on, 1, 0)
    c.sl_cand[i_b, i_s] = ti.select(acting, 0, 1)
    if on:
        func_bank_add(s, c.bank_n, i_b, i_s, pos, fn_pred * n, wn * n.outer_product(n))
        ga = c.slot_ga[i_s]
        gb = c.slot_gb[i_s]
        c.sl_pos[i_b, i_s] = pos
        c.sl_n[i_b, i_s] = n
        c.sl_u[i_b, i_s] = u
        c.sl_Fn[i_b, i_s] = fn_pred
        c.sl_wn[i_b, i_s] = wn
        c.sl_depth[i_b, i_s] = depth
        c.sl_corr[i_b, i_s] = corr
        c.sl_mu[i_b, i_s] = ti.max(c.geom_mu[i_b, ga], c.geom_mu[i_b, gb])
        c.c_pos[i_b, i_s] = pos
        c.c_normal[i_b, i_s] = n
        c.c_depth[i_b, i_s] = depth


@ti.func
def func_contact_slot(s: ti.template(), i_b, i_s, h):
    """Geometry and normal force of slot i_s (of an active pair): sl_on set if it is in contact."""
    c = s.contact
    pos, n, depth = func_slot_geometry(s, i_b, i_s)
    la = c.geom_link[c.slot_ga[i_s]]
    lb = c.geom_link[c.slot_gb[i_s]]
    ua = s.cvel_v[i_b, la] + s.cvel_w[i_b, la].cross(pos)
    ub = s.cvel_v[i_b, lb] + s.cvel_w[i_b, lb].cross(pos)
    u = ua - ub
    # the depth predicted for the end of the step is depth - h u.n - corr: the two sides' reference
    # points (func_rot_corr; on the normal through pos, where u.n is the same) moved as the integrator
    # moves them, each link turning by exactly h w (func_rot_excess), not along their velocity's tangent. For a slowly turning body corr is the
    # O(h^2 w^2 r) centripetal term; for a fast-spinning one it cancels the tangent's metres of
    # fictitious approach (a spinning box thrown by a surface it never reaches, issue #21)
    corr = func_rot_corr(s, i_b, i_s, h, pos, n, depth)
    # within the margin now, or at the end of the step if the velocity stays
    near = ti.max(depth, depth - h * u.dot(n) - corr) > -c.margin
    # or if either body could turn towards the other within the step (the one below stopped by a third
    # body while this one falls on): a candidate
    cand = depth + h * (ti.sqrt(ua.dot(ua) + TINY) + ti.sqrt(ub.dot(ub) + TINY)) > -c.margin
    if near | cand:
        func_contact_normal(s, i_b, i_s, h, pos, n, depth, u, cand, corr)


@ti.func
def func_contact_slots(s: ti.template(), i_b, e, src, h):
    """Geometry and normal force of every slot of an active pair. Single-assignment form (see
    kinematics.py): the contact's on/off is a 0/1 mask. The mask is cleared first and set only in the
    innermost branch: with `else` branches that write it, Taichi 1.7.4's reverse mode built an invalid
    IR for this loop in float32 (verify.cpp: block parent mismatch), so no float32 scene with contacts
    could take a gradient. Without gradients the loop runs over the active pairs' slots only (slots are
    stored by pair; the mask of an inactive pair's slots is left stale: read() masks it with
    pair_active) and lists the slots that are on (sl_list[i_b, :n_on[i_b]], in slot order) for the
    solve's passes, which then visit only those (a robot's geoms against the ground: a few of some
    hundred slots touch; visiting every slot was an eighth of ANYmal's step)."""
    c = s.contact
    if ti.static(s.requires_grad):
        for i_s in range(c.n_slots):
            c.sl_on[i_b, i_s] = 0
            if c.pair_active[i_b, c.slot_pair[i_s]] == 1:
                func_contact_slot(s, i_b, i_s, h)
    else:
        n_on = 0
        for i_p in range(c.n_pairs):
            if c.pair_active[i_b, i_p] == 1:
                for i_s in range(c.pair_s0[i_p], c.pair_s0[i_p + 1]):
                    c.sl_on[i_b, i_s] = 0
                    func_contact_slot(s, i_b, i_s, h)
                    if c.sl_on[i_b, i_s] == 1:
                        c.sl_list[i_b, n_on] = i_s
                        n_on += 1
        c.n_on[i_b] = n_on


@ti.func
def func_contact_tree(s: ti.template(), i_b, e, src, h):
    func_bank_tree(s, s.contact.bank_n, i_b)


@ti.func
def func_contact_dof(s: ti.template(), i_b, e, src, h):
    func_bank_dof(s, s.contact.bank_n, i_b)


@ti.func
def func_contact_project(s: ti.template(), i_b, e, src, h):
    func_bank_project(s, s.contact.bank_n, i_b)


@ti.func
def func_contact_cross(s: ti.template(), i_b, e, src, h):
    func_bank_cross(s, s.contact.bank_n, i_b)


CONTACT_STAGES = (func_geom_pose, func_broad_phase, func_contact_clear, func_contact_slots, func_contact_tree,
                  func_contact_dof, func_contact_project)
CROSS_STAGES = (func_contact_clear_pairs, func_contact_clear_cross, func_geom_pose, func_broad_phase,
                func_contact_clear, func_contact_slots, func_contact_tree, func_contact_dof, func_contact_project,
                func_contact_cross)


# ------------------------------------------------------------------------------------------------
# Friction passes (inside the solve, see func_contact_solve): differentiated by Taichi, each stage
# one loop per env as the dynamics stages
# ------------------------------------------------------------------------------------------------
@ti.func
def func_vec3(x: ti.template(), e, i_b, i):
    return ti.Vector([x[e, i_b, i], x[e, i_b, i + 1], x[e, i_b, i + 2]])


@ti.func
def func_link_motion(s: ti.template(), x: ti.template(), e, i_b, out_w: ti.template(), out_v: ti.template()):
    """Spatial velocity (about the world origin) of every link for the dof velocities h * x[e, i_b], h
    the evaluation's step (kinematics.func_velocity's recursion for another velocity vector). With
    gradients in single-assignment form, every joint shape's term masked (x is sized by the core's
    element capacity, so the clamped reads of masked-out shapes stay inside it); without, a branch per
    joint shape (the same sums, a quarter less time)."""
    for i_l in range(s.n_links):
        # read inside the loop: a field value loaded before a loop and used in it made Taichi 1.7.4's
        # adjoint of the loop fail LLVM verification ("Instruction does not dominate all uses")
        scale = s.contact.eval_h[i_b]
        p = s.link_parent[i_l]
        zero = ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)
        nd = s.link_ndof[i_l]
        if ti.static(s.requires_grad):
            has_p = p >= 0
            pp = ti.max(p, 0)
            d0 = ti.min(s.link_dof_start[i_l], s.cap_elems - 1)
            df = ti.max(ti.min(s.link_dof_start[i_l], s.cap_elems - 6), 0)
            one = ti.cast(nd == 1, s.dtype) * scale * x[e, i_b, d0]
            free = ti.cast(nd == 6, s.dtype) * scale
            vb = func_vec3(x, e, i_b, df)
            wb = func_vec3(x, e, i_b, df + 3)
            out_w[i_b, i_l] = ti.select(has_p, out_w[i_b, pp], zero) + s.cdof_w[i_b, d0] * one + free * wb
            out_v[i_b, i_l] = (ti.select(has_p, out_v[i_b, pp], zero) + s.cdof_v[i_b, d0] * one
                               + free * (vb + s.link_pos[i_b, i_l].cross(wb)))
        else:
            w = zero
            v = zero
            if p >= 0:
                w = out_w[i_b, p]
                v = out_v[i_b, p]
            d0 = s.link_dof_start[i_l]
            if nd == 1:
                one = scale * x[e, i_b, d0]
                w = w + s.cdof_w[i_b, d0] * one
                v = v + s.cdof_v[i_b, d0] * one
            elif nd == 6:
                vb = func_vec3(x, e, i_b, d0)
                wb = func_vec3(x, e, i_b, d0 + 3)
                w = w + scale * wb
                v = v + scale * (vb + s.link_pos[i_b, i_l].cross(wb))
            out_w[i_b, i_l] = w
            out_v[i_b, i_l] = v


@ti.func
def func_rel_motion(s: ti.template(), i_b, i_s, pos, lw: ti.template(), lv: ti.template()):
    """Velocity of the point side relative to the other at pos, for the link motions lw, lv."""
    c = s.contact
    la = c.geom_link[c.slot_ga[i_s]]
    lb = c.geom_link[c.slot_gb[i_s]]
    return (lv[i_b, la] + lw[i_b, la].cross(pos)) - (lv[i_b, lb] + lw[i_b, lb].cross(pos))


@ti.func
def func_normal_after(c: ti.template(), i_b, i_s, u0, u1, n):
    """The normal force the (first pass's) linear law gives at the end-of-step relative velocity u1 (u0
    at the start)."""
    return c.sl_Fn1[i_b, i_s] - c.sl_wn1[i_b, i_s] / c.eval_h[i_b] * (u1 - u0).dot(n)


# pass 1 (after the first solve): drop the contacts whose force pulled
@ti.func
def func_p1_clear(s: ti.template(), i_b):
    func_bank_clear(s, s.contact.bank_d, i_b)


@ti.func
def func_p1_clear_pairs(s: ti.template(), i_b):
    func_bank_clear_pairs(s, s.contact.bank_d, i_b)


@ti.func
def func_p1_motion(s: ti.template(), i_b):
    c = s.contact
    func_link_motion(s, c.qacc1, 0, i_b, c.lv1_w, c.lv1_v)


@ti.func
def func_p1_slot(s: ti.template(), i_b, i_s, lw: ti.template(), lv: ti.template(), add: ti.template()):
    """Pass 1 for touching slot i_s at the link motion (lw, lv) of the first solve; with `add` its change
    added onto bank_d. Returns 1 if the slot changes the system (a candidate, or a dropped contact)."""
    c = s.contact
    pos = c.sl_pos[i_b, i_s]
    n = c.sl_n[i_b, i_s]
    u0 = c.sl_u[i_b, i_s]
    h = c.eval_h[i_b]
    du = func_rel_motion(s, i_b, i_s, pos, lw, lv).dot(n)
    depth = c.sl_depth[i_b, i_s]
    # a contact acting at the start-of-step velocity keeps its linear law (dropped if its force
    # at u1 pulls); a candidate gets the law's tangent at u1 (its first linearisation, at the
    # start-of-step velocity, was ~0): it acts if the law pushes there
    lin = c.sl_Fn[i_b, i_s] - c.sl_wn[i_b, i_s] / h * du
    f1, w1, _ = func_normal_law(c, depth, depth - c.sl_corr[i_b, i_s] - h * (u0.dot(n) + du), h)
    cand = c.sl_cand[i_b, i_s] == 1
    keep = ti.select(cand, f1 > 0, lin > 0)
    F1 = ti.select(keep, ti.select(cand, f1 + w1 / h * du, c.sl_Fn[i_b, i_s]), 0.0)
    W1 = ti.select(keep, ti.select(cand, w1, c.sl_wn[i_b, i_s]), 0.0)
    c.sl_Fn1[i_b, i_s] = F1
    c.sl_wn1[i_b, i_s] = W1
    c.sl_keep1[i_b, i_s] = ti.select(keep, 1, 0)
    if ti.static(add):
        func_bank_add(s, c.bank_d, i_b, i_s, pos, (F1 - c.sl_Fn[i_b, i_s]) * n,
                      (W1 - c.sl_wn[i_b, i_s]) * n.outer_product(n))
    return ti.select(cand | (not keep), 1, 0)


@ti.func
def func_p1_slots(s: ti.template(), i_b):
    """Per touching slot: the normal force the first solve applied; a contact whose force pulled (a
    speculative contact that another contact stopped first, or one that separates) leaves the system."""
    c = s.contact
    for i_s in range(c.n_slots):
        if c.sl_on[i_b, i_s] == 1:
            func_p1_slot(s, i_b, i_s, c.lv1_w, c.lv1_v, True)


@ti.func
def func_p1_add_listed(s: ti.template(), i_b):
    """bank_d <- the changes func_p1_slot (without `add`) stored, for the listed slots in slot order:
    the same sums as func_p1_slots' (a kept contact adds exact zeros)."""
    c = s.contact
    for k in range(c.n_on[i_b]):
        i_s = c.sl_list[i_b, k]
        n = c.sl_n[i_b, i_s]
        func_bank_add(s, c.bank_d, i_b, i_s, c.sl_pos[i_b, i_s], (c.sl_Fn1[i_b, i_s] - c.sl_Fn[i_b, i_s]) * n,
                      (c.sl_wn1[i_b, i_s] - c.sl_wn[i_b, i_s]) * n.outer_product(n))


@ti.func
def func_p1_tree(s: ti.template(), i_b):
    func_bank_tree(s, s.contact.bank_d, i_b)


@ti.func
def func_p1_dof(s: ti.template(), i_b):
    func_bank_dof(s, s.contact.bank_d, i_b)


@ti.func
def func_p1_project(s: ti.template(), i_b):
    func_bank_project(s, s.contact.bank_d, i_b)


@ti.func
def func_p1_cross(s: ti.template(), i_b):
    func_bank_cross(s, s.contact.bank_d, i_b)


# pass 2 (after the second, normal solve): normal forces, Coulomb's forces for them
@ti.func
def func_p2_clear(s: ti.template(), i_b):
    func_bank_clear(s, s.contact.bank_c, i_b)


@ti.func
def func_p2_motion(s: ti.template(), i_b):
    c = s.contact
    func_link_motion(s, c.qacc2, 0, i_b, c.lv2_w, c.lv2_v)


@ti.func
def func_p2_slots(s: ti.template(), i_b):
    """Per kept slot: the velocity after the normal solve, the normal force it applied, and Coulomb's
    force for that load along that velocity's (smoothed) slip."""
    c = s.contact
    for i_s in range(c.n_slots):
        if (c.sl_on[i_b, i_s] == 1) & (c.sl_keep1[i_b, i_s] == 1):
            func_p2_slot(s, i_b, i_s)


@ti.func
def func_p2_slot(s: ti.template(), i_b, i_s):
    c = s.contact
    pos = c.sl_pos[i_b, i_s]
    n = c.sl_n[i_b, i_s]
    u0 = c.sl_u[i_b, i_s]
    u2 = u0 + func_rel_motion(s, i_b, i_s, pos, c.lv2_w, c.lv2_v)
    f2 = func_normal_after(c, i_b, i_s, u0, u2, n)
    u2t = u2 - u2.dot(n) * n
    g2 = u2t / ti.sqrt(u2t.dot(u2t) + c.eps * c.eps)
    c.sl_u2[i_b, i_s] = u2
    c.sl_f2[i_b, i_s] = f2
    load = ti.max(f2, 0.0)
    func_bank_add(s, c.bank_c, i_b, i_s, pos, -c.sl_mu[i_b, i_s] * load * g2, ti.Matrix.zero(s.dtype, 3, 3))


@ti.func
def func_p2_slots_listed(s: ti.template(), i_b):
    c = s.contact
    for k in range(c.n_on[i_b]):
        i_s = c.sl_list[i_b, k]
        if c.sl_keep1[i_b, i_s] == 1:
            func_p2_slot(s, i_b, i_s)


@ti.func
def func_p2_tree(s: ti.template(), i_b):
    func_bank_tree(s, s.contact.bank_c, i_b)


@ti.func
def func_p2_dof(s: ti.template(), i_b):
    """rhs_c = J^T (Coulomb forces of func_p2_slots)."""
    c = s.contact
    b = c.bank_c
    for i in range(s.n_dofs):
        i_l = s.dof_link[i]
        g = s.cdof_w[i_b, i].dot(b.link_fn[i_b, i_l]) + s.cdof_v[i_b, i].dot(b.link_ff[i_b, i_l])
        c.rhs_c[i_b, i] = ti.select(b.link_touch[i_b, i_l] == 1, g, 0.0)


# pass 3 (after the Coulomb response): friction, and the contacts that pulled in the normal solve leave
@ti.func
def func_p3_clear(s: ti.template(), i_b):
    func_bank_clear(s, s.contact.bank_t, i_b)


@ti.func
def func_p3_clear_pairs(s: ti.template(), i_b):
    func_bank_clear_pairs(s, s.contact.bank_t, i_b)


@ti.func
def func_p3_motion(s: ti.template(), i_b):
    c = s.contact
    func_link_motion(s, c.dqc, 0, i_b, c.lvc_w, c.lvc_v)


@ti.func
def func_p3_slots(s: ti.template(), i_b):
    """Per kept slot, the change to the normal system: friction (implicit, its viscosity the secant of
    Coulomb's law at the slip speed predicted with Coulomb's forces applied, never below zero), and the
    removal of contacts whose normal-solve force pulled."""
    c = s.contact
    for i_s in range(c.n_slots):
        if (c.sl_on[i_b, i_s] == 1) & (c.sl_keep1[i_b, i_s] == 1):
            func_p3_slot(s, i_b, i_s)
        else:
            c.sl_keep[i_b, i_s] = 0


@ti.func
def func_p3_slot(s: ti.template(), i_b, i_s):
    c = s.contact
    h = c.eval_h[i_b]
    pos = c.sl_pos[i_b, i_s]
    n = c.sl_n[i_b, i_s]
    u0 = c.sl_u[i_b, i_s]
    u2 = c.sl_u2[i_b, i_s]
    f2 = c.sl_f2[i_b, i_s]
    u2t = u2 - u2.dot(n) * n
    s2 = ti.sqrt(u2t.dot(u2t) + c.eps * c.eps)
    uc = u2 + func_rel_motion(s, i_b, i_s, pos, c.lvc_w, c.lvc_v)
    w = (uc - uc.dot(n) * n).dot(u2t) / s2
    # slip speed ahead, smoothly clipped at 0 (a reversal means the contact sticks)
    wc = ti.min(ti.max(w / c.eps, -60.0), 60.0)
    # (func_softplus's two branches, so that the adjoint at w == 0 is 1/2 as the derivative)
    vp = ti.select(w > 0, w + c.eps * ti.log(1.0 + ti.exp(-wc)), c.eps * ti.log(1.0 + ti.exp(wc)))
    keep = f2 > 0
    eta = c.sl_mu[i_b, i_s] * ti.max(f2, 0.0) / ti.sqrt(vp * vp + c.eps * c.eps)
    drop = ti.select(keep, 0.0, 1.0)
    nn = n.outer_product(n)
    u0t = u0 - u0.dot(n) * n
    dF = -eta * u0t - drop * c.sl_Fn1[i_b, i_s] * n
    dW = h * eta * (ti.Matrix.identity(s.dtype, 3) - nn) - drop * c.sl_wn1[i_b, i_s] * nn
    func_bank_add(s, c.bank_t, i_b, i_s, pos, dF, dW)
    c.sl_eta[i_b, i_s] = eta
    c.sl_keep[i_b, i_s] = ti.select(keep, 1, 0)


@ti.func
def func_p3_slots_listed(s: ti.template(), i_b):
    """func_p3_slots over the listed slots (sl_keep is then written for those only: every reader
    visits listed slots only)."""
    c = s.contact
    for k in range(c.n_on[i_b]):
        i_s = c.sl_list[i_b, k]
        if c.sl_keep1[i_b, i_s] == 1:
            func_p3_slot(s, i_b, i_s)
        else:
            c.sl_keep[i_b, i_s] = 0


@ti.func
def func_p3_tree(s: ti.template(), i_b):
    func_bank_tree(s, s.contact.bank_t, i_b)


@ti.func
def func_p3_dof(s: ti.template(), i_b):
    func_bank_dof(s, s.contact.bank_t, i_b)


@ti.func
def func_p3_project(s: ti.template(), i_b):
    func_bank_project(s, s.contact.bank_t, i_b)


@ti.func
def func_p3_cross(s: ti.template(), i_b):
    func_bank_cross(s, s.contact.bank_t, i_b)


@ti.func
def func_contact_report(s: ti.template(), i_b, e):
    """The forces the step applied (normal and friction at the final velocity), for the entity API's
    readers: not differentiated, own link-velocity fields."""
    c = s.contact
    c.eval_count[i_b] = c.eval_count[i_b] + 1
    func_link_motion(s, s.qacc, e, i_b, c.lvr_w, c.lvr_v)
    if ti.static(s.requires_grad):
        for i_s in range(c.n_slots):
            if (c.sl_on[i_b, i_s] == 1) & (c.sl_keep[i_b, i_s] == 1):
                func_report_slot(s, i_b, i_s)
            else:
                c.c_fn[i_b, i_s] = 0.0
    else:
        # the other slots' c_fn is left as it was: read() masks it with sl_on (as it masks inactive
        # pairs), and sl_keep is only read where sl_on is set
        for k in range(c.n_on[i_b]):
            i_s = c.sl_list[i_b, k]
            if c.sl_keep[i_b, i_s] == 1:
                func_report_slot(s, i_b, i_s)
            else:
                c.c_fn[i_b, i_s] = 0.0


@ti.func
def func_report_slot(s: ti.template(), i_b, i_s):
    c = s.contact
    pos = c.sl_pos[i_b, i_s]
    n = c.sl_n[i_b, i_s]
    u0 = c.sl_u[i_b, i_s]
    u3 = u0 + func_rel_motion(s, i_b, i_s, pos, c.lvr_w, c.lvr_v)
    f3 = func_normal_after(c, i_b, i_s, u0, u3, n)
    c.c_fn[i_b, i_s] = ti.max(f3, 0.0)
    c.c_force[i_b, i_s] = f3 * n - c.sl_eta[i_b, i_s] * (u3 - u3.dot(n) * n)
    # the depth the step ends at (the linear prediction with the final velocity): far past the
    # surface, the contact has not stopped the body. Per env, the first evaluation with such a
    # contact is recorded (its deepest one relative to the limit) for watch()
    depth_end = c.sl_depth[i_b, i_s] - c.sl_corr[i_b, i_s] - c.eval_h[i_b] * u3.dot(n)
    lim = DEEP_FRACTION * ti.min(c.geom_thick[c.slot_ga[i_s]], c.geom_thick[c.slot_gb[i_s]])
    if depth_end > lim:
        ev = c.eval_count[i_b]
        first = c.deep_i[i_b, 0] == 0
        # ranked by how much deeper it went within the step (a fast impact before a slow sinking)
        key = (depth_end - ti.max(c.sl_depth[i_b, i_s], 0.0)) / lim
        if first | ((c.deep_i[i_b, 2] == ev) & (key > c.deep_f[i_b, 3])):
            c.deep_i[i_b, 0] = 1
            c.deep_i[i_b, 1] = i_s
            c.deep_i[i_b, 2] = ev
            c.deep_f[i_b, 0] = depth_end
            c.deep_f[i_b, 1] = -u0.dot(n)
            c.deep_f[i_b, 2] = lim
            c.deep_f[i_b, 3] = key
            c.deep_any[0] = 1


PASS1 = (func_p1_clear, func_p1_motion, func_p1_slots, func_p1_tree, func_p1_dof, func_p1_project)
PASS1_CROSS = (func_p1_clear_pairs,) + PASS1 + (func_p1_cross,)
PASS2 = (func_p2_clear, func_p2_motion, func_p2_slots, func_p2_tree, func_p2_dof)
PASS3 = (func_p3_clear, func_p3_motion, func_p3_slots, func_p3_tree, func_p3_dof, func_p3_project)
PASS3_CROSS = (func_p3_clear_pairs,) + PASS3 + (func_p3_cross,)
# the fused step without gradients (func_contact_solve): pass 1's sums once its slots are known to change
# the system, and pass 3 over the listed slots
PASS1_ACC = (func_p1_clear, func_p1_add_listed, func_p1_tree, func_p1_dof, func_p1_project)
PASS1_ACC_CROSS = (func_p1_clear_pairs,) + PASS1_ACC + (func_p1_cross,)
PASS3_LISTED = (func_p3_clear, func_p3_motion, func_p3_slots_listed, func_p3_tree, func_p3_dof, func_p3_project)
PASS3_LISTED_CROSS = (func_p3_clear_pairs,) + PASS3_LISTED + (func_p3_cross,)


# ------------------------------------------------------------------------------------------------
# Solves (not differentiated by Taichi: forward and hand-written adjoint, as the tree factorisation in
# inertia.py). The solves of func_contact_solve reuse the first factor, kept in fac1; these variants
# of inertia.func_solve and func_dense_solve take the factor's field as an argument.
# ------------------------------------------------------------------------------------------------
@ti.func
def func_tree_solve(s: ti.template(), Fc: ti.template(), i_b, x: ti.template(), e):
    """x[e, i_b, :] <- A^-1 x[e, i_b, :] with the tree L^T D L factor of A in Fc (inertia.func_solve).
    Read-modify-writes spelled out: `-=` on a field in the env loop compiles to an atomic (a
    compare-and-swap loop), and these solves are never differentiated by Taichi."""
    n = s.n_dofs
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


@ti.func
def func_dense_solve(s: ti.template(), Fc: ti.template(), i_b, x: ti.template(), e):
    """x[e, i_b, :] <- A^-1 x[e, i_b, :] with A = L D L^T in Fc (unit lower L, D on the diagonal)."""
    n = s.n_dofs
    for i in range(n):
        acc = x[e, i_b, i]
        for k in range(i):
            acc -= Fc[i_b, i, k] * x[e, i_b, k]
        x[e, i_b, i] = acc
    for i in range(n):
        x[e, i_b, i] = x[e, i_b, i] / Fc[i_b, i, i]
    for ii in range(n):
        i = n - 1 - ii
        acc = x[e, i_b, i]
        for k in range(i + 1, n):
            acc -= Fc[i_b, k, i] * x[e, i_b, k]
        x[e, i_b, i] = acc


@ti.func
def func_factor_dense(s: ti.template(), i_b):
    """mass_fac <- L D L^T of A = M (tree entries) + mass_cross, dense."""
    func_factor_dense_to(s, i_b, s.mass_fac)


@ti.func
def func_factor_dense_to(s: ti.template(), i_b, F: ti.template()):
    """func_factor_dense into F (lower triangle only)."""
    c = s.contact
    n = s.n_dofs
    for i in range(n):
        for j in range(i + 1):
            F[i_b, i, j] = s.mass_mat[i_b, i, j] * s.dof_anc[i, j] + c.mass_cross[i_b, i, j]
    for j in range(n):
        dj = F[i_b, j, j]
        for k in range(j):
            dj -= F[i_b, j, k] * F[i_b, j, k] * F[i_b, k, k]
        F[i_b, j, j] = dj
        for i in range(j + 1, n):
            v = F[i_b, i, j]
            for k in range(j):
                v -= F[i_b, i, k] * F[i_b, j, k] * F[i_b, k, k]
            F[i_b, i, j] = v / dj


@ti.func
def func_factor_solve_dense(s: ti.template(), i_b, e):
    """qacc[e] = A^-1 force with A = M (tree entries) + mass_cross, by a dense L D L^T."""
    func_factor_dense(s, i_b)
    for i in range(s.n_dofs):
        s.qacc[e, i_b, i] = s.force[i_b, i]
    func_dense_solve(s, s.mass_fac, i_b, s.qacc, e)


@ti.func
def func_solve_adjoint(s: ti.template(), Fc: ti.template(), i_b, x: ti.template(), xg: ti.template(), e,
                       rhs_g: ti.template()):
    """Adjoint of x[e] = A^-1 rhs (A's factor in Fc): rhs_bar += A^-1 x_bar, A_bar = -rhs_bar x^T (lower
    triangle, symmetrised), onto the tree entries of mass_mat and, in dense scenes, mass_cross."""
    c = s.contact
    for i in range(s.n_dofs):
        c.solve_tmp[0, i_b, i] = xg[e, i_b, i]
    if ti.static(c.dense):
        func_dense_solve(s, Fc, i_b, c.solve_tmp, 0)
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
    func_solve_adjoint(s, s.mass_fac, i_b, s.qacc, s.qacc.grad, e, s.force.grad)


@ti.func
def func_factor_into(s: ti.template(), i_b, Fc: ti.template(), x: ti.template()):
    """Factor the current system (mass_mat, and mass_cross in dense scenes) into Fc (kept for the later
    solves and the adjoints; the solves read its lower triangle only), and solve x[0] = A^-1 force
    with it."""
    c = s.contact
    if ti.static(c.dense):
        func_factor_dense_to(s, i_b, Fc)
    else:
        func_factor_to(s, i_b, Fc)
    n = s.n_dofs
    for i in range(n):
        x[0, i_b, i] = s.force[i_b, i]
    func_any_solve(s, Fc, i_b, x, 0)


@ti.func
def func_any_solve(s: ti.template(), Fc: ti.template(), i_b, x: ti.template(), e):
    if ti.static(s.contact.dense):
        func_dense_solve(s, Fc, i_b, x, e)
    else:
        func_tree_solve(s, Fc, i_b, x, e)


@ti.func
def func_solve_first(s: ti.template(), i_b):
    """qacc1: the system with every candidate normal contact."""
    func_factor_into(s, i_b, s.contact.fac1, s.contact.qacc1)


@ti.func
def func_solve_second(s: ti.template(), i_b):
    """qacc2: the normal system without the contacts that pulled in the first."""
    func_factor_into(s, i_b, s.contact.fac2, s.contact.qacc2)


@ti.func
def func_solve_coulomb(s: ti.template(), i_b):
    """dqc = A2^-1 rhs_c: the response of the normal system to the Coulomb forces of pass 2."""
    c = s.contact
    for i in range(s.n_dofs):
        c.dqc[0, i_b, i] = c.rhs_c[i_b, i]
    func_any_solve(s, c.fac2, i_b, c.dqc, 0)


@ti.func
def func_p1_listed(s: ti.template(), i_b):
    """Pass 1 over the listed slots with the first solve's link motion (lv2), without gradients; where it
    changed something, its sums are accumulated into the system. Returns whether it did."""
    c = s.contact
    changed = 0
    for k in range(c.n_on[i_b]):
        changed |= func_p1_slot(s, i_b, c.sl_list[i_b, k], c.lv2_w, c.lv2_v, False)
    if changed:
        for stage in ti.static(c.pass1_acc):
            stage(s, i_b)
    return changed


@ti.func
def func_p2_listed(s: ti.template(), i_b):
    """Pass 2 over the listed slots, without gradients."""
    func_p2_clear(s, i_b)
    func_p2_slots_listed(s, i_b)
    func_p2_tree(s, i_b)
    func_p2_dof(s, i_b)


@ti.func
def func_contact_solve(s: ti.template(), i_b, e):
    """The solve of a scene with contacts, all stages for one env (the fused step; see
    ContactSolver.factor_solve). Without gradients (nothing reads the intermediate factors and
    solutions back) the same results are computed with less work:
    - the passes visit the slots listed by func_contact_slots, not all the scene's slots;
    - an env with no slot on skips to the final solve (every pass adds nothing: A3 = A1 = M);
    - the first solve goes to fac2/qacc2 and its link motion to lv2; when pass 1 changes nothing (no
      candidate, no dropped contact: its sums are exact zeros, A2 == A1 and force unchanged) those are
      the second solve's and its motion, and pass 1's sums, the second factorisation and solve and pass
      2's link motion are skipped."""
    c = s.contact
    if ti.static(s.requires_grad):
        func_solve_first(s, i_b)
        for stage in ti.static(c.pass1):
            stage(s, i_b)
        func_solve_second(s, i_b)
        for stage in ti.static(PASS2):
            stage(s, i_b)
        func_solve_coulomb(s, i_b)
        for stage in ti.static(c.pass3):
            stage(s, i_b)
    elif ti.static(s.unrolled and not c.dense):
        func_contact_solve_rounds(s, i_b, e)
    else:
        if c.n_on[i_b] > 0:
            func_factor_into(s, i_b, c.fac2, c.qacc2)
            func_link_motion(s, c.qacc2, 0, i_b, c.lv2_w, c.lv2_v)
            if func_p1_listed(s, i_b):
                func_factor_into(s, i_b, c.fac2, c.qacc2)
                func_link_motion(s, c.qacc2, 0, i_b, c.lv2_w, c.lv2_v)
            func_p2_listed(s, i_b)
            func_solve_coulomb(s, i_b)
            for stage in ti.static(c.pass3_listed):
                stage(s, i_b)
    if ti.static(c.dense):
        func_factor_solve_dense(s, i_b, e)
    elif ti.static(not s.unrolled):  # an unrolled core has no gradients; its rounds did the final solve
        func_factor_solve(s, i_b, e)
    func_contact_report(s, i_b, e)


@ti.func
def func_contact_solve_rounds(s: ti.template(), i_b, e):
    """func_contact_solve's no-gradient path, final solve included, for a core that unrolls the tree
    factorisation (inertia.TreeSchedule): its factorisations and solves are rounds of one loop, so the
    unrolled factor and solve are compiled once, not three and four times (the kernel's compile time
    grows by a third of what inlining each would cost). The factor stays a local between rounds:
    round 0 factors A1 and solves into qacc2; round 1 (only when pass 1 changed something) A2, into
    qacc2; round 2 solves the Coulomb response dqc with the last factor; round 3 factors A3 and solves
    into qacc[e]."""
    c = s.contact
    L = ti.Vector.zero(s.dtype, s.static_tree.n_lower)
    rnd = 0
    if c.n_on[i_b] == 0:
        rnd = 3
    while rnd < 4:
        b = ti.Vector.zero(s.dtype, s.static_tree.n)
        if rnd == 2:
            b = func_static_vec(s, c.rhs_c, i_b)
        else:
            L = func_static_factor(s, i_b)
            b = func_static_vec(s, s.force, i_b)
        y = func_static_solve(s, L, b)
        if rnd == 3:
            func_static_store(s, y, s.qacc, e, i_b)
            rnd = 4
        elif rnd == 2:
            func_static_store(s, y, c.dqc, 0, i_b)
            for stage in ti.static(c.pass3_listed):
                stage(s, i_b)
            rnd = 3
        else:
            func_static_store(s, y, c.qacc2, 0, i_b)
            func_link_motion(s, c.qacc2, 0, i_b, c.lv2_w, c.lv2_v)
            nxt = 2
            if rnd == 0:
                if func_p1_listed(s, i_b):
                    nxt = 1
            if nxt == 2:
                func_p2_listed(s, i_b)
            rnd = nxt


# run-time sizes of the contact model (indices into ContactSolver.cfg_i): the contact kernels read them
# from a field, so one compile serves every scene of a contact class. The model's constants (k, d,
# delta, eps) stay compile-time constants, part of the class: as run-time values they change the
# rounding of the force law (LLVM folds and reassociates them), and a chaotic rollout (a legged robot
# landing) then leaves main's trajectory; scenes share them anyway unless their options differ.
C_GEOMS, C_PAIRS, C_SLOTS, C_LP, C_CROSS, N_CCFG_I = range(6)


def _runtime(index):
    """A size of the scene a ContactSolver holds: that scene's number in Python scope, a read of the
    solver's cfg field inside a kernel being compiled (as solver._runtime)."""

    def get(self):
        if taichi_compat.inside_kernel() and not self.static_sizes:
            return taichi_compat.subscript(self.cfg_i, index)
        return self.plan.cfg_i[index]

    return property(get)


def _cap(n: int, least: int) -> int:
    return max(least, 1 << (max(n, 1) - 1).bit_length())


def _user_stacklevel() -> int:
    """warnings.warn's stacklevel, called from ContactSolver.watch, that names the first frame outside
    this library (the user's scene.step())."""
    import os
    import sys

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    ours = (os.path.join(root, "solvers") + os.sep, os.path.join(root, "genesis_lite") + os.sep)
    f, level = sys._getframe(2), 2  # level 1: watch, the caller of warnings.warn
    while f is not None and f.f_code.co_filename.startswith(ours):
        f, level = f.f_back, level + 1
    return level


def geom_half_thickness(geoms) -> np.ndarray:
    """(G,) half the thinnest extent of each geom (box: smallest half size; sphere, capsule: radius;
    cylinder: radius or half length; mesh: half the thinnest k-DOP slab; plane: inf)."""
    out = np.full(geoms.n, np.inf)
    for g in range(geoms.n):
        t, sz = int(geoms.type[g]), np.asarray(geoms.size[g], dtype=float)
        if t == GEOM_BOX:
            out[g] = sz.min()
        elif t in (GEOM_SPHERE, GEOM_CAPSULE):
            out[g] = sz[0]
        elif t == GEOM_CYLINDER:
            out[g] = min(sz[0], sz[1])
        elif t == GEOM_MESH:
            k = np.asarray(geoms.kdop[g], dtype=float)
            out[g] = 0.5 * (k[:N_KDOP // 2] + k[N_KDOP // 2:]).min()
    return out


def deep_contact_message(plan, i_s, i_b, n_envs, step, h, depth, speed, lim, gain):
    """What the deep-penetration watch tells the user: who, when, how deep, why and what to do."""
    geoms = plan.geoms
    ga, gb = int(plan.np_slot_ga[i_s]), int(plan.np_slot_gb[i_s])
    env = f" in env {i_b}" if n_envs > 1 else ""
    fast = gain > 1.0  # it went deeper than the limit within this one step
    approach = f" (approach speed {speed:.3g} m/s: {speed * h:.3g} m per step)" if speed > 0 else ""
    why = (f"it went {gain * lim:.3g} m deeper within one step of {h:g} s{approach}: too fast for the penalty "
           "contact to stop within a step" if fast else
           f"its contact stiffness (RigidOptions.contact_stiffness = {plan.k:g} N/m per contact point) cannot "
           "hold its weight and the loads on it")
    todo = ("use a smaller dt or more substeps (SimOptions.substeps), or raise RigidOptions.contact_stiffness"
            if fast else
            f"raise RigidOptions.contact_stiffness (penetration ~ load / stiffness; {plan.k:g} N/m now) and "
            "contact_damping, or lighten the body")
    return (f"contact between {geoms.names[ga]} and {geoms.names[gb]}{env}: at step {step} it ended "
            f"{depth:.3g} m deep, more than {lim:.3g} m ({DEEP_FRACTION:g} of the thinner geom's half thickness): "
            f"the body is sinking into or passing through the other; {why}. To fix: {todo}. "
            "(Warned once per scene.)")


class ContactPlan:
    """The contact model of one scene in numpy: geoms, pairs, slots, the static flags its kernels are
    specialised on, and the capacities its fields need (see ContactSolver)."""

    @staticmethod
    def create(solver, models, options, specialized=False):
        """The contact plan of a scene, or None when no two geoms can touch (nothing is compiled or
        launched for contacts then). Raises ContactBuildError for geometry it cannot simulate."""
        geoms = build_geoms(models, int(options.max_mesh_contact_points))
        if geoms.n == 0:
            return None
        pairs = candidate_pairs(geoms, solver, bool(options.enable_self_collision),
                                bool(getattr(options, "ignore_unsupported_pairs", False)))
        if not pairs:
            return None
        return ContactPlan(solver, geoms, pairs, options, specialized)

    def __init__(self, solver, geoms, pairs, options, specialized=False):
        self.geoms = geoms
        self.pairs = pairs
        slots = build_slots(geoms, pairs)
        self.slots = slots
        self.n_links = solver.n_links
        self.n_geoms, self.n_pairs, self.n_slots = geoms.n, len(pairs), len(slots)
        self.k = float(options.contact_stiffness)
        self.d = float(options.contact_damping)
        self.delta = float(options.contact_smoothing)
        self.eps = float(options.friction_smoothing)
        self.margin = MARGIN_WIDTHS * self.delta
        # static: code is generated only for the slot kinds and SDF types this scene uses
        self.has_rim = any(x[1] == SLOT_CYL_RIM for x in slots)
        self.has_segseg = any(x[1] == SLOT_SEGSEG for x in slots)
        self.has_boxedge = any(x[1] == SLOT_BOXEDGE for x in slots)
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
        self.link_dyn = link_is_dynamic(solver)
        lp_index, slot_lp = {}, []
        for la, lb in zip(self.np_slot_link_a, self.np_slot_link_b):
            if self.link_dyn[la] and self.link_dyn[lb]:
                key = (min(la, lb), max(la, lb))
                slot_lp.append(lp_index.setdefault(key, len(lp_index)))
            else:
                slot_lp.append(-1)
        self.slot_lp = slot_lp
        self.dense = len(lp_index) > 0
        self.n_lp = len(lp_index)
        cross = []
        for (la, lb), lp in lp_index.items():
            for i in _link_dofs(solver, la):
                for j in _link_dofs(solver, lb):
                    # (i, j) and (j, i) land on the same lower-triangle entry; on the diagonal (a common
                    # ancestor of a self-collision pair) both terms of J_a^T W J_b + J_b^T W J_a do
                    cross.append((i, j, lp, 2.0 if i == j else 1.0))
        self.cross = cross
        self.n_cross = len(cross)
        self.cfg_i = [0] * N_CCFG_I
        self.cfg_i[C_GEOMS], self.cfg_i[C_PAIRS], self.cfg_i[C_SLOTS] = self.n_geoms, self.n_pairs, self.n_slots
        self.cfg_i[C_LP], self.cfg_i[C_CROSS] = self.n_lp, self.n_cross
        # the contact class: capacities rounded up to powers of two, and the static flags. A specialised
        # plan (RigidOptions.specialize_kernels) has its sizes compiled in as constants and fields of its
        # exact sizes: measured on ANYmal with 1,024 envs (float32, full optimisation), 1.41x MuJoCo's
        # rollout against 1.28x with run-time sizes at exact capacities (1.21x at powers of two)
        self.static = bool(specialized)
        if self.static:
            self.caps = (self.n_geoms, self.n_pairs, self.n_slots, self.n_lp if self.dense else 0,
                         self.n_cross if self.dense else 0)
        else:
            self.caps = (_cap(self.n_geoms, 16), _cap(self.n_pairs, 16), _cap(self.n_slots, 64),
                         _cap(self.n_lp, 4) if self.dense else 0, _cap(self.n_cross, 16) if self.dense else 0)
        self.flags = (self.dense, self.has_rim, self.has_segseg, self.has_boxedge, self.sdf_types,
                      (self.k, self.d, self.delta, self.eps), self.static)


@ti.data_oriented
class ContactSolver:
    """Fields and stages of the contact model of a RigidSolver (see the module docstring).

    The fields are sized by a contact class (the capacities and static flags of a ContactPlan, on one
    RigidCore) and the scene's sizes and constants are read at run time from cfg_i / cfg_f, so a later
    scene whose plan fits (same flags, capacities no larger) takes this solver, with the kernels already
    compiled on it, from the pool (solver.POOL) and compiles nothing: `load` puts its plan in."""

    n_geoms = _runtime(C_GEOMS)
    n_pairs = _runtime(C_PAIRS)
    n_slots = _runtime(C_SLOTS)
    n_lp = _runtime(C_LP)
    n_cross = _runtime(C_CROSS)

    def __init__(self, core, plan: ContactPlan):
        self.plan = plan
        self.caps, self.flags = plan.caps, plan.flags
        self.dense, self.has_rim, self.has_segseg, self.has_boxedge, self.sdf_types, consts, self.static_sizes = plan.flags
        self.baked_sizes = tuple(plan.cfg_i)
        self.k, self.d, self.delta, self.eps = consts
        self.margin = MARGIN_WIDTHS * self.delta
        self.dtype = core.dtype
        G, Pn, S, n_lp, n_cross = plan.caps
        B, L = core.cap_envs, core.cap_elems
        # dof vectors at the core's element capacity: the link-motion pass reads a free joint's six
        # entries at a clamped index even in scenes with fewer dofs (masked out, as in kinematics.py)
        D = core.cap_elems
        f, g = core.dtype, core.requires_grad
        tree = FieldTree(f, g, B)
        I, V3, M3, F = tree.I, tree.V3, tree.M3, tree.F  # noqa: E741
        self.cfg_i = I(N_CCFG_I)
        # geoms
        self.geom_type, self.geom_link = I(G), I(G)
        self.geom_pos, self.geom_center, self.geom_size = V3(G, False), V3(G, False), V3(G, False)
        self.geom_R = M3(G, False)
        self.geom_rbound = F(G, False)
        self.geom_beta = F(G, False)
        # half thickness (box: smallest half size, sphere / capsule: radius, ...; plane: huge), for the
        # deep-penetration watch
        self.geom_thick = F(G, False)
        self.geom_kdop = F((G, N_KDOP), False)
        # the friction parameter [env, geom]; the scene sees its block through geom_friction
        self.geom_mu = F((B, G))
        self.link_dyn = I(L)
        # pairs and slots
        self.pair_ga, self.pair_gb = I(Pn), I(Pn)
        # the pair's slots: pair_s0[p] .. pair_s0[p + 1] - 1 (build_slots stores them by pair)
        self.pair_s0 = I(Pn + 1)
        self.pair_active = I((B, Pn))
        self.slot_pair, self.slot_kind, self.slot_ga, self.slot_gb = I(S), I(S), I(S), I(S)
        self.slot_p = V3(S, False)
        self.slot_r, self.slot_aux = F(S, False), F(S, False)
        # per evaluation: geom poses, the touching slots' data (normal model, for the friction passes),
        # the accumulators of the normal forces (n), the Coulomb forces of pass 1 (c) and the changes of
        # pass 2 (t), and the solves' vectors
        self.geom_xpos, self.geom_xR = V3((B, G)), M3((B, G))
        self.eval_h = F(B, False)
        self.sl_on = I((B, S))
        self.sl_pos, self.sl_n, self.sl_u = V3((B, S)), V3((B, S)), V3((B, S))
        self.sl_u2 = V3((B, S))
        self.sl_Fn, self.sl_wn, self.sl_mu, self.sl_f2 = F((B, S)), F((B, S)), F((B, S)), F((B, S))
        self.sl_depth, self.sl_Fn1, self.sl_wn1 = F((B, S)), F((B, S)), F((B, S))
        self.sl_corr = F((B, S))
        self.sl_keep1, self.sl_cand = I((B, S)), I((B, S))
        # without gradients: the slots that are on, in slot order (func_contact_slots), and their count
        self.sl_list, self.n_on = I((B, S)), I(B)
        self.bank_n = AccBank(B, L, D, n_lp, f, g, True)
        self.bank_d = AccBank(B, L, D, n_lp, f, g, True)
        self.bank_c = AccBank(B, L, D, 0, f, g, False)
        self.bank_t = AccBank(B, L, D, n_lp, f, g, True)
        self.qacc1, self.qacc2, self.dqc, self.rhs_c = F((1, B, D)), F((1, B, D)), F((1, B, D)), F((B, D))
        self.lv1_w, self.lv1_v, self.lv2_w, self.lv2_v = V3((B, L)), V3((B, L)), V3((B, L)), V3((B, L))
        self.lvc_w, self.lvc_v = V3((B, L)), V3((B, L))
        self.fac1, self.fac2 = F((B, D, D), False), F((B, D, D), False)
        self.sl_eta, self.sl_keep = F((B, S), False), I((B, S))
        self.lvr_w, self.lvr_v = V3((B, L), False), V3((B, L), False)
        self.solve_tmp = F((1, B, D), False)
        # placeholders where the scene has no pairs of moving links (kernel_load's arguments)
        self.slot_lp = I(S)
        self.cross_i, self.cross_j, self.cross_lp = I(max(n_cross, 1)), I(max(n_cross, 1)), I(max(n_cross, 1))
        self.cross_fac = F(max(n_cross, 1), False)
        if self.dense:
            self.mass_cross = F((B, D, D))
        # outputs of the last evaluation (read by the entity API; no gradient)
        self.c_pos, self.c_normal, self.c_force = V3((B, S), False), V3((B, S), False), V3((B, S), False)
        self.c_depth, self.c_fn = F((B, S), False), F((B, S), False)
        # the deep-penetration watch: evaluations per env, each env's first deep contact ([hit, slot,
        # evaluation], [depth at the end of the step, approach speed, limit, depth gained in the step /
        # limit]), any env's
        self.eval_count = I(B)
        self.deep_i, self.deep_f, self.deep_any = I((B, 3)), F((B, 4), False), I(1)
        self._deep_warned, self._watch_n = False, 0
        self.tree = tree.finalize()

        self.stages = CONTACT_STAGES
        self.pass1, self.pass3 = PASS1, PASS3
        self.pass1_acc, self.pass3_listed = PASS1_ACC, PASS3_LISTED
        # adjoints cleared before each solve's backward (read from the passes' backward onwards)
        self.scratch_grad_fields = ([self.sl_pos, self.sl_n, self.sl_u, self.sl_u2, self.sl_Fn, self.sl_depth,
                                     self.sl_corr, self.sl_Fn1, self.sl_wn1,
                                     self.sl_wn, self.sl_mu, self.sl_f2, self.qacc1, self.qacc2, self.dqc, self.rhs_c,
                                     self.lv1_w, self.lv1_v, self.lv2_w, self.lv2_v, self.lvc_w, self.lvc_v]
                                    + self.bank_d.grad_fields + self.bank_c.grad_fields
                                    + self.bank_t.grad_fields) if g else []
        # the adjoints the scene zeroes before each backward (fields [env, ...]); the scratch ones above
        # are zeroed before every solve's adjoint instead
        self.grad_fields = ([self.geom_mu, self.geom_xpos, self.geom_xR] + self.bank_n.grad_fields) if g else []
        if self.dense:
            self.stages = CROSS_STAGES
            self.pass1, self.pass3 = PASS1_CROSS, PASS3_CROSS
            self.pass1_acc, self.pass3_listed = PASS1_ACC_CROSS, PASS3_LISTED_CROSS
            if g:
                self.grad_fields += [self.mass_cross]

    def fits(self, plan: ContactPlan) -> bool:
        """Whether a scene's plan can run on this solver's fields and kernels."""
        if self.static_sizes:  # sizes compiled in: only a plan of the same sizes
            return plan.flags == self.flags and tuple(plan.cfg_i) == self.baked_sizes
        return plan.flags == self.flags and all(a <= b for a, b in zip(plan.caps, self.caps))

    def load(self, plan: ContactPlan, n_envs: int, np_dtype):
        """Make `plan` (a scene of n_envs envs) the model this solver's kernels run."""
        self.plan = plan
        self.n_envs = n_envs
        for name in ("geoms", "pairs", "entity_geom_start", "entity_geom_count", "np_slot_ga", "np_slot_gb",
                     "np_slot_pair", "np_slot_link_a", "np_slot_link_b"):
            setattr(self, name, getattr(plan, name))
        geoms, slots, npf = plan.geoms, plan.slots, np_dtype
        G, S = plan.n_geoms, plan.n_slots
        R = geom_rotations(geoms.quat / np.linalg.norm(geoms.quat, axis=1, keepdims=True)).reshape(G, 9)
        geom_f = np.concatenate([geoms.pos, geoms.center, geoms.size, R,
                                 np.minimum(geoms.rbound, np.finfo(npf).max)[:, None], geoms.beta[:, None],
                                 np.minimum(geom_half_thickness(geoms), 1e30)[:, None]], -1)
        self._deep_warned, self._watch_n = False, 0
        dyn = np.zeros(max(plan.n_links, 1), dtype=np.int32)
        dyn[: plan.n_links] = plan.link_dyn
        slot_i = np.array([[x[0], x[1], x[2], x[3], lp] for x, lp in zip(slots, plan.slot_lp)], dtype=np.int32)
        slot_f = np.array([list(x[4]) + [x[5], x[6]] for x in slots], dtype=float).reshape(S, 5)
        cross = plan.cross if plan.cross else [(0, 0, 0, 0.0)]
        pair_s0 = np.searchsorted(plan.np_slot_pair, np.arange(plan.n_pairs + 1))
        assert np.all(np.diff(plan.np_slot_pair) >= 0), "slots must be stored by pair"
        c = lambda a, t: np.ascontiguousarray(np.asarray(a, dtype=t))  # noqa: E731
        self.kernel_load(c(plan.cfg_i, np.int32),
                         c(np.stack([geoms.type, geoms.link], -1), np.int32), c(geom_f, npf), c(geoms.kdop, npf),
                         c(np.broadcast_to(geoms.friction, (n_envs, G)), npf), dyn,
                         c([[p[0], p[1], s0] for p, s0 in zip(plan.pairs, pair_s0)], np.int32),
                         c(pair_s0[-1:], np.int32), slot_i, c(slot_f, npf),
                         c([x[:3] for x in cross], np.int32), c([x[3] for x in cross], npf))

    @ti.kernel
    def kernel_load(self, cfg_i: ti.types.ndarray(), geom_i: ti.types.ndarray(),
                    geom_f: ti.types.ndarray(), kdop: ti.types.ndarray(), mu: ti.types.ndarray(),
                    dyn: ti.types.ndarray(), pair: ti.types.ndarray(), pair_end: ti.types.ndarray(), slot_i: ti.types.ndarray(),
                    slot_f: ti.types.ndarray(), cross_i: ti.types.ndarray(), cross_f: ti.types.ndarray()):
        """A scene's contact model into the fields (one kernel rather than a copy kernel per field). The
        dof vectors of the passes are zeroed over their whole capacity: the link-motion pass reads
        entries past the scene's dofs (multiplied by 0), and an earlier scene may have left NaN there."""
        for k in range(N_CCFG_I):
            self.cfg_i[k] = cfg_i[k]
        for g in range(geom_i.shape[0]):
            self.geom_type[g] = geom_i[g, 0]
            self.geom_link[g] = geom_i[g, 1]
            for k in ti.static(range(3)):
                self.geom_pos[g][k] = geom_f[g, k]
                self.geom_center[g][k] = geom_f[g, 3 + k]
                self.geom_size[g][k] = geom_f[g, 6 + k]
            for k, l in ti.static(ti.ndrange(3, 3)):
                self.geom_R[g][k, l] = geom_f[g, 9 + 3 * k + l]
            self.geom_rbound[g] = geom_f[g, 18]
            self.geom_beta[g] = geom_f[g, 19]
            self.geom_thick[g] = geom_f[g, 20]
            for k in range(kdop.shape[1]):
                self.geom_kdop[g, k] = kdop[g, k]
        for i_b, g in ti.ndrange(mu.shape[0], mu.shape[1]):
            self.geom_mu[i_b, g] = mu[i_b, g]
        for i in range(dyn.shape[0]):
            self.link_dyn[i] = dyn[i]
        for p in range(pair.shape[0]):
            self.pair_ga[p] = pair[p, 0]
            self.pair_gb[p] = pair[p, 1]
            self.pair_s0[p] = pair[p, 2]
        self.pair_s0[pair.shape[0]] = pair_end[0]
        for i_s in range(slot_i.shape[0]):
            self.slot_pair[i_s] = slot_i[i_s, 0]
            self.slot_kind[i_s] = slot_i[i_s, 1]
            self.slot_ga[i_s] = slot_i[i_s, 2]
            self.slot_gb[i_s] = slot_i[i_s, 3]
            self.slot_lp[i_s] = slot_i[i_s, 4]
            for k in ti.static(range(3)):
                self.slot_p[i_s][k] = slot_f[i_s, k]
            self.slot_r[i_s] = slot_f[i_s, 3]
            self.slot_aux[i_s] = slot_f[i_s, 4]
        for t in range(cross_i.shape[0]):
            self.cross_i[t] = cross_i[t, 0]
            self.cross_j[t] = cross_i[t, 1]
            self.cross_lp[t] = cross_i[t, 2]
            self.cross_fac[t] = cross_f[t]
        for I in ti.grouped(self.qacc1):
            self.qacc1[I] = 0.0
            self.qacc2[I] = 0.0
            self.dqc[I] = 0.0
        for i_b in range(self.eval_count.shape[0]):
            self.eval_count[i_b] = 0
        for i_b in range(self.deep_i.shape[0]):
            self.deep_i[i_b, 0] = 0
        self.deep_any[0] = 0

    @property
    def geom_friction(self):
        """The friction parameter as the scene's (n_envs, n_geoms) block (to_torch / from_torch)."""
        return _FrictionBlock(self)

    @ti.kernel
    def kernel_set_friction(self, v: ti.types.ndarray()):
        for i, j in ti.ndrange(v.shape[0], v.shape[1]):
            self.geom_mu[i, j] = v[i, j]

    # ------------------------------------------------------------------ the solve op
    # With contacts, the solve of an evaluation is a sequence of launches (see func_contact_solve, which
    # the fused step runs inside its own kernel). The passes modify force, mass_mat and mass_cross in
    # place (A2 = A1 + pass 1's changes, A3 = A2 + pass 3's), so backward reads each pass's adjoint off
    # the matrix adjoint accumulated by the solves after it. Backward: the hand-written adjoints of the
    # solves and Taichi's of the passes, in reverse order.
    def factor_solve(self, s, e: int):
        """qacc[e] of the evaluation e whose dynamics stages just ran (the solve op of the schedule)."""
        self.kernel_solve_first(s)
        self.kernel_pass1(s)
        self.kernel_solve_second(s)
        self.kernel_pass2(s)
        self.kernel_solve_coulomb(s)
        self.kernel_pass3(s)
        s._kernel_factor_solve(e)
        self.kernel_report(s, e)

    def solve_grad(self, s, e: int):
        """Adjoint of factor_solve, with its forward values in the fields."""
        if self.scratch_grad_fields:
            self.kernel_clear_scratch_grads(s)
        s._kernel_solve_grad(e)
        self.kernel_pass3.grad(s)
        self.kernel_adjoint_solve(s, 2)
        self.kernel_pass2.grad(s)
        self.kernel_adjoint_solve(s, 1)
        self.kernel_pass1.grad(s)
        self.kernel_adjoint_solve(s, 0)

    # Env loops over the core's env capacity with a guard, as solver._Kernels explains (a loop bound
    # read from a field in a kernel of several loops broke Taichi's adjoint).
    @ti.kernel
    def kernel_report(self, s: ti.template(), e: ti.i32):
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                func_contact_report(s, i_b, e)

    @ti.kernel
    def kernel_solve_first(self, s: ti.template()):
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                func_solve_first(s, i_b)

    @ti.kernel
    def kernel_solve_second(self, s: ti.template()):
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                func_solve_second(s, i_b)

    @ti.kernel
    def kernel_solve_coulomb(self, s: ti.template()):
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                func_solve_coulomb(s, i_b)

    @ti.kernel
    def kernel_pass1(self, s: ti.template()):
        for stage in ti.static(self.pass1):
            if ti.static(s.serial):
                ti.loop_config(serialize=True)
            for i_b in range(s.cap_envs):
                if i_b < s.n_envs:
                    stage(s, i_b)

    @ti.kernel
    def kernel_pass2(self, s: ti.template()):
        for stage in ti.static(PASS2):
            if ti.static(s.serial):
                ti.loop_config(serialize=True)
            for i_b in range(s.cap_envs):
                if i_b < s.n_envs:
                    stage(s, i_b)

    @ti.kernel
    def kernel_pass3(self, s: ti.template()):
        for stage in ti.static(self.pass3):
            if ti.static(s.serial):
                ti.loop_config(serialize=True)
            for i_b in range(s.cap_envs):
                if i_b < s.n_envs:
                    stage(s, i_b)

    @ti.kernel
    def kernel_adjoint_solve(self, s: ti.template(), which: ti.template()):
        """Adjoint of one of the solves before the final one: 0 the first (qacc1 = A1^-1 force), 1 the
        second (qacc2 = A2^-1 force), 2 the Coulomb response (dqc = A2^-1 rhs_c)."""
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                if ti.static(which == 0):
                    func_solve_adjoint(s, self.fac1, i_b, self.qacc1, self.qacc1.grad, 0, s.force.grad)
                elif ti.static(which == 1):
                    func_solve_adjoint(s, self.fac2, i_b, self.qacc2, self.qacc2.grad, 0, s.force.grad)
                else:
                    func_solve_adjoint(s, self.fac2, i_b, self.dqc, self.dqc.grad, 0, self.rhs_c.grad)

    @ti.kernel
    def kernel_clear_scratch_grads(self, s: ti.template()):
        for x in ti.static(self.scratch_grad_fields):
            if ti.static(s.serial):
                ti.loop_config(serialize=True)
            for I in ti.grouped(ti.ndrange(*x.shape)):
                if ti.static(not hasattr(x, "n")):
                    x.grad[I] = 0.0
                elif ti.static(x.m == 1):
                    x.grad[I] = ti.Vector.zero(s.dtype, x.n)
                else:
                    x.grad[I] = ti.Matrix.zero(s.dtype, x.n, x.m)

    def watch(self, step: int, evals_per_step: int, h: float):
        """After a step without gradients (scene step number `step`): warn once per scene when a
        contact has ended a step deep inside the other body (func_report_slot records the first one).
        Reads one int every step for the first 16 steps, then every 16th (a read costs a few µs)."""
        self._watch_n += 1
        if self._deep_warned or (self._watch_n > 16 and self._watch_n % 16):
            return
        if self.deep_any[0] == 0:
            return
        self._deep_warned = True
        di, df = self.deep_i.to_numpy()[: max(self.n_envs, 1)], self.deep_f.to_numpy()[: max(self.n_envs, 1)]
        hit = np.nonzero(di[:, 0])[0]
        # the earliest record, the deepest (relative to its limit) among those
        i_b = int(hit[np.lexsort((-df[hit, 3], di[hit, 2]))[0]])  # (gain / limit in column 3)
        i_s, e_hit = int(di[i_b, 1]), int(di[i_b, 2])
        depth, speed, lim, gain = (float(x) for x in df[i_b, :4])
        late = (int(self.eval_count[i_b]) - e_hit) // max(int(evals_per_step), 1)
        warnings.warn(ContactPenetrationWarning(deep_contact_message(
            self.plan, i_s, i_b, self.n_envs, step - late, h, depth, speed, lim, gain)), stacklevel=_user_stacklevel())

    def longest_loop(self) -> int:
        """Iterations of the longest loop the contact stages may run in any scene of this solver's class
        (for the autodiff stack, adstack.py): its kernels serve every such scene."""
        G, Pn, S, _, n_cross = self.caps
        D = self.fac1.shape[1]
        return max(S, Pn, G, D * (D + 1) // 2, n_cross)

    # ------------------------------------------------------------------ readers
    def read(self):
        """numpy views of the last evaluation: dict of position, normal, force (on the point side),
        depth, fn (normal force magnitude, 0 when not touching), each (B, n_slots[, 3])."""
        B, S = self.n_envs, self.plan.n_slots
        # without gradients the report writes c_fn of the slots that are on only (func_contact_report)
        active = ((self.pair_active.to_numpy()[:B][:, self.np_slot_pair] == 1)
                  & (self.sl_on.to_numpy()[:B, :S] == 1))
        return {"position": self.c_pos.to_numpy()[:B, :S], "normal": self.c_normal.to_numpy()[:B, :S],
                "force": self.c_force.to_numpy()[:B, :S], "depth": self.c_depth.to_numpy()[:B, :S],
                "fn": np.where(active, self.c_fn.to_numpy()[:B, :S], 0.0)}


class _FrictionBlock:
    """The friction parameter of a ContactSolver as its scene's (n_envs, n_geoms) block of the
    capacity-sized field (what the scene's parameter code reads and writes)."""

    def __init__(self, contact):
        self.contact = contact
        self.field = contact.geom_mu
        self.shape = (contact.n_envs, contact.plan.n_geoms)

    @property
    def grad(self):
        return self.field.grad

    def to_torch(self, device=None):
        B, G = self.shape
        return self.field.to_torch(device=device)[:B, :G].contiguous()

    def to_numpy(self):
        B, G = self.shape
        return self.field.to_numpy()[:B, :G]

    def from_torch(self, x):
        if x.shape != self.shape:
            raise ValueError(f"contact friction: expected shape {self.shape}, got {tuple(x.shape)}")
        self.contact.kernel_set_friction(x.contiguous())


def _link_dofs(solver, l):
    """The dofs that move link l: its own and its ancestors'."""
    out = []
    while l >= 0:
        d0 = solver.np_link_dof_start[l]
        out.extend(range(d0, d0 + solver.np_link_ndof[l]))
        l = solver.np_link_parent[l]
    return out


__all__ = ["ContactPlan", "ContactSolver", "ContactBuildError", "CONTACT_STAGES", "func_contact_solve", "func_factor_solve_dense",
           "func_solve_grad_dense"]
