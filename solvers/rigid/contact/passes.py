"""The passes between the solves of func_contact_solve (solve.py): link motion of a solve's dof
vector, per-slot forces at that motion, and their sums onto the system (banks.py). Differentiated by
Taichi, each stage one loop per env as the dynamics stages.

  relinearise  after the first solve (every candidate contact): drops the contacts whose force pulled,
               linearises the candidates' law again at that solve's velocity (step 2 of the package
               docstring); its changes to the system go to bank_relinearise
  coulomb      after the second, normal solve: the normal forces it applied and Coulomb's forces for
               them along the slip (step 3), summed into force_coulomb
  friction     after the Coulomb response: friction as a viscosity, and the contacts whose normal-solve
               force pulled leave (step 4); its changes go to bank_friction
  bound        after the final solve, while a contact's friction exceeds Coulomb's law at its slip:
               the law's secant there (step 5); its changes go to bank_bound (gradient path, one bank
               for every round) or bank_friction (without gradients)
"""
import taichi as ti

from ..kinematics import func_link_origin, func_point_velocity
from ..math3d import div_floor
from .banks import (func_bank_add, func_bank_clear, func_bank_clear_pairs, func_bank_cross, func_bank_dof,
                    func_bank_dof_vectors, func_bank_project, func_bank_tree)
from .linalg import func_if_coupled
from .law import func_heavy_scale, func_normal_law


# ------------------------------------------------------------------------------------------------
# Friction passes (inside the solve, see func_contact_solve): differentiated by Taichi, each stage
# one loop per env as the dynamics stages
# ------------------------------------------------------------------------------------------------
@ti.func
def func_vec3(x: ti.template(), e, i_b, i):
    return ti.Vector([x[e, i_b, i], x[e, i_b, i + 1], x[e, i_b, i + 2]])


