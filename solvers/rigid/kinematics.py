"""Stage 1, kinematics: link poses, world-frame joint motion subspaces (cdof), link velocities.

Differentiated stages here and in the other stage modules are written in single-assignment form:
every local is assigned once and joint-type cases are blended with ti.select or 0/1 masks instead
of if/else assignments. Taichi's reverse mode turns any local stored twice inside a loop into an
"adstack", which made the gradient kernels take minutes to compile; in this form they take seconds.
A branch whose every local is assigned once inside it is the same form: the joint-type branches around
a link's stores with gradients keep the free joint's reads to free joints (func_free_pose).
Reads at clamped indices feed only masked-out terms. A root link's (masked-out) parent reads go to
the world slot (func_parent_slot), not to a link this stage writes later.
"""
import taichi as ti

from .layout import func_take
from .math3d import (func_axis_angle_quat, func_cross_motion, func_mtv, func_mv, func_quat_mul, func_quat_mul_adjoint,
                     func_quat_rotate, func_quat_rotate_adjoint, func_quat_to_R, func_quat_to_R_adjoint,
                     func_rotate_inertia)

JOINT_FIXED, JOINT_FREE, JOINT_REVOLUTE, JOINT_PRISMATIC = 0, 1, 2, 3


@ti.func
def func_vec3(x: ti.template(), a, b, i):
    return ti.Vector([x[a, b, i], x[a, b, i + 1], x[a, b, i + 2]])


@ti.func
def func_free_twist(s: ti.template(), i_b, src, d0):
    """A free joint's six velocities from its first dof d0: the base origin's world velocity vb and the world
    angular velocity wb."""
    return func_vec3(s.qvel, src, i_b, d0), func_vec3(s.qvel, src, i_b, d0 + 3)


@ti.func
def func_hinge_rate(s: ti.template(), i_b, src, i_l):
    """With gradients, for a link whose joint is not free: (d0, qd) its dof (a clamped index) and velocity, qd
    = 0 for a fixed joint (single assignment; a free joint's link is func_free_velocity's)."""
    d0 = ti.min(s.link_dof_start[i_l], s.qvel_len - 1)
    return d0, s.qvel[src, i_b, d0] * ti.cast(s.link_ndof[i_l] == 1, s.dtype)


@ti.func
def func_link_joint_velocity(s: ti.template(), i_b, src, i_l):
    """Without gradients, the velocity a link's own joint contributes, for the two joint shapes that have dofs:
    (d0, qd) the dof and velocity of a 1-dof joint (qd = 0 otherwise), and (free, vb, wb) a 0/1 mask and a free
    joint's func_free_twist (zero otherwise); only the link's own joint type is read."""
    d0 = ti.min(s.link_dof_start[i_l], s.qvel_len - 1)
    nd = s.link_ndof[i_l]
    qd = ti.cast(0.0, s.dtype)
    free = ti.cast(0.0, s.dtype)
    vb = ti.Vector.zero(s.dtype, 3)
    wb = ti.Vector.zero(s.dtype, 3)
    if nd == 1:
        qd = s.qvel[src, i_b, d0]
    elif nd == 6:
        free = 1.0
        vb, wb = func_free_twist(s, i_b, src, d0)
    return d0, qd, free, vb, wb


@ti.func
def func_joint_pose(s: ti.template(), i_b, src, jt, qs, axis, jpos, jquat):
    """The pose (pos, quat) a link's joint gives it from the joint frame's pose (jpos, jquat) and
    qpos[src]. With gradients the fixed, revolute and prismatic joints' formulas are evaluated and blended
    (single assignment, reads at clamped indices, see above; a free joint's link is func_free_pose's);
    without, only the link's own."""
    if ti.static(s.requires_grad):
        q1 = s.qpos[src, i_b, ti.min(qs, s.qpos_len - 1)]
        rev = ti.cast(jt == JOINT_REVOLUTE, s.dtype)
        pri = ti.cast(jt == JOINT_PRISMATIC, s.dtype)
        return jpos + func_quat_rotate(jquat, axis * (q1 * pri)), func_quat_mul(jquat, func_axis_angle_quat(axis, q1 * rev))
    else:
        pos = jpos
        quat = jquat
        if jt == JOINT_REVOLUTE:
            quat = func_quat_mul(jquat, func_axis_angle_quat(axis, s.qpos[src, i_b, qs]))
        elif jt == JOINT_PRISMATIC:
            pos = jpos + func_quat_rotate(jquat, axis * s.qpos[src, i_b, qs])
        elif jt == JOINT_FREE:
            pos = func_vec3(s.qpos, src, i_b, qs)
            quat = func_free_quat(s, i_b, src, qs)
        return pos, quat


