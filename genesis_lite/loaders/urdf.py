"""URDF -> EntityModel.

yourdfpy parses the XML into dataclasses; everything after that (tree checks, merging fixed links,
mesh path resolution and loading, inertia from geometry) happens here so that errors can name the
file, link, joint and path involved.

Link order is a depth-first walk of the kinematic tree with each link's children visited in
ascending joint-name order. That is the order urdfdom builds its tree in (its joints live in a
name-sorted map), hence the order Pinocchio numbers its joints in, so our dofs line up with a
Pinocchio model of the same file.

Scaling by `morph.scale = s` treats the robot as a uniformly scaled copy made of the same material:
lengths (joint origins, geometry, COM, prismatic limits and velocities) times s, masses times s^3,
inertias times s^5. Efforts and damping are left as written.
"""
from __future__ import annotations

import os
import re
import warnings
from collections import defaultdict
from typing import Dict, List, Tuple

import numpy as np

from solvers.rigid.model import EntityModel, GeomDesc, LinkDesc, MimicDesc, VisualDesc

from . import cache as model_cache
from .primitives import (
    ROOT_JOINT_NAME,
    combine_inertias,
    geom_mass_properties,
    load_mesh_file,
    mat_to_quat,
    mesh_hull,
    mesh_shapes,
    pose_matrix,
    scale_mesh,
    zup_vertices,
    zup_visual,
)

_MOVING = {"revolute", "continuous", "prismatic"}
_KNOWN = _MOVING | {"fixed", "floating", "planar"}


_XML_DECL_VERSION = re.compile(rb"""\A(\s*<\?xml\s+version\s*=\s*["'])(?!1\.)[^"']*(["'])""")


def _err(path, msg):
    return ValueError(f"URDF '{path}': {msg}")


# --------------------------------------------------------------------------------------------
# Parsing
# --------------------------------------------------------------------------------------------
def _parse(path: str):
    """Return (yourdfpy Robot, {(link, collision index): (radius, length)} for capsules; visual
    capsules are keyed ('visual', link, visual index))."""
    from lxml import etree
    import yourdfpy

    if not os.path.isfile(path):
        raise FileNotFoundError(f"URDF '{path}': no such file; give the path of an existing .urdf file")
    parser = etree.XMLParser(remove_blank_text=True, remove_comments=True, remove_pis=True)
    with open(path, "rb") as f:
        text = f.read()
    # PyBullet's plane.urdf (which Genesis ships and its scripts load) declares `<?xml version="0.0" ?>`;
    # libxml2 refuses any XML version but 1.x, while the rest of such a file is well-formed: read it as 1.0
    text = _XML_DECL_VERSION.sub(rb"\g<1>1.0\g<2>", text, count=1)
    try:
        root = etree.fromstring(text, parser, base_url=path).getroottree().getroot()
    except etree.XMLSyntaxError as e:
        # yourdfpy would silently 'recover' a broken file; a half-read robot is worse than an error
        raise _err(path, f"malformed XML ({e}); fix the file so that it is well-formed XML") from e
    except OSError as e:
        raise _err(path, f"cannot be read ({e})") from e
    if not isinstance(root.tag, str) or etree.QName(root).localname != "robot":
        raise _err(path, f"the root element is <{root.tag}>, expected <robot>; is this a URDF file?")
    etree.cleanup_namespaces(root)
    if "name" not in root.attrib:
        root.set("name", os.path.splitext(os.path.basename(path))[0])
    if root.find("link") is None:
        raise _err(path, "it has no <link> elements; a URDF needs at least one link")

    for i, el in enumerate(root.findall("link")):
        if not el.get("name"):
            raise _err(path, f"<link> number {i + 1} (line {el.sourceline}) has no 'name' attribute")
    for i, el in enumerate(root.findall("joint")):
        jn = el.get("name")
        where = f"joint '{jn}'" if jn else f"<joint> number {i + 1} (line {el.sourceline})"
        if not jn:
            raise _err(path, f"{where} has no 'name' attribute")
        if not el.get("type"):
            raise _err(path, f"{where} has no 'type' attribute; use revolute, continuous, prismatic or fixed")
        for tag in ("parent", "child"):
            sub = el.find(tag)
            if sub is None or not sub.get("link"):
                raise _err(path, f"{where} needs a <{tag} link=\"...\"/> element")

    try:
        capsules = _take_capsules(root)
    except ValueError as e:
        raise _err(path, str(e)) from None
    try:
        parse_robot = getattr(yourdfpy.URDF, "_parse_robot", None)
        if parse_robot is not None:
            robot = parse_robot(xml_element=root)
        else:  # older/newer yourdfpy without the static helper: hand it the cleaned document
            import io

            robot = yourdfpy.URDF.load(io.BytesIO(etree.tostring(root)), build_scene_graph=False,
                                       load_meshes=False, load_collision_meshes=False).robot
    except Exception as e:
        raise _err(path, f"yourdfpy could not parse it ({type(e).__name__}: {e}); check that every <geometry> "
                         "holds exactly one <box>, <cylinder>, <sphere> or <mesh> with its required attributes") from e
    return robot, capsules


