"""Loaders: turn a user's morph (+ material) into a plain numpy `EntityModel` for the rigid solver."""
from __future__ import annotations

from solvers.rigid.model import EntityModel

from .mjcf import load_mjcf
from .primitives import load_mesh, load_primitive
from .urdf import load_urdf

__all__ = ["load_morph", "load_urdf", "load_mjcf", "load_primitive", "load_mesh"]


def load_morph(morph, material=None, name: str = "entity") -> EntityModel:
    """Dispatch on the morph's type. `material` defaults to gs.materials.Rigid()."""
    from genesis_lite import materials, morphs

    if material is None:
        material = materials.Rigid()
    if isinstance(morph, morphs.URDF):
        return load_urdf(morph, material, name)
    if isinstance(morph, morphs.MJCF):
        return load_mjcf(morph, material, name)
    if isinstance(morph, morphs.Mesh):
        return load_mesh(morph, material, name)
    if isinstance(morph, (morphs.Box, morphs.Sphere, morphs.Capsule, morphs.Cylinder, morphs.Plane)):
        return load_primitive(morph, material, name)
    raise TypeError(
        f"entity '{name}': cannot load a morph of type {type(morph).__name__}; expected one of gs.morphs.URDF, "
        "MJCF, Mesh, Box, Sphere, Capsule, Cylinder, Plane"
    )