@ti.func
def func_link_origin(s: ti.template(), i_b, i_l):
    """The point the spatial algebra of link i_l's kinematic tree is about: its root link's origin (fixed in
    space over the evaluation: its motion is not differentiated in time). Motion subspaces (cdof), link
    velocities (cvel: the velocity of the point of the link at this origin), spatial inertias (link_h, link_J)
    and the wrenches onto links are all about it. About the world origin instead, a light body far from it lost
    its rotation's digits in float32 (J = I_c + m |c|^2 ...: a 38 g cube 1 m away spun 4 % off in 4 s,
    tests/test_precision.py), as in MuJoCo's and Genesis's frames at a tree's centre of mass. Any point fixed
    over the evaluation gives the same dynamics; a tree rooted at the world origin keeps its numbers."""
    return s.link_pos[i_b, s.link_root[i_l]]


@ti.func
def func_point_velocity(s: ti.template(), lw: ti.template(), lv: ti.template(), i_b, i_l, x):
    """The velocity of the world point x moving with link i_l, from link spatial velocities lw, lv [env, link]
    about the link's tree's origin (func_link_origin): lv + lw x (x - o). lw, lv: cvel_w, cvel_v, or another
    velocity vector's (contact.passes.func_link_motion)."""
    return lv[i_b, i_l] + lw[i_b, i_l].cross(x - func_link_origin(s, i_b, i_l))


@ti.func
def func_parent_slot(s: ti.template(), p):
    """Where link data of parent p is read: p itself, or for a root (p = -1) the core's last link slot,
    which no scene's link occupies (the element capacity exceeds n_links) and nothing writes. Reading
    slot 0 instead would read, for link 0, the entry the loop is about to overwrite: a masked-out read,
    but one that breaks the global data access rule of Taichi's reverse mode (ti.ad.Tape(validation=
    True) rejects it)."""
    return ti.select(p >= 0, p, s.cap_elems - 1)


@ti.func
def func_free_quat(s: ti.template(), i_b, src, qs):
    """A free joint's orientation: its four qs from qs + 3 on, normalised."""
    fq = ti.Vector([s.qpos[src, i_b, qs + 3], s.qpos[src, i_b, qs + 4], s.qpos[src, i_b, qs + 5], s.qpos[src, i_b, qs + 6]])
    return fq / ti.sqrt(ti.max(fq.dot(fq), 1e-30))


@ti.func
def func_free_pose(s: ti.template(), i_b, e, src, h):
    """With gradients, the pose of each free joint's link, over the list of free joints (core.free_link),
    ahead of func_forward_kinematics, which leaves those links out: such a link is a root (model.py), and its
    pose is its qs (position, normalised quaternion). Blended into every link's formula instead (as until
    2026-12-05), the free joint's seven reads and its normalisation were differentiated at every link of every
    robot: a fixed-base Panda's backward took ~9 % longer (results/grad.md). Nothing without gradients
    (func_joint_pose's branch: the same numbers)."""
    if ti.static(s.requires_grad):
        for t in range(s.n_free_links):
            i_l = s.free_link[t]
            qs = s.link_q_start[i_l]
            quat = func_free_quat(s, i_b, src, qs)
            s.link_pos[i_b, i_l] = func_vec3(s.qpos, src, i_b, qs)
            s.link_quat[i_b, i_l] = quat
            s.link_R[i_b, i_l] = func_quat_to_R(quat)


