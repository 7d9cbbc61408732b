"""Genesis's `align` of a file morph (Mesh, URDF, MJCF): a free-floating root link's frame moved to its
centre of mass and turned to its principal axes of inertia, so that the free joint's position and
quaternion (get_pos, get_quat, get_qpos, get_dofs_position) describe that frame, as Genesis 0.4.5 reports
them for a basic rigid object (engine/entities/rigid_entity/rigid_entity.py, `_align_link`).

`align=None` (Genesis's default) aligns a root link with a free joint when nothing below it moves on a
hinge or slide joint (a basic rigid object: a mesh, a one-body URDF or MJCF); True asks for it wherever
such a root exists; False keeps the file's frame (what MuJoCo and Pinocchio report for the same file).
The body is the same either way: its geoms, visuals and kept child links are re-expressed in the new
frame, its inertia becomes diagonal about the new origin; only the frame the pose is read in moves.
"""
from __future__ import annotations

import dataclasses
from typing import List

import numpy as np

from solvers.rigid.model import EntityModel, LinkDesc

from ..utils.geom import inv_quat
from .primitives import mat_to_quat, quat_mul, quat_to_mat

# eigenvalues closer than this fraction of the largest are one (degenerate) group; a frame whose axes
# are within this of the principal axes is kept as it is
PRINCIPAL_TOL = 1e-3


def principal_axes(inertia, tol: float = PRINCIPAL_TOL) -> np.ndarray:
    """The rotation R (columns: principal axes in the link frame) that diagonalises `inertia`, chosen as
    Genesis chooses it, so that an aligned body's quaternion is Genesis's: the identity when the axes
    already are principal (within tol); else each axis of a distinct moment on the frame axis it lies
    nearest to, the axes of a repeated moment the rotation nearest to the frame's remaining axes, each
    column's largest component positive, and a right-handed frame."""
    I = 0.5 * (np.asarray(inertia, dtype=float) + np.asarray(inertia, dtype=float).T)
    lam, vec = np.linalg.eigh(I)  # ascending moments, orthonormal columns
    if np.mean(np.abs(vec).max(axis=1)) > 1.0 - tol:
        return np.eye(3)
    # groups of (nearly) equal moments
    groups, i = [], 0
    while i < 3:
        j = i + 1
        while j < 3 and lam[j] - lam[i] < tol * lam[-1]:
            j += 1
        groups.append(list(range(i, j)))
        i = j
    col_of_axis = [None, None, None]
    for g in groups:
        if len(g) == 1:
            for ax in np.argsort(-np.abs(vec[:, g[0]]), kind="stable"):
                if col_of_axis[ax] is None:
                    col_of_axis[ax] = g[0]
                    break
    free_axes = [ax for ax in range(3) if col_of_axis[ax] is None]
    for ax, col in zip(free_axes, [c for g in groups if len(g) > 1 for c in g]):
        col_of_axis[ax] = col
    R = vec[:, col_of_axis]
    if free_axes:
        # within a repeated moment any basis is principal: the one nearest the frame's own axes
        U = R[:, free_axes]
        E = np.eye(3)[:, free_axes]
        a, _, bt = np.linalg.svd(U.T @ E)
        Q = a @ bt
        if np.linalg.det(Q) < 0:
            a[:, -1] *= -1
            Q = a @ bt
        R[:, free_axes] = U @ Q
    R = R * np.sign(R[np.argmax(np.abs(R), axis=0), np.arange(3)])
    if np.linalg.det(R) < 0:
        R[:, 0] = -R[:, 0]
    return R


def _articulated_below(model: EntityModel, root: int) -> bool:
    """Whether a link under `root` (the root included) moves on a hinge or slide joint."""
    under = {root}
    for i, l in enumerate(model.links):
        if l.parent in under:
            under.add(i)
    return any(model.links[i].joint_type in ("revolute", "prismatic") for i in under)


def _reframe(pos, quat, c, R, qR):
    """A pose (pos, quat) in the old link frame, expressed in the frame at c turned by R (quaternion qR)."""
    return R.T @ (np.asarray(pos, dtype=float) - c), quat_mul(inv_quat(qR), quat)


def _reframed(d, c, R, qR):
    """A geom or visual (pos, quat in the link frame) re-expressed in the new frame."""
    pos, quat = _reframe(d.pos, d.quat, c, R, qR)
    return dataclasses.replace(d, pos=pos, quat=quat)


def align_model(model: EntityModel, align) -> EntityModel:
    """The model with its free root links aligned as `align` (None, True, False) asks; a new model (a
    loaded one may be the model cache's), or the same one when nothing moves."""
    if align is False:
        return model
    links: List[LinkDesc] = list(model.links)
    changed = False
    for i, l in enumerate(model.links):
        if l.parent != -1 or l.joint_type != "free" or l.mass <= 0:
            continue
        if align is None and _articulated_below(model, i):
            continue
        c = np.asarray(l.com, dtype=float)
        R = principal_axes(l.inertia)
        if not np.any(c) and np.array_equal(R, np.eye(3)):
            continue
        qR = mat_to_quat(R)
        links[i] = dataclasses.replace(
            l, joint_pos=np.asarray(l.joint_pos, dtype=float) + quat_to_mat(l.joint_quat) @ c,
            joint_quat=quat_mul(l.joint_quat, qR), com=np.zeros(3), inertia=R.T @ np.asarray(l.inertia) @ R,
            geoms=[_reframed(g, c, R, qR) for g in l.geoms], visuals=[_reframed(v, c, R, qR) for v in l.visuals])
        for k, child in enumerate(model.links):
            if child.parent == i:
                p, q = _reframe(child.joint_pos, child.joint_quat, c, R, qR)
                links[k] = dataclasses.replace(links[k], joint_pos=p, joint_quat=q)
        changed = True
    return dataclasses.replace(model, links=links) if changed else model
