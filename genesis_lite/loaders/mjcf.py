"""MJCF -> EntityModel, through MuJoCo's own compiler.

`mujoco.MjModel.from_xml_path` resolves everything an MJCF file can say indirectly (default classes,
<include>, mesh assets and their scale, inertias inferred from geoms, degrees vs radians, euler / axis-angle
/ xyaxes orientations, `fromto`), so this module never reads the XML: it reads the compiled model's arrays.

Mapping (solvers/rigid/model.py has the conventions the result follows):
- MuJoCo numbers bodies in pre-order of the XML tree, parent before child, so links keep MuJoCo's body
  order and dofs keep MuJoCo's dof order.
- A body without joints is welded to its parent: a link of its own with a 'fixed' joint, as Genesis
  keeps it (scripts read get_link("hand") of the Franka); a worldbody child without joints becomes a
  root with a 'fixed' joint (or a free one with gs.morphs.MJCF(fixed=False)).
- freejoint -> 'free' root, hinge -> 'revolute', slide -> 'prismatic'. MuJoCo's joint anchor (jnt_pos)
  may sit off the body origin while our link frame is the joint frame, so the link frame is put at the
  anchor (body axes kept) and everything the body carries is shifted by -anchor: the motion is the same.
  Link poses therefore differ from MuJoCo's body poses (data.xpos) by that anchor offset.
- Geoms of the worldbody (a floor) go to a fixed root link named after MuJoCo's world body, listed last so
  that the entity's base link is the robot's first body. morph.pos / quat move the whole model, floor too.
- Geoms with contype == conaffinity == 0 are drawn only (VisualDesc); the others collide (GeomDesc, the
  convex hull for meshes, as MuJoCo collides them), with MuJoCo's sliding friction (0 for condim 1).
- Joint equality constraints that are linear in the leader (polycoef a0 + a1 q) become mimic joints.
- A body with several hinge/slide joints becomes a chain of links, one per joint, in MuJoCo's joint order:
  all but the last are massless and shapeless and named '<body>_<joint>'; the last carries the body.

Not supported (a ValueError names the file, body and joint): ball joints, a free joint below the worldbody
or next to other joints, hinge/slide joints with a nonzero `ref`, colliding height fields and SDF geoms.
One warning lists what is not simulated as MuJoCo would: a free joint's stiffness, other equality
constraints and tendons are ignored, ellipsoids collide as convex polytopes. A hinge or slide joint's
`stiffness` is its spring, -stiffness (q - springref) as MuJoCo's (jnt_stiffness, qpos_spring), explicit
as in MuJoCo. Ignored silently, as they
shape contacts or actuation rather than the model: contype/conaffinity bit filtering beyond "visual
only", <contact> pairs and excludes, solver parameters (solref, solimp, margin), actuator dynamics.

Scaling by `morph.scale = s` is as in the URDF loader: lengths times s, masses s^3, inertias s^5.
"""
from __future__ import annotations

import os
import warnings
from typing import List

import numpy as np

from solvers.rigid.model import EntityModel, GeomDesc, LinkDesc, MimicDesc, VisualDesc

from .primitives import ROOT_JOINT_NAME, combine_inertias, mat_to_quat, mesh_hull, mesh_shapes, pose_matrix, quat_to_mat

# mjtGeom / mjtJoint / mjtEq / mjtTrn codes (stable across MuJoCo 2.x-3.x; spelled out so the module reads
# without the enums)
_PLANE, _HFIELD, _SPHERE, _CAPSULE, _ELLIPSOID, _CYLINDER, _BOX, _MESH = range(8)
_FREE, _BALL, _SLIDE, _HINGE = range(4)
_EQ_JOINT = 2
_TRN_JOINTS = (0, 1)  # mjTRN_JOINT, mjTRN_JOINTINPARENT
_GEOM_NAMES = {_PLANE: "plane", _SPHERE: "sphere", _CAPSULE: "capsule", _CYLINDER: "cylinder", _BOX: "box",
               _MESH: "mesh"}


def _err(path, msg):
    return ValueError(f"MJCF '{path}': {msg}")


