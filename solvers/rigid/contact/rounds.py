"""Step 2b of the contact solve (see the package docstring), the normal rounds: the normal system's
contacts are those whose linear law pushes at its solution. The second solve's set (the laws that pushed
at the first solve) need not be: a contact dropped there may be driven in by the others. Each round is a
step of an active-set Newton method on the convex energy whose minimiser is the frictionless step with
every law clipped at 0 (func_normal_round): the whole step where the energy falls, else an exact line
search, so the energy falls at every round, no set comes back, and the set is final after finitely many
(2 to 5 in a tumbling pile's steps): at most NORMAL_ROUNDS. A law within its round-off of 0 counts as on
either side (ROUND_OFF_*), so that noise alone does not call a round (it did not rescue float32's grasp
of benchmarks/franka_cube_precision.py, whose forces are noise at that precision). Without gradients the rounds run
in the fused step (func_normal_round_listed, from solve.func_contact_rounds); with gradients their search runs
forward only (ContactSolver.kernel_normal_round) and each round's change of the system is a pass of its
own (toggle_round), recorded with its adjoint."""
import taichi as ti

from .banks import func_bank_add, func_bank_cross, func_bank_dof, func_bank_dof_vectors, func_bank_project, func_bank_tree
from .linalg import func_if_coupled, func_tree_env
from .passes import (ROUND_OFF_F32, ROUND_OFF_F64, bank_clear_stage, bank_stage, func_rel_motion,
                     func_relinearise_clear, func_relinearise_clear_pairs, func_relinearise_cross,
                     func_relinearise_dof, func_relinearise_project, func_relinearise_tree, func_round_slot,
                     func_round_span)

NORMAL_ROUNDS = 8
LINE_ITERS = 60


@ti.func
def func_step_energy(s: ti.template(), i_b, x_new: ti.template(), x_old: ti.template()):
    """p^T A p for p = x_new[0] - x_old[0] and A the system as it stands (mass_mat's tree entries, and
    mass_cross in dense scenes: what the factorisations read)."""
    c = s.contact
    acc = ti.cast(0.0, s.dtype)
    for t in range(s.n_anc):
        i = s.anc_i[t]
        j = s.anc_j[t]
        m = s.mass_mat[i_b, i, j] * (x_new[0, i_b, i] - x_old[0, i_b, i]) * (x_new[0, i_b, j] - x_old[0, i_b, j])
        acc += ti.select(i == j, m, 2.0 * m)
    if ti.static(c.dense):
        if not func_tree_env(s, i_b):  # (mass_cross is not cleared then: linalg.func_tree_env)
            n = s.n_dofs
            for ij in range(n * n):
                i = ij // n
                j = ij % n
                if j < i:
                    acc += 2.0 * c.mass_cross[i_b, i, j] * (x_new[0, i_b, i] - x_old[0, i_b, i]) * (x_new[0, i_b, j] - x_old[0, i_b, j])
    return acc


@ti.func
def func_line_slope(s: ti.template(), i_b, alpha, pAp, pMp):
    """The energy's derivative along the round's step at alpha (0: the round's start, 1: the solution of
    the system as it stands) and its slope there. The energy, in the dof vector x: 1/2 x^T M x - f^T x +
    sum over slots of (law(x))+^2 / (2 W) (M with every term but the contacts', W the law's slope), so its
    derivative along p is -pAp + alpha pMp + sum (d / W) ((c + alpha d)+ - c+), c the law at the start and
    d its change over the step (the start is a point whose in-set is exactly the laws that push there)."""
    c = s.contact
    g = -pAp + alpha * pMp
    dg = pMp
    for k in range(func_round_span(s, i_b)):
        i_s, on = func_round_slot(s, i_b, k)
        W = c.sl_wn_normal[i_b, i_s]
        if on & (W > 0):
            c0 = c.sl_fk[i_b, i_s]
            d = c.sl_de[i_b, i_s]
            f = c0 + alpha * d
            g += d / W * (ti.max(f, 0.0) - ti.max(c0, 0.0))
            if f > 0:
                dg += d * d / W
    return g, dg