def _take_capsules(root) -> Dict[Tuple[str, int], Tuple[float, float]]:
    """yourdfpy knows no <capsule>; stand a cylinder in for each one so it parses, and remember the
    collision capsules so they can be restored afterwards."""
    caps = {}
    for link in root.findall("link"):
        for kind in ("collision", "visual"):
            for idx, el in enumerate(link.findall(kind)):
                g = el.find("geometry")
                if g is None or len(g) != 1:
                    raise ValueError(f"link '{link.get('name')}', <{kind}> number {idx + 1} (line {el.sourceline}): "
                                     "its <geometry> must hold exactly one <box>, <cylinder>, <sphere>, <capsule> or <mesh>")
                if g[0].tag != "capsule":
                    continue
                c = g[0]
                key = (link.get("name"), idx) if kind == "collision" else ("visual", link.get("name"), idx)
                caps[key] = (float(c.get("radius", "nan")), float(c.get("length", "nan")))
                c.tag = "cylinder"
    return caps


# --------------------------------------------------------------------------------------------
# Mesh paths
# --------------------------------------------------------------------------------------------
def _ancestors(d):
    out = []
    while True:
        out.append(d)
        up = os.path.dirname(d)
        if up == d:
            return out
        d = up


def _mesh_candidates(filename: str, urdf_path: str) -> List[str]:
    """Paths to try, in order, for a <mesh filename>.

    package://PKG/sub is looked for as <dir>/PKG/sub and, when <dir> itself is named PKG, as
    <dir>/sub, for every folder above the URDF and then for each ROS_PACKAGE_PATH entry: that covers
    both source trees (robots/<pkg>/urdf/x.urdf) and installed share/ layouts without any ROS. Last,
    everything after package:// relative to the URDF's folder (package://mesh.obj).
    """
    urdf_dir = os.path.dirname(urdf_path)
    fn = filename.strip()
    if fn.startswith("package://"):
        rest = fn[len("package://"):].lstrip("/")
        pkg, _, sub = rest.partition("/")
        bases = _ancestors(urdf_dir) + [p for p in os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep) if p]
        out = []
        if sub:
            for d in bases:
                out.append(os.path.join(d, pkg, sub))
                if os.path.basename(os.path.normpath(d)) == pkg:
                    out.append(os.path.join(d, sub))
        # package://file.obj (no package folder; Genesis's assets have some) or a package-less path:
        # relative to the URDF's folder, as Genesis reads it
        out.append(os.path.join(urdf_dir, rest))
        return out
    if fn.startswith("file://"):
        fn = fn[len("file://"):]
    if os.path.isabs(fn):
        return [fn]
    return [os.path.join(urdf_dir, fn)]


def _resolve_mesh(filename: str, urdf_path: str, link: str) -> str:
    tried = _mesh_candidates(filename, urdf_path)
    for p in tried:
        if model_cache.note_file(p):
            return p
    shown = "\n  ".join(tried[:12]) + ("\n  ..." if len(tried) > 12 else "")
    raise FileNotFoundError(
        f"URDF '{urdf_path}', link '{link}': collision mesh '{filename}' not found; tried:\n  {shown}\n"
        "put the mesh there, fix the filename, or add its package's parent folder to ROS_PACKAGE_PATH"
    )


# --------------------------------------------------------------------------------------------
# Link contents
# --------------------------------------------------------------------------------------------
def _origin(T, s) -> np.ndarray:
    out = np.eye(4) if T is None else np.array(T, dtype=float)
    out[:3, 3] *= s
    return out


