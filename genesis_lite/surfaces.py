"""Surfaces: how an entity looks to a camera (Genesis's gs.surfaces). The software rasteriser uses
`color` and `vis_mode`; the other fields exist so Genesis scripts run unchanged, and are ignored."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

VIS_MODES = ("visual", "collision", "particle", "sdf", "recon")


@dataclass
class Surface:
    """color: RGB or RGBA in [0, 1] for the whole entity (None: the mesh files' own colours, else a
    palette colour per entity); vis_mode: 'visual' draws URDF <visual> / the mesh file, 'collision'
    the collision shapes ('particle', 'sdf', 'recon' are accepted and drawn as 'visual')."""

    color: Optional[Sequence[float]] = None
    vis_mode: Optional[str] = None
    opacity: Optional[float] = None
    roughness: Optional[float] = None
    metallic: Optional[float] = None
    emissive: Optional[Sequence[float]] = None
    smooth: bool = True
    double_sided: Optional[bool] = None

    def __post_init__(self):
        owner = f"gs.surfaces.{type(self).__name__}"
        if self.color is not None:
            c = np.asarray(self.color, dtype=float).reshape(-1)
            if c.shape not in ((3,), (4,)) or not np.all(np.isfinite(c)) or np.any(c < 0) or np.any(c > 1):
                raise ValueError(f"{owner}(color={self.color!r}): expected 3 or 4 numbers in [0, 1] (RGB or RGBA)")
            self.color = tuple(float(x) for x in c)
        if self.vis_mode is not None and self.vis_mode not in VIS_MODES:
            raise ValueError(f"{owner}(vis_mode={self.vis_mode!r}): use one of {VIS_MODES}")


@dataclass
class Default(Surface):
    pass


@dataclass
class Plastic(Surface):
    pass


@dataclass
class Rough(Surface):
    pass


@dataclass
class Smooth(Surface):
    pass


@dataclass
class Metal(Surface):
    pass


@dataclass
class Glass(Surface):
    """Genesis's glass surface (water_wheel.py's emitter): drawn with its colour like the others."""


@dataclass
class Water(Surface):
    """Genesis's water surface: drawn with its colour like the others."""