@ti.func
def func_full_step_gain(s: ti.template(), i_b, pAp, pMp):
    """The energy's change over the whole step (func_line_slope's energy at 1 minus at 0): 1/2 pMp - pAp
    - sum (d / W) c+ + sum ((c + d)+^2 - c+^2) / (2 W), the linear term from the start's slope -pAp."""
    c = s.contact
    gain = 0.5 * pMp - pAp
    for k in range(func_round_span(s, i_b)):
        i_s, on = func_round_slot(s, i_b, k)
        W = c.sl_wn_normal[i_b, i_s]
        if on & (W > 0):
            c0 = ti.max(c.sl_fk[i_b, i_s], 0.0)
            d = c.sl_de[i_b, i_s]
            c1 = ti.max(c.sl_fk[i_b, i_s] + d, 0.0)
            gain += (0.5 * (c1 * c1 - c0 * c0) - d * c0) / W
    return gain


@ti.func
def func_normal_round(s: ti.template(), i_b, r):
    """Round r of the normal rounds, at the last solve (qacc_normal, its link motion in link_w_normal /
    link_v_normal) from the round's start (qacc_line, its laws' values in sl_fk, its set in
    sl_in_normal): 0 if every slot's law pushes at the solution exactly when the slot is in the system
    (the solution is the energy's minimiser); else the start moves to the minimiser along the step (an
    exact line search of the piecewise linear derivative), the set becomes the laws that push there,
    the slots that change are marked for round r (sl_tog, sl_togin: func_toggle_slot) and their number
    returned (the system is then to be changed by them and solved again)."""
    c = s.contact
    h = c.eval_h[i_b]
    ROUND_OFF = ti.static(ROUND_OFF_F64 if s.dtype == ti.f64 else ROUND_OFF_F32)
    pAp = func_step_energy(s, i_b, c.qacc_normal, c.qacc_line)
    in_sum = ti.cast(0.0, s.dtype)
    change = 0
    for k in range(func_round_span(s, i_b)):
        i_s, on = func_round_slot(s, i_b, k)
        if on:
            spring = c.sl_wn_normal[i_b, i_s] / h * func_rel_motion(
                s, i_b, i_s, c.sl_pos[i_b, i_s], c.link_w_normal, c.link_v_normal).dot(c.sl_n[i_b, i_s])
            e = c.sl_Fn_normal[i_b, i_s] - spring
            d = e - c.sl_fk[i_b, i_s]
            c.sl_de[i_b, i_s] = d
            inside = c.sl_in_normal[i_b, i_s] == 1
            W = c.sl_wn_normal[i_b, i_s]
            if inside & (W > 0):
                in_sum += d * d / W
            # a law within its round-off of 0 (the difference of its two terms, each up to kN where the
            # fixed damper meets a fast approach) is on the right side either way
            tol = ROUND_OFF * (ti.abs(c.sl_Fn_normal[i_b, i_s]) + ti.abs(spring))
            if ti.select(inside, e < -tol, e > tol):
                change += 1
    toggles = 0
    if change > 0:
        pMp = ti.max(pAp - in_sum, 0.0)
        alpha = ti.cast(1.0, s.dtype)
        if func_full_step_gain(s, i_b, pAp, pMp) >= 0:
            # the derivative is continuous, increasing and piecewise linear, -pAp < 0 at 0 and g1 > 0 at 1:
            # Newton's steps within the bracket, halving it where a step leaves it
            tol = ti.static(1e-13 if s.dtype == ti.f64 else 1e-6)
            lo = ti.cast(0.0, s.dtype)
            hi = ti.cast(1.0, s.dtype)
            a = ti.cast(0.0, s.dtype)
            for _it in range(LINE_ITERS):
                g, dg = func_line_slope(s, i_b, a, pAp, pMp)
                if g < 0:
                    lo = a
                else:
                    hi = a
                if (ti.abs(g) <= tol * pAp) | (hi - lo <= tol):
                    break
                nxt = ti.select(dg > 0, a - g / dg, lo)
                if (nxt <= lo) | (nxt >= hi):
                    nxt = 0.5 * (lo + hi)
                a = nxt
            alpha = a
        for k in range(func_round_span(s, i_b)):
            i_s, on = func_round_slot(s, i_b, k)
            if on:
                d = c.sl_de[i_b, i_s]
                f = c.sl_fk[i_b, i_s] + alpha * d
                c.sl_fk[i_b, i_s] = f
                inside = c.sl_in_normal[i_b, i_s] == 1
                if (f > 0) != inside:
                    toggles += 1
                    c.sl_tog[i_b, i_s] = c.sl_tog[i_b, i_s] | (1 << r)
                    if f > 0:
                        c.sl_togin[i_b, i_s] = c.sl_togin[i_b, i_s] | (1 << r)
                    c.sl_in_normal[i_b, i_s] = ti.select(f > 0, 1, 0)
        for i in range(s.n_dofs):
            c.qacc_line[0, i_b, i] = c.qacc_line[0, i_b, i] + alpha * (c.qacc_normal[0, i_b, i] - c.qacc_line[0, i_b, i])
    return toggles