def _compile(path: str):
    try:
        import mujoco
    except ImportError as e:
        raise ImportError(f"gs.morphs.MJCF(file='{path}') needs MuJoCo's compiler: pip install mujoco "
                          "(or pip install genesis_lite[mjcf])") from e
    if not os.path.isfile(path):
        raise FileNotFoundError(f"MJCF '{path}': no such file; give the path of an existing MJCF .xml file")
    try:
        return mujoco, mujoco.MjModel.from_xml_path(path)
    except Exception as e:  # mujoco raises ValueError("XML Error: ...") with the line and element
        raise _err(path, f"MuJoCo could not compile it: {e}") from e


def _inv(T):
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _trans(p):
    T = np.eye(4)
    T[:3, 3] = p
    return T


def load_mjcf(morph, material, name) -> EntityModel:
    """gs.morphs.MJCF -> EntityModel: the file is compiled by MuJoCo (`MjModel.from_xml_path`) and its
    bodies, joints, inertias (kg, m, kg m^2), geoms and joint parameters (limits in rad or m, damping,
    armature, friction loss, springs, actuator force ranges as effort in N or N m) are mapped onto links; a body
    without joints is a link of its own welded to its parent (Genesis keeps it). `material` is not used for
    mass (MuJoCo's compiled inertias are, unless the morph's recompute_inertia: loaders.load_morph), nor for
    friction (each geom keeps MuJoCo's sliding friction)."""
    path = os.path.abspath(os.fspath(morph.file))
    mujoco, m = _compile(path)
    s = float(getattr(morph, "scale", 1.0))
    fixed = getattr(morph, "fixed", None)
    default_armature = getattr(morph, "default_armature", None)

    def nm(kind, i):
        return mujoco.mj_id2name(m, kind, i) or ""

    OBJ = mujoco.mjtObj
    body_name = []
    for b in range(m.nbody):
        body_name.append(nm(OBJ.mjOBJ_BODY, b) or ("world" if b == 0 else f"body{b}"))
    joint_name = [nm(OBJ.mjOBJ_JOINT, j) for j in range(m.njnt)]
    keeps_armature = None if default_armature is None else _armature_given(path, m, joint_name)

    def pose(pos, quat):
        T = pose_matrix(np.asarray(pos, dtype=float), np.asarray(quat, dtype=float))
        T[:3, 3] *= s
        return T

    T_morph = pose_matrix(morph.pos, morph.quat)
    effort = _joint_efforts(m)
    kp, kv = _joint_gains(m)
    ignored = set()

    descs: List[LinkDesc] = []
    parts: List[list] = []
    link_of = np.full(m.nbody, -1)
    T_in_link = [np.eye(4)] * m.nbody  # body frame in its link's frame
    joint_desc = {}  # MuJoCo hinge/slide joint id -> its link

    def new_link(d):
        descs.append(d)
        parts.append([])
        return len(descs) - 1

    for b in range(1, m.nbody):
        p = int(m.body_parentid[b])
        bn = body_name[b]
        T_rel = pose(m.body_pos[b], m.body_quat[b])  # body frame in its parent body's frame
        jadr, jnum = int(m.body_jntadr[b]), int(m.body_jntnum[b])
        if jnum == 0 and p != 0:
            # welded to its parent, and a link of its own as in Genesis (scripts read get_link("hand"))
            T = T_in_link[p] @ T_rel
            link_of[b] = new_link(LinkDesc(name=bn, parent=int(link_of[p]), joint_name=f"{bn}_fixed",
                                           joint_type="fixed", joint_pos=T[:3, 3].copy(),
                                           joint_quat=mat_to_quat(T[:3, :3])))
        elif jnum == 0:
            jtype = "fixed" if fixed in (None, True) else "free"
            T = T_morph @ T_rel
            link_of[b] = new_link(LinkDesc(name=bn, parent=-1, joint_name=f"{bn}_{ROOT_JOINT_NAME}", joint_type=jtype,
                                           joint_pos=T[:3, 3].copy(), joint_quat=mat_to_quat(T[:3, :3])))
        elif m.jnt_type[jadr] == _FREE and jnum == 1:
            if p != 0:
                raise _err(path, f"body '{bn}', joint '{joint_name[jadr] or f'#{jadr}'}' is a free joint below body "
                                 f"'{body_name[p]}'; genesis_lite allows a free joint only on a body of the worldbody")
            if m.jnt_stiffness[jadr] != 0.0:
                ignored.add("free-joint stiffness (ignored, as Genesis ignores it)")
            T = T_morph @ T_rel
            link_of[b] = new_link(LinkDesc(name=bn, parent=-1, joint_name=joint_name[jadr] or ROOT_JOINT_NAME,
                                           joint_type="fixed" if fixed is True else "free",
                                           joint_pos=T[:3, 3].copy(), joint_quat=mat_to_quat(T[:3, :3])))
        else:
            # MuJoCo applies a body's joints in order, each about its anchor and along its axis in the body
            # frame as moved by the joints before it: exactly a chain of links, one per joint, all but the
            # last massless and shapeless (named '<body>_<joint>'); the last carries the body and its name
            parent_link = -1 if p == 0 else int(link_of[p])
            T_prev = (T_morph if p == 0 else T_in_link[p]) @ T_rel  # body frame (q = 0) in the parent link frame
            for k, j in enumerate(range(jadr, jadr + jnum)):
                jt, jn = int(m.jnt_type[j]), joint_name[j]
                where = f"body '{bn}', joint '{jn or f'#{j}'}'"
                if jt == _BALL:
                    raise _err(path, f"{where} is a ball joint, which genesis_lite does not support (only hinge, slide "
                                     "and free joints): replace it with hinges, one per rotation axis")
                if jt == _FREE:
                    raise _err(path, f"{where} is a free joint in a body with other joints; give it a body of its own")
                qa = int(m.jnt_qposadr[j])
                if m.qpos0[qa] != 0.0:
                    raise _err(path, f"{where} has ref={m.qpos0[qa]}; genesis_lite measures joint positions from the "
                                     "body pose given in the file, so only ref=0 is supported: rotate/move the body "
                                     "to its ref pose and drop ref")
                anchor = np.asarray(m.jnt_pos[j], dtype=float) * s
                T = T_prev @ _trans(anchor)  # link (joint) frame in the parent link frame
                lin = s if jt == _SLIDE else 1.0
                d = int(m.jnt_dofadr[j])
                lim = (-np.inf, np.inf)
                if m.jnt_limited[j]:
                    lim = (float(m.jnt_range[j, 0]) * lin, float(m.jnt_range[j, 1]) * lin)
                last = k == jnum - 1
                parent_link = new_link(LinkDesc(
                    name=bn if last else f"{bn}_{jn or f'joint{k}'}", parent=parent_link,
                    joint_name=jn or (f"{bn}_joint" if jnum == 1 else f"{bn}_joint{k}"),
                    joint_type="revolute" if jt == _HINGE else "prismatic",
                    joint_pos=T[:3, 3].copy(), joint_quat=mat_to_quat(T[:3, :3]),
                    joint_axis=np.asarray(m.jnt_axis[j], dtype=float) / np.linalg.norm(m.jnt_axis[j]),
                    limit=lim, effort=effort[j], damping=float(m.dof_damping[d]),
                    frictionloss=float(m.dof_frictionloss[d]),
                    armature=float(m.dof_armature[d] if keeps_armature is None or keeps_armature[j]
                                   else default_armature),
                    stiffness=float(m.jnt_stiffness[j]), springref=float(m.qpos_spring[qa]) * lin,
                    limit_solref=_limit_solref(m, j), limit_solimp=tuple(float(x) for x in m.jnt_solimp[j]),
                    kp=kp[j], kv=kv[j]))
                joint_desc[j] = descs[-1]
                T_prev = _trans(-anchor)
            link_of[b] = parent_link
            T_in_link[b] = T_prev

    if m.body_geomnum[0] > 0:
        # last, so that the entity's base link (links[0]: get_pos, get_quat) is the robot, not its floor
        link_of[0] = new_link(LinkDesc(name=body_name[0], parent=-1, joint_name=f"{body_name[0]}_{ROOT_JOINT_NAME}",
                                       joint_type="fixed", joint_pos=T_morph[:3, 3].copy(),
                                       joint_quat=mat_to_quat(T_morph[:3, :3])))

    robot_body = _robot_bodies(m)
    for b in range(m.nbody):
        li = int(link_of[b])
        if li < 0:  # the worldbody without geoms
            continue
        Tb = T_in_link[b]
        if b > 0:
            R = Tb[:3, :3] @ quat_to_mat(m.body_iquat[b])
            I = R @ np.diag(np.asarray(m.body_inertia[b], dtype=float)) @ R.T
            com = Tb[:3, :3] @ (np.asarray(m.body_ipos[b], dtype=float) * s) + Tb[:3, 3]
            parts[li].append((float(m.body_mass[b]) * s**3, com, I * s**5))
        for g in range(int(m.body_geomadr[b]), int(m.body_geomadr[b]) + int(m.body_geomnum[b])):
            _add_geom(path, mujoco, m, g, body_name[b], Tb, s, descs[li], ignored, morph, robot_body[b])

    for d, pt in zip(descs, parts):
        d.mass, d.com, d.inertia = combine_inertias(pt)

    _mimics(m, joint_desc, s, ignored)
    if m.ntendon:
        ignored.add("tendons (ignored)")
    if ignored:
        warnings.warn(f"MJCF '{path}': not simulated as MuJoCo would: {'; '.join(sorted(ignored))}", stacklevel=3)
    if not descs:
        raise _err(path, "it has no bodies and no worldbody geoms: nothing to simulate")
    model = EntityModel(name=name, links=descs, source=path)
    model.validate()
    return model