def _collision_geoms(path, link, s, capsules, morph, is_robot) -> List[GeomDesc]:
    """Collision shapes of a URDF link, in the link frame, scaled. A non-convex mesh collides as its convex
    hull, or as its CoACD parts (primitives.convex_parts) with morph.convexify=False or past the morph's
    decomposition threshold for a robot's links (is_robot: the file has a hinge or slide joint, infinite by
    default) or an object's (0.15 by default)."""
    geoms = []
    for idx, col in enumerate(link.collisions):
        T = _origin(col.origin, s)
        pos, quat = T[:3, 3].copy(), mat_to_quat(T[:3, :3])
        g = col.geometry
        where = f"link '{link.name}', collision {idx}"
        if g is None:
            raise _err(path, f"{where} has no <geometry>")
        if (link.name, idx) in capsules:
            r, length = capsules[(link.name, idx)]
            if not (r > 0 and length >= 0):
                raise _err(path, f"{where}: <capsule> needs radius > 0 and length >= 0")
            geoms.append(GeomDesc("capsule", pos, quat, (r * s, length * s / 2.0)))
        elif g.box is not None:
            size = np.asarray(g.box.size, dtype=float).reshape(-1)
            if size.shape != (3,) or np.any(size <= 0):
                raise _err(path, f"{where}: <box size> must be three positive numbers, got {g.box.size}")
            geoms.append(GeomDesc("box", pos, quat, tuple(float(v) for v in size * s / 2.0)))
        elif g.sphere is not None:
            if not g.sphere.radius or g.sphere.radius <= 0:
                raise _err(path, f"{where}: <sphere radius> must be positive")
            geoms.append(GeomDesc("sphere", pos, quat, (float(g.sphere.radius) * s,)))
        elif g.cylinder is not None:
            if not g.cylinder.radius or g.cylinder.radius <= 0 or g.cylinder.length is None or g.cylinder.length < 0:
                raise _err(path, f"{where}: <cylinder> needs radius > 0 and length >= 0")
            geoms.append(GeomDesc("cylinder", pos, quat,
                                  (float(g.cylinder.radius) * s, float(g.cylinder.length) * s / 2.0)))
        elif g.mesh is not None:
            file = _resolve_mesh(g.mesh.filename, path, link.name)
            V, F = load_mesh_file(file, f"URDF '{path}', link '{link.name}' (mesh '{g.mesh.filename}')")
            mscale = 1.0 if g.mesh.scale is None else np.asarray(g.mesh.scale, dtype=float)
            V, F = scale_mesh(zup_vertices(V, morph.file_meshes_are_zup), F, mscale * s)
            shapes = mesh_shapes(morph, V, F, f"URDF '{path}', {where} (mesh '{g.mesh.filename}')", is_robot)
            for Vs, Fs in shapes:
                geoms.append(GeomDesc("mesh", pos, quat, (), vertices=Vs, faces=Fs, hull=mesh_hull(Vs)))
        else:
            raise _err(path, f"{where}: empty <geometry>")
    return geoms


def _visual_descs(path, link, s, capsules, materials, zup=True) -> List[VisualDesc]:
    """Visual shapes of a URDF link, in the link frame, scaled (a mesh turned from y-up unless zup). Mesh files
    are located but not read (cameras read them on first use); a visual that cannot be drawn is skipped with a
    warning, since it changes nothing in the physics."""
    out = []
    for idx, vis in enumerate(link.visuals):
        T = _origin(vis.origin, s)
        pos, quat = T[:3, 3].copy(), mat_to_quat(T[:3, :3])
        g = vis.geometry
        rgba = None
        mat = vis.material
        if mat is not None:
            color = mat.color if mat.color is not None else getattr(materials.get(mat.name), "color", None)
            if color is not None and color.rgba is not None:
                rgba = tuple(float(c) for c in np.asarray(color.rgba, dtype=float).reshape(-1)[:4])
        try:
            if g is None:
                raise ValueError("no <geometry>")
            if ("visual", link.name, idx) in capsules:
                r, length = capsules[("visual", link.name, idx)]
                v = VisualDesc("capsule", pos, quat, (r * s, length * s / 2.0))
            elif g.box is not None:
                v = VisualDesc("box", pos, quat, tuple(float(x) * s / 2.0 for x in np.asarray(g.box.size).reshape(3)))
            elif g.sphere is not None:
                v = VisualDesc("sphere", pos, quat, (float(g.sphere.radius) * s,))
            elif g.cylinder is not None:
                v = VisualDesc("cylinder", pos, quat,
                               (float(g.cylinder.radius) * s, float(g.cylinder.length) * s / 2.0))
            elif g.mesh is not None:
                file = next((p for p in _mesh_candidates(g.mesh.filename, path) if model_cache.note_file(p)), None)
                mscale = np.broadcast_to(np.asarray(1.0 if g.mesh.scale is None else g.mesh.scale, dtype=float), (3,))
                vquat, vscale = zup_visual(quat, mscale * s, zup)
                v = VisualDesc("mesh", pos, vquat, (), file=file, filename=g.mesh.filename, scale=vscale)
            else:
                raise ValueError("empty <geometry>")
            d = np.asarray(v.size, dtype=float)
            # capsules and cylinders may have zero length (a sphere, a disc); everything else must be positive
            lo = 0.0 if v.type in ("capsule", "cylinder") else 1e-300
            if not (np.all(np.isfinite(d)) and np.all(d[:1] > 0) and np.all(d[1:] >= lo)):
                raise ValueError(f"<{v.type}> has non-positive or missing dimensions {v.size}")
        except (TypeError, ValueError) as e:
            warnings.warn(f"URDF '{path}', link '{link.name}', visual {idx}: {e}; it will not be drawn", stacklevel=3)
            continue
        v.rgba = rgba
        out.append(v)
    return out