@ti.func
def func_toggle_slot(s: ti.template(), i_b, i_s, r, bank: ti.template()):
    """Slot i_s's change to the normal system in round r (func_normal_round marked it): its linear law
    added where it came in, taken away where it left."""
    c = s.contact
    if (c.sl_tog[i_b, i_s] >> r) & 1 == 1:
        sign = ti.select((c.sl_togin[i_b, i_s] >> r) & 1 == 1, 1.0, -1.0)
        n = c.sl_n[i_b, i_s]
        func_bank_add(s, bank, i_b, i_s, c.sl_pos[i_b, i_s], sign * c.sl_Fn_normal[i_b, i_s] * n,
                      sign * c.sl_wn_normal[i_b, i_s] * n.outer_product(n))


@ti.func
def func_normal_round_listed(s: ti.template(), i_b, r):
    """Without gradients, normal round r if r < NORMAL_ROUNDS (func_normal_round) and, where it changed the
    set, its changes onto the system (func_toggle_sums). Returns 1 if the system is to be solved again."""
    again = 0
    if r < NORMAL_ROUNDS:
        if func_normal_round(s, i_b, r) > 0:
            func_toggle_sums(s, i_b, r)
            again = 1
    return again


@ti.func
def func_toggle_sums(s: ti.template(), i_b, r):
    """Round r's changes onto the system, without gradients (listed slots, bank_relinearise)."""
    c = s.contact
    func_relinearise_clear(s, i_b)
    func_if_coupled(s, i_b, func_relinearise_clear_pairs)
    for k in range(c.n_on[i_b]):
        func_toggle_slot(s, i_b, c.sl_list[i_b, k], r, c.bank_relinearise)
    func_relinearise_tree(s, i_b)
    func_relinearise_dof(s, i_b)
    func_relinearise_project(s, i_b)
    func_if_coupled(s, i_b, func_relinearise_cross)


@ti.func
def func_toggle_slots(s: ti.template(), i_b):
    """The laws of the slots marked for normal round round_now[0] onto bank_toggle (gradient path)."""
    c = s.contact
    r = c.round_now[0]
    for i_s in range(c.n_slots):
        if c.sl_on[i_b, i_s] == 1:
            func_toggle_slot(s, i_b, i_s, r, c.bank_toggle)


def toggle_round(n_lp: int):
    """The stages of a normal round's change on the gradient path (ContactSolver.steps["toggle"]), for the
    round in round_now[0]: the marked slots' laws onto bank_toggle, its sums onto the system. One kernel
    for every round (a kernel a round compiled up to 8 times the same code); the rounds share the bank, so
    the backward rebuilds round r's bank (TOGGLE_REBUILD) before its adjoint."""
    sums = tuple(bank_stage(op, "toggle") for op in (func_bank_tree, func_bank_dof, func_bank_project))
    if n_lp > 0:
        sums += (bank_stage(func_bank_cross, "toggle"),)
    return (bank_clear_stage("toggle"), func_toggle_slots) + sums


# The stages that write bank_toggle alone (ContactSolver.steps["toggle_rebuild"]): cleared, the marked slots'
# laws of round round_now[0], summed up the tree, the dofs' spatial vectors (not their forces). The adjoint of a
# round's sums reads the bank's forward values (which links it touched, the sums that multiply the dofs'
# motion), and the later rounds have overwritten them.
TOGGLE_REBUILD = (bank_clear_stage("toggle"), func_toggle_slots, bank_stage(func_bank_tree, "toggle"),
                  bank_stage(func_bank_dof_vectors, "toggle"))
