"""Collision, Taichi side: the stages of the step (geom poses, the broad phase) and the geometry of each
contact slot (its point, normal and depth): in the single-assignment form of the differentiated stages
where the scene takes gradients (every slot kind and SDF type the scene has, evaluated and selected), with
runtime branches where it does not (a slot evaluates its own kind and type only: a box corner on the ground
of a scene with meshes and box pairs no longer computes their planes and separating axes; the slot stage of
a Panda over a plane beside a box, 4.6 -> 1.2 us a step). The two forms agree slot by slot to round-off
(tests/test_narrow_phase.py), not to the bit: the compiler arranges each kernel's arithmetic its own way.
"""
import taichi as ti

from .geoms import (BOXEDGE_TOL, CYL_RIM_FADE, GEOM_BOX, GEOM_CAPSULE, GEOM_CYLINDER, GEOM_MESH, GEOM_PLANE,
                    GEOM_SPHERE, N_HULL_EDGES, N_HULLFACE, N_KDOP, SLOT_BOXEDGE, SLOT_BOXFACE, SLOT_CYL_RIM,
                    SLOT_HULLEDGE, SLOT_HULLFACE, SLOT_SEGSEG)
from ..kinematics import func_point_velocity
from ..math3d import div_floor, func_mm, func_mtv, func_mv
from .sdf import TINY, func_sdf_any, func_sdf_branched, func_sdf_round, func_segment_closest, func_sgn3

@ti.func
def func_geom_pose(s: ti.template(), i_b, e, src, h):
    """World pose of every collision geom (from its link's pose)."""
    c = s.contact
    for g in range(c.n_geoms):
        l = c.geom_link[g]
        R = s.link_R[i_b, l]
        c.geom_xpos[i_b, g] = s.link_pos[i_b, l] + func_mv(R, c.geom_pos[g])
        c.geom_xR[i_b, g] = func_mm(R, c.geom_R[g])


@ti.func
def func_plane_extent(c: ti.template(), g, R, n):
    """How far geom g (rotation R) reaches from its centre along -n: its support function. Exact for
    sphere, capsule, box and cylinder; the bounding radius for meshes. Only the geom's own type is
    evaluated (a branch: the broad phase, its one caller, has no adjoint)."""
    t = c.geom_type[g]
    sz = c.geom_size[g]
    a = func_mtv(R, n)  # n in the geom frame
    r = c.geom_rbound[g]
    if t == GEOM_BOX:
        r = sz[0] * ti.abs(a[0]) + sz[1] * ti.abs(a[1]) + sz[2] * ti.abs(a[2])
    elif t == GEOM_CYLINDER:
        r = sz[1] * ti.abs(a[2]) + sz[0] * ti.sqrt(ti.max(1.0 - a[2] * a[2], 0.0))
    elif t == GEOM_CAPSULE:
        r = sz[1] * ti.abs(a[2]) + sz[0]
    elif t == GEOM_SPHERE:
        r = sz[0]
    return r


@ti.func
def func_broad_phase(s: ti.template(), i_b, e, src, h):
    """pair_active: the geom reaches within the contact margin of a plane (support function), or two
    bounding spheres do, now or within the step (the margin grows by how far the two can approach each
    other in h at their current velocities: speculative contacts, see contact.py; a turn sweeps a
    geom's extent by at most its diameter, so the spin term is capped at 2 / h). Two geoms are apart
    by the larger of their bounding spheres' gap and their world-axis bounding boxes' (func_gap_boxes):
    both are lower bounds of their distance, so a pair either test leaves out has no slot that pushes
    in the step; the boxes keep long thin geoms apart that their spheres do not (the 100-box tower's
    2 m planks: 2,840 of its 5,151 pairs active with the spheres, 202 with the boxes; 58 -> 8 ms a
    step); the pairs both leave in are tested again as oriented boxes (func_gap_obbs). A far slot of a
    fast-turning body can still be a candidate (slots.func_contact_slot: its point's speed, not this
    bound) with an exactly zero force; leaving its pair out then moves the step's rounding, as the
    spheres' test already did (14 bodies thrown at 20 rad/s: 3e-14 m in the first step it happens;
    tests/test_many_bodies.py checks a pile at 6 rad/s to the bit). The tests are branches (each pair
    evaluates its own: a fifth of the stage on ANYmal), with gradients too: the stage writes only the
    integer pair_active and its own per-geom terms (fields without adjoints), so it has no adjoint
    (NO_ADJOINT: the gradient path's backward skips it). The terms of each geom (its sphere's centre,
    world box, speed and sweep) are computed once per geom before the pairs' loop, the same expressions
    the pairs evaluated each for themselves before (Genesis's MJCF Panda with self-collision: 211 pairs
    of 40 geoms, the stage 4.5 -> ~1 us a step)."""
    c = s.contact
    # each geom's share of its pairs' tests, once per geom (a robot's own links with self-collision: 211
    # pairs among 40 geoms): the bounding sphere's centre, the world box's half widths, and how fast the
    # geom can approach another, its centre's speed and its rotation's sweep of its extent (capped at 2 / h)
    for g in range(c.n_geoms):
        l = c.geom_link[g]
        R = c.geom_xR[i_b, g]
        cg = c.geom_xpos[i_b, g] + func_mv(R, c.geom_center[g])
        c.geom_bc[i_b, g] = cg
        c.geom_ext[i_b, g] = ti.Vector([func_plane_extent(c, g, R, ti.Vector([1.0, 0.0, 0.0])),
                                        func_plane_extent(c, g, R, ti.Vector([0.0, 1.0, 0.0])),
                                        func_plane_extent(c, g, R, ti.Vector([0.0, 0.0, 1.0]))])
        v = func_point_velocity(s, s.cvel_w, s.cvel_v, i_b, l, cg)
        w = s.cvel_w[i_b, l]
        c.geom_speed[i_b, g] = ti.sqrt(v.dot(v) + TINY)
        c.geom_sweep[i_b, g] = ti.min(ti.sqrt(w.dot(w) + TINY), 2.0 / h) * ti.min(c.geom_rbound[g], 1e6)
    for i_p in range(c.n_pairs):
        ga = c.pair_ga[i_p]
        gb = c.pair_gb[i_p]
        ca = c.geom_bc[i_b, ga]
        cb = c.geom_bc[i_b, gb]
        is_plane = c.geom_type[gb] == GEOM_PLANE
        # closing speed bound: centre velocities, plus rotation of the geoms' extents (a plane does not
        # move: candidate_pairs rejects moving planes); either body may also turn towards the other
        # within the step (stopped by a third one): their speeds bound that (contact.py linearises such
        # candidate contacts again after its first solve)
        closing = c.geom_speed[i_b, ga] + c.geom_speed[i_b, gb] + c.geom_sweep[i_b, ga]
        gap = ti.cast(0.0, s.dtype)
        if is_plane:
            gap = func_gap_plane(c, ga, c.geom_xR[i_b, ga], c.geom_xR[i_b, gb], ca, cb)
        else:
            gap = ti.max(func_gap_spheres(c, ga, gb, ca, cb), func_gap_boxes(c, i_b, ga, gb, ca, cb))
            closing += c.geom_sweep[i_b, gb]
            # the oriented boxes, for the pairs those two leave in (compiled where some pair is not against a
            # plane), and two meshes' planes against each other's points
            if ti.static(c.sdf_types != (GEOM_PLANE,)):
                if gap - h * closing < c.margin:
                    Ra = c.geom_xR[i_b, ga]
                    Rb = c.geom_xR[i_b, gb]
                    gap = ti.max(gap, func_gap_obbs(c, i_b, ga, gb, Ra, Rb))
                    if ti.static(c.has_hulledge):  # (two meshes are a hull-edge pair: geoms.hull_edge_pair)
                        if gap - h * closing < c.margin and c.geom_type[ga] == GEOM_MESH and c.geom_type[gb] == GEOM_MESH:
                            gap = ti.max(gap, func_gap_mesh_planes(c, i_b, i_p, ga, gb, Ra, Rb, c.margin + h * closing))
        c.pair_active[i_b, i_p] = ti.select(gap - h * closing < c.margin, 1, 0)
        if ti.static(c.has_boxedge):  # a box pair's separating-axis test, once for its slots
            if (c.pair_active[i_b, i_p] == 1) & (c.geom_type[ga] == GEOM_BOX) & (c.geom_type[gb] == GEOM_BOX):
                c.pair_box[i_b, i_p] = func_box_pair_test(c, i_b, ga, gb)
        if ti.static(c.has_hulledge):  # two convex volumes' separating-axis test, for their edge slot
            if (c.pair_active[i_b, i_p] == 1) & func_is_hull_pair(c, ga, gb):
                func_hull_pair_test(c, i_b, i_p, ga, gb)


