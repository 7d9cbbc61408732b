"""The autograd functions through which torch sees a simulation.

One mechanism for every solver: a solver bridge implements `step_context()`, `to_save(inputs)` /
`restore(saved, context)` (which may drop the state and recompute it from a checkpoint: see
solvers/buffer.py), `forward_step()`, `backward_step(saved, ...)`, `outputs()` and
`backward_outputs(saved, grads)`; `StepFunction` makes one scene step a
node of torch's graph, `OutputFunction` makes a getter one. torch then orders the backward calls
(reverse time), sums gradients over steps and delivers them to leaf tensors.
"""
import weakref

import torch

from ..errors import GenesisException


def _bridge(ctx):
    """The bridge a node belongs to. Nodes hold it weakly: a strong reference would make a cycle
    through torch's C++ graph (bridge -> state tensor -> grad_fn -> ctx -> bridge) that Python's
    collector cannot break, keeping Taichi alive at exit so it never writes its kernel cache."""
    bridge = ctx.bridge()
    if bridge is None:
        raise GenesisException("backward through a rollout whose scene no longer exists: keep the scene alive "
                               "until loss.backward() has run")
    return bridge


class StepFunction(torch.autograd.Function):
    """(state_t, controls_t, parameters) -> state_{t+1}; the forward has already been set up in the
    solver fields by the bridge, the backward replays the step and its adjoint."""

    @staticmethod
    def forward(ctx, bridge, *inputs):
        ctx.bridge = weakref.ref(bridge)
        ctx.token = bridge.rollout_token
        ctx.extra = bridge.step_context()
        ctx.save_for_backward(*bridge.to_save(inputs))
        return bridge.forward_step()

    @staticmethod
    def backward(ctx, *grads):
        bridge = _bridge(ctx)
        bridge.check_token(ctx.token, "step")
        saved = bridge.restore(ctx.saved_tensors, ctx.extra)
        in_grads = bridge.backward_step(saved, ctx.extra, grads, ctx.needs_input_grad[1:])
        return (None,) + tuple(in_grads)


class OutputFunction(torch.autograd.Function):
    """state_t -> a getter's outputs (link poses, velocities) at that step."""

    @staticmethod
    def forward(ctx, bridge, *state):
        ctx.bridge = weakref.ref(bridge)
        ctx.token = bridge.rollout_token
        ctx.extra = bridge.step_context()
        ctx.save_for_backward(*bridge.to_save(state))
        return bridge.outputs()

    @staticmethod
    def backward(ctx, *grads):
        bridge = _bridge(ctx)
        bridge.check_token(ctx.token, "getter")
        saved = bridge.restore(ctx.saved_tensors, ctx.extra)
        return (None,) + tuple(bridge.backward_outputs(saved, grads))


def require_token(current, token, what):
    if token != current:
        raise GenesisException(
            f"backward through a {what} of a rollout that scene.reset() has ended: the simulation state of that "
            "rollout is gone. Call loss.backward() before scene.reset(), then reset and run the next rollout.")