@ti.func
def func_link_pose(s: ti.template(), i_b, src, i_l):
    """Link i_l's origin position and orientation (quat and R) from its parent's pose and qpos[src]."""
    p = s.link_parent[i_l]
    jt = s.link_jtype[i_l]
    qs = s.link_q_start[i_l]
    has_p = p >= 0
    pp = func_parent_slot(s, p)
    ppos = ti.select(has_p, s.link_pos[i_b, pp], ti.Vector([0.0, 0.0, 0.0], dt=s.dtype))
    pquat = ti.select(has_p, s.link_quat[i_b, pp], ti.Vector([1.0, 0.0, 0.0, 0.0], dt=s.dtype))
    jquat = func_quat_mul(pquat, s.link_jquat[i_l])
    jpos = ppos + func_quat_rotate(pquat, s.link_jpos[i_l])
    pos, quat = func_joint_pose(s, i_b, src, jt, qs, s.link_jaxis[i_l], jpos, jquat)
    s.link_pos[i_b, i_l] = pos
    s.link_quat[i_b, i_l] = quat
    s.link_R[i_b, i_l] = func_quat_to_R(quat)


@ti.func
def func_forward_kinematics(s: ti.template(), i_b, e, src, h):
    """Link origin positions and orientations (quat and R) from qpos[src]; with gradients those of the
    links of free joints are func_free_pose's."""
    for i_l in range(s.n_links):
        if ti.static(s.requires_grad):
            if s.link_jtype[i_l] != JOINT_FREE:
                func_link_pose(s, i_b, src, i_l)
        else:
            func_link_pose(s, i_b, src, i_l)


@ti.func
def func_world_inertia(s: ti.template(), i_b, e, src, h):
    """COM and spatial inertia about the tree's origin (func_link_origin): mass, first moment m c, J = I_c -
    m [c]x[c]x, c the COM from that origin.
    Without gradients it also starts the composite inertias (inertia.func_link_inertia's copy, here
    while the values are in registers: a pass over the links less) and skips link_cpos, which no
    stage reads."""
    for i_l in range(s.n_links):
        R = s.link_R[i_b, i_l]
        c = s.link_pos[i_b, i_l] - func_link_origin(s, i_b, i_l) + func_mv(R, s.link_com[i_b, i_l])
        m = s.link_mass[i_b, i_l]
        mc = m * c
        J = func_rotate_inertia(R, s.link_inertia[i_b, i_l]) + m * (c.dot(c) * ti.Matrix.identity(s.dtype, 3) - c.outer_product(c))
        s.link_h[i_b, i_l] = mc
        s.link_J[i_b, i_l] = J
        if ti.static(s.requires_grad):
            s.link_cpos[i_b, i_l] = c
        else:
            s.crb_m[i_b, i_l] = m
            s.crb_h[i_b, i_l] = mc
            s.crb_J[i_b, i_l] = J


@ti.func
def func_dof_subspace(s: ti.template(), i_b, e, src, h):
    """cdof: the spatial motion each dof produces per unit velocity, in world frame about the tree's origin."""
    for i_d in range(s.n_dofs):
        i_l = s.dof_link[i_d]
        jt = s.link_jtype[i_l]
        k = i_d - s.link_dof_start[i_l]
        pos = s.link_pos[i_b, i_l] - func_link_origin(s, i_b, i_l)
        axis = func_mv(s.link_R[i_b, i_l], s.link_jaxis[i_l])
        a = k % 3
        unit = ti.Vector([a == 0, a == 1, a == 2], dt=s.dtype)
        rev = ti.cast(jt == JOINT_REVOLUTE, s.dtype)
        pri = ti.cast(jt == JOINT_PRISMATIC, s.dtype)
        free_lin = ti.cast(jt == JOINT_FREE and k < 3, s.dtype)
        free_ang = ti.cast(jt == JOINT_FREE and k >= 3, s.dtype)
        w = rev * axis + free_ang * unit
        s.cdof_w[i_b, i_d] = w
        s.cdof_v[i_b, i_d] = pri * axis + free_lin * unit + pos.cross(w)