@ti.func
def func_gap_obbs(c: ti.template(), i_b, ga, gb, Ra, Rb):
    """Gap of the oriented boxes around geoms ga and gb (rotations Ra, Rb; geoms.mesh_box, primitive_box)
    by the separating-axis test: the largest separation along each box's three axes and the nine cross
    products of one's with the other's. A lower bound of the distance of the two collision volumes, as the
    spheres' and the world boxes' gaps are, and a tighter one for the parts of one robot that sit beside
    each other: Genesis's MJCF Panda holding a bent pose has three pairs of its own meshes that the spheres
    and world boxes leave in at every step (link 5's third piece beside link 3, link 7 and the hand; 28-76
    mm apart as hulls); the boxes part it from link 3 and the hand (by 7.5 mm and more), and overlap link
    7's by 17 mm (func_gap_mesh_planes parts those)."""
    A = func_mm(Ra, c.geom_obb_A[ga])
    B = func_mm(Rb, c.geom_obb_A[gb])
    T = c.geom_xpos[i_b, gb] + func_mv(Rb, c.geom_obb_c[gb]) - c.geom_xpos[i_b, ga] - func_mv(Ra, c.geom_obb_c[ga])
    ha = c.geom_obb_h[ga]
    hb = c.geom_obb_h[gb]
    sep = func_box_axis_sep(T, ti.Vector([A[0, 0], A[1, 0], A[2, 0]]), A, ha, B, hb)
    for k in ti.static(range(3)):
        ak = ti.Vector([A[0, k], A[1, k], A[2, k]])
        bk = ti.Vector([B[0, k], B[1, k], B[2, k]])
        sep = ti.max(sep, func_box_axis_sep(T, ak, A, ha, B, hb), func_box_axis_sep(T, bk, A, ha, B, hb))
        for m in ti.static(range(3)):
            L = ak.cross(ti.Vector([B[0, m], B[1, m], B[2, m]]))
            n2 = L.dot(L)
            if n2 > 1e-12:  # (parallel axes: their cross product is no axis)
                sep = ti.max(sep, func_box_axis_sep(T, L / ti.sqrt(n2), A, ha, B, hb))
    return sep


@ti.func
def func_gap_mesh_planes(c: ti.template(), i_b, i_p, ga, gb, Ra, Rb, thr):
    """Whether mesh pair i_p is apart by at least thr (> 0: the margin and the closing sweep): a value >= thr
    if it is, below thr if not. What its slots will find: a point slot, one side's corner against the other
    side's SDF, the largest of that side's plane distances (sdf.func_sdf_kdop); the edge and face slots the
    separating-axis test's planes (func_hull_pair_test). A side's bound (func_mesh_plane_side) is the largest
    over the SDF side's planes of the least plane distance of the other side's corners: the corners' SDF is at
    least that, and, where positive, the two volumes are at least that far apart. Where the first side's
    planes do not part the volumes by thr (a plane of each face of a rounded link, none flat against the
    link beside it), the second side's plane may, by thr / kappa (the first side's collision.
    sdf_distance_ratio): then the first side's corners are that far from its volume and their SDF at least
    thr. The Panda's link 5 beside link 7 in a bent pose: 20 mm apart by link 5's planes, none of link 7's
    parting link 5's corners (-0.2 mm); thr 0.1 mm.
    The oriented boxes bound the planes' intersection, which reaches up to centimetres past a hull at its
    corners; this test sees the volumes' corners themselves (link 5 beside link 7: boxes overlapping by 17
    mm). Only whether the value reaches thr decides (func_broad_phase), so a side stops at the first plane
    that parts it by what it must, starting from the one that did in the pair's last test (pair_hint), and
    the second side is tested only where it must be: at a plane or two a side instead of 26 (a robot's own
    links beside each other at every step: Genesis's MJCF Panda with self-collision). Each decision asks
    whether some plane parts by a given amount, never how much the one found first does, so that the hint
    (the plane tried first) decides nothing."""
    out = func_mesh_plane_side(c, i_b, i_p, 0, gb, ga, Rb, Ra, thr)
    if out >= thr:
        # gb's corners against ga's SDF: a plane of gb parting by thr / kappa of ga is enough (the one found
        # may be it), else a plane of ga parting them by thr
        need = thr / ti.max(c.hull_kappa[ga], 1e-6)
        if out < need:
            out = func_mesh_plane_side(c, i_b, i_p, 1, ga, gb, Ra, Rb, thr)
            if out < thr:  # no plane of ga does: another plane of gb may part by need
                if func_mesh_plane_side(c, i_b, i_p, 0, gb, ga, Rb, Ra, need) >= need:
                    out = thr
    else:  # no plane of gb parts ga's corners by thr: one of ga's by thr / kappa of gb may
        need = thr / ti.max(c.hull_kappa[gb], 1e-6)
        if func_mesh_plane_side(c, i_b, i_p, 1, ga, gb, Ra, Rb, need) >= need:
            out = thr
    return out


@ti.func
def func_mesh_plane_side(c: ti.template(), i_b, i_p, side, X, Y, RX, RY, stop):
    """The largest over geom X's planes of the least distance of geom Y's volume's corners beyond it (>= stop
    where a plane parts them by stop; else a value below stop), from the plane that did in the pair's last
    test (pair_hint[i_b, i_p, side])."""
    dx = c.geom_xpos[i_b, X] - c.geom_xpos[i_b, Y]
    best = ti.cast(-1e30, c.dtype)
    k0 = c.pair_hint[i_b, i_p, side]
    j = 0
    while j < N_KDOP and best < stop:
        k = (k0 + j) % N_KDOP
        nw = func_mv(RX, c.geom_kdop_dir[X, k])
        # the plane in Y's frame: n . p <= d there
        least = func_corners_beyond(c, Y, func_mtv(RY, nw), c.geom_kdop[X, k] + nw.dot(dx), stop)
        best = ti.max(best, least)
        if least >= stop:
            c.pair_hint[i_b, i_p, side] = k
        j += 1
    return best


