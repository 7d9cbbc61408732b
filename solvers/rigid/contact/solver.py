"""ContactSolver: the fields of the contact model on a RigidCore, its loading, and the launches of the
solve op (factor_solve) and of its adjoint (solve_grad)."""
import warnings

import numpy as np
import taichi as ti

from ... import taichi_compat
from ..collision import (N_HULL_CORNERS, N_HULL_EDGES, N_HULLFACE, N_KDOP, func_broad_phase, func_geom_pose, geom_box_columns,
                         geom_rotations)
from ..kinematics import LINK_STATE
from ..layout import FieldTree, ZeroPlan, by_env_axis, func_zero_plan
from .banks import AccBank
from .law import MARGIN_WIDTHS
from .linalg import ENV_BOUND, ENV_CANDIDATES, ENV_FINAL, ENV_NORMAL, N_ENV, func_solve_adjoint
from .passes import (BOUND_REBUILD, BOUND_ROUNDS, COULOMB_PASS, FRICTION_PASS, FRICTION_PASS_CROSS,
                     RELINEARISE_PASS, RELINEARISE_PASS_CROSS, bound_round, func_bound_count, func_link_motion)
from .rounds import NORMAL_ROUNDS, TOGGLE_REBUILD, func_normal_round, toggle_round
from .plan import C_CROSS, C_GEOMS, C_LP, C_PAIRS, C_SLOTS, N_CCFG_I, ContactPlan
from .report import (MAX_DEEP_WARNINGS, ContactPenetrationWarning, _user_stacklevel, deep_contact_message, func_contact_report,
                     geom_half_thickness)
from .slots import CONTACT_STAGES, CROSS_STAGES
from .solve import func_solve_coulomb, func_solve_candidates, func_solve_normal


def _runtime(index):
    """A size of the scene a ContactSolver holds: that scene's number in Python scope, a read of the
    solver's cfg field inside a kernel being compiled (as core._runtime)."""

    def get(self):
        if taichi_compat.inside_kernel() and not self.static_sizes:
            return taichi_compat.subscript(self.cfg_i, index)
        return self.plan.cfg_i[index]

    return property(get)


class WatchClock:
    """When ContactSolver.watch reads the device (one int, ~15 us): after each of the first 16 steps,
    then after every 16th, never once it has warned MAX_DEEP_WARNINGS times. A plain object, so that
    the fused step's Python asks it without the ~1 us that each attribute of a data-oriented class costs."""
    __slots__ = ("n", "done")

    def __init__(self):
        self.reset()

    def reset(self):
        self.n, self.done = 0, False

    def due(self) -> bool:
        self.n += 1
        return not self.done and (self.n <= 16 or self.n % 16 == 0)


