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
