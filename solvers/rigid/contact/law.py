"""The contact force law (see the package docstring): the smoothed normal force of the depth now and
at the end of the step, and the rotational correction of the predicted depth. Pure functions of one
slot's numbers; the friction law is applied where its inputs are known (passes.py)."""
import taichi as ti

from ..math3d import div_floor
from ..collision import GEOM_CAPSULE, GEOM_CYLINDER, GEOM_SPHERE, SLOT_BOXEDGE, SLOT_BOXFACE, SLOT_HULLEDGE, SLOT_HULLFACE

# slots whose depth is below -MARGIN_WIDTHS * delta carry no force (softplus(-20) ~ 2e-9)
MARGIN_WIDTHS = 20.0
# a pair whose effective mass m_eff is above k HEAVY_TIME^2 (heavy_mass: 10 kg at the default k of 1e5 N/m) gets
# its contact stiffness (and a fixed damping) scaled by m_eff / heavy_mass (func_heavy_scale): the options' k is
# per contact point, in N/m, which holds a body of a few kg within a millimetre but lets a 400 t box sink metres.
# Scaling k by the mass keeps the contact's time constant sqrt(m / k) at most HEAVY_TIME, as MuJoCo's solref does
# for every body (its constraint stiffness follows the effective mass: 0.11 mm for the 400 t box). Below
# heavy_mass the stiffness is the options' N/m: robots' links, tools and props keep it. The damping is critical
# for each pair (RigidOptions.contact_damping_ratio, 1 by default: see func_normal_law), or the fixed
# RigidOptions.contact_damping (scaled like k for a heavy pair) when that is given. (With k = 1e6, the default
# until 2026-12-05, heavy_mass is 100 kg, the fixed threshold of before.)
HEAVY_TIME = 0.01


def heavy_mass(k):
    """The effective mass (kg) above which a pair's contact stiffness k (N/m per point) is scaled up."""
    return k * HEAVY_TIME ** 2
# the mass-relative damping (the default) is at least STEP_DAMPING k h: the damper's time
# constant c / k spans at least STEP_DAMPING steps. At a coarse step (h well above the contact's sqrt(m_eff / k)) the
# implicit step of a critically damped hinge spring chatters (a box resting on another at dt = 10 ms
# alternated 11 um in depth every other step and was thrown off after 0.7 s); this floor keeps such
# steps as damped, relative to k, as the fixed 4e4 N s/m on 1e6 N/m (the default until 2026-12-05) was at
# dt = 10 ms (4 * 1e6 * 0.01), and fades
# as h shrinks, leaving the dt-independent critical law once h < zeta sqrt(m_eff / k) / 2 (MuJoCo
# keeps its constraints' time constant at least 2 dt, solref's safety clamp, for the same reason)
STEP_DAMPING = 4.0
# the mass-relative damper's mass of a link through its articulation is at most this many times its own
MAX_WEIGHED_MASS = 1e4
# friction's load (RigidOptions(friction_load="coulomb"), the default) is at most this many times the
# frictionless solve's (passes.func_coulomb_load): Coulomb's forces applied explicitly can overshoot and predict a
# load far off (measured 2026-12-01, before a free body's gyroscopic moment was implicit: uncapped, and at 1.25,
# a pile of thrown bodies, tests/workers/broad_phase_pile.py, went to NaN)
LOAD_SHIFT = 2.0
# a link lighter than this (a massless frame) counts as this heavy in m_eff: 1 / 0 has no adjoint
MIN_LINK_MASS = 1e-9


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
def func_link_invmass(s: ti.template(), i_b, l, n):
    """(own, weighed): link l's inverse mass, its own 1 / mass, and the inverse mass along the normal n
    the mass-relative damper takes: n.W n, W the inverse weight of the link's centre of mass through its
    articulation at the initial configuration (ContactSolver.set_link_weights: a foot moves with the leg
    and the body above it, ANYmal's with about 13 times its own mass), at least MAX_WEIGHED_MASS times less
    than its own (a direction its joints cannot move it in has n.W n = 0), or its own where the link moves
    alone (a free body: link_wmass 1); both 0 for a static link."""
    c = s.contact
    own = ti.select(c.link_dyn[l] == 1, 1.0 / ti.max(s.link_mass[i_b, l], MIN_LINK_MASS), 0.0)
    weighed = own
    if ti.static(c.zeta > 0.0):
        weighed = ti.select(c.link_wmass[l] == 1, own, ti.max(n.dot(c.link_W[l] @ n), own / MAX_WEIGHED_MASS))
    return own, weighed