def _link_inertia(path, link, s, geoms, rho):
    """(mass, com, inertia about com) of a URDF link in its own frame."""
    if link.inertial is None:
        # no <inertial>: a solid of the material's density filling the collision shapes (overlaps
        # counted twice); a link with neither is massless
        parts = [geom_mass_properties(g, rho, f"URDF '{path}', link '{link.name}'") for g in geoms]
        return combine_inertias(parts)
    inr = link.inertial
    m = 0.0 if inr.mass is None else float(inr.mass)
    if not (np.isfinite(m) and m >= 0):
        raise _err(path, f"link '{link.name}': <mass value> {inr.mass} must be finite and >= 0")
    I = np.zeros((3, 3)) if inr.inertia is None else np.array(inr.inertia, dtype=float)
    T = _origin(inr.origin, 1.0)
    R = T[:3, :3]
    return m * s**3, T[:3, 3] * s, (R @ I @ R.T) * s**5


# --------------------------------------------------------------------------------------------
# Loader
# --------------------------------------------------------------------------------------------
def _check_tree(path, robot):
    """Validate names and tree shape; return (links by name, children joints by parent, root name)."""
    links = {}
    for l in robot.links:
        if l.name in links:
            raise _err(path, f"two <link>s are named '{l.name}'; link names must be unique")
        links[l.name] = l
    seen_j = set()
    parent_joint = {}
    children = defaultdict(list)
    for j in robot.joints:
        where = f"joint '{j.name}'"
        if j.name in seen_j:
            raise _err(path, f"two <joint>s are named '{j.name}'; joint names must be unique")
        seen_j.add(j.name)
        if j.type not in _KNOWN:
            raise _err(path, f"{where} has unknown type '{j.type}'; use revolute, continuous, prismatic or fixed")
        for role, ln in (("parent", j.parent), ("child", j.child)):
            if ln not in links:
                raise _err(path, f"{where} names {role} link '{ln}', which is not defined; add a <link name=\"{ln}\"> "
                                 "or fix the joint")
        if j.parent == j.child:
            raise _err(path, f"{where} connects link '{j.child}' to itself; a URDF must be a tree")
        if j.child in parent_joint:
            raise _err(path, f"link '{j.child}' is the child of two joints, '{parent_joint[j.child].name}' and "
                             f"'{j.name}': that closes a kinematic loop, which URDF and this loader do not support; "
                             "remove one of the joints")
        parent_joint[j.child] = j
        children[j.parent].append(j)
    for v in children.values():
        v.sort(key=lambda j: j.name)

    roots = [n for n in links if n not in parent_joint]
    if not roots:
        raise _err(path, "has no root link (every link is some joint's child): its joints form a closed loop "
                         f"({', '.join(repr(j.name) for j in robot.joints)}); a URDF must be a tree")
    if len(roots) > 1:
        raise _err(path, f"has {len(roots)} root links ({', '.join(repr(r) for r in roots)}), i.e. parts not "
                         "connected by joints; connect them with joints or load them as separate entities")
    reached, stack = set(), [roots[0]]
    while stack:
        n = stack.pop()
        reached.add(n)
        stack.extend(j.child for j in children[n])
    if len(reached) < len(links):
        loop = [parent_joint[n].name for n in links if n not in reached]
        raise _err(path, f"joints {', '.join(repr(n) for n in loop)} form a closed loop detached from root "
                         f"'{roots[0]}'; a URDF must be a tree")
    return links, children, roots[0]