@ti.func
def func_free_velocity(s: ti.template(), i_b, e, src, h):
    """With gradients, the spatial velocity of each free joint's link (a root), over the list of free joints,
    ahead of func_velocity, which leaves those links out (see func_free_pose): its six dofs are the base
    origin's world velocity vb and the world angular velocity wb, cvel = (wb, vb + (p - o) x wb). Nothing
    without gradients (func_velocity's branch)."""
    if ti.static(s.requires_grad):
        for t in range(s.n_free_links):
            i_l = s.free_link[t]
            vb, wb = func_free_twist(s, i_b, src, s.link_dof_start[i_l])
            s.cvel_w[i_b, i_l] = wb
            s.cvel_v[i_b, i_l] = vb + (s.link_pos[i_b, i_l] - func_link_origin(s, i_b, i_l)).cross(wb)


@ti.func
def func_velocity(s: ti.template(), i_b, e, src, h):
    """Link spatial velocities (cvel, about the tree's origin o). A free joint's six dofs are the base origin's
    world velocity vb and the world angular velocity wb: cvel = (wb, vb + (p - o) x wb) (with gradients
    func_free_velocity's)."""
    for i_l in range(s.n_links):
        p = s.link_parent[i_l]
        has_p = p >= 0
        pp = func_parent_slot(s, p)
        zero = ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)
        if ti.static(s.requires_grad):
            if s.link_jtype[i_l] != JOINT_FREE:
                d0, qd = func_hinge_rate(s, i_b, src, i_l)
                s.cvel_w[i_b, i_l] = ti.select(has_p, s.cvel_w[i_b, pp], zero) + s.cdof_w[i_b, d0] * qd
                s.cvel_v[i_b, i_l] = ti.select(has_p, s.cvel_v[i_b, pp], zero) + s.cdof_v[i_b, d0] * qd
        else:
            d0, qd, free, vb, wb = func_link_joint_velocity(s, i_b, src, i_l)
            w = ti.select(has_p, s.cvel_w[i_b, pp], zero)
            v = ti.select(has_p, s.cvel_v[i_b, pp], zero)
            s.cvel_w[i_b, i_l] = w + s.cdof_w[i_b, d0] * qd + free * wb
            s.cvel_v[i_b, i_l] = v + s.cdof_v[i_b, d0] * qd + free * (vb + (s.link_pos[i_b, i_l]
                                                                             - func_link_origin(s, i_b, i_l)).cross(wb))


@ti.func
def func_dof_subspace_dot(s: ti.template(), i_b, e, src, h):
    """Time derivative of cdof (cdofd): cvel x cdof for joints fixed in their link; for a free
    joint the world-frame linear dofs are constant and the angular ones move with the base origin."""
    for i_d in range(s.n_dofs):
        i_l = s.dof_link[i_d]
        is_free = s.link_jtype[i_l] == JOINT_FREE
        if ti.static(s.requires_grad):
            # a branch: the free joint's reads only at its dofs (see func_free_pose)
            if is_free:
                ang = ti.cast(i_d - s.link_dof_start[i_l] >= 3, s.dtype)
                s.cdofd_w[i_b, i_d] = ti.Vector([0.0, 0.0, 0.0], dt=s.dtype)
                s.cdofd_v[i_b, i_d] = ang * func_vec3(s.qvel, src, i_b, s.link_dof_start[i_l]).cross(s.cdof_w[i_b, i_d])
            else:
                dw, dv = func_cross_motion(s.cvel_w[i_b, i_l], s.cvel_v[i_b, i_l], s.cdof_w[i_b, i_d], s.cdof_v[i_b, i_d])
                s.cdofd_w[i_b, i_d] = dw
                s.cdofd_v[i_b, i_d] = dv
        else:
            ang = ti.cast(is_free and i_d - s.link_dof_start[i_l] >= 3, s.dtype)
            df = ti.max(ti.min(s.link_dof_start[i_l], s.qvel_len - 6), 0)
            vb = func_vec3(s.qvel, src, i_b, df)
            dw, dv = func_cross_motion(s.cvel_w[i_b, i_l], s.cvel_v[i_b, i_l], s.cdof_w[i_b, i_d], s.cdof_v[i_b, i_d])
            s.cdofd_w[i_b, i_d] = ti.select(is_free, ti.Vector([0.0, 0.0, 0.0], dt=s.dtype), dw)
            s.cdofd_v[i_b, i_d] = ti.select(is_free, ang * vb.cross(s.cdof_w[i_b, i_d]), dv)


