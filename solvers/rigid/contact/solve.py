"""The solve of one evaluation with contacts (func_contact_solve): the factorisations and solves of
linalg.py and the passes of passes.py in order; see the package docstring's steps 1 to 4."""
import taichi as ti

from ..inertia import (func_factor_solve, func_factor_to, func_static_factor, func_static_solve, func_static_store,
                       func_static_vec)
from .linalg import (ENV_CANDIDATES, ENV_FINAL, ENV_NORMAL, func_any_solve, func_dense_solve, func_factor_dense_to,
                     func_factor_into, func_tree_env, func_tree_solve)
from .passes import (BOUND_ROUNDS, func_coulomb_listed, func_friction_or_bound, func_keep_for_bound,
                     func_link_motion, func_relinearise_listed)
from .rounds import func_normal_round_listed
from .report import func_contact_report
from ..actuation import func_limit_rounds_next


@ti.func
def func_solve_candidates(s: ti.template(), i_b):
    """qacc_candidates: the system with every candidate normal contact."""
    func_factor_into(s, i_b, s.contact.factor_candidates, ENV_CANDIDATES, s.contact.qacc_candidates)


@ti.func
def func_solve_normal(s: ti.template(), i_b):
    """qacc_normal: the normal system without the contacts that pulled in the first."""
    func_factor_into(s, i_b, s.contact.factor_normal, ENV_NORMAL, s.contact.qacc_normal)


@ti.func
def func_solve_coulomb(s: ti.template(), i_b):
    """dqacc_coulomb = A2^-1 force_coulomb: the response of the normal system to the Coulomb pass's
    forces."""
    c = s.contact
    for i in range(s.n_dofs):
        c.dqacc_coulomb[0, i_b, i] = c.force_coulomb[i_b, i]
    func_any_solve(s, c.factor_normal, ENV_NORMAL, i_b, c.dqacc_coulomb, 0)


@ti.func
def func_contact_solve(s: ti.template(), i_b, e):
    """The solve of a scene with contacts, all stages for one env, in the fused step (no gradients). The
    gradient path's ContactSolver.factor_solve launches the same steps one by one; here (nothing reads the
    intermediate factors and solutions back) the same results are computed with less work:
    - the passes visit the slots listed by func_contact_slots, not all the scene's slots;
    - an env with no slot on skips to the final solve (every pass adds nothing: A3 = A1 = M);
    - the first solve goes to factor_normal / qacc_normal and its link motion to link_w_normal /
      link_v_normal; when the relinearise pass changes nothing (no candidate, no dropped contact: its
      sums are exact zeros, A2 == A1 and force unchanged) those are the second solve's and its motion,
      and the relinearise pass's sums, the second factorisation and solve and the Coulomb pass's link
      motion are skipped;
    - the bound rounds stop at the first that changes no viscosity (it added exact zeros: solving
      again would give the same qacc), as on the gradient path (ContactSolver.factor_solve);
    - in a dense scene, an env whose listed slots couple no two moving links factors and solves M's tree
      (linalg.func_tree_env), unrolled in a specialised core (func_round_unrolled)."""
    c = s.contact
    # a scene built for gradients never runs the fused step (RigidSolver._fused: op by op, through
    # ContactSolver.factor_solve, whose sequence of launches its adjoint replays)
    ti.static_assert(not s.requires_grad, "func_contact_solve is the fused step's, without gradients")
    if ti.static(s.unrolled and not c.dense):
        func_contact_rounds(s, i_b, e, func_round_unrolled, ti.Vector.zero(s.dtype, s.static_tree.n_lower))
    elif ti.static(s.unrolled):
        # a dense scene's env whose listed slots couple no two moving links (linalg.func_tree_env)
        if func_tree_env(s, i_b):
            func_contact_rounds(s, i_b, e, func_round_unrolled, ti.Vector.zero(s.dtype, s.static_tree.n_lower))
        else:
            func_contact_rounds(s, i_b, e, func_round_solve, ti.Vector.zero(s.dtype, 1))
    else:
        func_contact_rounds(s, i_b, e, func_round_solve, ti.Vector.zero(s.dtype, 1))
    func_contact_report(s, i_b, e)