@ti.func
def func_gap_plane(c: ti.template(), ga, Ra, Rb, ca, cb):
    """Gap of geom ga (rotation Ra, centre ca) above the plane of rotation Rb through cb (its normal the
    plane's z axis)."""
    nb = ti.Vector([Rb[0, 2], Rb[1, 2], Rb[2, 2]])
    return (ca - cb).dot(nb) - func_plane_extent(c, ga, Ra, nb)


@ti.func
def func_gap_boxes(c: ti.template(), i_b, ga, gb, ca, cb):
    """Gap of the world-axis bounding boxes of geoms ga and gb (centres ca, cb; half widths their support
    functions along the axes, func_plane_extent, in geom_ext): the largest separation along an axis."""
    e = c.geom_ext[i_b, ga] + c.geom_ext[i_b, gb]
    d = ti.abs(ca - cb)
    sep = ti.max(d[0] - e[0], d[1] - e[1], d[2] - e[2])
    return sep


@ti.func
def func_gap_spheres(c: ti.template(), ga, gb, ca, cb):
    """Gap of the bounding spheres of geoms ga and gb (centres ca, cb)."""
    dc = ca - cb
    # norms with TINY under the root: no infinite derivative at 0 in the adjoint (0 * inf is NaN)
    return ti.sqrt(dc.dot(dc) + TINY) - c.geom_rbound[ga] - c.geom_rbound[gb]


@ti.func
def func_slot_point(c: ti.template(), i_s, kind, ga, xa, Ra, zb):
    """The point-side point of a slot: a fixed sample point, or the deepest rim point of a cylinder cap
    towards a plane (normal zb), faded towards the cap's centre where the cap is within CYL_RIM_FADE contact
    widths of level (its rim's heights differ by less than that): the deepest point's direction is undefined
    at level, and unfaded it jumped to the opposite side of the rim each time a standing cylinder's tilt
    changed sign (it rocked at |w| ~0.01 rad/s, tests/test_contact.py). The faded point's depth is at most
    ~0.3 CYL_RIM_FADE widths short of the rim's deepest."""
    p_fixed = xa + func_mv(Ra, c.slot_p[i_s])
    if ti.static(c.has_rim):
        nl = func_mtv(Ra, zb)
        r_cyl = c.geom_size[ga][0]
        fade = CYL_RIM_FADE * c.delta / r_cyl
        rho = ti.sqrt(nl[0] * nl[0] + nl[1] * nl[1] + fade * fade)
        p_rim = xa + func_mv(Ra, ti.Vector([-r_cyl * nl[0] / rho, -r_cyl * nl[1] / rho, c.slot_aux[i_s] * c.geom_size[ga][1]]))
        return ti.select(kind == SLOT_CYL_RIM, p_rim, p_fixed)
    else:
        return p_fixed


@ti.func
def func_segseg(c: ti.template(), ga, gb, xa, za, xb, zb):
    """(point, signed distance, normal) of a capsule pair's slot: the closest points of the two segments."""
    hla = c.geom_size[ga][1]
    hlb = c.geom_size[gb][1]
    pa, pb = func_segment_closest(xa - hla * za, xa + hla * za, xb - hlb * zb, xb + hlb * zb)
    phi_ss, n_ss = func_sdf_round(pa - pb, c.geom_size[gb][0], zb)
    return pa, phi_ss, n_ss


@ti.func
def func_with_segseg(c: ti.template(), kind, ga, gb, xa, za, xb, zb, p, phi, n):
    """(point, signed distance, normal) of the slot: those of the SDF test, or for capsule pairs the
    closest points of the two segments."""
    if ti.static(c.has_segseg):
        pa, phi_ss, n_ss = func_segseg(c, ga, gb, xa, za, xb, zb)
        ss = kind == SLOT_SEGSEG
        return ti.select(ss, pa, p), ti.select(ss, phi_ss, phi), ti.select(ss, n_ss, n)
    else:
        return p, phi, n


@ti.func
def func_box_axis_sep(T, L, Ra, ha, Rb, hb):
    """Separation of two boxes (centre offset T = xb - xa, rotations, half sizes) along the unit axis L:
    |T . L| minus the two boxes' half extents along L (negative: the projections overlap)."""
    ra = ha[0] * ti.abs(Ra[0, 0] * L[0] + Ra[1, 0] * L[1] + Ra[2, 0] * L[2]) \
        + ha[1] * ti.abs(Ra[0, 1] * L[0] + Ra[1, 1] * L[1] + Ra[2, 1] * L[2]) \
        + ha[2] * ti.abs(Ra[0, 2] * L[0] + Ra[1, 2] * L[1] + Ra[2, 2] * L[2])
    rb = hb[0] * ti.abs(Rb[0, 0] * L[0] + Rb[1, 0] * L[1] + Rb[2, 0] * L[2]) \
        + hb[1] * ti.abs(Rb[0, 1] * L[0] + Rb[1, 1] * L[1] + Rb[2, 1] * L[2]) \
        + hb[2] * ti.abs(Rb[0, 2] * L[0] + Rb[1, 2] * L[1] + Rb[2, 2] * L[2])
    return ti.abs(T.dot(L)) - ra - rb


@ti.func
def func_col(R, i: ti.template()):
    return ti.Vector([R[0, i], R[1, i], R[2, i]])


@ti.func
def func_col_at(R, i):
    """Column i (a run-time 0, 1 or 2) of R, by selection."""
    return ti.select(i == 0, func_col(R, 0), ti.select(i == 1, func_col(R, 1), func_col(R, 2)))


@ti.func
def func_face_axis(Ra, Rb, k: ti.template()):
    """Face axis k of two boxes: box a's axes 0..2, then box b's 3..5."""
    if ti.static(k < 3):
        return func_col(Ra, k)
    else:
        return func_col(Rb, ti.static(k - 3))


@ti.func
def func_face_best(T, Ra, ha, Rb, hb, k: ti.template()):
    """Over the face axes k..5 (func_face_axis): (separation, index) of the one that separates the two
    boxes best; ties go to the lower index (box a's faces), so a face-on-face stack whose two axes tie
    to the last bit keeps one choice."""
    v = func_box_axis_sep(T, func_face_axis(Ra, Rb, k), Ra, ha, Rb, hb)
    if ti.static(k == 5):
        return v, k
    else:
        bv, bk = func_face_best(T, Ra, ha, Rb, hb, k + 1)
        take = v >= bv
        return ti.select(take, v, bv), ti.select(take, k, bk)


@ti.func
def func_edge_axis(T, a, b, Ra, ha, Rb, hb):
    """(separation, unit axis oriented from box a to box b) of the edge axis a x b (a: a column of Ra, b:
    one of Rb); separation -1e30 for a near-parallel pair (it never wins)."""
    C = a.cross(b)
    ln = ti.sqrt(C.dot(C) + TINY)
    ok = ln > 1e-6
    Lu = C / ti.max(ln, 1e-6)
    L = ti.select(T.dot(Lu) >= 0, Lu, -Lu)
    return ti.select(ok, func_box_axis_sep(T, L, Ra, ha, Rb, hb), -1e30), L


