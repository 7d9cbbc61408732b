"""ToolEntity: Genesis's tool (an entity made of gs.materials.Tool), a rigid body that moves only as it
is told and pushes MPM material.

Genesis moves a tool kinematically: every substep its position advances by its velocity and its
orientation by its angular velocity, which keep the values last set. Here a tool is a rigid body of the
rigid solver on which no force acts, so that its dynamics are that same motion:
- no gravity (gravity_compensation = 1), no contact with other rigid bodies (its entity's
  `rigid_contact` is off), and no reaction from the MPM material (the coupler leaves its geoms out of the
  wrench it returns to the rigid solver, bridges/coupler.py);
- its centre of mass at its origin and an isotropic inertia: a free body with no torque and isotropic
  inertia keeps its angular velocity, and with the centre of mass at the origin the origin keeps its
  linear velocity.
Its pose and velocity are the rigid state, so everything that reads or sets them differentiably
(set_position, set_velocity with tensors that require grad) carries gradients through the coupling.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import GenesisException
from .rigid_entity import RigidEntity


def make_tool_model(model, name):
    """The EntityModel of a tool: its one free link with the centre of mass at the origin, an isotropic
    inertia (the trace of its inertia about the origin, over 3) and no rigid contact."""
    if model.n_links != 1 or model.links[0].joint_type != "free":
        what = f"{model.n_links} links" if model.n_links != 1 else f"a {model.links[0].joint_type} base"
        raise GenesisException(f"entity '{name}': a gs.materials.Tool entity is one body that moves (Genesis's tool), "
                               f"but this morph gives {what}: use a Mesh or a primitive morph with fixed=False")
    link = model.links[0]
    c = np.asarray(link.com, dtype=float)
    I_origin = np.asarray(link.inertia, dtype=float) + link.mass * (c @ c * np.eye(3) - np.outer(c, c))
    link.com = np.zeros(3)
    link.inertia = np.trace(I_origin) / 3.0 * np.eye(3)
    model.rigid_contact = False
    return model


@dataclass
class ToolEntityState:
    """A tool's pose and velocity (Genesis's ToolEntityState): pos (m), quat (w, x, y, z), vel (m/s) and
    ang (rad/s, world frame), each with a leading env axis in a batched scene."""

    pos: torch.Tensor
    quat: torch.Tensor
    vel: torch.Tensor
    ang: torch.Tensor


class ToolEntity(RigidEntity):
    """An entity of gs.materials.Tool (see the module docstring); a RigidEntity with Genesis's tool API."""

    def set_position(self, pos, envs_idx=None):
        """The tool's position (m), keeping its velocity (Genesis's)."""
        self.set_pos(pos, envs_idx, zero_velocity=False)

    def set_quat(self, quat, envs_idx=None, zero_velocity=False):
        """The tool's orientation (w, x, y, z), keeping its velocity (Genesis's)."""
        super().set_quat(quat, envs_idx, zero_velocity=zero_velocity)

    def set_velocity(self, vel=None, ang=None, envs_idx=None):
        """The tool's linear velocity (m/s) and angular velocity (rad/s, world frame), which it keeps until
        set again; either may be left out (kept as is)."""
        if vel is None and ang is None:
            raise GenesisException(f"entity '{self.name}': set_velocity needs vel= or ang= (or both)")
        if vel is not None:
            self.set_dofs_velocity(vel, [0, 1, 2], envs_idx)
        if ang is not None:
            self.set_dofs_velocity(ang, [3, 4, 5], envs_idx)

    def get_state(self, envs_idx=None) -> ToolEntityState:
        v = self.get_dofs_velocity(envs_idx=envs_idx)
        return ToolEntityState(self.get_pos(envs_idx), self.get_quat(envs_idx), v[..., :3], v[..., 3:])
