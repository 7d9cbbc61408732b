"""Loaders: turn a user's morph (+ material) into a plain numpy `EntityModel` for the rigid solver."""
from __future__ import annotations

import dataclasses

from solvers.rigid.model import EntityModel

from .align import align_model
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
        model = _with_default_armature(load_urdf(morph, material, name), morph.default_armature)
        return align_model(_with_recomputed_inertia(model, morph, material), morph.align)
    if isinstance(morph, morphs.MJCF):
        # its default_armature applied as it reads the file
        return align_model(_with_recomputed_inertia(load_mjcf(morph, material, name), morph, material), morph.align)
    if isinstance(morph, morphs.Mesh):
        return align_model(load_mesh(morph, material, name), morph.align)
    if isinstance(morph, (morphs.Box, morphs.Sphere, morphs.Capsule, morphs.Cylinder, morphs.Plane)):
        return load_primitive(morph, material, name)
    raise TypeError(
        f"entity '{name}': cannot load a morph of type {type(morph).__name__}; expected one of gs.morphs.URDF, "
        "MJCF, Mesh, Box, Sphere, Capsule, Cylinder, Plane"
    )


def _with_recomputed_inertia(model: EntityModel, morph, material) -> EntityModel:
    """Genesis's recompute_inertia=True: each link that moves (its joint not fixed) takes its mass, centre of mass
    and inertia from its collision shapes filled at the material's density (Genesis's default for a robot's links
    when the file has a hinge or slide joint, else for an object), not from the file; a link without collision
    shapes keeps the file's. A new model (a loaded one may be the model cache's)."""
    if not morph.recompute_inertia:
        return model
    from .primitives import combine_inertias, geom_mass_properties

    rho = material.density(robot=any(l.joint_type in ("revolute", "prismatic") for l in model.links))
    links = []
    for l in model.links:
        if l.joint_type != "fixed" and l.geoms:
            mass, com, inertia = combine_inertias([geom_mass_properties(g, rho, f"entity '{model.name}', link "
                                                                          f"'{l.name}'") for g in l.geoms])
            l = dataclasses.replace(l, mass=mass, com=com, inertia=inertia)
        links.append(l)
    return dataclasses.replace(model, links=links)


def _with_default_armature(model: EntityModel, armature) -> EntityModel:
    """The URDF's model with `armature` on every hinge and slide joint, as Genesis's URDF morph's
    default_armature; a new model (a loaded one may be the model cache's)."""
    if armature is None:
        return model
    links = [dataclasses.replace(l, armature=float(armature))
             if l.joint_type in ("revolute", "prismatic") else l
             for l in model.links]
    return dataclasses.replace(model, links=links)