@ti.func
def func_contact_rounds(s: ti.template(), i_b, e, round_solve: ti.template(), L):
    """func_contact_solve's steps as rounds of one loop, each round's factor and solve by round_solve
    (func_round_solve: linalg.py's, dense or tree; func_round_unrolled: the unrolled tree of a specialised
    core, its factor L carried from round to round): round 0 factors A1 and solves into qacc_normal;
    round 1 (only when the relinearise pass changed something) A2, into qacc_normal, and again after each
    normal round that changed the system; round 2 solves the Coulomb response dqacc_coulomb with the last
    factor; round 3 factors A3 and solves into qacc[e], and again after each bound round that changed the
    system and each joint-limit round (actuation.func_limit_release). So each factorisation and solve is
    compiled once, not three and four times (the dense ones alone took ~4 s of LLVM code generation in every
    process: two spheres on a plane, 7.6 -> 4.0 s to the first step from the kernel cache)."""
    c = s.contact
    rnd = 0
    rounds = 0
    normal_rounds = 0
    limit_round = 0
    if c.n_on[i_b] == 0:
        rnd = 3
    while rnd < 4:
        L = round_solve(s, i_b, e, rnd, L)
        phase = 0
        if rnd == 3:
            rnd = 4
            if limit_round > 0:  # a limit round's solve: no bound rounds after it
                phase = 3
            elif (c.n_on[i_b] > 0) & (rounds < BOUND_ROUNDS):
                rounds += 1
                func_keep_for_bound(s, i_b, e)
                phase = 2
        elif rnd == 2:
            phase = 1
        else:
            func_link_motion(s, c.qacc_normal, 0, i_b, c.link_w_normal, c.link_v_normal)
            nxt = 2
            if rnd == 0:
                if func_relinearise_listed(s, i_b):
                    func_start_line(s, i_b, c.qacc_normal)
                    nxt = 1
            elif func_normal_round_listed(s, i_b, normal_rounds) == 1:
                normal_rounds += 1
                nxt = 1
            if nxt == 2:
                func_coulomb_listed(s, i_b)
            rnd = nxt
        if (phase == 1) | (phase == 2):
            if func_friction_or_bound(s, i_b, phase) == 1:
                rnd = 3
        if rnd == 4:  # the final solution: solve again while it releases a limit constraint that pulls
            limit_round = func_limit_rounds_next(s, i_b, e, limit_round)
            if limit_round > 0:
                rnd = 3


@ti.func
def func_round_solve(s: ti.template(), i_b, e, rnd, L):
    """Round rnd's factor and solve (func_contact_rounds; L passes through): the tree ones where func_tree_env
    says the system is M's tree (into factor_normal, or inertia's final solve into mass_fac), else the dense
    ones, one copy for every round: the factor into mass_fac over envelope ENV_NORMAL (rounds 0, 1; round 2
    solves with it) or ENV_FINAL (round 3), the solve in solve_tmp, copied to its round's field. (Nothing
    reads the normal factor back in this path: the gradient path keeps it in factor_normal for its adjoints.)
    The tree branches call the tree forms directly, on purpose, not func_factor_into / func_solve_coulomb:
    in a dense scene those would inline the dense forms again at every call, which is what this function
    is for (each inlined copy is code-generated again in every process)."""
    c = s.contact
    dense = False
    if ti.static(c.dense):
        dense = not func_tree_env(s, i_b)
    if dense:
        if ti.static(c.dense):
            k = ti.select(rnd == 3, ENV_FINAL, ENV_NORMAL)
            if rnd != 2:
                func_factor_dense_to(s, i_b, s.mass_fac, k)
            for i in range(s.n_dofs):
                c.solve_tmp[0, i_b, i] = ti.select(rnd == 2, c.force_coulomb[i_b, i], s.force[i_b, i])
            func_dense_solve(s, s.mass_fac, k, i_b, c.solve_tmp, 0)
            for i in range(s.n_dofs):
                y = c.solve_tmp[0, i_b, i]
                if rnd == 3:
                    s.qacc[e, i_b, i] = y
                elif rnd == 2:
                    c.dqacc_coulomb[0, i_b, i] = y
                else:
                    c.qacc_normal[0, i_b, i] = y
    elif rnd == 3:
        func_factor_solve(s, i_b, e)
    elif rnd == 2:
        for i in range(s.n_dofs):
            c.dqacc_coulomb[0, i_b, i] = c.force_coulomb[i_b, i]
        func_tree_solve(s, c.factor_normal, i_b, c.dqacc_coulomb, 0)
    else:
        func_factor_to(s, i_b, c.factor_normal)
        for i in range(s.n_dofs):
            c.qacc_normal[0, i_b, i] = s.force[i_b, i]
        func_tree_solve(s, c.factor_normal, i_b, c.qacc_normal, 0)
    return L


@ti.func
def func_start_line(s: ti.template(), i_b, x: ti.template()):
    """qacc_line <- x[0] (the first solve's solution: where the normal rounds start)."""
    c = s.contact
    for i in range(s.n_dofs):
        c.qacc_line[0, i_b, i] = x[0, i_b, i]


@ti.func
def func_round_unrolled(s: ti.template(), i_b, e, rnd, L):
    """Round rnd's factor and solve (func_contact_rounds) for a core that unrolls the tree factorisation
    (inertia.TreeSchedule): the factor stays a local between rounds (L, returned: round 2 solves with the
    last one), and the solution goes to qacc_normal (rounds 0, 1), dqacc_coulomb (2) or qacc[e] (3)."""
    c = s.contact
    F = L
    b = ti.Vector.zero(s.dtype, s.static_tree.n)
    if rnd == 2:
        b = func_static_vec(s, c.force_coulomb, i_b)
    else:
        F = func_static_factor(s, i_b)
        b = func_static_vec(s, s.force, i_b)
    y = func_static_solve(s, F, b)
    if rnd == 3:
        func_static_store(s, y, s.qacc, e, i_b)
    elif rnd == 2:
        func_static_store(s, y, c.dqacc_coulomb, 0, i_b)
    else:
        func_static_store(s, y, c.qacc_normal, 0, i_b)
    return F
