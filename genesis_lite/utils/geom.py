"""The rotation helpers of Genesis's `gs.utils.geom` that its example scripts use (the locomotion and drone
envs import quat_to_xyz, transform_by_quat, inv_quat, transform_quat_by_quat; others xyz_to_quat and the
trans/quat transforms), on numpy arrays and torch tensors alike, with Genesis's conventions:

- the last axis holds the components, every leading axis is a batch axis, and two arguments broadcast
  against each other (a (3,) vector with (N, 4) quaternions gives (N, 3));
- quaternions are (w, x, y, z); one that is not of unit norm stands for its normalised rotation (as in
  Genesis's quat_to_R, transform_by_quat, transform_quat_by_quat and quat_to_xyz);
- Euler angles (x, y, z) are radians unless degrees=True. rpy=True: roll, pitch, yaw about the fixed axes,
  R = Rz(z) Ry(y) Rx(x) (URDF's rpy, what the locomotion envs read with quat_to_xyz(q, rpy=True,
  degrees=True) and what morphs' `euler=` means); rpy=False (the default): about the moving axes in the
  order x, y, z, R = Rx(x) Ry(y) Rz(z). quat_to_xyz gives x and z in [-pi, pi], y in [-pi/2, pi/2]; at
  y = +-pi/2 (gimbal lock) it gives x = 0 and puts the whole turn about the locked axis in z.

Everything here is differentiable through torch. The entity code uses the `_unit_*` forms, which take unit
quaternions as they are (no normalisation in their gradients).
"""
from __future__ import annotations

import math

import numpy as np
import torch


def _lib(x, fname="gs.utils.geom"):
    if torch.is_tensor(x):
        return torch
    if isinstance(x, np.ndarray):
        return np
    raise TypeError(f"{fname}: expected a numpy array or a torch tensor, got {type(x).__name__} (wrap a list in "
                    "np.array(...) or torch.tensor(...))")


def _check(fname, **args):
    """One library for every argument, and the component count each names on its last axis."""
    libs = set()
    for name, (x, n) in args.items():
        libs.add(_lib(x, fname))
        if x.ndim < 1 or x.shape[-1] != n:
            raise ValueError(f"{fname}: {name} must have {n} components on its last axis, got shape "
                             f"{tuple(x.shape)}")
    if len(libs) > 1:
        raise TypeError(f"{fname}: give all arguments as torch tensors or all as numpy arrays, not a mix "
                        "(convert with torch.as_tensor or .numpy())")
    return libs.pop()


def _stack(lib, parts):
    return torch.stack(parts, -1) if lib is torch else np.stack(parts, axis=-1)


def xyz_to_quat(xyz, rpy=False, degrees=False):
    """Unit quaternions (..., 4) of Euler angles xyz (..., 3) (radians, or degrees with degrees=True;
    rpy=True: R = Rz Ry Rx about fixed axes, rpy=False: R = Rx Ry Rz about moving axes)."""
    lib = _check("xyz_to_quat", xyz=(xyz, 3))
    if degrees:
        xyz = xyz * (math.pi / 180.0)
    half = 0.5 * xyz
    cr, sr = lib.cos(half[..., 0]), lib.sin(half[..., 0])
    cp, sp = lib.cos(half[..., 1]), lib.sin(half[..., 1])
    cy, sy = lib.cos(half[..., 2]), lib.sin(half[..., 2])
    s = 1.0 if rpy else -1.0
    w = cr * cp * cy + s * sr * sp * sy
    x = sr * cp * cy - s * cr * sp * sy
    y = cr * sp * cy + s * sr * cp * sy
    z = cr * cp * sy - s * sr * sp * cy
    return _stack(lib, [w, x, y, z])


def _unit_quat_to_R(quat, scale=2.0):
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4), taken as they are."""
    w, x, y, z = (quat[..., i] for i in range(4))
    rows = [[1 - scale * (y * y + z * z), scale * (x * y - w * z), scale * (x * z + w * y)],
            [scale * (x * y + w * z), 1 - scale * (x * x + z * z), scale * (y * z - w * x)],
            [scale * (x * z - w * y), scale * (y * z + w * x), 1 - scale * (x * x + y * y)]]
    if torch.is_tensor(quat):
        return torch.stack([torch.stack(r, -1) for r in rows], -2)
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def quat_to_R(quat):
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) (w, x, y, z); a quaternion of any non-zero
    norm gives the rotation of its normalised form."""
    _check("quat_to_R", quat=(quat, 4))
    return _unit_quat_to_R(quat, 2.0 / (quat * quat).sum(-1))