def _armature_given(path, m, joint_name) -> List[bool]:
    """Per MuJoCo joint, whether its own <joint> element names an armature (read for hinges and slides), as
    Genesis's default_armature reads the file: it fills in `armature` on the worldbody's <joint> elements that
    give none, overriding a default class's value; joints of included files keep theirs, as Genesis does not
    see them.
    The compiled joints follow the elements in document order; where they do not (an <include> or
    <replicate> inside the worldbody), joints are matched by name, and an unnamed one keeps its armature."""
    import xml.etree.ElementTree as ET

    elems = []
    for wb in ET.parse(path).getroot().iter("worldbody"):
        elems += [e for e in wb.iter() if e.tag in ("joint", "freejoint")]

    types = {"free": _FREE, "ball": _BALL, "slide": _SLIDE, "hinge": _HINGE}
    if len(elems) == m.njnt and all((e.tag == "freejoint" and m.jnt_type[j] == _FREE)
                                    or (e.tag == "joint" and types.get(e.get("type"), m.jnt_type[j]) == m.jnt_type[j])
                                    for j, e in enumerate(elems)):
        return ["armature" in e.attrib for e in elems]
    by_name = {e.get("name"): e for e in elems if e.get("name")}
    return ["armature" in by_name[n].attrib if n in by_name else True for n in joint_name]


