"""The autograd functions through which torch sees a simulation.

`StepFunction` makes one scene step a node of torch's graph: its inputs are the states, controls and
parameters of every solver of the scene (genesis_lite/simulator.py lists them), its outputs their next
states. `OutputFunction` makes a getter that needs the solver (link poses from joint angles) a node.
torch then orders the backward calls (reverse time), sums gradients over steps and delivers them to
leaf tensors. Inside a node's backward the owner replays the step's kernel launches on a
`ti.ad.Tape`, which runs their adjoints in reverse.
"""
import weakref

import torch

from ..errors import GenesisException


def _owner(ctx):
    """The simulator or solver bridge a node belongs to. Nodes hold it weakly: a strong reference
    would make a cycle through torch's C++ graph (owner -> state tensor -> grad_fn -> ctx -> owner)
    that Python's collector cannot break, keeping Taichi alive at exit so it never writes its kernel
    cache."""
    owner = ctx.owner()
    if owner is None:
        raise GenesisException("backward through a rollout whose scene no longer exists: keep the scene alive "
                               "until loss.backward() has run")
    return owner


def _refuse_second_order():
    """A node's backward runs with grad mode on only under create_graph=True: the step's adjoint is Taichi's
    kernels, whose results torch cannot differentiate again, so the second-order part would be silently missing."""
    if torch.is_grad_enabled():
        raise GenesisException(
            "backward with create_graph=True through a scene's steps: genesis_lite gives first derivatives only (the "
            "step's backward runs Taichi's adjoint kernels, which torch cannot differentiate again), so a second "
            "derivative would silently miss the simulation's part. Call backward / torch.autograd.grad without "
            "create_graph; for a Hessian-vector product take central differences of two gradients.")


class StepFunction(torch.autograd.Function):
    """(states_t, controls_t, parameters) of every solver -> states_{t+1}; the forward has already
    been set up in the solver fields by the simulator, the backward replays the step on a Tape."""

    @staticmethod
    def forward(ctx, sim, *inputs):
        ctx.owner = weakref.ref(sim)
        ctx.token = sim.rollout_token
        ctx.extra = sim.step_context()
        saved = sim.to_save(inputs)
        outs = sim.forward_step()
        kept = sim.substep_states() or ()  # what the step's backward need not recompute
        ctx.n_kept = len(kept)
        ctx.save_for_backward(*saved, *kept)
        return outs

    @staticmethod
    def backward(ctx, *grads):
        _refuse_second_order()
        sim = _owner(ctx)
        sim.check_token(ctx.token, "step")
        tensors = ctx.saved_tensors
        n = len(tensors) - ctx.n_kept
        saved = sim.restore(tensors[:n], ctx.extra)
        in_grads = sim.backward_step(saved, ctx.extra, grads, ctx.needs_input_grad[1:], tensors[n:] or None)
        return (None,) + tuple(in_grads)


class OutputFunction(torch.autograd.Function):
    """A solver's state at one step -> a getter's outputs (link poses, velocities) at that step."""

    @staticmethod
    def forward(ctx, bridge, *state):
        ctx.owner = weakref.ref(bridge)
        ctx.token = bridge.sim.rollout_token
        ctx.step = bridge.sim.step_count
        ctx.save_for_backward(*bridge.sim.getter_to_save(bridge, state))
        return bridge.outputs()

    @staticmethod
    def backward(ctx, *grads):
        _refuse_second_order()
        bridge = _owner(ctx)
        bridge.sim.check_token(ctx.token, "getter")
        state = bridge.sim.getter_restore(bridge, ctx.saved_tensors, ctx.step)
        return (None,) + tuple(bridge.backward_outputs(state, grads, ctx.step))


def require_token(current, token, what):
    if token != current:
        raise GenesisException(
            f"backward through a {what} of a rollout that scene.reset() has ended: the simulation state of that "
            "rollout is gone. Call loss.backward() before scene.reset(), then reset and run the next rollout.")