def quat_to_xyz(quat, rpy=False, degrees=False):
    """Euler angles (..., 3) of quaternions (..., 4): the inverse of xyz_to_quat with the same rpy
    convention (rpy=True: R = Rz Ry Rx; rpy=False: R = Rx Ry Rz); radians unless degrees=True. x and z in
    [-pi, pi], y in [-pi/2, pi/2]; at gimbal lock (|y| = pi/2) x is 0 and z carries the turn."""
    lib = _check("quat_to_xyz", quat=(quat, 4))
    R = quat_to_R(quat)
    if rpy:  # R = Rz Ry Rx: R20 = -sin y, (R21, R22) = cos y (sin x, cos x), (R10, R00) = cos y (sin z, cos z)
        sin_y, sx, cx, sz, cz = -R[..., 2, 0], R[..., 2, 1], R[..., 2, 2], R[..., 1, 0], R[..., 0, 0]
        # at cos y = 0 with x = 0: (-R01, R11) = (sin z, cos z)
        lock_sz, lock_cz = -R[..., 0, 1], R[..., 1, 1]
    else:  # R = Rx Ry Rz: R02 = sin y, (-R12, R22) = cos y (sin x, cos x), (-R01, R00) = cos y (sin z, cos z)
        sin_y, sx, cx, sz, cz = R[..., 0, 2], -R[..., 1, 2], R[..., 2, 2], -R[..., 0, 1], R[..., 0, 0]
        lock_sz, lock_cz = R[..., 1, 0], R[..., 1, 1]  # at cos y = 0 with x = 0
    cos_y = lib.hypot(sz, cz)
    eps = 8.0 * (torch.finfo(quat.dtype).eps if lib is torch else np.finfo(R.dtype).eps)
    lock = cos_y < eps
    x = lib.where(lock, 0.0 * sx, lib.arctan2(sx, cx))
    y = lib.arctan2(sin_y, cos_y)
    z = lib.where(lock, lib.arctan2(lock_sz, lock_cz), lib.arctan2(sz, cz))
    out = _stack(lib, [x, y, z])
    return out * (180.0 / math.pi) if degrees else out


def inv_quat(quat):
    """The inverse rotation of unit quaternions (w, x, y, z): the conjugate (w, -x, -y, -z)."""
    lib = _check("inv_quat", quat=(quat, 4))
    return _stack(lib, [quat[..., 0], -quat[..., 1], -quat[..., 2], -quat[..., 3]])


def quat_mul(a, b):
    """The Hamilton product a b of quaternions (w, x, y, z), as they are: the rotation b followed by a."""
    aw, ax, ay, az = (a[..., i] for i in range(4))
    bw, bx, by, bz = (b[..., i] for i in range(4))
    return _stack(torch if torch.is_tensor(a) else np,
                  [aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                   aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def transform_by_quat(v, quat):
    """Vectors v (..., 3) rotated by quaternions quat (..., 4) (normalised), broadcast against each other."""
    _check("transform_by_quat", v=(v, 3), quat=(quat, 4))
    return (quat_to_R(quat) * v[..., None, :]).sum(-1)


def inv_transform_by_quat(v, quat):
    """Vectors v (..., 3) rotated by the inverse of quaternions quat (..., 4): world to body frame."""
    _check("inv_transform_by_quat", v=(v, 3), quat=(quat, 4))
    return transform_by_quat(v, inv_quat(quat))


def transform_by_trans_quat(pos, trans, quat):
    """Points pos (..., 3) of a frame at trans (..., 3) turned by quat (..., 4), in the parent frame."""
    _check("transform_by_trans_quat", pos=(pos, 3), trans=(trans, 3), quat=(quat, 4))
    return transform_by_quat(pos, quat) + trans


def inv_transform_by_trans_quat(pos, trans, quat):
    """The inverse of transform_by_trans_quat: points pos (..., 3) of the parent frame in the frame at
    trans turned by quat."""
    _check("inv_transform_by_trans_quat", pos=(pos, 3), trans=(trans, 3), quat=(quat, 4))
    return inv_transform_by_quat(pos - trans, quat)


def transform_quat_by_quat(v, u):
    """The rotation v followed by the rotation u: the unit quaternion of u v (Genesis's argument order;
    R(result) = R(u) R(v)), broadcast against each other."""
    _check("transform_quat_by_quat", v=(v, 4), u=(u, 4))
    q = quat_mul(u, v)
    norm = (q * q).sum(-1)[..., None] ** 0.5
    return q / norm