@ti.data_oriented
class ContactSolver:
    """Fields and stages of the contact model of a RigidSolver (see the module docstring).

    The fields are sized by a contact class (the capacities and static flags of a ContactPlan, on one
    RigidCore) and the scene's sizes and constants are read at run time from cfg_i / cfg_f, so a later
    scene whose plan fits (same flags, capacities no larger) takes this solver, with the kernels already
    compiled on it, from the pool (pool.POOL) and compiles nothing: `load` puts its plan in."""

    n_geoms = _runtime(C_GEOMS)
    n_pairs = _runtime(C_PAIRS)
    n_slots = _runtime(C_SLOTS)
    n_lp = _runtime(C_LP)
    n_cross = _runtime(C_CROSS)

    def __init__(self, core, plan: ContactPlan):
        self.plan = plan
        self.caps, self.flags = plan.caps, plan.flags
        (self.dense, self.has_rim, self.has_segseg, self.has_boxedge, self.has_boxface, self.has_hulledge,
         self.sdf_types, consts, self.static_sizes) = plan.flags
        self.baked_sizes = tuple(plan.cfg_i)
        self.k, self.d, self.zeta, self.delta, self.eps, self.load_shift, self.slip_accel = consts
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
        self.geom_kdop_dir = V3((G, N_KDOP), False)  # the planes' normals (collision.hull_planes)
        # a box around the collision volume (geoms.mesh_box, primitive_box): centre, axes (columns), half sizes
        self.geom_obb_c, self.geom_obb_A, self.geom_obb_h = V3(G, False), M3(G, False), V3(G, False)
        # the friction parameter [env, geom]; the scene sees its block through geom_friction
        self.geom_mu = F((B, G))
        self.link_dyn = I(L)
        # the contact damper's weights of the links (law.func_heavy_scale, set_link_weights): whether a link's
        # inverse mass is its own 1 / mass (1), else its 3x3 inverse weight at the centre of mass through the
        # articulation at the initial configuration (link_W)
        self.link_wmass = I(L)
        self.link_W = M3(L, False)
        # pairs and slots
        self.pair_ga, self.pair_gb = I(Pn), I(Pn)
        # the pair's slots: pair_s0[p] .. pair_s0[p + 1] - 1 (build_slots stores them by pair)
        self.pair_s0 = I(Pn + 1)
        self.pair_active = I((B, Pn))
        # per pair and side, the plane that parted two meshes in their last broad-phase test (a hint:
        # narrow.func_gap_mesh_planes starts there; no result depends on it)
        self.pair_hint = I((B, Pn, 2))
        # a box pair's separating-axis test (collision.func_box_pair_test: the broad phase's, for the active box
        # pairs; their edge and face slots read it)
        self.pair_box = I((B, Pn) if self.has_boxedge else 1)
        # the convex volumes of the geoms of hull-edge pairs (collision.polytope_hull, in the geom frame): their
        # planes' normals and offsets, corners, edges (two ends, the normals of the two faces that meet there)
        # and how many of each (hull_n [g] = planes, corners, edges); and a pair's separating-axis test of the
        # two volumes (narrow.func_hull_pair_test: the broad phase's, for the active pairs)
        Gh = G if self.has_hulledge else 1
        self.hull_pn, self.hull_pd = V3((Gh, N_KDOP), False), F((Gh, N_KDOP), False)
        self.hull_c = V3((Gh, N_HULL_CORNERS), False)
        self.hull_e0, self.hull_e1 = V3((Gh, N_HULL_EDGES), False), V3((Gh, N_HULL_EDGES), False)
        self.hull_f1, self.hull_f2 = V3((Gh, N_HULL_EDGES), False), V3((Gh, N_HULL_EDGES), False)
        self.hull_n = I((Gh, 3))
        self.hull_kappa = F(Gh, False)  # its SDF outside over the distance, at least (collision.sdf_distance_ratio)
        self.hull_ef = I((Gh, N_HULL_EDGES, 2))  # the planes of an edge's two faces (indices into hull_pn)
        self.pair_hull = I((B, Pn) if self.has_hulledge else 1)
        # face on face: the crossings of the incident face's edges with the reference face's rim that the pair's
        # test found (narrow.func_hull_face_crossings; -1: none), one per hull-face slot
        self.pair_hcross = I((B, Pn, N_HULLFACE) if self.has_hulledge else 1)
        # the broad phase's per-geom terms (narrow.func_broad_phase): bounding sphere centre, world box half
        # widths, centre speed, rotation sweep
        self.geom_bc, self.geom_ext = V3((B, G), False), V3((B, G), False)
        self.geom_speed, self.geom_sweep = F((B, G), False), F((B, G), False)
        self.slot_pair, self.slot_kind, self.slot_ga, self.slot_gb = I(S), I(S), I(S), I(S)
        self.slot_p = V3(S, False)
        self.slot_r, self.slot_aux = F(S, False), F(S, False)
        # per evaluation: geom poses, the touching slots' data (normal model, for the passes), the
        # accumulators (banks.py) of the normal forces, of the relinearise pass's changes, of the Coulomb
        # forces and of the friction pass's changes, and the solves' vectors (solve.py: "candidates" is
        # the first solve's system, with every candidate contact; "normal" the second, frictionless one)
        self.geom_xpos, self.geom_xR = V3((B, G)), M3((B, G))
        self.eval_h = F(B, False)
        self.sl_on = I((B, S))
        self.sl_pos, self.sl_n, self.sl_u = V3((B, S)), V3((B, S)), V3((B, S))
        self.sl_u_normal = V3((B, S))
        self.sl_Fn, self.sl_wn, self.sl_mu, self.sl_load = F((B, S)), F((B, S)), F((B, S)), F((B, S))
        # friction's load with RigidOptions(friction_load="coulomb") (passes.func_friction_slot)
        self.sl_load_c = F((B, S))
        self.sl_depth, self.sl_Fn_normal, self.sl_wn_normal = F((B, S)), F((B, S)), F((B, S))
        self.sl_corr = F((B, S))
        # sl_*_normal: the slot in the normal (second) system: its linear law there, and whether it is in
        # it (the relinearise pass kept it); sl_u_normal, sl_load: the velocity and the normal force of
        # the normal solve (Coulomb's load); sl_in_final: still in after the friction pass
        self.sl_in_normal, self.sl_cand = I((B, S)), I((B, S))
        # the normal rounds (rounds.func_normal_round): each slot's law at the rounds' current start and
        # its change over a round's step; the rounds in which the slot changed sides (bit r) and came in
        # (bit r of sl_togin); the start (a dof vector); whether an env's rounds are over (gradient path)
        self.sl_fk, self.sl_de = F((B, S), False), F((B, S), False)
        self.sl_tog, self.sl_togin = I((B, S)), I((B, S))
        self.qacc_line = F((1, B, D), False)
        self.line_done = I(B)
        # without gradients: the slots that are on, in slot order (func_contact_slots), and their count
        self.sl_list, self.n_on = I((B, S)), I(B)
        # dense scenes without gradients: how many listed slots couple two moving links (linalg.func_tree_env:
        # none, and the evaluation's system is M's tree, solved as in a scene without such pairs)
        self.n_cross_on = I(B)
        self.bank_normal = AccBank(B, L, D, n_lp, f, g, True)
        self.bank_relinearise = AccBank(B, L, D, n_lp, f, g, True)
        self.bank_coulomb = AccBank(B, L, D, 0, f, g, False)
        self.bank_friction = AccBank(B, L, D, n_lp, f, g, True)
        # by pass, for the passes' bank stages (passes.bank_stage)
        self.banks = {"normal": self.bank_normal, "relinearise": self.bank_relinearise, "coulomb": self.bank_coulomb,
                      "friction": self.bank_friction}
        # qacc_*: a solve's dof vector (h-scaled acceleration); dqacc_coulomb: the normal system's response
        # to force_coulomb (J^T of the Coulomb pass's forces); link_w_* / link_v_*: the link motion of a
        # dof vector (passes.func_link_motion)
        self.qacc_candidates = F((1, B, D))
        self.qacc_normal = F((1, B, D))
        self.dqacc_coulomb = F((1, B, D))
        self.force_coulomb = F((B, D))
        self.link_w_candidates, self.link_v_candidates = V3((B, L)), V3((B, L))
        self.link_w_normal, self.link_v_normal = V3((B, L)), V3((B, L))
        self.link_w_coulomb, self.link_v_coulomb = V3((B, L)), V3((B, L))
        self.factor_candidates, self.factor_normal = F((B, D, D), False), F((B, D, D), False)
        # sl_eta: the friction pass's viscosities; sl_eta_now: those in the system now (after the bound
        # rounds: the report's)
        self.sl_eta, self.sl_eta_now, self.sl_in_final = F((B, S)), F((B, S), False), I((B, S))
        # sl_in_now: in the final system now (the bound rounds release a law that pulls and bring back one
        # that pushes again: passes.func_release_slot); sl_rel: a round's changes (without gradients)
        self.sl_in_now, self.sl_rel = I((B, S)), I((B, S))
        self.sl_back = I((B, S))  # brought back once this step (it is not again)
        # the bound rounds on the gradient path (passes.bound_round, one kernel for every round, the round in
        # round_now[0]): the round's starting solution (bnd_x; every round's kept in bnd_xs, and the factor
        # it was solved with in bnd_fac, for the backward), its link motion, its bank (shared by the rounds);
        # round r's viscosities and set at [env, r + 1] of bnd_eta / bnd_in, its choices at [env, r] of
        # bnd_rel (without gradients the rounds reuse the report's link motion and bank_friction)
        K = BOUND_ROUNDS if g else 0
        self.bound_rounds = K
        if g:
            self.bnd_x, self.bnd_xs = F((1, B, D)), F((B, K, D), False)
            self.bnd_fac, self.bnd_fac_now = F((B, K, D, D), False), F((B, D, D), False)
            self.bnd_w, self.bnd_v = V3((B, L)), V3((B, L))
            self.bnd_eta, self.bnd_in, self.bnd_rel = F((B, K + 1, S)), I((B, K + 1, S)), I((B, K, S))
            self.bank_bound = AccBank(B, L, D, n_lp, f, g, True)
            self.banks["bound"] = self.bank_bound
        self.rounds = 0  # the bound rounds the last factor_solve recorded
        # the normal rounds' changes on the gradient path (rounds.toggle_round): one bank for every round, the
        # round in round_now[0]
        self.bank_toggle = AccBank(B, L, D, n_lp, f, g, True) if g else None
        self.round_now = I(1)
        self.normal_rounds = 0  # the normal rounds the last factor_solve recorded
        if g:
            self.banks["toggle"] = self.bank_toggle
        self.link_w_report, self.link_v_report = V3((B, L), False), V3((B, L), False)
        self.solve_tmp = F((1, B, D), False)
        # placeholders where the scene has no pairs of moving links (kernel_load's arguments)
        self.slot_lp = I(S)
        self.cross_i, self.cross_j, self.cross_lp = I(max(n_cross, 1)), I(max(n_cross, 1)), I(max(n_cross, 1))
        self.cross_fac = F(max(n_cross, 1), False)
        if self.dense:
            self.mass_cross = F((B, D, D))
            # the envelopes of the three dense factors (linalg.ENV_*): each row's first nonzero column, and
            # each column's last row that reaches it
            self.env_first, self.env_last = I((B, N_ENV + K, D)), I((B, N_ENV + K, D))
            # the order of the dense factorisation (plan._dense_order: position k holds dof dense_perm[k]), and
            # the solves' right-hand side in that order
            self.dense_perm, self.perm_tmp = I(D), F((B, D), False)
        # outputs of the last evaluation (read by the entity API; no gradient)
        self.c_pos, self.c_normal, self.c_force = V3((B, S), False), V3((B, S), False), V3((B, S), False)
        self.c_depth, self.c_fn = F((B, S), False), F((B, S), False)
        # the deep-penetration watch: evaluations per env, each env's first deep contact ([hit, slot,
        # evaluation], [depth at the end of the step, approach speed, limit, depth gained in the step /
        # limit]), any env's
        self.eval_count = I(B)
        self.deep_i, self.deep_f, self.deep_any = I((B, 3)), F((B, 4), False), I(1)
        # the pairs the watch has warned about (not recorded again), and how many it has
        self.pair_warned = I(Pn)
        self.n_deep_warned = 0
        self.clock = WatchClock()
        self.tree = tree.finalize()

        self.stages = CONTACT_STAGES
        self.relinearise_pass, self.friction_pass = RELINEARISE_PASS, FRICTION_PASS
        # adjoints cleared before each solve's backward (read from the passes' backward onwards)
        self.scratch_grad_fields = ([self.sl_pos, self.sl_n, self.sl_u, self.sl_u_normal, self.sl_Fn, self.sl_depth,
                                     self.sl_corr, self.sl_Fn_normal, self.sl_wn_normal,
                                     self.sl_wn, self.sl_mu, self.sl_load, self.qacc_candidates, self.qacc_normal,
                                     self.dqacc_coulomb, self.force_coulomb, self.link_w_candidates,
                                     self.link_v_candidates, self.link_w_normal, self.link_v_normal,
                                     self.link_w_coulomb, self.link_v_coulomb]
                                    + self.bank_relinearise.grad_fields + self.bank_coulomb.grad_fields
                                    + self.bank_friction.grad_fields + [self.sl_eta, self.bnd_x, self.bnd_w,
                                                                        self.bnd_v, self.bnd_eta]
                                    + self.bank_bound.grad_fields
                                    + self.bank_toggle.grad_fields
                                    + ([self.sl_load_c] if self.load_shift > 0.0 else [])
                                    ) if g else []
        # zeroed in one loop over the envs, a group of fields per shape of the rest (a loop per field made
        # the kernel one task per field: 238 in a scene of boxes, 26 s of its 200 s cold compile; 3 s now,
        # the gradients the same to the bit, the launch 2.8 against 3.1 ms; measured 2026-12-02)
        self.scratch_grad_plan = ZeroPlan((), (), 0, *by_env_axis([x.grad for x in self.scratch_grad_fields], B))
        # the adjoints the scene zeroes before each backward (fields [env, ...]); the scratch ones above
        # are zeroed before every solve's adjoint instead
        self.grad_fields = ([self.geom_mu, self.geom_xpos, self.geom_xR] + self.bank_normal.grad_fields) if g else []
        if self.dense:
            self.stages = CROSS_STAGES
            self.relinearise_pass, self.friction_pass = RELINEARISE_PASS_CROSS, FRICTION_PASS_CROSS
            if g:
                self.grad_fields += [self.mass_cross]
        # the launches of the solve op on the gradient path (factor_solve), by name: kernel_run(s, name)
        self.steps = {"solve_candidates": (func_solve_candidates,), "relinearise_pass": self.relinearise_pass,
                      "solve_normal": (func_solve_normal,), "coulomb_pass": COULOMB_PASS,
                      "solve_coulomb": (func_solve_coulomb,), "friction_pass": self.friction_pass}
        if g:
            self.steps.update({"toggle": toggle_round(n_lp), "toggle_rebuild": TOGGLE_REBUILD,
                               "bound": bound_round(n_lp), "bound_rebuild": BOUND_REBUILD})
            # the shared fields' adjoints, zeroed between two rounds' adjoints
            self.toggle_grad_plan = ZeroPlan((), (), 0, *by_env_axis([x.grad for x in self.bank_toggle.grad_fields], B))
            self.bound_grad_plan = ZeroPlan((), (), 0, *by_env_axis(
                [x.grad for x in [self.bnd_x, self.bnd_w, self.bnd_v] + self.bank_bound.grad_fields], B))

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
                                 np.minimum(geom_half_thickness(geoms), 1e30)[:, None], *geom_box_columns(geoms)], -1)
        self.clock.reset()
        self.n_deep_warned = 0
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
                         c(geoms.kdop_dirs, npf),
                         c(np.broadcast_to(geoms.friction, (n_envs, G)), npf), dyn,
                         c([[p[0], p[1], s0] for p, s0 in zip(plan.pairs, pair_s0)], np.int32),
                         c(pair_s0[-1:], np.int32), slot_i, c(slot_f, npf),
                         c([x[:3] for x in cross], np.int32), c([x[3] for x in cross], npf),
                         c(plan.np_dense_perm, np.int32))
        if self.has_hulledge:
            hp, hc, he = np.zeros((G, N_KDOP, 4)), np.zeros((G, N_HULL_CORNERS, 3)), np.zeros((G, N_HULL_EDGES, 4, 3))
            hn, hf = np.zeros((G, 3), dtype=np.int32), np.zeros((G, N_HULL_EDGES, 2), dtype=np.int32)
            for g, (planes, corners, edges, faces) in plan.hulls.items():
                hn[g] = len(planes), len(corners), len(edges)
                hp[g, : len(planes)], hc[g, : len(corners)], he[g, : len(edges)] = planes, corners, edges
                hf[g, : len(edges)] = faces
            hk = np.ones(G)
            hk[list(plan.hull_kappa)] = list(plan.hull_kappa.values())
            self.kernel_load_hulls(c(hp, npf), c(hc, npf), c(he, npf), hn, hf, c(hk, npf))

    @ti.kernel
    def kernel_load_hulls(self, hp: ti.types.ndarray(), hc: ti.types.ndarray(), he: ti.types.ndarray(),
                          hn: ti.types.ndarray(), hf: ti.types.ndarray(), hk: ti.types.ndarray()):
        """The convex volumes of the hull-edge pairs' geoms into the hull_* fields."""
        for g in range(hn.shape[0]):
            self.hull_kappa[g] = hk[g]
            for k in ti.static(range(3)):
                self.hull_n[g, k] = hn[g, k]
            for m in range(N_HULL_EDGES):
                for k in ti.static(range(2)):
                    self.hull_ef[g, m, k] = hf[g, m, k]
            for m in range(N_KDOP):
                self.hull_pd[g, m] = hp[g, m, 3]
                for k in ti.static(range(3)):
                    self.hull_pn[g, m][k] = hp[g, m, k]
            for m in range(N_HULL_CORNERS):
                for k in ti.static(range(3)):
                    self.hull_c[g, m][k] = hc[g, m, k]
            for m in range(N_HULL_EDGES):
                for k in ti.static(range(3)):
                    self.hull_e0[g, m][k] = he[g, m, 0, k]
                    self.hull_e1[g, m][k] = he[g, m, 1, k]
                    self.hull_f1[g, m][k] = he[g, m, 2, k]
                    self.hull_f2[g, m][k] = he[g, m, 3, k]

    @ti.kernel
    def kernel_load(self, cfg_i: ti.types.ndarray(), geom_i: ti.types.ndarray(),
                    geom_f: ti.types.ndarray(), kdop: ti.types.ndarray(), kdop_dir: ti.types.ndarray(),
                    mu: ti.types.ndarray(),
                    dyn: ti.types.ndarray(), pair: ti.types.ndarray(), pair_end: ti.types.ndarray(), slot_i: ti.types.ndarray(),
                    slot_f: ti.types.ndarray(), cross_i: ti.types.ndarray(), cross_f: ti.types.ndarray(),
                    perm: ti.types.ndarray()):
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
            for k in ti.static(range(3)):
                self.geom_obb_c[g][k] = geom_f[g, 21 + k]
                self.geom_obb_h[g][k] = geom_f[g, 33 + k]
            for k, l in ti.static(ti.ndrange(3, 3)):
                self.geom_obb_A[g][k, l] = geom_f[g, 24 + 3 * k + l]
            for k in range(kdop.shape[1]):
                self.geom_kdop[g, k] = kdop[g, k]
                for d in ti.static(range(3)):
                    self.geom_kdop_dir[g, k][d] = kdop_dir[g, k, d]
        for i_b, g in ti.ndrange(mu.shape[0], mu.shape[1]):
            self.geom_mu[i_b, g] = mu[i_b, g]
        for i in range(dyn.shape[0]):
            self.link_dyn[i] = dyn[i]
        for i in range(self.link_wmass.shape[0]):
            self.link_wmass[i] = 1  # until set_link_weights: each link its own mass
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
        if ti.static(self.dense):
            for k in range(self.dense_perm.shape[0]):
                self.dense_perm[k] = k  # past the scene's dofs: themselves
                if k < perm.shape[0]:
                    self.dense_perm[k] = perm[k]
        for I in ti.grouped(self.qacc_candidates):
            self.qacc_candidates[I] = 0.0
            self.qacc_normal[I] = 0.0
            self.dqacc_coulomb[I] = 0.0
        for i_b in range(self.eval_count.shape[0]):
            self.eval_count[i_b] = 0
        for i_b in range(self.deep_i.shape[0]):
            self.deep_i[i_b, 0] = 0
        self.deep_any[0] = 0
        for i_p in range(self.pair_warned.shape[0]):
            self.pair_warned[i_p] = 0

    def set_link_weights(self, W, own_mass):
        """The links' weights for the mass-relative contact damper (law.func_heavy_scale): W (n_links, 3, 3)
        the inverse weight of each link's centre of mass through its articulation (1/kg, in the solver's float
        type), own_mass (n_links,) 1 where a link's own 1 / mass is used instead."""
        self._kernel_link_weights(np.ascontiguousarray(W),
                                  np.ascontiguousarray(own_mass, dtype=np.int32))

    @ti.kernel
    def _kernel_link_weights(self, W: ti.types.ndarray(), own_mass: ti.types.ndarray()):
        for l in range(own_mass.shape[0]):
            self.link_wmass[l] = own_mass[l]
            for a, b in ti.static(ti.ndrange(3, 3)):
                self.link_W[l][a, b] = W[l, a, b]

    @ti.kernel
    def kernel_rearm(self, i_p: ti.i32):
        """After a warning about pair i_p: not that pair again, and the record open for another."""
        self.pair_warned[i_p] = 1
        for i_b in range(self.deep_i.shape[0]):
            self.deep_i[i_b, 0] = 0
        self.deep_any[0] = 0

    @property
    def geom_friction(self):
        """The friction parameter as the scene's (n_envs, n_geoms) block (to_numpy / load)."""
        return _FrictionBlock(self)

    @ti.kernel
    def kernel_set_friction(self, v: ti.types.ndarray()):
        for i, j in ti.ndrange(v.shape[0], v.shape[1]):
            self.geom_mu[i, j] = v[i, j]

    # ------------------------------------------------------------------ the solve op
    # With contacts, the solve of an evaluation is a sequence of launches (see func_contact_solve, which
    # the fused step runs inside its own kernel). The passes modify force, mass_mat and mass_cross in
    # place (A2 = A1 + the relinearise pass's changes, A3 = A2 + the friction pass's), so backward
    # reads each pass's adjoint off
    # the matrix adjoint accumulated by the solves after it. Backward: the hand-written adjoints of the
    # solves and Taichi's of the passes, in reverse order.
    def factor_solve(self, s, e: int):
        """qacc[e] of the evaluation e whose dynamics stages just ran (the solve op of the schedule). The
        bound rounds are recorded while one would change a viscosity or release a pulling law
        (kernel_bound_count; a round that changes none adds exact zeros and solves the same system again,
        so stopping there changes no number, and the fused step stops at the same round)."""
        for which in ("solve_candidates", "relinearise_pass", "solve_normal"):
            self.kernel_run(s, which)
        # the normal rounds, while one changes an env's system (as the fused step's, which stops each env
        # at its first round that changes nothing: an env done here is left alone by the later rounds)
        self.normal_rounds = 0
        while self.normal_rounds < NORMAL_ROUNDS and self.kernel_normal_round(s, self.normal_rounds) > 0:
            self.round_now[0] = self.normal_rounds
            self.kernel_run(s, "toggle")
            self.kernel_run(s, "solve_normal")
            self.normal_rounds += 1
        for which in ("coulomb_pass", "solve_coulomb", "friction_pass"):
            self.kernel_run(s, which)
        s.kernel_mass_solve(e, False)
        self.rounds = 0
        while self.rounds < self.bound_rounds and self.kernel_bound_count(s, e, self.rounds) > 0:
            self.kernel_bound_keep(s, e, self.rounds)
            self.round_now[0] = self.rounds
            self.kernel_run(s, "bound")
            s.kernel_mass_solve(e, False)
            self.rounds += 1
        s.release_limits(e)
        self.kernel_report(s, e)

    def solve_grad(self, s, e: int):
        """Adjoint of factor_solve, with its forward values in the fields (its last run's rounds)."""
        if self.scratch_grad_fields:
            self.kernel_clear_grads(s, self.scratch_grad_plan)
        s.kernel_mass_solve(e, True)
        for r in reversed(range(self.rounds)):
            self._round_grad(s, "bound", r, self.rounds, self.bound_grad_plan)
            self.kernel_adjoint_bound_solve(s, r)
        self.kernel_run.grad(s, "friction_pass")
        self.kernel_adjoint_solve(s, 2)
        self.kernel_run.grad(s, "coulomb_pass")
        self.kernel_adjoint_solve(s, 1)
        # the rounds' solves before the last feed only their choices of slots (no gradient); the system
        # the last one solved is the relinearise pass's plus every round's change
        for r in reversed(range(self.normal_rounds)):
            self._round_grad(s, "toggle", r, self.normal_rounds, self.toggle_grad_plan)
        self.kernel_run.grad(s, "relinearise_pass")
        self.kernel_adjoint_solve(s, 0)

    def _round_grad(self, s, step: str, r: int, n: int, plan):
        """The adjoint of round r of the n rounds of `step` ("toggle" or "bound": one kernel for every round,
        the round in round_now[0]) that the last factor_solve recorded. The rounds share fields: before any
        round but the last, they hold the last round's forward values and round r + 1's adjoints, so round
        r's are rebuilt (steps[step + "_rebuild"]) and the shared adjoints zeroed (plan) first."""
        self.round_now[0] = r
        if r < n - 1:
            self.kernel_run(s, step + "_rebuild")
            self.kernel_clear_grads(s, plan)
        self.kernel_run.grad(s, step)

    @ti.kernel
    def kernel_normal_round(self, s: ti.template(), r: ti.i32) -> ti.i32:
        """Normal round r on the gradient path (rounds.func_normal_round, forward only) for every env whose
        rounds are not over: how many slots change sides, over the envs."""
        n = 0
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                if r == 0:
                    self.line_done[i_b] = 0
                    for i in range(s.n_dofs):
                        self.qacc_line[0, i_b, i] = self.qacc_candidates[0, i_b, i]
                if self.line_done[i_b] == 0:
                    func_link_motion(s, self.qacc_normal, 0, i_b, self.link_w_normal, self.link_v_normal)
                    t = func_normal_round(s, i_b, r)
                    if t == 0:
                        self.line_done[i_b] = 1
                    n += t
        return n

    @ti.kernel
    def kernel_bound_count(self, s: ti.template(), e: ti.i32, r: ti.i32) -> ti.i32:
        """How many slots, over the envs, a bound round at qacc[e] would change (passes.func_bound_count),
        round r's releases and returns decided into bnd_rel[env, r]."""
        n = 0
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                n += func_bound_count(s, i_b, e, r)
        return n

    @ti.kernel
    def kernel_bound_keep(self, s: ti.template(), e: ti.i32, r: ti.i32):
        """Round r's inputs, before its pass changes the system and the next solve overwrites them: the
        solution qacc[e] (bnd_x, and bnd_xs[env, r] for the backward), its factor (bnd_fac[env, r]) and, in
        dense scenes, that factor's envelope (ENV_BOUND + r)."""
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                for i in range(s.n_dofs):
                    self.bnd_x[0, i_b, i] = s.qacc[e, i_b, i]
                    self.bnd_xs[i_b, r, i] = s.qacc[e, i_b, i]
                    for j in range(i + 1):
                        self.bnd_fac[i_b, r, i, j] = s.mass_fac[i_b, i, j]
                    if ti.static(self.dense):
                        self.env_first[i_b, ENV_BOUND + r, i] = self.env_first[i_b, ENV_FINAL, i]
                        self.env_last[i_b, ENV_BOUND + r, i] = self.env_last[i_b, ENV_FINAL, i]

    # Env loops over the core's env capacity with a guard, as core.RigidCore explains (a loop bound
    # read from a field in a kernel of several loops broke Taichi's adjoint).
    @ti.kernel
    def kernel_active_pairs(self, s: ti.template(), src: ti.i32, h: float) -> ti.i32:
        """How many (env, pair) the broad phase finds active at the state in slot src for a (sub)step h:
        the link state, geom poses and broad phase of the evaluation, alone (forward only: one loop over
        envs, each env's stages in turn). 0 means that the evaluation's contact stages and passes would
        add exact zeros (see RigidSolver._evaluation_unit)."""
        n = 0
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                for stage in ti.static(LINK_STATE + (func_geom_pose, func_broad_phase)):
                    stage(s, i_b, 0, src, h)
                for i_p in range(self.n_pairs):
                    n += self.pair_active[i_b, i_p]
        return n

    @ti.kernel
    def kernel_report(self, s: ti.template(), e: ti.i32):
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                func_contact_report(s, i_b, e)

    @ti.kernel
    def kernel_run(self, s: ti.template(), which: ti.template()):
        """One step of the solve op by name (self.steps: a solve, or a pass between solves), each of its
        stages one top-level loop over envs."""
        for stage in ti.static(self.steps[which]):
            if ti.static(s.serial):
                ti.loop_config(serialize=True)
            for i_b in range(s.cap_envs):
                if i_b < s.n_envs:
                    stage(s, i_b)

    @ti.kernel
    def kernel_adjoint_solve(self, s: ti.template(), which: ti.template()):
        """Adjoint of one of the solves before the final one: 0 the first (qacc_candidates = A1^-1 force), 1 the
        second (qacc_normal = A2^-1 force), 2 the Coulomb response (dqacc_coulomb = A2^-1 force_coulomb)
        (the bound rounds': kernel_adjoint_bound_solve)."""
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                if ti.static(which == 0):
                    func_solve_adjoint(s, self.factor_candidates, ENV_CANDIDATES, i_b, self.qacc_candidates, self.qacc_candidates.grad, 0, s.force.grad)
                elif ti.static(which == 1):
                    func_solve_adjoint(s, self.factor_normal, ENV_NORMAL, i_b, self.qacc_normal, self.qacc_normal.grad, 0, s.force.grad)
                else:
                    func_solve_adjoint(s, self.factor_normal, ENV_NORMAL, i_b, self.dqacc_coulomb, self.dqacc_coulomb.grad, 0, self.force_coulomb.grad)

    @ti.kernel
    def kernel_adjoint_bound_solve(self, s: ti.template(), r: ti.i32):
        """Adjoint of the solve before bound round r (bnd_x = A^-1 force: round r's when this runs), its factor
        kept in bnd_fac[env, r] and copied to bnd_fac_now (the solves take a factor [env, i, j])."""
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            if i_b < s.n_envs:
                for i in range(s.n_dofs):
                    for j in range(i + 1):
                        self.bnd_fac_now[i_b, i, j] = self.bnd_fac[i_b, r, i, j]
                func_solve_adjoint(s, self.bnd_fac_now, ENV_BOUND + r, i_b, self.bnd_x, self.bnd_x.grad, 0, s.force.grad)

    @ti.kernel
    def kernel_clear_grads(self, s: ti.template(), plan: ti.template()):
        """Zero the adjoints of a plan's fields (scratch_grad_plan: the scratch fields', before each solve's
        backward; toggle_grad_plan: bank_toggle's, between two normal rounds' adjoints), every env of the
        capacity (as constants: no NaN survives)."""
        if ti.static(s.serial):
            ti.loop_config(serialize=True)
        for i_b in range(s.cap_envs):
            func_zero_plan(plan, i_b, 0)

    def watch(self, step: int, evals_per_step: int, h: float):
        """After a step without gradients (scene step number `step`) when `clock.due()` says so: warn
        when a contact has ended a step deep inside the other body (func_report_slot records the first
        one), once per pair of geoms and for at most MAX_DEEP_WARNINGS pairs a scene: a body that tunnels
        at the start (placed inside the ground) does not hide a tangle later in the run."""
        if self.deep_any[0] == 0:
            return
        di, df = self.deep_i.to_numpy()[: max(self.n_envs, 1)], self.deep_f.to_numpy()[: max(self.n_envs, 1)]
        hit = np.nonzero(di[:, 0])[0]
        # the earliest record, the deepest (relative to its limit) among those
        i_b = int(hit[np.lexsort((-df[hit, 3], di[hit, 2]))[0]])  # (gain / limit in column 3)
        i_s, e_hit = int(di[i_b, 1]), int(di[i_b, 2])
        depth, speed, lim, gain = (float(x) for x in df[i_b, :4])
        late = (int(self.eval_count[i_b]) - e_hit) // max(int(evals_per_step), 1)
        self.n_deep_warned += 1
        last = self.n_deep_warned >= MAX_DEEP_WARNINGS
        self.clock.done = last
        self.kernel_rearm(int(self.plan.np_slot_pair[i_s]))
        warnings.warn(ContactPenetrationWarning(deep_contact_message(
            self.plan, i_s, i_b, self.n_envs, step - late, h, depth, speed, lim, gain, last)),
            stacklevel=_user_stacklevel())

    # ------------------------------------------------------------------ readers
    def read(self):
        """numpy views of the last evaluation: dict of position, normal, force (on the point side: the force
        the step applied, 0 for a slot that applied none), depth, fn (the normal force where it pushes,
        else 0), each (B, n_slots[, 3]). A contact whose linearised normal law pulled in the step (see
        the package docstring, step 5) has fn 0 and a force whose normal component is negative: the
        forces, not fn, add up to what the bodies felt."""
        B, S = self.n_envs, self.plan.n_slots
        # without gradients the report writes c_fn and c_force of the slots that are on only (func_contact_report)
        active = ((self.pair_active.to_numpy()[:B][:, self.np_slot_pair] == 1)
                  & (self.sl_on.to_numpy()[:B, :S] == 1))
        return {"position": self.c_pos.to_numpy()[:B, :S], "normal": self.c_normal.to_numpy()[:B, :S],
                "force": np.where(active[..., None], self.c_force.to_numpy()[:B, :S], 0.0),
                "depth": self.c_depth.to_numpy()[:B, :S], "fn": np.where(active, self.c_fn.to_numpy()[:B, :S], 0.0)}


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

    def to_numpy(self):
        B, G = self.shape
        return self.field.to_numpy()[:B, :G]

    def load(self, x):
        """The scene's block from x (n_envs, n_geoms), a numpy array or a contiguous CPU tensor."""
        if x.shape != self.shape:
            raise ValueError(f"contact friction: expected shape {self.shape}, got {tuple(x.shape)}")
        self.contact.kernel_set_friction(x.contiguous())
