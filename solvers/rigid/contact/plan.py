"""ContactPlan: the contact model of one scene in numpy (host side): geoms, pairs, slots, the static
flags its kernels are specialised on and the capacities its fields need."""
import numpy as np

from ..collision import (SLOT_BOXEDGE, SLOT_BOXFACE, SLOT_CYL_RIM, SLOT_HULLEDGE, SLOT_SEGSEG, build_geoms, build_slots,
                         candidate_pairs, geom_hull, link_is_dynamic, sdf_distance_ratio)
from ..flatten import JTYPE
from .law import LOAD_SHIFT, MARGIN_WIDTHS

# run-time sizes of the contact model (indices into ContactSolver.cfg_i): the contact kernels read them
# from a field, so one compile serves every scene of a contact class. The model's constants (k, d,
# delta, eps) stay compile-time constants, part of the class: as run-time values they change the
# rounding of the force law (LLVM folds and reassociates them), and a chaotic rollout (a legged robot
# landing) then leaves main's trajectory; scenes share them anyway unless their options differ.
C_GEOMS, C_PAIRS, C_SLOTS, C_LP, C_CROSS, N_CCFG_I = range(6)


def _cap(n: int, least: int) -> int:
    return max(least, 1 << (max(n, 1) - 1).bit_length())


class ContactPlan:
    """The contact model of one scene in numpy: geoms, pairs, slots, the static flags its kernels are
    specialised on, and the capacities its fields need (see ContactSolver)."""

    @staticmethod
    def create(flat, models, options, specialized=False):  # flat: the scene's flatten.FlatModel
        """The contact plan of a scene, or None when no two geoms can touch (nothing is compiled or
        launched for contacts then). Raises ContactBuildError for geometry it cannot simulate."""
        geoms = build_geoms(models, int(options.max_mesh_contact_points))
        if geoms.n == 0:
            return None
        pairs = candidate_pairs(geoms, flat, bool(options.enable_self_collision),
                                bool(getattr(options, "ignore_unsupported_pairs", False)),
                                {i for i, m in enumerate(models) if not m.rigid_contact},
                                bool(getattr(options, "enable_adjacent_collision", False)),
                                bool(getattr(options, "enable_neutral_collision", False)))
        if not pairs:
            return None
        return ContactPlan(flat, geoms, pairs, options, specialized)

    def __init__(self, flat, geoms, pairs, options, specialized=False):
        self.geoms = geoms
        self.pairs = pairs
        slots = build_slots(geoms, pairs)
        self.slots = slots
        self.n_links = flat.n_links
        self.n_geoms, self.n_pairs, self.n_slots = geoms.n, len(pairs), len(slots)
        self.k = float(options.contact_stiffness)
        # the damping: a ratio of each pair's critical damping (contact_damping_ratio, 1 when neither it nor
        # contact_damping is given: the default), then zeta > 0 and d = 0 (unused, not a class of its own); or
        # a fixed N s/m when contact_damping is given (zeta = 0)
        fixed = getattr(options, "contact_damping", None)
        ratio = getattr(options, "contact_damping_ratio", None)
        if ratio is None and fixed is None:
            ratio = 1.0
        self.zeta = float(ratio) if ratio is not None else 0.0
        self.d = 0.0 if ratio is not None else float(fixed)
        self.delta = float(options.contact_smoothing)
        self.eps = float(options.friction_smoothing)
        # RigidOptions.friction_smoothing_accel: eps at most this times the step (None, here 0: off)
        accel = getattr(options, "friction_smoothing_accel", None)
        self.slip_accel = float(accel) if accel is not None else 0.0
        # friction's load (RigidOptions.friction_load): > 0 the normal force predicted with Coulomb's forces
        # applied, at most this many times the frictionless solve's (the default), 0 the frictionless solve's
        self.load_shift = LOAD_SHIFT if getattr(options, "friction_load", "coulomb") == "coulomb" else 0.0
        self.margin = MARGIN_WIDTHS * self.delta
        # static: code is generated only for the slot kinds and SDF types this scene uses
        self.has_rim = any(x[1] == SLOT_CYL_RIM for x in slots)
        self.has_segseg = any(x[1] == SLOT_SEGSEG for x in slots)
        self.has_boxedge = any(x[1] == SLOT_BOXEDGE for x in slots)
        # (box-box pairs have both; the broad phase runs their pair's separating-axis test)
        self.has_boxface = any(x[1] == SLOT_BOXFACE for x in slots)
        self.has_hulledge = any(x[1] == SLOT_HULLEDGE for x in slots)
        # the convex volumes of the geoms of hull-edge pairs (collision.polytope_hull), by geom, each once (a geom
        # is in many such pairs: 180 volumes for the 18 geoms of a self-colliding Panda beside a cube)
        hull_geoms = sorted({g for x in slots if x[1] == SLOT_HULLEDGE for g in x[2:4]})
        self.hulls = {g: geom_hull(geoms, g) for g in hull_geoms}
        # each volume's SDF-to-distance ratio (collision.sdf_distance_ratio), for the broad phase's mesh pairs
        self.hull_kappa = {g: sdf_distance_ratio(*self.hulls[g][:3]) for g in hull_geoms}
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
        self.link_dyn = link_is_dynamic(flat)
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
            for i in _link_dofs(flat, la):
                for j in _link_dofs(flat, lb):
                    # (i, j) and (j, i) land on the same lower-triangle entry; on the diagonal (a common
                    # ancestor of a self-collision pair) both terms of J_a^T W J_b + J_b^T W J_a do
                    cross.append((i, j, lp, 2.0 if i == j else 1.0))
        self.cross = cross
        self.n_cross = len(cross)
        self.np_dense_perm = _dense_order(flat) if self.dense else np.zeros(1, dtype=np.int32)
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
        self.flags = (self.dense, self.has_rim, self.has_segseg, self.has_boxedge, self.has_boxface, self.has_hulledge,
                      self.sdf_types,
                      (self.k, self.d, self.zeta, self.delta, self.eps, self.load_shift, self.slip_accel), self.static)


def _dense_order(flat):
    """The order the dense contact system is factorised in (linalg.func_factor_dense_to): position k
    holds dof perm[k]. The kinematic trees by the starting height of their root (stable: trees at one
    height keep the scene's order), each tree's dofs in its own order: bodies stacked or heaped touch
    the ones above and below them, so the system's envelope is a band however the entities were added
    (the 100-box tower added in a shuffled order: 45 ms a step in scene order, 11 ms in this one; 8-9
    ms in the order it was built)."""
    parent = flat.np_link_parent
    height = np.zeros(len(parent))
    for l, p in enumerate(parent):  # parents come before their children
        if p >= 0:
            height[l] = height[p]
        elif flat.np_link_jtype[l] == JTYPE["free"]:
            height[l] = flat.np_qpos0[flat.np_link_q_start[l] + 2]
        else:
            height[l] = flat.np_link_jpos[l, 2]
    order = np.argsort(height[flat.np_dof_link], kind="stable")
    return order.astype(np.int32)


def _link_dofs(flat, l):
    """The dofs that move link l: its own and its ancestors'."""
    out = []
    while l >= 0:
        d0 = flat.np_link_dof_start[l]
        out.extend(range(d0, d0 + flat.np_link_ndof[l]))
        l = flat.np_link_parent[l]
    return out