def _limit_solref(m, j):
    """A joint's solreflimit (time constant s, damping ratio), or None where it is MuJoCo's default (0.02, 1):
    Genesis reads an MJCF joint without one as having none (its time constant then the scene's,
    RigidOptions.constraint_timeconst, at least twice the substep; one given explicitly as (0.02, 1) reads the
    same here, which differs only at substeps below 10 ms)."""
    ref = tuple(float(x) for x in m.jnt_solref[j])
    return None if ref == (0.02, 1.0) else ref


def _joint_efforts(m) -> np.ndarray:
    """Per joint, the largest |force| (N or N m) its actuators may apply: MuJoCo's joint actuatorfrcrange
    and each joint-transmission actuator's forcerange times its gear; inf where nothing limits it."""
    eff = np.full(m.njnt, np.inf)
    for j in range(m.njnt):
        if m.jnt_actfrclimited[j]:
            eff[j] = float(np.max(np.abs(m.jnt_actfrcrange[j])))
    for a in range(m.nu):
        if m.actuator_trntype[a] in _TRN_JOINTS and m.actuator_forcelimited[a]:
            j = int(m.actuator_trnid[a, 0])
            eff[j] = min(eff[j], float(np.max(np.abs(m.actuator_forcerange[a])) * abs(m.actuator_gear[a, 0])))
    return eff


def _joint_gains(m):
    """Per joint, the PD gains of its position actuator (MuJoCo's <position> or a <general> with a fixed
    gain and an affine bias: force = gear (kp ctrl - kp gear q - kv gear qdot)), so kp = -biasprm[1] gear^2
    and kv = -biasprm[2] gear^2; 0 for a joint without one. That is Genesis's reading of an MJCF: an
    unactuated joint has no PD gains (a URDF's get kp 100, kv 10)."""
    kp, kv = np.zeros(m.njnt), np.zeros(m.njnt)
    for a in range(m.nu):
        if m.actuator_trntype[a] not in _TRN_JOINTS:
            continue
        if int(m.actuator_gaintype[a]) != 0 or int(m.actuator_biastype[a]) != 1 or m.actuator_biasprm[a, 1] >= 0:
            continue  # a motor (no bias) or another law: no PD gains
        j, g = int(m.actuator_trnid[a, 0]), float(m.actuator_gear[a, 0])
        kp[j] = -float(m.actuator_biasprm[a, 1]) * g * g
        kv[j] = -float(m.actuator_biasprm[a, 2]) * g * g
    return kp, kv


