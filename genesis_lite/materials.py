"""Materials: physical properties an entity is made of."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Rigid:
    """rho: density (kg/m^3) used for links without a URDF <inertial> and for primitive shapes;
    friction: Coulomb coefficient (dimensionless, >= 0)."""

    rho: float = 200.0
    friction: float = 1.0

    def __post_init__(self):
        if not (np.isfinite(self.rho) and self.rho > 0):
            raise ValueError(f"gs.materials.Rigid(rho={self.rho!r}): density must be a positive number (kg/m^3)")
        if not (np.isfinite(self.friction) and self.friction >= 0):
            raise ValueError(f"gs.materials.Rigid(friction={self.friction!r}): friction must be a finite number >= 0")
