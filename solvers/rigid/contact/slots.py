"""The contact stages of an evaluation's dynamics (before the solve): geom poses, broad phase, and per
slot its geometry and normal force with its implicit block, accumulated onto bank_normal; the first solve
of solve.py takes them as they are."""
import taichi as ti

from ..collision import TINY, func_broad_phase, func_geom_pose, func_slot_geometry
from .banks import func_bank_add, func_bank_clear, func_bank_clear_pairs, func_bank_cross, func_bank_dof, func_bank_project, func_bank_tree
from ..kinematics import func_point_velocity
from .linalg import func_tree_env
from .law import func_heavy_scale, func_normal_law, func_rot_corr


# ------------------------------------------------------------------------------------------------
# Dynamics stages (inside the evaluation, before the solve): geometry, and the normal forces with their
# implicit blocks, which the first solve of func_contact_solve takes as they are
# ------------------------------------------------------------------------------------------------
@ti.func
def func_contact_clear(s: ti.template(), i_b, e, src, h):
    c = s.contact
    c.eval_h[i_b] = h
    func_bank_clear(s, c.bank_normal, i_b)


@ti.func
def func_contact_clear_pairs(s: ti.template(), i_b, e, src, h):
    func_bank_clear_pairs(s, s.contact.bank_normal, i_b)


@ti.func
def func_contact_clear_cross(s: ti.template(), i_b, e, src, h):
    """mass_cross <- 0 (with gradients; without, func_contact_cross clears it once the slots stage has told
    whether the evaluation couples two moving links at all, linalg.func_tree_env)."""
    if ti.static(s.requires_grad):
        func_clear_mass_cross(s, i_b)


@ti.func
def func_clear_mass_cross(s: ti.template(), i_b):
    c = s.contact
    for ij in range(s.n_dofs * s.n_dofs):
        c.mass_cross[i_b, ij // s.n_dofs, ij % s.n_dofs] = 0.0


@ti.func
def func_contact_normal(s: ti.template(), i_b, i_s, h, pos, n, depth, u, cand, corr):
    """Normal force and its implicit block of slot i_s (within the contact margin, now or at the end
    of the step), added onto its two links; the slot's data for the friction passes."""
    c = s.contact
    # the normal force is linearised about the depth predicted for the end of the step, so a contact
    # that closes its gap within the step acts in it (speculative contact, see the module docstring)
    # (corr: how much further the rotations close the gap than the linear prediction h u.n says)
    heavy, scale, inv = func_heavy_scale(s, i_b, i_s, n)
    fn_pred, wn, fn_now = func_normal_law(c, depth, depth - h * u.dot(n) - corr, h, heavy, scale, inv)
    # on while the force of the current state pushes (a contact creeping out of a deep overlap, whose
    # predicted force sits at ~0), the predicted one does (a gap closing within the step), or the pair
    # is a candidate (cand: its gap could close within the step if the bodies' motion changes; the
    # first pass linearises it again at the velocity the first solve gives). Beyond the margin "acting" can be
    # the sign of rounding noise in a ~0 force; the first pass treats such a slot as a candidate either way
    # (passes.func_relinearise_share)
    acting = (fn_now > 0) | (fn_pred > 0)
    on = acting | cand
    c.sl_on[i_b, i_s] = ti.select(on, 1, 0)
    c.sl_cand[i_b, i_s] = ti.select(acting, 0, 1)
    if on:
        func_bank_add(s, c.bank_normal, i_b, i_s, pos, fn_pred * n, wn * n.outer_product(n))
        ga = c.slot_ga[i_s]
        gb = c.slot_gb[i_s]
        c.sl_pos[i_b, i_s] = pos
        c.sl_n[i_b, i_s] = n
        c.sl_u[i_b, i_s] = u
        c.sl_Fn[i_b, i_s] = fn_pred
        c.sl_wn[i_b, i_s] = wn
        c.sl_tog[i_b, i_s] = 0
        c.sl_togin[i_b, i_s] = 0
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
    ua = func_point_velocity(s, s.cvel_w, s.cvel_v, i_b, la, pos)
    ub = func_point_velocity(s, s.cvel_w, s.cvel_v, i_b, lb, pos)
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
    hundred slots touch; visiting every slot was an eighth of ANYmal's step), and counts those that couple
    two moving links (n_cross_on: linalg.func_tree_env)."""
    c = s.contact
    if ti.static(s.requires_grad):
        for i_s in range(c.n_slots):
            c.sl_on[i_b, i_s] = 0
            if c.pair_active[i_b, c.slot_pair[i_s]] == 1:
                func_contact_slot(s, i_b, i_s, h)
    else:
        n_on = 0
        n_cross = 0
        for i_p in range(c.n_pairs):
            if c.pair_active[i_b, i_p] == 1:
                for i_s in range(c.pair_s0[i_p], c.pair_s0[i_p + 1]):
                    c.sl_on[i_b, i_s] = 0
                    func_contact_slot(s, i_b, i_s, h)
                    if c.sl_on[i_b, i_s] == 1:
                        c.sl_list[i_b, n_on] = i_s
                        n_on += 1
                        if ti.static(c.dense):
                            if c.slot_lp[i_s] >= 0:
                                n_cross += 1
        c.n_on[i_b] = n_on
        c.n_cross_on[i_b] = n_cross


@ti.func
def func_contact_tree(s: ti.template(), i_b, e, src, h):
    func_bank_tree(s, s.contact.bank_normal, i_b)


@ti.func
def func_contact_dof(s: ti.template(), i_b, e, src, h):
    func_bank_dof(s, s.contact.bank_normal, i_b)


@ti.func
def func_contact_project(s: ti.template(), i_b, e, src, h):
    func_bank_project(s, s.contact.bank_normal, i_b)


@ti.func
def func_contact_cross(s: ti.template(), i_b, e, src, h):
    """The normal bank's coupling of moving link pairs onto mass_cross (without gradients, cleared here, and
    only where a listed slot couples two moving links: else nothing reads it, linalg.func_tree_env)."""
    if ti.static(s.requires_grad):
        func_bank_cross(s, s.contact.bank_normal, i_b)
    else:
        if not func_tree_env(s, i_b):
            func_clear_mass_cross(s, i_b)
            func_bank_cross(s, s.contact.bank_normal, i_b)


CONTACT_STAGES = (func_geom_pose, func_broad_phase, func_contact_clear, func_contact_slots, func_contact_tree,
                  func_contact_dof, func_contact_project)
CROSS_STAGES = (func_contact_clear_pairs, func_contact_clear_cross, func_geom_pose, func_broad_phase,
                func_contact_clear, func_contact_slots, func_contact_tree, func_contact_dof, func_contact_project,
                func_contact_cross)