def load_urdf(morph, material, name) -> EntityModel:
    """gs.morphs.URDF -> EntityModel (fixed links merged into their parents). A URDF loaded before, with
    the same morph, material density and files, comes from the on-disk cache (loaders/cache.py)."""
    path = os.path.abspath(os.fspath(morph.file))
    return model_cache.cached(path, morph, material, name, lambda: _load_urdf(morph, material, name))


def _load_urdf(morph, material, name) -> EntityModel:
    path = os.path.abspath(os.fspath(morph.file))
    s = float(getattr(morph, "scale", 1.0))
    robot, capsules = _parse(path)
    # a link without <inertial> is filled at the material's density: Genesis's default for an articulated
    # robot's links when the file has a hinge or slide joint, else its default for an object
    # (and Genesis's rule for which decomposition threshold its meshes take: a link is a robot's when it or a
    # link it is welded to hangs on or carries a hinge or slide joint; in a URDF, whose floating joints are
    # refused, that is every link of a file with one such joint)
    is_robot = any(j.type in _MOVING for j in robot.joints)
    rho = material.density(robot=is_robot)
    links, children, root = _check_tree(path, robot)
    merge = getattr(morph, "merge_fixed_links", True)
    keep = set(getattr(morph, "links_to_keep", ()))
    missing = sorted(keep - set(links))
    if missing:
        raise _err(path, f"links_to_keep names {missing}, which are not links of this robot; its links are "
                         f"{sorted(links)}")

    # A massless, shapeless placeholder root ('world' with one fixed joint, or any such link with one
    # floating joint) only says where the robot sits: fold that offset into the base placement.
    base_T = np.eye(4)
    root_joint_name = ROOT_JOINT_NAME
    r = links[root]
    kids = children[root]
    if len(kids) == 1 and not r.collisions and (r.inertial is None or not r.inertial.mass):
        j = kids[0]
        if j.type == "floating" or (j.type == "fixed" and root == "world"):
            base_T = _origin(j.origin, s)
            root_joint_name = j.name
            root = j.child
    if root_joint_name == ROOT_JOINT_NAME and root_joint_name in {j.name for j in robot.joints}:
        root_joint_name = f"{root}_{ROOT_JOINT_NAME}"

    T_world = pose_matrix(morph.pos, morph.quat) @ base_T
    descs: List[LinkDesc] = [
        LinkDesc(
            name=root,
            parent=-1,
            joint_name=root_joint_name,
            joint_type="fixed" if morph.fixed else "free",
            joint_pos=T_world[:3, 3].copy(),
            joint_quat=mat_to_quat(T_world[:3, :3]),
        )
    ]
    parts: List[list] = [[]]
    moving = {}
    materials = {m.name: m for m in robot.materials if m.name}

    # Iterative pre-order DFS over URDF links. Each entry: (urdf link, its joint (None for the root),
    # index of the desc the joint hangs from, joint frame pose in that desc). A desc is created when
    # its link is popped, so descs come out exactly in pre-order, fixed links merged in place.
    stack = [(root, None, 0, np.eye(4))]
    while stack:
        ln, j, di, T = stack.pop()
        if j is not None and j.type != "fixed":
            descs.append(_moving_link(path, j, di, T, s))
            parts.append([])
            moving[j.name] = j
            di, T = len(descs) - 1, np.eye(4)
        elif j is not None and (not merge or ln in keep):
            # a kept fixed link: a link of its own, welded to the one it hangs from
            descs.append(LinkDesc(name=ln, parent=di, joint_name=j.name, joint_type="fixed",
                                  joint_pos=T[:3, 3].copy(), joint_quat=mat_to_quat(T[:3, :3])))
            parts.append([])
            di, T = len(descs) - 1, np.eye(4)
        link = links[ln]
        geoms = _collision_geoms(path, link, s, capsules, morph, is_robot)
        m, c, I = _link_inertia(path, link, s, geoms, rho)
        R = T[:3, :3]
        parts[di].append((m, R @ c + T[:3, 3], R @ I @ R.T))
        for g in geoms:
            Tg = T @ pose_matrix(g.pos, g.quat)
            g.pos, g.quat = Tg[:3, 3].copy(), mat_to_quat(Tg[:3, :3])
            descs[di].geoms.append(g)
        for v in _visual_descs(path, link, s, capsules, materials, morph.file_meshes_are_zup):
            Tv = T @ pose_matrix(v.pos, v.quat)
            v.pos, v.quat = Tv[:3, 3].copy(), mat_to_quat(Tv[:3, :3])
            descs[di].visuals.append(v)

        for cj in reversed(children[ln]):  # reversed: children pop in ascending joint-name order
            if cj.type in ("floating", "planar"):
                raise _err(path, f"joint '{cj.name}' has type '{cj.type}', which is not supported inside a URDF "
                                 "(only revolute, continuous, prismatic and fixed joints; a floating base comes from "
                                 "the morph with fixed=False); replace the joint or split the robot")
            stack.append((cj.child, cj, di, T @ _origin(cj.origin, s)))

    for d, p in zip(descs, parts):
        d.mass, d.com, d.inertia = combine_inertias(p)
        if d.mimic is not None and d.mimic.joint not in moving:
            # such files exist in the wild (example-robot-data's alex_psyonic_hands) and Pinocchio loads
            # them with the joint left independent; do the same rather than refuse the robot
            warnings.warn(f"URDF '{path}': joint '{d.joint_name}' mimics '{d.mimic.joint}', which is not a "
                          "revolute, continuous or prismatic joint of this robot; the <mimic> is ignored and the "
                          "joint moves independently", stacklevel=2)
            d.mimic = None
    model = EntityModel(name=name, links=descs, source=path)
    model.validate()
    return model