def _robot_bodies(m) -> List[bool]:
    """Per MuJoCo body, whether Genesis counts it a robot's (its mesh decomposition threshold then the morph's
    decompose_robot_error_threshold, else decompose_object_error_threshold): bodies welded to each other (no
    joint between them, the worldbody included) form a group, and a group is a robot's when one of its bodies
    hangs on a hinge or slide joint or carries a body that does; a free body with nothing articulated below it is
    an object."""
    group = list(range(m.nbody))

    def find(b):
        while group[b] != b:
            group[b] = group[group[b]]
            b = group[b]
        return b

    for b in range(1, m.nbody):
        if int(m.body_jntnum[b]) == 0:
            group[find(b)] = find(int(m.body_parentid[b]))
    robot = set()
    for b in range(1, m.nbody):
        jadr, jnum = int(m.body_jntadr[b]), int(m.body_jntnum[b])
        if any(int(m.jnt_type[j]) in (_HINGE, _SLIDE) for j in range(jadr, jadr + jnum)):
            robot.update((find(b), find(int(m.body_parentid[b]))))
    return [find(b) in robot for b in range(m.nbody)]


def _add_geom(path, mujoco, m, g, bname, Tb, s, desc: LinkDesc, ignored, morph, is_robot):
    gt = int(m.geom_type[g])
    T = Tb @ pose_matrix(np.asarray(m.geom_pos[g], dtype=float) * s, m.geom_quat[g])
    size = np.asarray(m.geom_size[g], dtype=float) * s
    visual = m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0
    gname = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or f"#{g}"
    where = f"body '{bname}', geom '{gname}'"
    rgba = tuple(float(c) for c in (m.mat_rgba[m.geom_matid[g]] if m.geom_matid[g] >= 0 else m.geom_rgba[g]))

    if visual:
        if rgba[3] == 0.0:
            return  # invisible in MuJoCo too
        pos, quat = T[:3, 3].copy(), mat_to_quat(T[:3, :3])
        if gt == _MESH:
            mid = int(m.geom_dataid[g])
            # MuJoCo moved the vertices to the mesh's inertial frame (mesh_pos, mesh_quat in the file's
            # scaled frame) and moved the geom to compensate; the renderer reads the file, so undo that
            Tf = T @ _inv(pose_matrix(np.asarray(m.mesh_pos[mid], dtype=float) * s, m.mesh_quat[mid]))
            filename, file = _mesh_file(path, m, mid)
            desc.visuals.append(VisualDesc("mesh", Tf[:3, 3].copy(), mat_to_quat(Tf[:3, :3]), (), file=file,
                                           filename=filename, scale=np.asarray(m.mesh_scale[mid], dtype=float) * s,
                                           rgba=rgba))
        elif gt in (_SPHERE, _BOX, _CAPSULE, _CYLINDER):
            n = {_SPHERE: 1, _BOX: 3, _CAPSULE: 2, _CYLINDER: 2}[gt]
            desc.visuals.append(VisualDesc(_GEOM_NAMES[gt], pos, quat, tuple(float(v) for v in size[:n]), rgba=rgba))
        # other visual-only shapes (planes, ellipsoids, height fields) are not drawn: they do not move anything
        return

    friction = 0.0 if m.geom_condim[g] == 1 else float(m.geom_friction[g, 0])
    if gt == _MESH:
        mid = int(m.geom_dataid[g])
        va, vn = int(m.mesh_vertadr[mid]), int(m.mesh_vertnum[mid])
        fa, fn = int(m.mesh_faceadr[mid]), int(m.mesh_facenum[mid])
        V = np.asarray(m.mesh_vert[va:va + vn], dtype=np.float64) * s
        F = np.asarray(m.mesh_face[fa:fa + fn], dtype=np.int64)
        # Genesis's rules: an object's non-convex mesh is split into CoACD's parts, a robot's only past its
        # threshold (never by default: the hull, as MuJoCo collides every mesh)
        shapes = mesh_shapes(morph, V, F, f"MJCF '{path}', {where}", is_robot)
        for Vs, Fs in shapes:
            desc.geoms.append(GeomDesc("mesh", T[:3, 3].copy(), mat_to_quat(T[:3, :3]), (), vertices=Vs, faces=Fs,
                                       friction=friction, hull=mesh_hull(Vs)))
        return
    if gt == _ELLIPSOID:
        V, F = _ellipsoid_polytope(size[:3])
        ignored.add("ellipsoids (they collide as inscribed 114-point convex polytopes)")
        desc.geoms.append(GeomDesc("mesh", T[:3, 3].copy(), mat_to_quat(T[:3, :3]), (), vertices=V, faces=F,
                                   friction=friction, hull=mesh_hull(V)))
        return
    if gt not in _GEOM_NAMES:
        kind = {_HFIELD: "height field"}.get(gt, f"type {gt} (SDF or plugin)")
        raise _err(path, f"{where} is a colliding {kind}, which genesis_lite cannot collide; use planes, "
                         "primitives or meshes, or make it visual-only (contype=\"0\" conaffinity=\"0\")")
    n = {_PLANE: 0, _SPHERE: 1, _BOX: 3, _CAPSULE: 2, _CYLINDER: 2}[gt]
    desc.geoms.append(GeomDesc(_GEOM_NAMES[gt], T[:3, 3].copy(), mat_to_quat(T[:3, :3]),
                               tuple(float(v) for v in size[:n]), friction=friction))