@ti.func
def func_add_vec3(x: ti.template(), a, b, i, v):
    """x[a, b, i .. i + 2] += v (plain adds)."""
    for k in ti.static(range(3)):
        x[a, b, i + k] = x[a, b, i + k] + v[k]


@ti.func
def func_origin_adjoint(s: ti.template(), i_b, i_l, g):
    """Adds the adjoint g of (link_pos[i_l] - func_link_origin(s, i_b, i_l)) to the link positions' adjoints."""
    r = s.link_root[i_l]
    s.link_pos.grad[i_b, i_l] = s.link_pos.grad[i_b, i_l] + g
    s.link_pos.grad[i_b, r] = s.link_pos.grad[i_b, r] - g


@ti.func
def func_kinematics_adjoint(s: ti.template(), i_b, src, full):
    """The adjoint of the KINEMATICS stages of env i_b at state slot src, written out (solver.HAND_ADJOINTS), with
    plain adds (an env is one thread's); `full` 0: of LINK_STATE only (the getters' kinematics, which stops
    there). The stages in reverse order, each store's adjoint reading and zeroing the stored field's adjoint (as
    Taichi's do) and adding into the adjoints of what the stage read, differentiated as written (the quaternion
    helpers' adjoints: math3d), the grad-path branches only:
    - func_world_inertia: c = p - o + R com, h = m c, J = R I R^T + m (c.c E - c c^T);
    - func_dof_subspace_dot: a free joint's cdofd_v = ang vb x cdof_w, the others' cvel x cdof (motion cross);
    - func_velocity / func_free_velocity: cvel = cvel[parent] + cdof qd over the links, children first, then the
      free links' (wb, vb + (p - o) x wb);
    - func_dof_subspace: cdof_w = rev R axis + free_ang e, cdof_v = pri R axis + free_lin e + (p - o) x cdof_w;
    - func_forward_kinematics / func_free_pose: each link's pose from its parent's and its q, children first (a
      parent's adjoint is complete when its turn comes: links are in topological order), then the free links'
      (the position and the normalised quaternion of their qs)."""
    if full:
        for i_l in range(s.n_links):
            gh = func_take(s.link_h, i_b, i_l)
            gJ = func_take(s.link_J, i_b, i_l)
            gc = func_take(s.link_cpos, i_b, i_l)
            R = s.link_R[i_b, i_l]
            com = s.link_com[i_b, i_l]
            I = s.link_inertia[i_b, i_l]
            m = s.link_mass[i_b, i_l]
            c = s.link_pos[i_b, i_l] - func_link_origin(s, i_b, i_l) + func_mv(R, com)
            cc = c.dot(c)
            trJ = gJ[0, 0] + gJ[1, 1] + gJ[2, 2]
            gm = gh.dot(c) + cc * trJ - c.dot(gJ @ c)
            gct = gc + m * gh + m * (2.0 * trJ * c - (gJ @ c + gJ.transpose() @ c))
            s.link_mass.grad[i_b, i_l] = s.link_mass.grad[i_b, i_l] + gm
            s.link_inertia.grad[i_b, i_l] = s.link_inertia.grad[i_b, i_l] + R.transpose() @ gJ @ R
            s.link_com.grad[i_b, i_l] = s.link_com.grad[i_b, i_l] + func_mtv(R, gct)
            s.link_R.grad[i_b, i_l] = (s.link_R.grad[i_b, i_l] + gJ @ R @ I.transpose() + gJ.transpose() @ R @ I
                                       + gct.outer_product(com))
            func_origin_adjoint(s, i_b, i_l, gct)
        for i_d in range(s.n_dofs):
            i_l = s.dof_link[i_d]
            gdw = func_take(s.cdofd_w, i_b, i_d)
            gdv = func_take(s.cdofd_v, i_b, i_d)
            a = s.cdof_w[i_b, i_d]
            if s.link_jtype[i_l] == JOINT_FREE:
                d0 = s.link_dof_start[i_l]
                if i_d - d0 >= 3:
                    vb = func_vec3(s.qvel, src, i_b, d0)
                    func_add_vec3(s.qvel.grad, src, i_b, d0, a.cross(gdv))
                    s.cdof_w.grad[i_b, i_d] = s.cdof_w.grad[i_b, i_d] + gdv.cross(vb)
            else:
                w = s.cvel_w[i_b, i_l]
                v = s.cvel_v[i_b, i_l]
                b = s.cdof_v[i_b, i_d]
                s.cvel_w.grad[i_b, i_l] = s.cvel_w.grad[i_b, i_l] + a.cross(gdw) + b.cross(gdv)
                s.cvel_v.grad[i_b, i_l] = s.cvel_v.grad[i_b, i_l] + a.cross(gdv)
                s.cdof_w.grad[i_b, i_d] = s.cdof_w.grad[i_b, i_d] + gdw.cross(w) + gdv.cross(v)
                s.cdof_v.grad[i_b, i_d] = s.cdof_v.grad[i_b, i_d] + gdv.cross(w)
    for k in range(s.n_links):
        i_l = s.n_links - 1 - k
        if s.link_jtype[i_l] != JOINT_FREE:
            gw = func_take(s.cvel_w, i_b, i_l)
            gv = func_take(s.cvel_v, i_b, i_l)
            p = s.link_parent[i_l]
            if p >= 0:
                s.cvel_w.grad[i_b, p] = s.cvel_w.grad[i_b, p] + gw
                s.cvel_v.grad[i_b, p] = s.cvel_v.grad[i_b, p] + gv
            if s.link_ndof[i_l] == 1:
                d0 = s.link_dof_start[i_l]
                qd = s.qvel[src, i_b, d0]
                s.cdof_w.grad[i_b, d0] = s.cdof_w.grad[i_b, d0] + gw * qd
                s.cdof_v.grad[i_b, d0] = s.cdof_v.grad[i_b, d0] + gv * qd
                s.qvel.grad[src, i_b, d0] = (s.qvel.grad[src, i_b, d0] + gw.dot(s.cdof_w[i_b, d0])
                                             + gv.dot(s.cdof_v[i_b, d0]))
    for t in range(s.n_free_links):
        i_l = s.free_link[t]
        d0 = s.link_dof_start[i_l]
        gw = func_take(s.cvel_w, i_b, i_l)
        gv = func_take(s.cvel_v, i_b, i_l)
        wb = func_vec3(s.qvel, src, i_b, d0 + 3)
        r = s.link_pos[i_b, i_l] - func_link_origin(s, i_b, i_l)
        func_origin_adjoint(s, i_b, i_l, wb.cross(gv))
        func_add_vec3(s.qvel.grad, src, i_b, d0, gv)
        func_add_vec3(s.qvel.grad, src, i_b, d0 + 3, gw + gv.cross(r))
    for i_d in range(s.n_dofs):
        i_l = s.dof_link[i_d]
        jt = s.link_jtype[i_l]
        gw0 = func_take(s.cdof_w, i_b, i_d)
        gv = func_take(s.cdof_v, i_b, i_d)
        pos = s.link_pos[i_b, i_l] - func_link_origin(s, i_b, i_l)
        gw = gw0 + gv.cross(pos)
        func_origin_adjoint(s, i_b, i_l, s.cdof_w[i_b, i_d].cross(gv))
        rev = ti.cast(jt == JOINT_REVOLUTE, s.dtype)
        pri = ti.cast(jt == JOINT_PRISMATIC, s.dtype)
        if rev + pri > 0.0:  # (a free joint's cdof_w is a constant unit vector: (p - o) x it its only read)
            s.link_R.grad[i_b, i_l] = s.link_R.grad[i_b, i_l] + (rev * gw + pri * gv).outer_product(s.link_jaxis[i_l])
    for k in range(s.n_links):
        i_l = s.n_links - 1 - k
        if s.link_jtype[i_l] != JOINT_FREE:
            func_link_pose_adjoint(s, i_b, src, i_l)
    for t in range(s.n_free_links):
        i_l = s.free_link[t]
        qs = s.link_q_start[i_l]
        gpos = func_take(s.link_pos, i_b, i_l)
        gR = func_take(s.link_R, i_b, i_l)
        gq = func_take(s.link_quat, i_b, i_l) + func_quat_to_R_adjoint(s.link_quat[i_b, i_l], gR)
        func_add_vec3(s.qpos.grad, src, i_b, qs, gpos)
        fq = ti.Vector([s.qpos[src, i_b, qs + 3 + j] for j in ti.static(range(4))])
        n2 = fq.dot(fq)
        n = ti.sqrt(ti.max(n2, 1e-30))
        gfq = gq / n - ti.cast(n2 > 1e-30, s.dtype) * (gq.dot(fq) / (n * n * n)) * fq
        for j in ti.static(range(4)):
            s.qpos.grad[src, i_b, qs + 3 + j] = s.qpos.grad[src, i_b, qs + 3 + j] + gfq[j]


