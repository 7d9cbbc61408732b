"""Physical parameters checked where they are set: when a morph or URDF is loaded (validate_model)
and in the entities' setters (before a value reaches the solver).

The rules (SI units): an inertia tensor about the COM is symmetric positive semi-definite with
principal moments satisfying the triangle inequalities I1 + I2 >= I3 (those of some rigid body), and
positive definite for a free body; a free body has a positive mass; a link on a revolute or prismatic
joint has a positive mass, or (a massless intermediate link, as MuJoCo allows) massive links below it;
a fixed root link may be massless; joint damping, armature, dry friction and spring stiffness are >= 0; joint limits
have lower <= upper; actuator efforts are >= 0. (A hinge link may be a point mass, inertia 0 about its
COM, as textbook pendulums in URDF are; a free body may not.) Every check reads plain numbers (numpy, or a detached copy of a torch tensor), so a
value that requires grad keeps its autograd history.
"""
from __future__ import annotations

import numpy as np

from .errors import GenesisException

# Tolerances of the symmetry and triangle checks (kg m^2): relative, for URDFs' rounded numbers, and
# absolute, for finite differences (gs.grad.check steps one entry by 1e-6 * max(1, |x|)), so that the
# check of a gradient with respect to an inertia entry, even of a flat plate (I1 + I2 = I3), runs
INERTIA_RTOL = 1e-3
INERTIA_ATOL = 2e-6

INERTIA_HINT = ("Give a symmetric positive-definite tensor about the COM, in kg m^2, whose principal moments "
                "satisfy I1 + I2 >= I3 (a solid box of mass m and edges a, b, c has diag(m (b^2 + c^2) / 12, "
                "m (a^2 + c^2) / 12, m (a^2 + b^2) / 12)).")


def inertia_problems(I, strict=True):
    """For a stack of 3x3 inertia tensors I (..., 3, 3) (numpy), a list of (index tuple, what is
    wrong) for the bad ones. strict: positive definite (else semi-definite: a massless link's zero
    tensor passes)."""
    I = np.asarray(I, dtype=np.float64)
    flat = I.reshape(-1, 3, 3)
    out = []
    finite = np.isfinite(flat).all((1, 2))
    scale = np.maximum(np.abs(np.where(np.isfinite(flat), flat, 0)).max((1, 2)), 1e-300)
    asym = np.abs(flat - np.swapaxes(flat, 1, 2)).max((1, 2))
    sym = 0.5 * (flat + np.swapaxes(flat, 1, 2))
    ev = np.linalg.eigvalsh(np.where(finite[:, None, None], sym, 0.0))  # ascending
    for k in range(len(flat)):
        where = np.unravel_index(k, I.shape[:-2]) if I.ndim > 2 else ()
        if not finite[k]:
            out.append((where, "is not finite"))
        elif asym[k] > INERTIA_RTOL * scale[k] + INERTIA_ATOL:
            out.append((where, f"is not symmetric (I - I^T has an entry of {asym[k]:.3g})"))
        elif (ev[k, 0] <= 0) if strict else (ev[k, 0] < -INERTIA_ATOL):
            out.append((where, f"is not positive {'definite' if strict else 'semi-definite'} (principal moments "
                               f"{np.array2string(ev[k], precision=4)})"))
        elif ev[k, 0] + ev[k, 1] < ev[k, 2] * (1 - INERTIA_RTOL) - INERTIA_ATOL:
            out.append((where, f"has principal moments {np.array2string(ev[k], precision=4)} with I1 + I2 < I3 "
                               "(the triangle inequality): no rigid body has them"))
    return out


def mass_rule(joint_type):
    """'free': the link needs a positive mass and a positive-definite inertia; 'hinge': a positive
    mass (or massive links below it); None: a fixed root, anything >= 0."""
    return {"free": "free", "revolute": "hinge", "prismatic": "hinge"}.get(joint_type)


def _fmt(x):
    return np.array2string(np.asarray(x, dtype=np.float64), precision=6, separator=", ").replace("\n", "")


def validate_model(model) -> None:
    """Raise GenesisException naming the entity, the link and the value for a physically impossible
    mass, inertia or joint parameter of a loaded model (solvers/rigid/model.EntityModel)."""
    below = [float(l.mass) if np.isfinite(l.mass) else 0.0 for l in model.links]  # mass of each subtree
    for i in range(len(model.links) - 1, -1, -1):  # parents come before children
        p = model.links[i].parent
        if p >= 0:
            below[p] += below[i]
    for i, l in enumerate(model.links):
        where = f"entity '{model.name}' ({model.source or 'morph'}), link '{l.name}'"
        need = mass_rule(l.joint_type)
        if not np.isfinite(l.mass) or l.mass < 0 or (need and l.mass <= 0 and (need == "free" or below[i] <= 0)):
            raise GenesisException(
                f"{where}: mass {l.mass} kg; a link that moves ({l.joint_type} joint) needs a positive finite mass"
                f"{'' if need == 'free' else ' (or massive links below it)'}, else its equations of motion are "
                "singular. Give the link an <inertial> with a positive <mass>, or attach it to its parent with a "
                "fixed joint.")
        bad = inertia_problems(l.inertia, strict=need == "free")
        if bad:
            raise GenesisException(f"{where}: inertia {_fmt(l.inertia)} {bad[0][1]}. {INERTIA_HINT}")
        for name in ("damping", "armature", "frictionloss", "stiffness"):
            v = getattr(l, name)
            if not (np.isfinite(v) and v >= 0):
                raise GenesisException(f"{where}: joint '{l.joint_name}' has {name} {v}; it must be finite and "
                                       ">= 0. Fix the value in the model file.")
        if not np.isfinite(l.springref):
            raise GenesisException(f"{where}: joint '{l.joint_name}' has springref {l.springref}; it must be finite. "
                                   "Fix the value in the model file.")
        lo, hi = l.limit
        if np.isnan(lo) or np.isnan(hi) or lo > hi:
            raise GenesisException(f"{where}: joint '{l.joint_name}' has limits lower {lo} > upper {hi}; give "
                                   "lower <= upper (or no limit).")
        if np.isnan(l.effort) or l.effort < 0:
            raise GenesisException(f"{where}: joint '{l.joint_name}' has effort {l.effort}; it must be >= 0.")
        for g in l.geoms:
            size = np.asarray(g.size, dtype=np.float64)
            if size.size and not (np.isfinite(size).all() and (size > 0).all()):
                raise GenesisException(f"{where}: a {g.type} collision shape has size {size.tolist()} m; sizes "
                                       "must be positive and finite.")

