"""The rotation helpers of Genesis's `gs.utils.geom` that its example scripts use, on numpy arrays and
torch tensors alike (the last axis holds the components; quaternions are (w, x, y, z))."""
from __future__ import annotations

import math

import numpy as np
import torch


def _lib(x):
    if torch.is_tensor(x):
        return torch
    if isinstance(x, np.ndarray):
        return np
    raise TypeError(f"gs.utils.geom: expected a numpy array or a torch tensor, got {type(x).__name__}")


def xyz_to_quat(xyz, rpy=False, degrees=False):
    """Quaternion of Euler angles (x, y, z). rpy=True: roll, pitch, yaw about the fixed axes, R = Rz Ry Rx
    (URDF's rpy, what morphs' `euler=` means); rpy=False: about the moving axes in the order x, y, z,
    R = Rx Ry Rz."""
    lib = _lib(xyz)
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
    return lib.stack([w, x, y, z], -1) if lib is torch else np.stack([w, x, y, z], axis=-1)


def quat_to_R(quat):
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4)."""
    lib = _lib(quat)
    w, x, y, z = (quat[..., i] for i in range(4))
    rows = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    if lib is torch:
        return torch.stack([torch.stack(r, -1) for r in rows], -2)
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def _stack(lib, parts):
    return lib.stack(parts, -1) if lib is torch else np.stack(parts, axis=-1)


def quat_to_xyz(quat, rpy=False, degrees=False):
    """Euler angles (x, y, z) of unit quaternions, the inverse of xyz_to_quat with the same conventions
    (rpy=True: R = Rz Ry Rx; rpy=False: R = Rx Ry Rz); radians unless degrees=True."""
    lib = _lib(quat)
    R = quat_to_R(quat)
    clip = (lambda a: torch.clamp(a, -1.0, 1.0)) if lib is torch else (lambda a: np.clip(a, -1.0, 1.0))
    if rpy:
        parts = [lib.arctan2(R[..., 2, 1], R[..., 2, 2]), lib.arcsin(clip(-R[..., 2, 0])),
                 lib.arctan2(R[..., 1, 0], R[..., 0, 0])]
    else:
        parts = [lib.arctan2(-R[..., 1, 2], R[..., 2, 2]), lib.arcsin(clip(R[..., 0, 2])),
                 lib.arctan2(-R[..., 0, 1], R[..., 0, 0])]
    out = _stack(lib, parts)
    return out * (180.0 / math.pi) if degrees else out


def inv_quat(quat):
    """The inverse rotation of unit quaternions (w, x, y, z): the conjugate."""
    lib = _lib(quat)
    return _stack(lib, [quat[..., 0], -quat[..., 1], -quat[..., 2], -quat[..., 3]])


def quat_mul(a, b):
    """The Hamilton product a b of quaternions (w, x, y, z): the rotation b followed by a."""
    lib = _lib(a)
    aw, ax, ay, az = (a[..., i] for i in range(4))
    bw, bx, by, bz = (b[..., i] for i in range(4))
    return _stack(lib, [aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def transform_by_quat(v, quat):
    """Vectors v (..., 3) rotated by unit quaternions (..., 4)."""
    R = quat_to_R(quat)
    if torch.is_tensor(v):
        return (R @ v.unsqueeze(-1)).squeeze(-1)
    return (R @ v[..., None])[..., 0]


def transform_quat_by_quat(v, u):
    """The rotation v followed by the rotation u: the quaternion u v (Genesis's argument order)."""
    return quat_mul(u, v)