@ti.func
def func_link_pose_adjoint(s: ti.template(), i_b, src, i_l):
    """The adjoint of func_link_pose (grad path) for link i_l, its parent's pose adjoints added to."""
    gpos = func_take(s.link_pos, i_b, i_l)
    quat = s.link_quat[i_b, i_l]
    gq = func_take(s.link_quat, i_b, i_l) + func_quat_to_R_adjoint(quat, func_take(s.link_R, i_b, i_l))
    p = s.link_parent[i_l]
    jt = s.link_jtype[i_l]
    qs = s.link_q_start[i_l]
    has_p = p >= 0
    pp = func_parent_slot(s, p)
    pquat = ti.select(has_p, s.link_quat[i_b, pp], ti.Vector([1.0, 0.0, 0.0, 0.0], dt=s.dtype))
    jq = s.link_jquat[i_l]
    jp = s.link_jpos[i_l]
    axis = s.link_jaxis[i_l]
    jquat = func_quat_mul(pquat, jq)
    q1 = s.qpos[src, i_b, ti.min(qs, s.qpos_len - 1)]
    rev = ti.cast(jt == JOINT_REVOLUTE, s.dtype)
    pri = ti.cast(jt == JOINT_PRISMATIC, s.dtype)
    half = 0.5 * (q1 * rev)
    aq = func_axis_angle_quat(axis, q1 * rev)
    gjq, gaq = func_quat_mul_adjoint(jquat, aq, gq)
    gjq2, gu = func_quat_rotate_adjoint(jquat, axis * (q1 * pri), gpos)
    gjq += gjq2
    if rev + pri > 0.0:
        gaxis = axis[0] * gaq[1] + axis[1] * gaq[2] + axis[2] * gaq[3]
        gq1 = pri * axis.dot(gu) + rev * 0.5 * (-ti.sin(half) * gaq[0] + ti.cos(half) * gaxis)
        s.qpos.grad[src, i_b, qs] = s.qpos.grad[src, i_b, qs] + gq1
    if has_p:
        gpq, gjq_static = func_quat_mul_adjoint(pquat, jq, gjq)
        gpq2, gjp_static = func_quat_rotate_adjoint(pquat, jp, gpos)
        s.link_pos.grad[i_b, p] = s.link_pos.grad[i_b, p] + gpos
        s.link_quat.grad[i_b, p] = s.link_quat.grad[i_b, p] + gpq + gpq2


# Each stage is one loop over elements for one env; kernels run every stage as its own top-level
# loop over envs, the shape Taichi's reverse mode differentiates correctly (several inner loops in
# one env loop lose gradients between them).
KINEMATICS = (func_free_pose, func_forward_kinematics, func_dof_subspace, func_free_velocity, func_velocity,
              func_dof_subspace_dot, func_world_inertia)
# what the getters need (link poses and velocities)
LINK_STATE = KINEMATICS[:5]