@ti.func
def func_edge_best(T, Ra, ha, Rb, hb, k: ti.template()):
    """Over the edge axes k..8 (a_i x b_j, i = k // 3, j = k % 3): (separation, unit axis oriented from
    box a to box b, i, j) of the best-separating one; near-parallel edge pairs never win."""
    i = ti.static(k // 3)
    j = ti.static(k % 3)
    v, L = func_edge_axis(T, func_col(Ra, i), func_col(Rb, j), Ra, ha, Rb, hb)
    if ti.static(k == 8):
        return v, L, i, j
    else:
        bv, bL, bi, bj = func_edge_best(T, Ra, ha, Rb, hb, k + 1)
        take = v > bv
        return ti.select(take, v, bv), ti.select(take, L, bL), ti.select(take, i, bi), ti.select(take, j, bj)


@ti.func
def func_box_edge_contact(xa, Ra, ha, xb, Rb, hb, wins, sep_e, L, i, j):
    """(point midway between the two edges, normal from box b towards box a, depth) of the edge pair
    whose axis (func_edge_best: separation sep_e, unit axis L from a to b, edge axes a_i, b_j) separates
    boxes a and b best; depth -1 (no contact) unless that axis beats every face axis by the slot's tol
    (`wins`: sep_e > sep_f + tol) and the closest points lie inside both edges (else corners and faces
    carry the contact)."""
    # the supporting edge of a (towards b) runs along a_i; that of b (towards a) along b_j
    sa = func_sgn3(func_mtv(Ra, L))
    sb = func_sgn3(func_mtv(Rb, L))
    ea = ti.Vector([ti.select(i == 0, 0.0, sa[0] * ha[0]), ti.select(i == 1, 0.0, sa[1] * ha[1]),
                    ti.select(i == 2, 0.0, sa[2] * ha[2])])
    eb = ti.Vector([ti.select(j == 0, 0.0, sb[0] * hb[0]), ti.select(j == 1, 0.0, sb[1] * hb[1]),
                    ti.select(j == 2, 0.0, sb[2] * hb[2])])
    ua = ti.Vector([ti.select(i == 0, ha[0], 0.0), ti.select(i == 1, ha[1], 0.0), ti.select(i == 2, ha[2], 0.0)])
    ub = ti.Vector([ti.select(j == 0, hb[0], 0.0), ti.select(j == 1, hb[1], 0.0), ti.select(j == 2, hb[2], 0.0)])
    ca = xa + func_mv(Ra, ea)
    cb = xb - func_mv(Rb, eb)
    da = func_mv(Ra, ua)
    db = func_mv(Rb, ub)
    pa, pb = func_segment_closest(ca - da, ca + da, cb - db, cb + db)
    # inside both edges: the closest points are not end points (parameters strictly inside (0, 1))
    ta = (pa - (ca - da)).dot(da) / ti.max(2.0 * da.dot(da), ti.static(div_floor()))
    tb = (pb - (cb - db)).dot(db) / ti.max(2.0 * db.dot(db), ti.static(div_floor()))
    inner = (ta > 1e-9) & (ta < 1.0 - 1e-9) & (tb > 1e-9) & (tb < 1.0 - 1e-9)
    on = wins & inner
    return 0.5 * (pa + pb), -L, ti.select(on, -sep_e, -1.0)


@ti.func
def func_pick(q, i):
    """Component i (a run-time 0, 1 or 2) of the 3-vector q, by selection: no dynamic index into a
    local vector (single-assignment form, and an adjoint that is a select too)."""
    return ti.select(i == 0, q[0], ti.select(i == 1, q[1], q[2]))


@ti.func
def func_axis_vec(i, v):
    """The 3-vector v e_i (i a run-time 0, 1 or 2)."""
    return ti.Vector([ti.select(i == 0, v, 0.0), ti.select(i == 1, v, 0.0), ti.select(i == 2, v, 0.0)])


@ti.func
def func_slab(a0, da, hw):
    """Interval (lo, hi) of s over which the line a0 + s da stays within |a| <= hw (empty: lo > hi),
    clipped to [-2, 2] (the callers want s within [-1, 1]). A line parallel to the slab is inside for
    every s or for none: the divisor is then replaced by 1 (finite in the discarded branch's adjoint)."""
    par = ti.abs(da) <= 1e-9 * hw
    inv = 1.0 / ti.select(par, 1.0, da)
    t1 = (-hw - a0) * inv
    t2 = (hw - a0) * inv
    inside = ti.abs(a0) <= hw
    lo = ti.select(par, ti.select(inside, -2.0, 2.0), ti.min(ti.max(ti.min(t1, t2), -2.0), 2.0))
    hi = ti.select(par, ti.select(inside, 2.0, -2.0), ti.min(ti.max(ti.max(t1, t2), -2.0), 2.0))
    return lo, hi


@ti.func
def func_box_face_contact(xa, Ra, ha, xb, Rb, hb, f, code, on, tol):
    """(point, normal from box b towards box a, depth) of face-face slot `code` of two boxes: where an
    edge of one box's face (the incident face) crosses the rim of the other box's face (the reference
    face), in the reference face's plane. Two boxes lying face on face touch over the overlap of the two
    faces, a polygon whose vertices are corners of either face (the corner slots' points) and such
    crossings: crossed planks touch only at crossings (no corner, no edge midpoint of either lies in the
    square where they overlap), and without these slots they fell through each other.

    The reference face is the face of best-separating face axis f (func_face_best: 0..2 box a's, 3..5 box
    b's) that looks at the other box; the incident face is the other box's face most anti-parallel to it.
    Its edge code // 2 (two along each of the face's axes, at -/+ the other half size), as s runs over
    [-1, 1], enters the reference rectangle at s_in and leaves it at s_out (the rectangle is convex: at
    most once each); the slot takes the entry (code even) or the exit (odd). It is a contact where the
    crossing lies inside the incident edge and on a reference edge, both at least tol from their ends
    (nearer, the corners' own slots stand for it: no double count where the two faces' corners meet, as
    in a stack of equal boxes), and `on` (no edge axis separates better: then the edge slot has it).
    The point is midway between the incident edge and the reference face's plane, the normal the
    reference face's (turned to point from b to a), the depth how far the edge lies below that plane.
    Depth -1 where there is no contact."""
    rb = f >= 3
    ax = f - ti.select(rb, 3, 0)
    xr = ti.select(rb, xb, xa)
    Rr = ti.select(rb, Rb, Ra)
    hr = ti.select(rb, hb, ha)
    xe = ti.select(rb, xa, xb)
    Re = ti.select(rb, Ra, Rb)
    he = ti.select(rb, ha, hb)
    # the reference face's outward normal, towards the incident box
    ar = ti.select(ax == 0, func_col(Rr, 0), ti.select(ax == 1, func_col(Rr, 1), func_col(Rr, 2)))
    sr = ti.select((xe - xr).dot(ar) >= 0, 1.0, -1.0)
    nr = sr * ar
    # the incident face: axis j of box e, on the side facing the reference face
    d = func_mtv(Re, nr)
    ad = ti.abs(d)
    j = ti.select((ad[0] >= ad[1]) & (ad[0] >= ad[2]), 0, ti.select(ad[1] >= ad[2], 1, 2))
    se = ti.select(func_pick(d, j) >= 0, -1.0, 1.0)
    # its edge k: along the face's axis u (k = 0, 1) or w (k = 2, 3), at -/+ the other half size
    k = code // 2
    u = (j + 1) % 3
    w = (j + 2) % 3
    along = ti.select(k < 2, u, w)
    across = ti.select(k < 2, w, u)
    lh = func_pick(he, along)
    side = ti.select(k % 2 == 0, -1.0, 1.0)
    mid_e = func_axis_vec(j, se * func_pick(he, j)) + func_axis_vec(across, side * func_pick(he, across))
    pm = xe + func_mv(Re, mid_e)
    dv = func_mv(Re, func_axis_vec(along, lh))
    # the edge pm + s dv (s in [-1, 1]) in the reference box's frame, clipped to the reference face's
    # rectangle (axes ur, wr of that box)
    qm = func_mtv(Rr, pm - xr)
    qd = func_mtv(Rr, dv)
    ur = (ax + 1) % 3
    wr = (ax + 2) % 3
    hu = func_pick(hr, ur)
    hw = func_pick(hr, wr)
    lo_u, hi_u = func_slab(func_pick(qm, ur), func_pick(qd, ur), hu)
    lo_w, hi_w = func_slab(func_pick(qm, wr), func_pick(qd, wr), hw)
    s_in = ti.max(lo_u, lo_w)
    s_out = ti.min(hi_u, hi_w)
    s = ti.select(code % 2 == 0, s_in, s_out)
    q = qm + s * qd
    inner_e = (s_in < s_out) & (ti.abs(s) * lh < lh - tol)
    inner_r = ti.max(hu - ti.abs(func_pick(q, ur)), hw - ti.abs(func_pick(q, wr))) > tol
    depth = func_pick(hr, ax) - sr * func_pick(q, ax)
    p = pm + s * dv
    return p + (0.5 * depth) * nr, ti.select(rb, nr, -nr), ti.select(on & inner_e & inner_r, depth, -1.0)


@ti.func
def func_box_pair_test(c: ti.template(), i_b, ga, gb):
    """The separating-axis test of box pair (ga, gb), once for all its edge and face slots (the broad phase
    runs it for each active box pair; its choices go to pair_box): the best face axis f (func_face_best:
    0..2 box a's, 3..5 box b's), the best edge pair (a_i, b_j) (func_edge_best), and whether that edge axis
    beats every face axis by the pair's tol (func_face_tol): then the edge slot has the contact, else the
    face slots. The slots' geometry, without gradients and with, evaluates the chosen edge axis alone
    (func_box_edge_slot), so the gradient path's adjoint holds no maximum over 15 axes: the adjoint of the
    slots stage of six boxes on a plane compiled in 15.6-16.7 s with it, 5.6-5.8 s without (cold, two
    alternated pairs, 2026-12-02). Until then each of a pair's 9 edge and face slots ran the test itself
    (in a stage of its own on the gradient path): Genesis's 100-box tower (benchmarks/tower_bounce.py) took
    6.30-6.40 s for steps 25-1,000, now 6.00-6.10 s (three alternated pairs, warm caches)."""
    xa = c.geom_xpos[i_b, ga]
    xb = c.geom_xpos[i_b, gb]
    Ra = c.geom_xR[i_b, ga]
    Rb = c.geom_xR[i_b, gb]
    ha = c.geom_size[ga]
    hb = c.geom_size[gb]
    T = xb - xa
    sep_f, f = func_face_best(T, Ra, ha, Rb, hb, 0)
    sep_e, _L, i, j = func_edge_best(T, Ra, ha, Rb, hb, 0)
    return func_box_pack(f, i, j, sep_e > sep_f + func_face_tol(ha, hb))


@ti.func
def func_box_pack(f, i, j, edge_wins):
    """func_box_pair_test's choices as one integer, pair_box's: f + 8 (3 i + j) + 128 edge_wins
    (func_box_unpack)."""
    return f + 8 * (3 * i + j) + ti.select(edge_wins, 128, 0)


@ti.func
def func_box_unpack(code):
    """(f, i, j, edge_wins) of func_box_pack's integer."""
    e = (code // 8) % 16
    return code % 8, e // 3, e % 3, code >= 128


@ti.func
def func_box_choices(c: ti.template(), i_b, i_s, kind):
    """Box slot i_s's share of its pair's test (pair_box): the face axis f, the edge pair (i, j), and the
    slot's verdict: for the edge slot whether the edge axis wins, for a face slot whether it does not."""
    f, i, j, edge_wins = func_box_unpack(c.pair_box[i_b, c.slot_pair[i_s]])
    return f, i, j, edge_wins == (kind == SLOT_BOXEDGE)


@ti.func
def func_box_edge_slot(xa, Ra, ha, xb, Rb, hb, i, j, verdict):
    """(point, normal, depth) of a box pair's edge slot at the test's edge pair (i, j): that axis's separation
    and direction (func_edge_axis), then the edge-edge contact."""
    sep_e, L = func_edge_axis(xb - xa, func_col_at(Ra, i), func_col_at(Rb, j), Ra, ha, Rb, hb)
    return func_box_edge_contact(xa, Ra, ha, xb, Rb, hb, verdict, sep_e, L, i, j)


@ti.func
def func_box_face_slot(c: ti.template(), i_s, xa, Ra, ha, xb, Rb, hb, f, verdict):
    """(point, normal, depth) of box face slot i_s (its aux is its code) at the test's face axis f and verdict."""
    return func_box_face_contact(xa, Ra, ha, xb, Rb, hb, f, ti.cast(c.slot_aux[i_s], ti.i32), verdict,
                                 func_face_tol(ha, hb))


@ti.func
def func_face_tol(ha, hb):
    """A box pair's tol: 2 % of the two boxes' smallest half size (func_box_pair_test)."""
    return BOXEDGE_TOL * ti.min(ha.min(), hb.min())


@ti.func
def func_with_boxedge(c: ti.template(), i_b, i_s, kind, ga, gb, xa, Ra, xb, Rb, pos, n, depth):
    """(point, normal, depth) of the slot: those given, or for box edge slots the edge-edge contact and
    for box face slots the face-face crossing, at the choices of their pair's separating-axis test
    (func_box_pair_test): only the chosen edge axis is differentiated."""
    if ti.static(c.has_boxedge):
        f, i, j, verdict = func_box_choices(c, i_b, i_s, kind)
        ha = c.geom_size[ga]
        hb = c.geom_size[gb]
        pe, ne, de = func_box_edge_slot(xa, Ra, ha, xb, Rb, hb, i, j, verdict)
        be = kind == SLOT_BOXEDGE
        pos_e = ti.select(be, pe, pos)
        n_e = ti.select(be, ne, n)
        depth_e = ti.select(be, de, depth)
        if ti.static(c.has_boxface):
            pf, nf, df = func_box_face_slot(c, i_s, xa, Ra, ha, xb, Rb, hb, f, verdict)
            bf = kind == SLOT_BOXFACE
            return ti.select(bf, pf, pos_e), ti.select(bf, nf, n_e), ti.select(bf, df, depth_e)
        else:
            return pos_e, n_e, depth_e
    else:
        return pos, n, depth


@ti.func
def func_box_slot(c: ti.template(), i_b, i_s, kind, ga, gb, xa, Ra, xb, Rb):
    """(point, normal, depth) of a box pair's edge or face slot (kind, at run time), only its own (no
    gradients: runtime branches)."""
    ha = c.geom_size[ga]
    hb = c.geom_size[gb]
    f, i, j, verdict = func_box_choices(c, i_b, i_s, kind)
    pos = ti.Vector.zero(c.dtype, 3)
    n = ti.Vector.zero(c.dtype, 3)
    depth = ti.cast(0.0, c.dtype)
    if kind == SLOT_BOXEDGE:
        pos, n, depth = func_box_edge_slot(xa, Ra, ha, xb, Rb, hb, i, j, verdict)
    else:
        if ti.static(c.has_boxface):
            pos, n, depth = func_box_face_slot(c, i_s, xa, Ra, ha, xb, Rb, hb, f, verdict)
    return pos, n, depth


@ti.func
def func_is_hull_pair(c: ti.template(), ga, gb):
    """Whether pair (ga, gb) has a hull-edge slot (geoms.hull_edge_pair: two meshes, or a mesh and a box)."""
    ta = c.geom_type[ga]
    tb = c.geom_type[gb]
    return ((ta == GEOM_MESH) | (tb == GEOM_MESH)) & ((ta == GEOM_MESH) | (ta == GEOM_BOX)) & \
        ((tb == GEOM_MESH) | (tb == GEOM_BOX))


@ti.func
def func_corners_beyond(c: ti.template(), Y, nY, dY, stop):
    """The least distance beyond the plane nY . x = dY (in geom Y's frame) of Y's volume's corners
    (collision.polytope_hull): >= 0 where the plane parts Y from the side it bounds. Exact where it is at least
    `stop`; else the corners are left at the first one below `stop`, and the value returned is below it too (the
    callers only ask whether a plane beats `stop`: func_gap_mesh_planes its threshold, func_hull_face_sep the best
    plane so far, so that most planes are left after a few corners)."""
    least = ti.cast(1e30, c.dtype)
    m = 0
    while m < c.hull_n[Y, 1] and least >= stop:
        least = ti.min(least, nY.dot(c.hull_c[Y, m]) - dY)
        m += 1
    return least


@ti.func
def func_hull_face_sep(c: ti.template(), X, Y, xX, RX, xY, RY):
    """(separation, plane) of the best of geom X's face planes: the least distance of geom Y's corners beyond
    it, largest over X's planes (negative: every plane has a corner of Y inside it)."""
    dx = xX - xY
    best = ti.cast(-1e30, c.dtype)
    kb = 0
    for k in range(c.hull_n[X, 0]):
        nw = func_mv(RX, c.hull_pn[X, k])
        nY = func_mtv(RY, nw)
        dY = c.hull_pd[X, k] + nw.dot(dx)
        least = func_corners_beyond(c, Y, nY, dY, best)
        if least > best:
            best = least
            kb = k
    return best, kb


@ti.func
def func_hull_pair_test(c: ti.template(), i_b, i_p, ga, gb):
    """The separating-axis test of two convex volumes (a mesh's planes, a box; collision.polytope_hull), once
    per step for the pair's edge and face slots (the broad phase runs it for the active pairs): the best face
    axis (func_hull_face_sep, both sides), the best edge pair, and whether that edge axis separates better than
    every face axis by the pair's tol (into pair_hull, func_hull_pack); where it does not, the crossings of the
    best face's rim with the other volume's face most opposed to it (func_hull_face_crossings, into
    pair_hcross). Only the edge pairs whose Gauss-map arcs cross are axes of the Minkowski difference
    (Gregorius, "The Separating Axis Test between Convex Polyhedra", GDC 2013): edge a's two face normals
    against the negated normals of edge b's; along such an axis, turned away from a's inside, the separation
    is the axis's projection of one edge's point from the other's. The pairs are tested in b's frame; the
    axis's sign by geom a's centre (inside it)."""
    xa = c.geom_xpos[i_b, ga]
    xb = c.geom_xpos[i_b, gb]
    Ra = c.geom_xR[i_b, ga]
    Rb = c.geom_xR[i_b, gb]
    sep_a, ka = func_hull_face_sep(c, ga, gb, xa, Ra, xb, Rb)
    sep_b, kb = func_hull_face_sep(c, gb, ga, xb, Rb, xa, Ra)
    sep_f = ti.max(sep_a, sep_b)
    Rab = Rb.transpose() @ Ra
    tab = func_mtv(Rb, xa - xb)
    ca = func_mv(Rab, c.geom_center[ga]) + tab
    best = ti.cast(-1e30, c.dtype)
    bi = 0
    bj = 0
    # each of b's face normals against edge a's arc plane once (an edge's two faces are planes of hull_pn:
    # hull_ef), not twice for each of b's edges
    side = ti.Vector([0.0] * N_KDOP, dt=c.dtype)
    for i in range(c.hull_n[ga, 2]):
        p0 = func_mv(Rab, c.hull_e0[ga, i]) + tab
        da = func_mv(Rab, c.hull_e1[ga, i]) + tab - p0
        a1 = func_mv(Rab, c.hull_f1[ga, i])
        a2 = func_mv(Rab, c.hull_f2[ga, i])
        bxa = a2.cross(a1)
        for f in range(c.hull_n[gb, 0]):
            side[f] = -c.hull_pn[gb, f].dot(bxa)
        for j in range(c.hull_n[gb, 2]):
            cba = side[c.hull_ef[gb, j, 0]]
            dba = side[c.hull_ef[gb, j, 1]]
            if cba * dba < 0:
                b1 = c.hull_f1[gb, j]
                b2 = c.hull_f2[gb, j]
                dxc = b2.cross(b1)
                adc = a1.dot(dxc)
                bdc = a2.dot(dxc)
                if (adc * bdc < 0) & (cba * bdc > 0):
                    q0 = c.hull_e0[gb, j]
                    db = c.hull_e1[gb, j] - q0
                    L = da.cross(db)
                    l2 = L.dot(L)
                    if l2 > 1e-12 * da.dot(da) * db.dot(db):
                        L = L / ti.sqrt(l2)
                        if L.dot(p0 - ca) < 0:
                            L = -L
                        sep = L.dot(q0 - p0)
                        if sep > best:
                            best = sep
                            bi = i
                            bj = j
    tol = func_hull_tol(c, ga, gb)
    edge_wins = best > sep_f + tol
    c.pair_hull[i_b, i_p] = func_hull_pack(bi, bj, edge_wins)
    n_cross = 0
    if not edge_wins:
        on_b = sep_b > sep_a  # (ties: a's face, as the box pairs' test)
        n_cross = func_hull_face_crossings(c, i_b, i_p, ti.select(on_b, gb, ga), ti.select(on_b, ga, gb),
                                           ti.select(on_b, kb, ka), ti.select(on_b, 1, 0), tol)
    for m in range(n_cross, N_HULLFACE):
        c.pair_hcross[i_b, i_p, m] = -1


@ti.func
def func_hull_tol(c: ti.template(), ga, gb):
    """A volume pair's tol: 2 % of the thinner one's half thickness (func_face_tol's rule for box pairs)."""
    return BOXEDGE_TOL * ti.min(c.geom_thick[ga], c.geom_thick[gb])


@ti.func
def func_hull_face_crossings(c: ti.template(), i_b, i_p, X, Y, k, side, tol):
    """Face on face: where the edges of geom Y's incident face (its plane most opposed to X's plane k, the
    reference face) cross the reference face's rim, each at least tol from the ends of both edges (the corners
    are the point slots'), into pair_hcross[i_b, i_p, :] (func_hull_cross_pack, up to N_HULLFACE; the rest
    left to the caller). In X's frame; the rim edge's outward direction in the face's plane is its other
    face's normal less its part along the plane's. Returns how many it found."""
    xX = c.geom_xpos[i_b, X]
    RX = c.geom_xR[i_b, X]
    RXY = RX.transpose() @ c.geom_xR[i_b, Y]
    tXY = func_mtv(RX, c.geom_xpos[i_b, Y] - xX)
    nk = c.hull_pn[X, k]
    inc = 0
    least = ti.cast(1e30, c.dtype)
    for j in range(c.hull_n[Y, 0]):
        d = func_mv(RXY, c.hull_pn[Y, j]).dot(nk)
        if d < least:
            least = d
            inc = j
    n = 0
    for e in range(c.hull_n[Y, 2]):
        if (c.hull_ef[Y, e, 0] == inc) | (c.hull_ef[Y, e, 1] == inc):
            q0 = func_mv(RXY, c.hull_e0[Y, e]) + tXY
            dq = func_mv(RXY, c.hull_e1[Y, e]) + tXY - q0
            lq = ti.sqrt(dq.dot(dq))
            for r in range(c.hull_n[X, 2]):
                f0 = c.hull_ef[X, r, 0]
                if (f0 == k) | (c.hull_ef[X, r, 1] == k):
                    no = c.hull_pn[X, ti.select(f0 == k, c.hull_ef[X, r, 1], f0)]
                    sr = no - no.dot(nk) * nk
                    p0 = c.hull_e0[X, r]
                    dp = c.hull_e1[X, r] - p0
                    lp = ti.sqrt(dp.dot(dp))
                    den = sr.dot(dq)
                    if ti.abs(den) > 1e-9 * ti.sqrt(sr.dot(sr)) * lq:
                        t = sr.dot(p0 - q0) / den
                        u = (q0 + t * dq - p0).dot(dp) / (lp * lp)
                        if (t * lq > tol) & ((1.0 - t) * lq > tol) & (u * lp > tol) & ((1.0 - u) * lp > tol):
                            if n < N_HULLFACE:
                                c.pair_hcross[i_b, i_p, n] = func_hull_cross_pack(e, r, k, side)
                                n += 1
    return n


@ti.func
def func_hull_cross_pack(e, r, k, side):
    """A face-on-face crossing as one integer, pair_hcross's: incident edge e, rim edge r, reference plane k,
    and which geom of the pair holds the reference face (side 1: its second)."""
    return e + 128 * (r + 128 * (k + 32 * side))


@ti.func
def func_hull_cross_unpack(code):
    """(e, r, k, whether the reference face is the pair's second geom's) of func_hull_cross_pack's integer."""
    return code % 128, (code // 128) % 128, (code // 16384) % 32, code >= 524288


@ti.func
def func_hull_face_slot(c: ti.template(), i_b, i_s, ga, gb, xa, Ra, xb, Rb):
    """(point, normal from geom b towards geom a, depth) of hull-face slot i_s (its aux: which of its pair's
    crossings, func_hull_face_crossings): where the incident edge crosses the plane through the rim edge
    perpendicular to the reference face, midway between it and the reference face's plane; the normal the
    reference face's (turned from b to a), the depth how far the crossing lies below that plane. Depth -1 (no
    contact) where the pair has no such crossing or it lies within tol of an edge's end. Finite for every
    slot (the single-assignment form evaluates it for slots of other kinds, whose code reads edge 0)."""
    code = c.pair_hcross[i_b, c.slot_pair[i_s], ti.min(ti.max(ti.cast(c.slot_aux[i_s], ti.i32), 0), N_HULLFACE - 1)]
    e, r, k, on_b = func_hull_cross_unpack(ti.max(code, 0))
    X = ti.select(on_b, gb, ga)
    Y = ti.select(on_b, ga, gb)
    xX = ti.select(on_b, xb, xa)
    RX = ti.select(on_b, Rb, Ra)
    xY = ti.select(on_b, xa, xb)
    RY = ti.select(on_b, Ra, Rb)
    nk = func_mv(RX, c.hull_pn[X, k])
    f0 = c.hull_ef[X, r, 0]
    nl = c.hull_pn[X, ti.select(f0 == k, c.hull_ef[X, r, 1], f0)]
    sr = func_mv(RX, nl - nl.dot(c.hull_pn[X, k]) * c.hull_pn[X, k])
    p0 = xX + func_mv(RX, c.hull_e0[X, r])
    dp = func_mv(RX, c.hull_e1[X, r] - c.hull_e0[X, r])
    q0 = xY + func_mv(RY, c.hull_e0[Y, e])
    dq = func_mv(RY, c.hull_e1[Y, e] - c.hull_e0[Y, e])
    den = sr.dot(dq)
    ok = ti.abs(den) > 1e-9 * ti.sqrt(sr.dot(sr) * dq.dot(dq) + TINY)
    t = sr.dot(p0 - q0) / ti.select(ok, den, 1.0)
    x = q0 + t * dq
    lq = ti.sqrt(dq.dot(dq) + TINY)
    lp = ti.sqrt(dp.dot(dp) + TINY)
    u = (x - p0).dot(dp) / ti.max(lp * lp, ti.static(div_floor()))
    depth = c.hull_pd[X, k] + nk.dot(xX) - nk.dot(x)
    tol = func_hull_tol(c, ga, gb)
    inner = ok & (code >= 0) & (t * lq > tol) & ((1.0 - t) * lq > tol) & (u * lp > tol) & ((1.0 - u) * lp > tol)
    # (a slot without a crossing takes the rim edge's start as its point: x is then anywhere on the incident
    # edge's line, metres away, and the solve's speculative test reads the point's speed)
    return (ti.select(inner, x + (0.5 * depth) * nk, p0), ti.select(on_b, nk, -nk),
            ti.select(inner, depth, -1.0))


@ti.func
def func_hull_pack(i, j, edge_wins):
    """func_hull_pair_test's choices as one integer, pair_hull's: i + N (j + N edge_wins), N the edges' capacity."""
    return i + N_HULL_EDGES * (j + ti.select(edge_wins, N_HULL_EDGES, 0))


@ti.func
def func_hull_unpack(code):
    """(i, j, edge_wins) of func_hull_pack's integer."""
    return code % N_HULL_EDGES, (code // N_HULL_EDGES) % N_HULL_EDGES, code >= N_HULL_EDGES * N_HULL_EDGES


@ti.func
def func_hull_edge_slot(c: ti.template(), i_b, i_s, ga, gb, xa, Ra, xb, Rb):
    """(point midway between the two edges, normal from geom b towards geom a, depth) of a hull-edge slot, at
    its pair's test's edge pair (func_hull_pair_test: edge i of a, edge j of b): the edges' closest points and
    the separation along their cross product, turned away from a's inside. Depth -1 (no contact) unless the
    edge axis beat every face axis and the closest points lie inside both edges (else corners and faces carry
    the contact: the point slots). Finite for every slot (the single-assignment form evaluates it for slots
    of other kinds, whose code reads edge 0)."""
    i, j, verdict = func_hull_unpack(c.pair_hull[i_b, c.slot_pair[i_s]])
    pa0 = xa + func_mv(Ra, c.hull_e0[ga, i])
    pa1 = xa + func_mv(Ra, c.hull_e1[ga, i])
    pb0 = xb + func_mv(Rb, c.hull_e0[gb, j])
    pb1 = xb + func_mv(Rb, c.hull_e1[gb, j])
    pa, pb = func_segment_closest(pa0, pa1, pb0, pb1)
    da = pa1 - pa0
    db = pb1 - pb0
    C = da.cross(db)
    Lu = C / ti.max(ti.sqrt(C.dot(C) + TINY), ti.static(div_floor()))
    L = ti.select(Lu.dot(pa0 - xa - func_mv(Ra, c.geom_center[ga])) >= 0, Lu, -Lu)
    ta = (pa - pa0).dot(da) / ti.max(da.dot(da), ti.static(div_floor()))
    tb = (pb - pb0).dot(db) / ti.max(db.dot(db), ti.static(div_floor()))
    inner = (ta > 1e-9) & (ta < 1.0 - 1e-9) & (tb > 1e-9) & (tb < 1.0 - 1e-9)
    return 0.5 * (pa + pb), -L, ti.select(verdict & inner, -L.dot(pb0 - pa0), -1.0)


@ti.func
def func_with_hulledge(c: ti.template(), i_b, i_s, kind, ga, gb, xa, Ra, xb, Rb, pos, n, depth):
    """(point, normal, depth) of the slot: those given, or for hull-edge slots the edge-edge contact and for
    hull-face slots the face-on-face crossing."""
    if ti.static(c.has_hulledge):
        pe, ne, de = func_hull_edge_slot(c, i_b, i_s, ga, gb, xa, Ra, xb, Rb)
        pf, nf, df = func_hull_face_slot(c, i_b, i_s, ga, gb, xa, Ra, xb, Rb)
        he = kind == SLOT_HULLEDGE
        hf = kind == SLOT_HULLFACE
        return (ti.select(he, pe, ti.select(hf, pf, pos)), ti.select(he, ne, ti.select(hf, nf, n)),
                ti.select(he, de, ti.select(hf, df, depth)))
    else:
        return pos, n, depth


@ti.func
def func_slot_geometry(s: ti.template(), i_b, i_s):
    """(contact point, normal from the SDF side to the point side, depth) of slot i_s; depth > 0 is
    penetration. Without gradients only the slot's own kind and the SDF side's own type are evaluated
    (func_slot_geometry_branched); with them every kind and type the scene has, selected (the
    single-assignment form of the differentiated stages): the same expressions either way."""
    if ti.static(not s.requires_grad):
        return func_slot_geometry_branched(s, i_b, i_s)
    else:
        return func_slot_geometry_selected(s, i_b, i_s)


@ti.func
def func_slot_contact_point(c: ti.template(), gb, pt, n, ra, phi):
    """The contact point: on the point side's surface against a static geom (where that side's velocity
    and Jacobian belong: a speculative contact's gap can be centimetres, and a fast-turning link's
    velocity changes across it), else midway between the two surfaces."""
    mid = pt - n * (0.5 * (ra + phi))
    return ti.select(c.link_dyn[c.geom_link[gb]] == 1, mid, pt - n * ra)


@ti.func
def func_slot_sides(c: ti.template(), i_b, i_s):
    """Slot i_s's kind, its point side's geom ga and SDF side's gb, and their world poses."""
    ga = c.slot_ga[i_s]
    gb = c.slot_gb[i_s]
    return c.slot_kind[i_s], ga, gb, c.geom_xpos[i_b, ga], c.geom_xR[i_b, ga], c.geom_xpos[i_b, gb], c.geom_xR[i_b, gb]


@ti.func
def func_slot_geometry_branched(s: ti.template(), i_b, i_s):
    """func_slot_geometry with runtime branches: a box pair's edge and face slots take the separating-axis
    test alone, the other slots the SDF of their SDF side's type alone (a box corner on the ground no longer
    evaluates the meshes' planes and the boxes' axes of a scene that has them)."""
    c = s.contact
    kind, ga, gb, xa, Ra, xb, Rb = func_slot_sides(c, i_b, i_s)
    pos = ti.Vector.zero(c.dtype, 3)
    n = ti.Vector.zero(c.dtype, 3)
    depth = ti.cast(0.0, c.dtype)
    box_kind = False
    if ti.static(c.has_boxedge):
        box_kind = (kind == SLOT_BOXEDGE) | (kind == SLOT_BOXFACE)
    hull_kind = False
    if ti.static(c.has_hulledge):
        hull_kind = (kind == SLOT_HULLEDGE) | (kind == SLOT_HULLFACE)
    if box_kind:
        if ti.static(c.has_boxedge):
            pos, n, depth = func_box_slot(c, i_b, i_s, kind, ga, gb, xa, Ra, xb, Rb)
    elif hull_kind:
        if ti.static(c.has_hulledge):
            if kind == SLOT_HULLEDGE:
                pos, n, depth = func_hull_edge_slot(c, i_b, i_s, ga, gb, xa, Ra, xb, Rb)
            else:
                pos, n, depth = func_hull_face_slot(c, i_b, i_s, ga, gb, xa, Ra, xb, Rb)
    else:
        ra = c.slot_r[i_s]
        zb = ti.Vector([Rb[0, 2], Rb[1, 2], Rb[2, 2]])
        seg = False
        if ti.static(c.has_segseg):
            seg = kind == SLOT_SEGSEG
        if seg:
            if ti.static(c.has_segseg):
                za = ti.Vector([Ra[0, 2], Ra[1, 2], Ra[2, 2]])
                pt, phi, nw = func_segseg(c, ga, gb, xa, za, xb, zb)
                pos = func_slot_contact_point(c, gb, pt, nw, ra, phi)
                n = nw
                depth = ra - phi
        else:
            p = func_slot_point(c, i_s, kind, ga, xa, Ra, zb)
            q = func_mtv(Rb, p - xb)
            cl = func_mtv(Rb, xa + func_mv(Ra, c.geom_center[ga]) - xb) - c.geom_center[gb]
            chat = cl / ti.sqrt(cl.dot(cl) + 1e-24)
            phi, n_loc = func_sdf_branched(c, c.geom_type[gb], gb, q, chat, c.geom_beta[gb])
            nw = func_mv(Rb, n_loc)
            pos = func_slot_contact_point(c, gb, p, nw, ra, phi)
            n = nw
            depth = ra - phi
    return pos, n, depth


@ti.func
def func_slot_geometry_selected(s: ti.template(), i_b, i_s):
    """func_slot_geometry in single-assignment form: every kind's and type's geometry, selected."""
    c = s.contact
    kind, ga, gb, xa, Ra, xb, Rb = func_slot_sides(c, i_b, i_s)
    ra = c.slot_r[i_s]
    za = ti.Vector([Ra[0, 2], Ra[1, 2], Ra[2, 2]])
    zb = ti.Vector([Rb[0, 2], Rb[1, 2], Rb[2, 2]])
    p = func_slot_point(c, i_s, kind, ga, xa, Ra, zb)
    q = func_mtv(Rb, p - xb)
    # unit direction from the SDF geom's centre to the point geom's centre, in the SDF frame
    cl = func_mtv(Rb, xa + func_mv(Ra, c.geom_center[ga]) - xb) - c.geom_center[gb]
    chat = cl / ti.sqrt(cl.dot(cl) + 1e-24)
    phi_sdf, n_loc = func_sdf_any(c, 0, c.geom_type[gb], gb, q, chat, c.geom_beta[gb])
    pt, phi, n = func_with_segseg(c, kind, ga, gb, xa, za, xb, zb, p, phi_sdf, func_mv(Rb, n_loc))
    depth = ra - phi
    cp = func_slot_contact_point(c, gb, pt, n, ra, phi)
    pos_b, n_b, depth_b = func_with_boxedge(c, i_b, i_s, kind, ga, gb, xa, Ra, xb, Rb, cp, n, depth)
    return func_with_hulledge(c, i_b, i_s, kind, ga, gb, xa, Ra, xb, Rb, pos_b, n_b, depth_b)


# stages that write no float: their adjoint is empty, and the gradient path's backward does not run it
NO_ADJOINT = (func_broad_phase,)
