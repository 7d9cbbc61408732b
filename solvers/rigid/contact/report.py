"""What the contact solver tells its scene and the user: the forces each step applied (for the entity
API's readers) and the deep-penetration watch (ContactPenetrationWarning, deep_contact_message)."""
import numpy as np
import taichi as ti

from ..collision import GEOM_BOX, GEOM_CAPSULE, GEOM_CYLINDER, GEOM_MESH, GEOM_SPHERE
from .law import heavy_mass
from .passes import func_link_motion, func_normal_after, func_rel_motion

# a contact whose depth at the end of a step exceeds this fraction of the thinner geom's half
# thickness has gone (or is going) through it: the scene warns (ContactSolver.watch). Half: the
# thinner body's middle has reached the other's surface, past which its normal can flip. (A quarter
# warned on ANYmal's ordinary 1.6 m/s foot landing at dt = 0.01 s: 5.6 mm into a 15 mm shank.)
DEEP_FRACTION = 0.5
# the watch warns once per pair of geoms, for at most this many pairs a scene (ContactSolver.watch)
MAX_DEEP_WARNINGS = 3


class ContactPenetrationWarning(UserWarning):
    """A contact ended a step deeper than DEEP_FRACTION of the thinner geom's half thickness: the
    penalty contact could not stop the body within the step (too fast for dt, or too heavy for
    RigidOptions.contact_stiffness), so it sinks into or tunnels through the other body."""


@ti.func
def func_contact_report(s: ti.template(), i_b, e):
    """The forces the step applied (normal and friction at the final velocity), for the entity API's
    readers: not differentiated, own link-velocity fields."""
    c = s.contact
    c.eval_count[i_b] = c.eval_count[i_b] + 1
    func_link_motion(s, s.qacc, e, i_b, c.link_w_report, c.link_v_report)
    if ti.static(s.requires_grad):
        for i_s in range(c.n_slots):
            if (c.sl_on[i_b, i_s] == 1) & (c.sl_in_now[i_b, i_s] == 1):
                func_report_slot(s, i_b, i_s)
            else:
                func_report_none(s, i_b, i_s)
    else:
        # the other slots' c_fn and c_force are left as they were: read() masks them with sl_on (as it
        # masks inactive pairs), and sl_in_now is only read where sl_on is set
        for k in range(c.n_on[i_b]):
            i_s = c.sl_list[i_b, k]
            if c.sl_in_now[i_b, i_s] == 1:
                func_report_slot(s, i_b, i_s)
            else:
                func_report_none(s, i_b, i_s)


@ti.func
def func_report_none(s: ti.template(), i_b, i_s):
    """A touching slot out of the final system applied no force."""
    s.contact.c_fn[i_b, i_s] = 0.0
    s.contact.c_force[i_b, i_s] = ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)


@ti.func
def func_report_slot(s: ti.template(), i_b, i_s):
    c = s.contact
    pos = c.sl_pos[i_b, i_s]
    n = c.sl_n[i_b, i_s]
    u0 = c.sl_u[i_b, i_s]
    u3 = u0 + func_rel_motion(s, i_b, i_s, pos, c.link_w_report, c.link_v_report)
    f3 = func_normal_after(c, i_b, i_s, u0, u3, n)
    c.c_fn[i_b, i_s] = ti.max(f3, 0.0)
    c.c_force[i_b, i_s] = f3 * n - c.sl_eta_now[i_b, i_s] * (u3 - u3.dot(n) * n)
    # the depth the step ends at (the linear prediction with the final velocity): far past the
    # surface, the contact has not stopped the body. Per env, the first evaluation with such a
    # contact is recorded (its deepest one relative to the limit) for watch()
    depth_end = c.sl_depth[i_b, i_s] - c.sl_corr[i_b, i_s] - c.eval_h[i_b] * u3.dot(n)
    lim = DEEP_FRACTION * ti.min(c.geom_thick[c.slot_ga[i_s]], c.geom_thick[c.slot_gb[i_s]])
    if (depth_end > lim) & (c.pair_warned[c.slot_pair[i_s]] == 0):
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


def _user_stacklevel() -> int:
    """warnings.warn's stacklevel, called from ContactSolver.watch, that names the first frame outside
    this library (the user's scene.step())."""
    import os
    import sys

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
    ours = (os.path.join(root, "solvers") + os.sep, os.path.join(root, "genesis_lite") + os.sep)
    f, level = sys._getframe(2), 2  # level 1: watch, the caller of warnings.warn
    while f is not None and f.f_code.co_filename.startswith(ours):
        f, level = f.f_back, level + 1
    return level


def geom_half_thickness(geoms) -> np.ndarray:
    """(G,) half the thinnest extent of each geom (box: smallest half size; sphere, capsule: radius;
    cylinder: radius or half length; mesh: half its hull's thinnest width across its SDF's plane normals,
    collision.hull_planes; plane: inf)."""
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
            out[g] = geoms.half_thick[g]
    return out


def deep_contact_message(plan, i_s, i_b, n_envs, step, h, depth, speed, lim, gain, last=False):
    """What the deep-penetration watch tells the user: who, when, how deep, why and what to do."""
    geoms = plan.geoms
    ga, gb = int(plan.np_slot_ga[i_s]), int(plan.np_slot_gb[i_s])
    env = f" in env {i_b}" if n_envs > 1 else ""
    fast = gain > 1.0  # it went deeper than the limit within this one step
    heavy = heavy_mass(plan.k)
    approach = f" (approach speed {speed:.3g} m/s: {speed * h:.3g} m per step)" if speed > 0 else ""
    why = (f"it went {gain * lim:.3g} m deeper within one step of {h:g} s{approach}: too fast for the penalty "
           "contact to stop within a step" if fast else
           f"its contact stiffness (RigidOptions.contact_stiffness = {plan.k:g} N/m per contact point, times "
           f"m / {heavy:g} kg for a pair of effective mass m above {heavy:g} kg) cannot hold its weight "
           "and the loads on it (a light body carrying a heavy one keeps its own stiffness)")
    todo = ("use a smaller dt or more substeps (SimOptions.substeps), or raise RigidOptions.contact_stiffness"
            if fast else
            f"raise RigidOptions.contact_stiffness (penetration ~ load / stiffness; {plan.k:g} N/m now) and "
            "(with a fixed RigidOptions.contact_damping) the damping, or lighten the body")
    return (f"contact between {geoms.names[ga]} and {geoms.names[gb]}{env}: at step {step} it ended "
            f"{depth:.3g} m deep, more than {lim:.3g} m ({DEEP_FRACTION:g} of the thinner geom's half thickness): "
            f"the body is sinking into or passing through the other; {why}. To fix: {todo}. "
            f"(Warned once per pair of geoms, for at most {MAX_DEEP_WARNINGS} pairs a scene"
            + ("; this is the last.)" if last else ".)"))