def _moving_link(path, j, parent_idx, TJ, s) -> LinkDesc:
    axis = np.asarray(j.axis if j.axis is not None else (1.0, 0.0, 0.0), dtype=float).reshape(-1)
    n = np.linalg.norm(axis) if axis.shape == (3,) else 0.0
    if not (n > 1e-12 and np.isfinite(n)):
        raise _err(path, f"joint '{j.name}': <axis xyz> {j.axis} is not a non-zero 3-vector")
    axis = axis / n

    lim = j.limit
    lin = 1.0 if j.type != "prismatic" else s  # prismatic limits/velocities are lengths
    effort = np.inf if lim is None or lim.effort is None else float(lim.effort)
    velocity = np.inf if lim is None or lim.velocity is None else float(lim.velocity) * lin
    if j.type == "continuous" or lim is None:
        limit = (-np.inf, np.inf)
    else:
        # the URDF spec's defaults for a missing bound are 0
        lo = 0.0 if lim.lower is None else float(lim.lower) * lin
        hi = 0.0 if lim.upper is None else float(lim.upper) * lin
        if lo > hi:
            raise _err(path, f"joint '{j.name}': lower limit {lim.lower} exceeds upper limit {lim.upper}")
        limit = (lo, hi)

    dyn = j.dynamics
    damping = 0.0 if dyn is None or dyn.damping is None else float(dyn.damping)
    friction = 0.0 if dyn is None or dyn.friction is None else float(dyn.friction)
    mimic = None
    if j.mimic is not None:
        mimic = MimicDesc(
            joint=j.mimic.joint,
            multiplier=1.0 if j.mimic.multiplier is None else float(j.mimic.multiplier),
            offset=0.0 if j.mimic.offset is None else float(j.mimic.offset) * lin,
        )
    # Genesis reads <safety_controller k_position k_velocity> as the joint's PD gains (ROS means the
    # soft-limit controller's gains by them); we follow Genesis, so its scripts drive robots alike
    sc = getattr(j, "safety_controller", None)
    kp = None if sc is None or sc.k_position is None else float(sc.k_position)
    kv = None if sc is None or sc.k_velocity is None else float(sc.k_velocity)
    return LinkDesc(
        name=j.child,
        parent=parent_idx,
        kp=kp,
        kv=kv,
        joint_name=j.name,
        joint_type="prismatic" if j.type == "prismatic" else "revolute",
        joint_pos=TJ[:3, 3].copy(),
        joint_quat=mat_to_quat(TJ[:3, :3]),
        joint_axis=axis,
        limit=limit,
        effort=effort,
        velocity=velocity,
        damping=damping,
        frictionloss=friction,
        mimic=mimic,
    )