def _mesh_file(path, m, mid):
    """(the file name MuJoCo recorded for mesh `mid`, its resolved path or None). MuJoCo keeps the path as
    written plus the compiler's meshdir/assetdir, relative to the main model file's folder."""
    adr = int(m.mesh_pathadr[mid]) if hasattr(m, "mesh_pathadr") else -1
    if adr < 0 or not hasattr(m, "paths"):
        return "", None
    raw = bytes(m.paths)[adr:]
    fn = raw[: raw.index(b"\0") if b"\0" in raw else len(raw)].decode()
    full = fn if os.path.isabs(fn) else os.path.join(os.path.dirname(path), fn)
    return fn, (full if os.path.isfile(full) else None)


def _ellipsoid_polytope(radii):
    """Points on an ellipsoid with semi-axes `radii` (m), a 16 x 7 longitude-latitude grid plus the poles,
    and the triangles of their convex hull (inscribed in the ellipsoid, touching it at the axis ends)."""
    import trimesh

    th, ph = np.meshgrid(np.linspace(0, 2 * np.pi, 16, endpoint=False), np.linspace(0, np.pi, 9)[1:-1])
    P = np.stack([np.sin(ph) * np.cos(th), np.sin(ph) * np.sin(th), np.cos(ph)], -1).reshape(-1, 3)
    P = np.vstack([P, [[0, 0, 1], [0, 0, -1]]]) * np.asarray(radii, dtype=float)
    hull = trimesh.Trimesh(vertices=P, process=False).convex_hull
    return np.asarray(hull.vertices, dtype=np.float64), np.asarray(hull.faces, dtype=np.int64)


def _mimics(m, joint_desc, s, ignored):
    """Joint equality constraints q1 = a0 + a1 q2 (MuJoCo's polycoef with zero higher terms; refs are zero
    here) become mimic joints: joint1 follows joint2. Anything else is reported as ignored."""
    for e in range(m.neq):
        if not m.eq_active0[e]:
            continue
        j1, j2 = int(m.eq_obj1id[e]), int(m.eq_obj2id[e])
        a = np.asarray(m.eq_data[e, :5], dtype=float)
        if int(m.eq_type[e]) != _EQ_JOINT or j1 not in joint_desc or j2 not in joint_desc or np.any(a[2:] != 0.0):
            ignored.add("equality constraints other than linear joint couplings (ignored)")
            continue
        follower, leader = joint_desc[j1], joint_desc[j2]
        # lengths scale with the model: a0 when the follower slides, a1 by follower unit / leader unit
        sf = s if follower.joint_type == "prismatic" else 1.0
        sl = s if leader.joint_type == "prismatic" else 1.0
        follower.mimic = MimicDesc(joint=leader.joint_name, multiplier=float(a[1]) * sf / sl, offset=float(a[0]) * sf)