@ti.func
def func_link_motion(s: ti.template(), x: ti.template(), e, i_b, out_w: ti.template(), out_v: ti.template()):
    """Spatial velocity (about its tree's origin, kinematics.func_link_origin) of every link for the dof velocities h * x[e, i_b], h
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
                               + free * (vb + (s.link_pos[i_b, i_l] - func_link_origin(s, i_b, i_l)).cross(wb)))
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
                v = v + scale * (vb + (s.link_pos[i_b, i_l] - func_link_origin(s, i_b, i_l)).cross(wb))
            out_w[i_b, i_l] = w
            out_v[i_b, i_l] = v


@ti.func
def func_rel_motion(s: ti.template(), i_b, i_s, pos, lw: ti.template(), lv: ti.template()):
    """Velocity of the point side relative to the other at pos, for the link motions lw, lv."""
    c = s.contact
    la = c.geom_link[c.slot_ga[i_s]]
    lb = c.geom_link[c.slot_gb[i_s]]
    return func_point_velocity(s, lw, lv, i_b, la, pos) - func_point_velocity(s, lw, lv, i_b, lb, pos)


# the relative round-off of a law's value in the normal rounds' check (rounds.py), by precision, and in
# the bound rounds' release check in float32 (func_release_slot: ROUND_OFF_F64 in float64)
ROUND_OFF_F64, ROUND_OFF_F32 = 1e-12, 1e-5
ROUND_OFF_RELEASE_F32 = 1e-3


@ti.func
def func_slip_eps(c: ti.template(), i_b):
    """The friction law's slip speed eps for env i_b's step h: RigidOptions.friction_smoothing, or, where
    RigidOptions.friction_smoothing_accel is given (c.slip_accel > 0), at most that times h. With a fixed eps the
    law depends on h a / eps (a the contact's tangential acceleration): step 3's predicted slip carries the
    Coulomb impulse h mu f / m, which decides between the sticking viscosity and the creep below eps, so near
    h ~ eps m / (mu f) the model moves from one to the other and steps finer than that leave the limit of the
    coarser ones (ANYmal standing: the base sank 1.3e-5 m more per halving of dt below 25 us), and a body resting
    on a slope creeps at about (tan / mu) eps whatever the step. With eps proportional to h the ratio is fixed,
    the creep falls with h and the limit as h -> 0 is exact Coulomb friction, at first order. The default cap,
    0.25 m/s^2, acts below h = 4 ms only: with 0.1 (acting below 10 ms) the gradient matrix's mesh raft at 5 ms
    started within 1e-7 m of a kink of its loss (the sharper law moves the jump of Coulomb's response where a law
    enters the normal system at zero force, package docstring); None (c.slip_accel == 0) keeps eps fixed."""
    if ti.static(c.slip_accel > 0.0):
        return ti.min(c.eps, c.slip_accel * c.eval_h[i_b])
    else:
        return c.eps


@ti.func
def func_round_span(s: ti.template(), i_b):
    """How many entries func_round_slot walks: every slot with gradients, the listed ones without."""
    n = s.contact.n_slots
    if ti.static(not s.requires_grad):
        n = s.contact.n_on[i_b]
    return n


@ti.func
def func_round_slot(s: ti.template(), i_b, k):
    """Entry k of func_round_span's walk: (slot, whether it is on), in slot order either way."""
    c = s.contact
    i_s = k
    if ti.static(not s.requires_grad):
        i_s = c.sl_list[i_b, k]
    return i_s, c.sl_on[i_b, i_s] == 1


@ti.func
def func_normal_after(c: ti.template(), i_b, i_s, u0, u1, n):
    """The normal force the (first pass's) linear law gives at the end-of-step relative velocity u1 (u0
    at the start)."""
    return c.sl_Fn_normal[i_b, i_s] - c.sl_wn_normal[i_b, i_s] / c.eval_h[i_b] * (u1 - u0).dot(n)


def bank_stage(op, bank: str):
    """The pass stage (s, i_b) that runs the bank operation `op` (banks.py: clear, sum up the tree,
    project onto the dofs, ...) on the contact solver's bank `bank` (ContactSolver.banks)."""

    @ti.func
    def func_bank_stage(s: ti.template(), i_b):
        op(s, s.contact.banks[bank], i_b)

    return func_bank_stage


def bank_clear_stage(bank: str):
    """The stage (s, i_b) that clears the contact solver's bank `bank` (ContactSolver.banks), its link
    pairs' sums too where it has them."""

    @ti.func
    def func_clear(s: ti.template(), i_b):
        b = s.contact.banks[bank]
        func_bank_clear(s, b, i_b)
        if ti.static(b.pairs):
            func_bank_clear_pairs(s, b, i_b)

    return func_clear


# the passes' bank operations: each pass accumulates its changes into a bank of its own
func_relinearise_clear, func_relinearise_clear_pairs, func_relinearise_tree, func_relinearise_dof, \
    func_relinearise_project, func_relinearise_cross = (
        bank_stage(op, "relinearise") for op in (func_bank_clear, func_bank_clear_pairs, func_bank_tree,
                                                 func_bank_dof, func_bank_project, func_bank_cross))
func_coulomb_clear, func_coulomb_tree = (bank_stage(op, "coulomb") for op in (func_bank_clear, func_bank_tree))
func_friction_clear, func_friction_clear_pairs, func_friction_tree, func_friction_dof, func_friction_project, \
    func_friction_cross = (
        bank_stage(op, "friction") for op in (func_bank_clear, func_bank_clear_pairs, func_bank_tree, func_bank_dof,
                                              func_bank_project, func_bank_cross))


# the relinearise pass (after the first solve): drop the contacts whose force pulled. An acting slot whose depth
# predicted at the start-of-step velocity is more than RELIN_FROM contact widths out takes the law's tangent at the
# first solve's velocity too, wholly from RELIN_FROM + RELIN_OVER widths out (func_relinearise_share)
RELIN_FROM = 2.0
RELIN_OVER = 8.0


@ti.func
def func_relinearise_motion(s: ti.template(), i_b):
    c = s.contact
    func_link_motion(s, c.qacc_candidates, 0, i_b, c.link_w_candidates, c.link_v_candidates)


@ti.func
def func_relinearise_slot(s: ti.template(), i_b, i_s, lw: ti.template(), lv: ti.template(), add: ti.template()):
    """Pass 1 for touching slot i_s at the link motion (lw, lv) of the first solve; with `add` its change
    added onto bank_relinearise. Returns 1 if the slot changes the system (a candidate, or a dropped contact)."""
    c = s.contact
    pos = c.sl_pos[i_b, i_s]
    n = c.sl_n[i_b, i_s]
    u0 = c.sl_u[i_b, i_s]
    h = c.eval_h[i_b]
    du = func_rel_motion(s, i_b, i_s, pos, lw, lv).dot(n)
    depth = c.sl_depth[i_b, i_s]
    # a contact acting at the start-of-step velocity keeps its linear law, a candidate (its first
    # linearisation, at the start-of-step velocity, was ~0) gets the law's tangent at u1, and a contact
    # acting but predicted out by more than a few widths a share of each (func_relinearise_share); it is
    # in the normal system if that law pushes at u1
    heavy, scale, inv = func_heavy_scale(s, i_b, i_s, n)
    f1, w1, _ = func_normal_law(c, depth, depth - c.sl_corr[i_b, i_s] - h * (u0.dot(n) + du), h, heavy, scale, inv)
    beta = func_relinearise_share(c, c.sl_cand[i_b, i_s] == 1, depth - c.sl_corr[i_b, i_s] - h * u0.dot(n))
    # the slot's linear law in the normal system, kept for the slots that leave it too (the normal
    # rounds may bring them back), and its value at the first solve's velocity (where the rounds start):
    # the first linearisation's share 1 - beta, the tangent at u1's beta; in if it pushes there
    F1 = (1.0 - beta) * c.sl_Fn[i_b, i_s] + beta * (f1 + w1 / h * du)
    W1 = (1.0 - beta) * c.sl_wn[i_b, i_s] + beta * w1
    fk = F1 - W1 / h * du
    keep = fk > 0
    c.sl_Fn_normal[i_b, i_s] = F1
    c.sl_wn_normal[i_b, i_s] = W1
    c.sl_in_normal[i_b, i_s] = ti.select(keep, 1, 0)
    c.sl_fk[i_b, i_s] = fk
    if ti.static(add):
        func_bank_add(s, c.bank_relinearise, i_b, i_s, pos, (ti.select(keep, F1, 0.0) - c.sl_Fn[i_b, i_s]) * n,
                      (ti.select(keep, W1, 0.0) - c.sl_wn[i_b, i_s]) * n.outer_product(n))
    return ti.select((beta > 0) | (not keep), 1, 0)


@ti.func
def func_relinearise_share(c: ti.template(), cand, depth_end):
    """The share beta of the law's tangent at the first solve's velocity u1 in a slot's normal law (the rest
    its first linearisation, at the start-of-step velocity): 1 for a candidate; for a slot acting at the start,
    0 where the depth predicted at that velocity (depth_end) is above -RELIN_FROM contact widths (the law's
    first linearisation is good there, and a resting contact keeps it: linearising every contact again left a
    30-link chain on the ground swinging), rising to 1 at -RELIN_FROM - RELIN_OVER widths (the law's slope is
    then below 5e-5 of its full), along a smootherstep (C2: a body set exactly on the ground starts at 0 widths,
    and a kink there, even of the second derivative, moved its central differences by 5e-5). Before 2026-12-05
    an acting slot kept its first linearisation however far out. Beyond the margin whether a slot counted as
    acting was the sign of rounding noise in its ~0 force (two boxes falling together 8 mm apart: fn_pred = 0
    and fn_now = -d sigmoid(-60) (h u.n + corr) / h with u.n ~1e-84 m/s), different in the fused step and the
    gradient schedule: on the fused path the upper box kept its null law when the ground stopped the lower
    one and fell 8.4 mm into it in one step. Within the margin, one that the start-of-step velocity brought
    only near kept a slope ~1e-8 of the law's, and a box falling onto one that the step had just stopped went
    2.9 mm into it (four boxes stacked 45 degrees apart). Relinearised, as a candidate is, both are caught
    (tests/test_contact.py). Continuous in the state, and beyond ten widths the same whatever the slot's count."""
    t = ti.min(ti.max((-RELIN_FROM - depth_end / c.delta) / RELIN_OVER, 0.0), 1.0)
    return ti.select(cand, 1.0, t * t * t * (10.0 + t * (6.0 * t - 15.0)))


@ti.func
def func_relinearise_slots(s: ti.template(), i_b):
    """Per touching slot: the normal force the first solve applied; a contact whose force pulled (a
    speculative contact that another contact stopped first, or one that separates) leaves the system."""
    c = s.contact
    for i_s in range(c.n_slots):
        if c.sl_on[i_b, i_s] == 1:
            func_relinearise_slot(s, i_b, i_s, c.link_w_candidates, c.link_v_candidates, True)


@ti.func
def func_relinearise_add_listed(s: ti.template(), i_b):
    """bank_relinearise <- the changes func_relinearise_slot (without `add`) stored, for the listed slots in slot order:
    the same sums as func_relinearise_slots' (a kept contact adds exact zeros)."""
    c = s.contact
    for k in range(c.n_on[i_b]):
        i_s = c.sl_list[i_b, k]
        n = c.sl_n[i_b, i_s]
        keep = c.sl_in_normal[i_b, i_s] == 1
        func_bank_add(s, c.bank_relinearise, i_b, i_s, c.sl_pos[i_b, i_s],
                      (ti.select(keep, c.sl_Fn_normal[i_b, i_s], 0.0) - c.sl_Fn[i_b, i_s]) * n,
                      (ti.select(keep, c.sl_wn_normal[i_b, i_s], 0.0) - c.sl_wn[i_b, i_s]) * n.outer_product(n))


# the Coulomb pass (after the second, normal solve): normal forces, Coulomb's forces for them
@ti.func
def func_coulomb_motion(s: ti.template(), i_b):
    c = s.contact
    func_link_motion(s, c.qacc_normal, 0, i_b, c.link_w_normal, c.link_v_normal)


@ti.func
def func_coulomb_slots(s: ti.template(), i_b):
    """Per kept slot: the velocity after the normal solve, the normal force it applied, and Coulomb's
    force for that load along that velocity's (smoothed) slip."""
    c = s.contact
    for i_s in range(c.n_slots):
        if (c.sl_on[i_b, i_s] == 1) & (c.sl_in_normal[i_b, i_s] == 1):
            func_coulomb_slot(s, i_b, i_s)


@ti.func
def func_coulomb_slot(s: ti.template(), i_b, i_s):
    c = s.contact
    pos = c.sl_pos[i_b, i_s]
    n = c.sl_n[i_b, i_s]
    u0 = c.sl_u[i_b, i_s]
    u2 = u0 + func_rel_motion(s, i_b, i_s, pos, c.link_w_normal, c.link_v_normal)
    f2 = func_normal_after(c, i_b, i_s, u0, u2, n)
    u2t = u2 - u2.dot(n) * n
    eps = func_slip_eps(c, i_b)
    g2 = u2t / ti.sqrt(u2t.dot(u2t) + eps * eps)
    c.sl_u_normal[i_b, i_s] = u2
    c.sl_load[i_b, i_s] = f2
    load = ti.max(f2, 0.0)
    func_bank_add(s, c.bank_coulomb, i_b, i_s, pos, -c.sl_mu[i_b, i_s] * load * g2, ti.Matrix.zero(s.dtype, 3, 3))


@ti.func
def func_coulomb_slots_listed(s: ti.template(), i_b):
    c = s.contact
    for k in range(c.n_on[i_b]):
        i_s = c.sl_list[i_b, k]
        if c.sl_in_normal[i_b, i_s] == 1:
            func_coulomb_slot(s, i_b, i_s)


@ti.func
def func_coulomb_dof(s: ti.template(), i_b):
    """force_coulomb = J^T (Coulomb forces of func_coulomb_slots)."""
    c = s.contact
    b = c.bank_coulomb
    for i in range(s.n_dofs):
        i_l = s.dof_link[i]
        g = s.cdof_w[i_b, i].dot(b.link_fn[i_b, i_l]) + s.cdof_v[i_b, i].dot(b.link_ff[i_b, i_l])
        c.force_coulomb[i_b, i] = ti.select(b.link_touch[i_b, i_l] == 1, g, 0.0)


# the friction pass (after the Coulomb response): friction, and the contacts that pulled in the normal solve leave
@ti.func
def func_friction_motion(s: ti.template(), i_b):
    c = s.contact
    func_link_motion(s, c.dqacc_coulomb, 0, i_b, c.link_w_coulomb, c.link_v_coulomb)


@ti.func
def func_friction_slots(s: ti.template(), i_b):
    """Per kept slot, the change to the normal system: friction (implicit, its viscosity the secant of
    Coulomb's law at the slip speed predicted with Coulomb's forces applied, never below zero), and the
    removal of contacts whose normal-solve force pulled."""
    c = s.contact
    for i_s in range(c.n_slots):
        if (c.sl_on[i_b, i_s] == 1) & (c.sl_in_normal[i_b, i_s] == 1):
            func_friction_slot(s, i_b, i_s)
        else:
            func_friction_out(s, i_b, i_s)


@ti.func
def func_friction_out(s: ti.template(), i_b, i_s):
    """A slot out of the normal system leaves the friction pass out of the final system, with no friction
    and no load: what func_friction_slot gives a slot whose normal force is 0 (the limit at which a slot
    leaves the normal system). A bound round may bring its law back (func_release_slot), with that
    friction."""
    c = s.contact
    c.sl_eta[i_b, i_s] = 0.0
    c.sl_eta_now[i_b, i_s] = 0.0
    if ti.static(c.load_shift > 0.0):
        c.sl_load_c[i_b, i_s] = 0.0
    c.sl_in_final[i_b, i_s] = 0
    c.sl_in_now[i_b, i_s] = 0
    c.sl_back[i_b, i_s] = 0


@ti.func
def func_coulomb_load(s: ti.template(), i_b, i_s, u0, uc, n, f2, w, s2, keep):
    """Friction's load of slot i_s with RigidOptions(friction_load="coulomb") (package docstring, step 4):
    the normal force its law gives at the velocity uc predicted with Coulomb's forces applied, not the
    frictionless solve's f2: friction's own torque moves load between a body's contacts (a box sliding on a
    face presses its leading edge; a standing robot's splayed legs load their feet through friction), and the
    normal law carries that shift within the step. Only the share r of Coulomb's force that acts counts: all
    of it while the slip goes on (w, the predicted slip along the slip before, s2, at least 0), the part that
    stops it where the slip would reverse (s2 / (s2 - w)). At least 0, at most LOAD_SHIFT f2, 0 where f2 is
    (the slot leaves the final system); kept in sl_load_c for the bound rounds."""
    c = s.contact
    fc = func_normal_after(c, i_b, i_s, u0, uc, n)
    r = ti.select(w >= 0.0, 1.0, s2 / ti.max(s2 - w, s2))
    load = ti.select(keep, ti.min(ti.max(f2 + r * (fc - f2), 0.0), c.load_shift * f2), 0.0)
    c.sl_load_c[i_b, i_s] = load
    return load


@ti.func
def func_friction_slot(s: ti.template(), i_b, i_s):
    c = s.contact
    h = c.eval_h[i_b]
    pos = c.sl_pos[i_b, i_s]
    n = c.sl_n[i_b, i_s]
    u0 = c.sl_u[i_b, i_s]
    u2 = c.sl_u_normal[i_b, i_s]
    f2 = c.sl_load[i_b, i_s]
    u2t = u2 - u2.dot(n) * n
    eps = func_slip_eps(c, i_b)
    s2 = ti.sqrt(u2t.dot(u2t) + eps * eps)
    uc = u2 + func_rel_motion(s, i_b, i_s, pos, c.link_w_coulomb, c.link_v_coulomb)
    w = (uc - uc.dot(n) * n).dot(u2t) / s2
    # slip speed ahead, smoothly clipped at 0 (a reversal means the contact sticks)
    wc = ti.min(ti.max(w / eps, -60.0), 60.0)
    # (func_softplus's two branches, so that the adjoint at w == 0 is 1/2 as the derivative)
    vp = ti.select(w > 0, w + eps * ti.log(1.0 + ti.exp(-wc)), eps * ti.log(1.0 + ti.exp(wc)))
    keep = f2 > 0
    # the load: the frictionless solve's f2 (the default), or the normal force predicted with Coulomb's forces
    # applied (RigidOptions.friction_load = "coulomb": func_coulomb_load)
    load = func_coulomb_load(s, i_b, i_s, u0, uc, n, f2, w, s2, keep) if ti.static(c.load_shift > 0.0) else ti.max(f2, 0.0)
    eta = c.sl_mu[i_b, i_s] * load / ti.sqrt(vp * vp + eps * eps)
    drop = ti.select(keep, 0.0, 1.0)
    nn = n.outer_product(n)
    u0t = u0 - u0.dot(n) * n
    dF = -eta * u0t - drop * c.sl_Fn_normal[i_b, i_s] * n
    dW = h * eta * (ti.Matrix.identity(s.dtype, 3) - nn) - drop * c.sl_wn_normal[i_b, i_s] * nn
    func_bank_add(s, c.bank_friction, i_b, i_s, pos, dF, dW)
    c.sl_eta[i_b, i_s] = eta
    c.sl_eta_now[i_b, i_s] = eta
    c.sl_in_final[i_b, i_s] = ti.select(keep, 1, 0)
    c.sl_in_now[i_b, i_s] = ti.select(keep, 1, 0)
    c.sl_back[i_b, i_s] = 0


@ti.func
def func_friction_slots_listed(s: ti.template(), i_b):
    """func_friction_slots over the listed slots (sl_in_final is then written for those only: every reader
    visits listed slots only)."""
    c = s.contact
    for k in range(c.n_on[i_b]):
        i_s = c.sl_list[i_b, k]
        if c.sl_in_normal[i_b, i_s] == 1:
            func_friction_slot(s, i_b, i_s)
        else:
            func_friction_out(s, i_b, i_s)


@ti.func
def func_relinearise_listed(s: ti.template(), i_b):
    """Pass 1 over the listed slots with the first solve's link motion (link_w_normal, link_v_normal), without gradients; where it
    changed something, its sums are accumulated into the system. Returns whether it did."""
    c = s.contact
    changed = 0
    for k in range(c.n_on[i_b]):
        changed |= func_relinearise_slot(s, i_b, c.sl_list[i_b, k], c.link_w_normal, c.link_v_normal, False)
    if changed:
        func_if_coupled(s, i_b, func_relinearise_clear_pairs)
        for stage in ti.static(RELINEARISE_SUMS):
            stage(s, i_b)
        func_if_coupled(s, i_b, func_relinearise_cross)
    return changed


@ti.func
def func_coulomb_listed(s: ti.template(), i_b):
    """Pass 2 over the listed slots, without gradients."""
    func_coulomb_clear(s, i_b)
    func_coulomb_slots_listed(s, i_b)
    func_coulomb_tree(s, i_b)
    func_coulomb_dof(s, i_b)


RELINEARISE_PASS = (func_relinearise_clear, func_relinearise_motion, func_relinearise_slots, func_relinearise_tree,
                    func_relinearise_dof, func_relinearise_project)
RELINEARISE_PASS_CROSS = (func_relinearise_clear_pairs,) + RELINEARISE_PASS + (func_relinearise_cross,)
COULOMB_PASS = (func_coulomb_clear, func_coulomb_motion, func_coulomb_slots, func_coulomb_tree, func_coulomb_dof)
FRICTION_PASS = (func_friction_clear, func_friction_motion, func_friction_slots, func_friction_tree, func_friction_dof,
                 func_friction_project)
FRICTION_PASS_CROSS = (func_friction_clear_pairs,) + FRICTION_PASS + (func_friction_cross,)
# the fused step without gradients (func_contact_solve): the relinearise pass's sums once its slots are
# known to change the system (the friction pass over the listed slots: func_friction_or_bound)
RELINEARISE_SUMS = (func_relinearise_clear, func_relinearise_add_listed, func_relinearise_tree, func_relinearise_dof,
                    func_relinearise_project)


# the bound rounds (after the final solve; step 5 of the package docstring): where a contact's
# friction at the final slip exceeds Coulomb's bound mu f2 by more than BOUND_TOL, its viscosity becomes
# the law's secant at that slip; where its normal law pulls it leaves the system, and where a law that
# left pushes again it comes back; the system is solved again, at most BOUND_ROUNDS times
BOUND_ROUNDS = 8
BOUND_TOL = 0.01


@ti.func
def func_bound_eta(eta, speed, bound, sec):
    """The viscosity after a bound round, for a contact of viscosity eta slipping at `speed` after the
    last solve, so applying eta * speed of friction, against Coulomb's bound mu f2 (`bound`): eta while
    that friction is within (1 + BOUND_TOL) bound; the smoothed law's secant at that slip (`sec`, at most
    bound / speed) from (1 + 2 BOUND_TOL) bound on; linear between (continuous, so that the round is, and
    a contact near the tolerance cannot make it jump). A contact within Coulomb's bound keeps its
    viscosity, however far from the smoothed law (a sticking contact's viscous creep below eps)."""
    w = ti.min(ti.max((eta * speed - (1.0 + BOUND_TOL) * bound) / ti.max(BOUND_TOL * bound, ti.static(div_floor())), 0.0), 1.0)
    return eta + w * (sec - eta)


@ti.func
def func_u_at(s: ti.template(), i_b, i_s, lw: ti.template(), lv: ti.template()):
    """Slot i_s's relative velocity at the end of the step for the link motion (lw, lv) of a solve: what a
    bound round reads of a slot, its normal law's value (func_release_slot) and its slip (func_bound_slot),
    computed once per slot and round."""
    c = s.contact
    return c.sl_u[i_b, i_s] + func_rel_motion(s, i_b, i_s, c.sl_pos[i_b, i_s], lw, lv)


@ti.func
def func_tangential(s: ti.template(), i_b, i_s, u3):
    """The part of slot i_s's relative velocity u3 in its tangent plane (the slip)."""
    n = s.contact.sl_n[i_b, i_s]
    return u3 - u3.dot(n) * n


@ti.func
def func_coulomb_bound(s: ti.template(), i_b, i_s, u3):
    """Coulomb's bound of slot i_s at its relative velocity u3 after a solve (func_u_at): mu times friction's
    load. By default (RigidOptions.friction_load = "coulomb") the friction pass's load (func_coulomb_load), or
    where less the normal force the slot's law gives at u3: the load was a prediction, and a bound round holds
    friction to the normal force the solution applies (a law at or below 0 there is func_release_slot's to
    release: it keeps the load); with "frictionless" mu f2, f2 the normal solve's load (at least 0)."""
    c = s.contact
    # (one assignment per local: a static ternary, not an overwrite; DESIGN's autodiff-stack rule)
    load = func_bound_load(s, i_b, i_s, u3) if ti.static(c.load_shift > 0.0) else ti.max(c.sl_load[i_b, i_s], 0.0)
    return c.sl_mu[i_b, i_s] * load


@ti.func
def func_bound_load(s: ti.template(), i_b, i_s, u3):
    """func_coulomb_bound's load with friction_load = "coulomb": the friction pass's, or where less (and
    positive) the law's force at u3."""
    c = s.contact
    f3 = func_normal_after(c, i_b, i_s, c.sl_u[i_b, i_s], u3, c.sl_n[i_b, i_s])
    lc = c.sl_load_c[i_b, i_s]
    return ti.select(f3 > 0.0, ti.min(lc, f3), lc)


@ti.func
def func_law_secant(bound, u3t, eps):
    """The smoothed friction law's secant at the slip u3t for Coulomb's bound `bound` (func_coulomb_bound):
    bound / sqrt(|u_t|^2 + eps^2), eps func_slip_eps's."""
    return bound / ti.sqrt(u3t.dot(u3t) + eps * eps)


@ti.func
def func_bound_next(bound, u3t, eta, eps):
    """func_bound_eta for a slot of viscosity eta and Coulomb's bound `bound` (func_coulomb_bound, computed
    once per slot and round by the caller) at the slip u3t of a solve (func_tangential): its slip speed
    (|u_t|, with a 1e-4 eps floor inside the root so that its derivative stays finite at rest), the bound
    and the law's secant."""
    speed = ti.sqrt(u3t.dot(u3t) + 1e-8 * eps * eps)
    return func_bound_eta(eta, speed, bound, func_law_secant(bound, u3t, eps))


@ti.func
def func_release_slot(s: ti.template(), i_b, i_s, u3):
    """Whether a bound round at slot i_s's relative velocity u3 (func_u_at) changes its set, for a slot that is
    on: 1 where it is in the system now and pulls there, beyond its round-off (released: its law
    and friction leave the system), 2 where it is out of the system (released in an earlier round, or left
    out by the normal solve or the friction pass) and pushes there (it comes back, once: a contact that pulls
    when in and pushes when out, the solution between the two sets, was released and brought back until the
    rounds ran out, and ended in, pulling 0.85 N), else 0. A law left out of the normal solve comes back too
    (since 2026-12-05): friction moves load, and a box corner whose law pushed ~0 without friction pushed
    8.3 N with it when in, and nothing when out, so the state jumped by 1.5e-5 m in a step between two drop
    heights 1e-6 m apart (tests/test_contact.py, the fixed damper's landing gradient). The
    round-off is relative to the law's two terms; in float32 it is ROUND_OFF_RELEASE_F32 (with 1e-5, a 38 g
    cube squeezed on the ground by a Panda's pads, a law of a few tenths of a newton against terms of tens,
    was released and brought back on noise, and the cube was spun out of the grasp)."""
    c = s.contact
    ROUND_OFF = ti.static(ROUND_OFF_F64 if s.dtype == ti.f64 else ROUND_OFF_RELEASE_F32)
    r = 0
    f = func_normal_after(c, i_b, i_s, c.sl_u[i_b, i_s], u3, c.sl_n[i_b, i_s])
    # the scale of its round-off: the sum of its two terms' sizes
    a = ti.abs(c.sl_Fn_normal[i_b, i_s]) + ti.abs(c.sl_Fn_normal[i_b, i_s] - f)
    if c.sl_in_now[i_b, i_s] == 1:
        r = ti.select(f < -ROUND_OFF * a, 1, 0)
    elif c.sl_back[i_b, i_s] == 0:
        r = ti.select(f > ROUND_OFF * a, 2, 0)
        c.sl_back[i_b, i_s] = ti.select(r == 2, 1, 0)
    return r


@ti.func
def func_bound_slot(s: ti.template(), i_b, i_s, u3, eta, inside, rel, bank: ti.template()):
    """A bound round for slot i_s at its relative velocity u3 after the last solve (func_u_at), of viscosity
    eta, in the final system at the round's start where `inside`, by func_release_slot's choice `rel`: a slot
    inside keeps its normal law, its viscosity eta -> eta2 (func_bound_eta), or is released (rel 1: law
    and friction out of the system); a slot released earlier comes back (rel 2: law and the friction
    pass's viscosity). The change added onto `bank` and recorded in sl_eta_now and sl_in_now. Returns
    eta2, 1 if the slot is in the system after the round (else 0), and 1 if the system changed."""
    c = s.contact
    # single-assignment (DESIGN: a local overwritten in a loop lives on Taichi's autodiff stack)
    back = rel == 2
    release = inside & (rel == 1)
    n = c.sl_n[i_b, i_s]
    u0 = c.sl_u[i_b, i_s]
    u3t = func_tangential(s, i_b, i_s, u3)
    # a law brought back: the friction pass's viscosity or, where lower, the law's secant at the slip there
    # (within Coulomb's bound: the friction pass's sticking viscosity mu f2 / eps, brought back by a last
    # round, threw two boxes pushed into each other into a 7 rad/s spin)
    bound = func_coulomb_bound(s, i_b, i_s, u3)
    eps = func_slip_eps(c, i_b)
    eta_back = ti.min(c.sl_eta[i_b, i_s], func_law_secant(bound, u3t, eps))
    eta2 = ti.select(back, eta_back, ti.select(release, 0.0, ti.select(inside, func_bound_next(bound, u3t, eta, eps),
                                                                        eta)))
    stays = back | (inside & (not release))  # in the system after the round
    if back | inside:
        de = eta2 - ti.select(back, 0.0, eta)
        law = ti.select(back, 1.0, ti.select(release, -1.0, 0.0))
        nn = n.outer_product(n)
        u0t = u0 - u0.dot(n) * n
        func_bank_add(s, bank, i_b, i_s, c.sl_pos[i_b, i_s], -de * u0t + law * c.sl_Fn_normal[i_b, i_s] * n,
                      c.eval_h[i_b] * de * (ti.Matrix.identity(s.dtype, 3) - nn) + law * c.sl_wn_normal[i_b, i_s] * nn)
        c.sl_eta_now[i_b, i_s] = eta2
        c.sl_in_now[i_b, i_s] = ti.select(stays, 1, 0)
    return eta2, ti.select(stays, 1, 0), ti.select(back | release | (inside & (eta2 < eta)), 1, 0)


@ti.func
def func_keep_for_bound(s: ti.template(), i_b, e):
    """dqacc_coulomb[0] <- qacc[e] (without gradients), so that a bound round reads the last solution's
    link motion through the friction pass's stage (func_friction_or_bound): the Coulomb response is not
    read after the friction pass."""
    c = s.contact
    for i in range(s.n_dofs):
        c.dqacc_coulomb[0, i_b, i] = s.qacc[e, i_b, i]


@ti.func
def func_friction_or_bound(s: ti.template(), i_b, phase):
    """Without gradients, over the listed slots: the friction pass (phase 1, at the Coulomb response in
    dqacc_coulomb) or a bound round (phase 2, at the last solution, kept in dqacc_coulomb by
    func_keep_for_bound), with one copy of their bank stages (the fused kernel's compile time); phase 0
    does nothing. Returns 1 if the system is to be solved (again): after the friction pass or phase 0
    always, after a bound round if it changed a viscosity (else it added exact zeros: solving again
    would give the same qacc)."""
    c = s.contact
    solve = 1
    if phase > 0:
        func_friction_clear(s, i_b)
        func_if_coupled(s, i_b, func_friction_clear_pairs)
        func_friction_motion(s, i_b)
        changed = 1
        if phase == 1:
            func_friction_slots_listed(s, i_b)
        else:
            changed = 0
            # each slot's choice (func_release_slot) reads only its own state, so it is made just before
            # the slot's round: the same choices as deciding every slot first
            for k in range(c.n_on[i_b]):
                i_s = c.sl_list[i_b, k]
                u3 = func_u_at(s, i_b, i_s, c.link_w_coulomb, c.link_v_coulomb)
                c.sl_rel[i_b, i_s] = func_release_slot(s, i_b, i_s, u3)
                _eta2, _stays, ch = func_bound_slot(s, i_b, i_s, u3, c.sl_eta_now[i_b, i_s],
                                                    c.sl_in_now[i_b, i_s] == 1, c.sl_rel[i_b, i_s], c.bank_friction)
                changed |= ch
        solve = changed
        if changed == 1:
            func_friction_tree(s, i_b)
            func_friction_dof(s, i_b)
            func_friction_project(s, i_b)
            func_if_coupled(s, i_b, func_friction_cross)
    return solve


@ti.func
def func_bound_count(s: ti.template(), i_b, e, r):
    """How many of env i_b's slots a bound round at qacc[e] would change (the gradient path's check
    before it records round r), its releases and returns decided into bnd_rel[i_b, r] (func_release_slot);
    it writes only those, sl_back and the scratch link motion link_w_report / link_v_report."""
    c = s.contact
    func_link_motion(s, s.qacc, e, i_b, c.link_w_report, c.link_v_report)
    n = 0
    for k in range(func_round_span(s, i_b)):
        i_s, on = func_round_slot(s, i_b, k)
        rel = 0
        if on:
            u3 = func_u_at(s, i_b, i_s, c.link_w_report, c.link_v_report)
            rel = func_release_slot(s, i_b, i_s, u3)
            if (rel == 0) & (c.sl_in_now[i_b, i_s] == 1):
                eta = c.sl_eta_now[i_b, i_s]
                bound = func_coulomb_bound(s, i_b, i_s, u3)
                n += ti.select(func_bound_next(bound, func_tangential(s, i_b, i_s, u3), eta,
                                               func_slip_eps(c, i_b)) < eta, 1, 0)
        c.bnd_rel[i_b, r, i_s] = rel
        n += ti.select(rel > 0, 1, 0)
    return n


# The bound rounds on the gradient path share one kernel and one bank (as the normal rounds: rounds.py), the
# round read at run time from round_now[0]. Round r's starting solution is in bnd_x (the shared field its
# stages read; every round's kept in bnd_xs [env, round] for the backward), its viscosities and set go to
# bnd_eta / bnd_in [env, r + 1] (index 0 unused: round 0 starts from the friction pass's sl_eta and
# sl_in_final), its choices are in bnd_rel [env, r].
@ti.func
def func_bound_motion(s: ti.template(), i_b):
    """The link motion of the round's starting solution (bnd_x) into bnd_w / bnd_v."""
    c = s.contact
    func_link_motion(s, c.bnd_x, 0, i_b, c.bnd_w, c.bnd_v)


@ti.func
def func_bound_slots(s: ti.template(), i_b):
    """Bound round round_now[0] for every slot in the system at its start (func_bound_slot), onto
    bank_bound."""
    c = s.contact
    for i_s in range(c.n_slots):
        # read in the loop, one assignment each (DESIGN's autodiff-stack rule)
        r = c.round_now[0]
        if c.sl_on[i_b, i_s] == 1:
            eta = ti.select(r == 0, c.sl_eta[i_b, i_s], c.bnd_eta[i_b, r, i_s])
            inside = ti.select(r == 0, c.sl_in_final[i_b, i_s], c.bnd_in[i_b, r, i_s]) == 1
            eta2, stays, _changed = func_bound_slot(s, i_b, i_s, func_u_at(s, i_b, i_s, c.bnd_w, c.bnd_v), eta, inside,
                                                    c.bnd_rel[i_b, r, i_s], c.bank_bound)
            c.bnd_eta[i_b, r + 1, i_s] = eta2
            c.bnd_in[i_b, r + 1, i_s] = stays


@ti.func
def func_bound_restore(s: ti.template(), i_b):
    """bnd_x <- round round_now[0]'s starting solution, kept in bnd_xs (forward only: the rebuild)."""
    c = s.contact
    r = c.round_now[0]
    for i in range(s.n_dofs):
        c.bnd_x[0, i_b, i] = c.bnd_xs[i_b, r, i]


def bound_round(n_lp: int):
    """The stages of a bound round on the gradient path (ContactSolver.steps["bound"]), for the round in
    round_now[0]: the link motion of the solution that the last round (or the friction system) gave, per
    slot in the final system the viscosity from the last round's to the round's, the changes' sums onto the
    system from bank_bound. One kernel for every round (a kernel a round compiled up to 8 times the same
    code); the rounds share bnd_x, the link motion and the bank, so the backward rebuilds round r's
    (BOUND_REBUILD) before its adjoint."""
    # each sum one stage (one top-level loop over envs), as in the passes: with tree, dof and project in
    # one stage, Taichi's adjoint of the round was wrong (a gradient off by a factor 37, against finite
    # differences): Taichi 1.7.4 runs the adjoints of sibling loops of one loop body in their forward order
    # (tests/sibling_loops.py; tests/test_autodiff_rules.py checks every stage it differentiates)
    sums = tuple(bank_stage(op, "bound") for op in (func_bank_tree, func_bank_dof, func_bank_project))
    if n_lp > 0:
        sums += (bank_stage(func_bank_cross, "bound"),)
    return (bank_clear_stage("bound"), func_bound_motion, func_bound_slots) + sums


# What round round_now[0]'s adjoint reads of the forward values that the later rounds overwrote
# (ContactSolver.steps["bound_rebuild"]): its starting solution (the adjoint of its solve), its link motion
# (the slots' laws), and bank_bound as toggle_rebuild rebuilds bank_toggle (rounds.TOGGLE_REBUILD). Its
# slots stage writes the round's viscosities and set again (the same numbers) and sl_eta_now / sl_in_now
# (the report's, read in the forward only).
BOUND_REBUILD = (func_bound_restore, bank_clear_stage("bound"), func_bound_motion, func_bound_slots,
                 bank_stage(func_bank_tree, "bound"), bank_stage(func_bank_dof_vectors, "bound"))