@ti.func
def func_heavy_scale(s: ti.template(), i_b, i_s, n):
    """(heavy, scale, inv): whether slot i_s's pair is heavier than heavy_mass(k), m_eff / heavy_mass(k) (the
    factor on its stiffness, and on a fixed damping: see HEAVY_TIME) and the inverse mass the
    mass-relative damper takes; m_eff = 1 / (1 / m_a + 1 / m_b) over the sides that move (a static side
    is infinitely heavy), each side its own link's mass: a light link pressed by a heavy load through its
    joints (a foot under a heavy robot) keeps the options' stiffness. The damper's inverse mass sums
    each side's along the normal n through its articulation (func_link_invmass)."""
    c = s.contact
    own_a, w_a = func_link_invmass(s, i_b, c.geom_link[c.slot_ga[i_s]], n)
    own_b, w_b = func_link_invmass(s, i_b, c.geom_link[c.slot_gb[i_s]], n)
    own = own_a + own_b
    hm = ti.static(heavy_mass(c.k))
    heavy = own * hm < 1.0
    # own > 0 on the heavy side; the other side's value is never used (nor its adjoint: 0)
    scale = ti.select(heavy, 1.0 / (ti.max(own, ti.static(div_floor())) * hm), 1.0)
    return heavy, scale, w_a + w_b


@ti.func
def func_normal_law(c: ti.template(), depth, depth_end, h, heavy, scale, inv):
    """(normal force, slope h * dF/d(approach speed)) of the implicit law for the depth now and the
    depth predicted for the end of the step, and the force of the current state alone (the spring on
    the current depth and the damper on the current approach). heavy, scale, inv: func_heavy_scale's.
    The stiffness is c.k, times `scale` for a heavy pair. The damping is the pair's critical damping
    times c.zeta (RigidOptions.contact_damping_ratio, 1 by default), 2 zeta sqrt(k m_eff), or STEP_DAMPING h k if
    more, when c.zeta > 0 (the default), else the fixed c.d (RigidOptions.contact_damping given) times `scale`;
    each side of the kink is its own branch (ti.select),
    exact on its side."""
    z = depth / c.delta
    zp = depth_end / c.delta
    # clamped so that exp stays finite in the adjoint (the force is ~0 below -MARGIN_WIDTHS anyway)
    zc = ti.min(ti.max(z, -60.0), 60.0)
    zpc = ti.min(ti.max(zp, -60.0), 60.0)
    sp = func_softplus(z, zc)
    spp = func_softplus(zp, zpc)
    sg = 1.0 / (1.0 + ti.exp(-zpc))
    if ti.static(c.zeta > 0.0):
        # mass-relative damping: the contact's damping ratio is zeta for every pair, light or heavy, so
        # its fastest time scale is sqrt(m_eff / k) / (2 zeta) whatever the mass (a fixed damper of
        # 4e4 N s/m gave a 0.3 kg foot 1e-5 s, which no practical step resolves: the quadruped drop did
        # not converge as dt shrank, issue #24)
        k = c.k * scale
        d = ti.max((2.0 * c.zeta) * ti.sqrt(k / ti.max(inv, ti.static(div_floor()))), STEP_DAMPING * h * k)
        return func_spring_damper(c.delta, k, d, h, sp, spp, sg, zc, depth, depth_end)
    else:
        # the heavy law spelled out with its own k and c, not as scale * fn: LLVM's fast math folds
        # select(heavy, scale * fn, fn) into fn * select(heavy, scale, 1) and regroups that product with
        # fn's terms, which moved the light law's rounding (a contact scene's gradient build left main's
        # trajectory by 1e-19 m in its first steps). Spelled out, a light pair's forces are the options'
        # law's to the bit; its gradients move at rounding level (the adjoint sums are regrouped)
        fl, wl, fl_now = func_spring_damper(c.delta, c.k, c.d, h, sp, spp, sg, zc, depth, depth_end)
        fh, wh, fh_now = func_spring_damper(c.delta, c.k * scale, c.d * scale, h, sp, spp, sg, zc, depth, depth_end)
        return ti.select(heavy, fh, fl), ti.select(heavy, wh, wl), ti.select(heavy, fh_now, fl_now)


@ti.func
def func_spring_damper(delta, k, d, h, sp, spp, sg, zc, depth, depth_end):
    """func_normal_law's three values for stiffness k and damping d, given the softplus of the depth now
    (sp) and at the end of the step (spp), the sigmoid of the latter (sg) and the clamped z (zc)."""
    ch = d / h
    fn = (k + ch) * delta * spp - ch * delta * sp
    wn = h * (d + h * k) * sg
    fn_now = k * delta * sp - d / (1.0 + ti.exp(-zc)) * (depth - depth_end) / h
    return fn, wn, fn_now


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
    # pos is midway between the two surfaces against a moving geom and for edge and face slots, else
    # on the point side's surface (func_slot_geometry)
    kind = c.slot_kind[i_s]
    mid = (c.link_dyn[lb] == 1) | (kind == SLOT_BOXEDGE) | (kind == SLOT_BOXFACE) | (kind == SLOT_HULLEDGE) | (kind == SLOT_HULLFACE)
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
