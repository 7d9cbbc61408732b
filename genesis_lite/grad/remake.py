"""How a setter's value is made again in each new rollout.

A parameter set once (a mass, a friction coefficient, a shift) lives across rollouts, but its torch graph
belongs to the rollout it was made in: the backward of that rollout frees it. So at every scene.reset()
the scene recomposes its parameter tensors from the setters' values (RigidSim.rebuild_params,
MPMSim.rebuild_params), and a value that carries a recipe (`_gs_remake`, a function of no arguments) is
made again from it, so the user's leaf keeps receiving gradients rollout after rollout; a value without
one keeps its number only. A leaf that requires grad is its own recipe; a value a setter computes from the
user's input (a ratio times the model's friction, a mass times a ratio, a scalar broadcast to every geom)
gets one from `derive`, whatever its input was (a leaf, or a value derived in turn)."""
import torch

from .indexing import index_put


def recipe(x):
    """How to make x again in a new rollout: its own recipe where it carries one, x itself where it is a leaf
    that requires grad, else None (a number or a constant tensor: its value is kept)."""
    if not torch.is_tensor(x):
        return None
    own = getattr(x, "_gs_remake", None)
    if own is not None:
        return own
    if x.requires_grad and x.is_leaf:
        return lambda: x
    return None


def derive(make, *sources):
    """make(*sources), carrying a recipe (make applied to the sources made again) when a source has one.
    Sources without a recipe enter the remade value as the numbers they had (detached: their graph belongs
    to the rollout they came from)."""
    out = make(*sources)
    recipes = [recipe(s) for s in sources]
    if torch.is_tensor(out) and any(r is not None for r in recipes):
        def again():
            return make(*(r() if r is not None else (s.detach() if torch.is_tensor(s) else s)
                          for r, s in zip(recipes, sources)))
        out._gs_remake = again
    return out


def made_again(values, name):
    """The value of a setter's call on parameter `name` in a new rollout, and whether it was made again: from
    its recipe; else its number (detached), with a GenesisWarning where it was computed from tensors that
    require grad, which then get no gradient through it from this rollout on (the caller keeps the number so
    the warning comes once)."""
    again = getattr(values, "_gs_remake", None)
    if again is not None:
        return again(), True
    if values.requires_grad:
        import os
        import sys
        import warnings

        from ..errors import GenesisWarning

        # point at the user's line (the scene.reset() call), past the package's frames
        package, frame, level = os.path.dirname(os.path.dirname(os.path.abspath(__file__))), sys._getframe(1), 2
        while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(package + os.sep):
            frame, level = frame.f_back, level + 1
        warnings.warn(
            f"the value given to a setter of '{name}' before this scene.reset() was computed from tensors that "
            "require grad, not given as a leaf: the new rollout keeps its number but cannot compute it again, so "
            "those tensors get no gradient through it from now on. Give the setter the leaf itself (a tensor "
            "created with requires_grad=True), or call the setter again after each scene.reset().",
            GenesisWarning, stacklevel=level)
    return values.detach(), False


def recomposed(base, ops, name):
    """Parameter `name` for a new rollout: `base` with each setter call's values put in at (envs, idx), in call
    order, each made again (made_again); a value that cannot be made again keeps its number from now on (its op
    in `ops` is replaced, so its warning comes once)."""
    p = base
    for k, (values, envs, idx) in enumerate(ops):
        v, again = made_again(values, name)
        if not again:
            ops[k] = (v, envs, idx)
        p = index_put(p, envs, idx, v)
    return p
