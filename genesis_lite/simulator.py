"""The simulator: steps every solver of a scene together, as one node of torch's graph per step.

A scene has one bridge per solver it needs (bridges/rigid.py RigidSim, bridges/mpm.py MPMSim): each holds torch
mirrors of its solver's state, controls and parameters and moves them in and out of the solver's
Taichi fields. A scene with both kinds, coupled, also has a coupler bridge (bridges/coupler.py), a
stage of the step with no state of its own. One substep, in this order (Genesis's and MJX's; here
and nowhere else, `_substep`):

    mpm.substep_pre_coupling     clear the grid, constitutive update (F, stress), particle-to-grid
    coupler.couple               grid velocities with gravity, walls and the rigid bodies as moving
                                 boundaries; the momentum the grid loses becomes a wrench on the links
                                 (mpm.grid_update instead: gravity and walls, when nothing couples)
    mpm.substep_post_coupling    grid-to-particle (coupler.g2p_attached instead when particles are
                                 attached to links: the same, with each attached particle's spring)
    rigid.substep                rigid dynamics with that wrench, contacts, integration

A solver or a coupler the scene does not have is skipped (None). A scene of rigid bodies alone steps
without gradients through its solver's fused step (one launch per step; the same numbers), unless it
was built for gradients: then its untracked steps run the tracked steps' kernels (RigidSolver._fused).

Without gradients the step is plain kernel launches and the state stays in the fields. With
gradients the step is a `StepFunction` node (grad/functions.py) whose inputs are every bridge's
state, controls and parameters. Its backward loads the step's inputs back into the fields (from the
node's saved tensors, or recomputed from a checkpoint by `solvers/buffer.py`), replays the step's
launches on a `ti.ad.Tape` whose loss is <gradient of the outputs, outputs>, and lets the Tape run
their adjoints in reverse; the pieces whose scratch later pieces overwrite (a rigid evaluation, an
MPM substep) are `ti.ad.grad_replaced` calls that recompute it in their adjoint. Then each bridge
reads the gradients of its inputs out of the fields.

With gradients, the MPM part of a substep (its two stages and the coupling between them) is one call
on the Tape (MPMSim.record_substep): the grid is scratch that the next substep overwrites, so its
adjoint replays these same stages (`_mpm_substep` with replay=True) under a nested Tape. A step node of
a scene whose MPM nothing couples also keeps the step's substeps as its forward left them
(`substep_states`, up to a budget per rollout): its backward loads them into the solver's slots and
records the substeps without computing them again.

The bridges' protocol is in bridges/__init__.py.
"""
from __future__ import annotations

import functools
from typing import List

import taichi as ti
import torch

from solvers.buffer import StepBuffer

from .errors import GenesisException
from .grad.functions import StepFunction, require_token
from .grad.growth import GrowthMonitor
from .grad.indexing import incoming_grads


@functools.cache
def tape_loss():
    """The loss every Tape of the process names (the scenes' step Tapes, the MPM substeps' nested ones): a token,
    which no kernel reads (the solvers' vjp kernels accumulate into scalars of their own). A 0-d torch tensor:
    a Tape zeroes its loss on entry and seeds its adjoint with 1 on exit, which for a Taichi field are two
    launches of a fill kernel per Tape (two per step and two per MPM substep in a backward), for a tensor two
    torch calls; nor does a tensor take an SNode tree."""
    return torch.zeros((), dtype=torch.float64, requires_grad=True)


class Simulator:
    """rigid, mpm: the scene's solver bridges (RigidSim, MPMSim) or None; coupler: its CouplerBridge or None."""

    def __init__(self, rigid, mpm, coupler, sim_options):
        self.rigid, self.mpm, self.coupler = rigid, mpm, coupler
        # the bridges with state, in the order of the step node's inputs and outputs
        self.bridges: List = [b for b in (mpm, rigid) if b is not None]
        self.substeps = sim_options.substeps
        self.requires_grad = sim_options.requires_grad
        self.rollout_token = 0
        self.view_nodes = {}  # grad/views.py: a node per base of the setters' views, for this rollout
        self.step_count = 0
        self._backward_done = False
        self._step_inputs = {}
        self.nan_watch = None  # the scene's (nan_watch.py), set by the scene
        self.growth = GrowthMonitor()  # warns when a backward pass blows the gradient up (grad/growth.py)
        self.buffer = StepBuffer(sim_options.checkpoint_every, self._replay_step) if self.requires_grad else None
        # the Tape's loss: <gradient torch hands a node's outputs, those outputs>
        self.loss = tape_loss() if self.requires_grad else None
        for b in self.bridges:
            b.sim = self

    # ---------------------------------------------------------------- stepping
    def grad_tracking(self) -> bool:
        """True when this step must be recorded for torch (something upstream requires grad)."""
        if not (self.requires_grad and torch.is_grad_enabled()):
            return False
        return any(x.requires_grad for b in self.bridges for x in b.inputs())

    def step(self):
        if self._backward_done:
            raise GenesisException("scene.step() after loss.backward(): this rollout's gradient buffers have been "
                                   "consumed. Call scene.reset() to start a new rollout.")
        for b in self.bridges:
            b.upload()
        if self.grad_tracking():
            inputs = [x for b in self.bridges for x in b.inputs()]
            outs = StepFunction.apply(self, *inputs)
            outs = outs if isinstance(outs, tuple) else (outs,)
            for b, o in zip(self.bridges, self._split(outs, [b.n_outputs for b in self.bridges])):
                b.set_state(*b.state_from_outputs(o))
        else:
            self._run(grad=False)
            for b in self.bridges:
                b.untracked_step_done()
        self.step_count += 1

    def _run(self, grad: bool):
        """One step of every solver: substep by substep, or the rigid solver's fused step when it is the
        only solver and nothing is recorded."""
        step = self.step_count + 1
        if not grad and self.mpm is None:
            self.rigid.step_fused(step)
            return
        for i in range(self.substeps):
            self._substep(i, grad, step)

    def _substep(self, i: int, grad: bool, step: int):
        """Substep i of the step: the MPM material and its coupling to the rigid bodies, then the bodies."""
        if self.mpm is not None:
            if grad:
                self.mpm.record_substep(i, self._mpm_substep)
            else:
                self._mpm_substep(i, False)
        if self.rigid is not None:
            self.rigid.substep(i, grad, step)

    def _mpm_substep(self, i: int, grad: bool, replay: bool = False):
        """The MPM part of substep i (replay: recorded again by its adjoint, see the module docstring)."""
        if not grad and self.coupler is None:
            self.mpm.substep_uncoupled(i)  # the three stages below, in this order, in one kernel launch
            return
        self.mpm.substep_pre_coupling(i, grad, replay)
        if self.coupler is not None:
            self.coupler.couple(i, grad, replay)
        else:
            self.mpm.grid_update(i, replay)
        if self.coupler is not None and self.coupler.attached:
            self.coupler.g2p_attached(i, grad)
        else:
            self.mpm.substep_post_coupling(i, grad, replay)

    @staticmethod
    def _split(xs, counts):
        out, k = [], 0
        for n in counts:
            out.append(list(xs[k:k + n]))
            k += n
        return out

    def _input_counts(self):
        return [len(b.inputs()) for b in self.bridges]

    # ---------------------------------------------------------------- the step node (grad/functions.py)
    def check_token(self, token, what):
        require_token(self.rollout_token, token, what)
        self._backward_done = True

    def step_context(self):
        """What a step node remembers besides its tensors: the step index, each bridge's input counts
        and context (control modes, ...)."""
        return (self.step_count, self._input_counts(), [b.context() for b in self.bridges])

    def _states(self, per_bridge):
        return tuple(tuple(x.detach() for x in xs[:b.n_state]) for b, xs in zip(self.bridges, per_bridge))

    def to_save(self, inputs):
        """The tensors a node keeps: everything, or everything but the states when checkpointing
        (the states at a checkpoint go to the buffer, the others are recomputed in backward)."""
        t = self.step_count
        per = self._split(inputs, self._input_counts())
        keep = self.buffer.record(t, self._states(per))
        if keep:
            return inputs
        # the non-state inputs themselves: a replay recognises parameter tensors and uploads nothing
        self._step_inputs[t] = ([xs[b.n_state:] for b, xs in zip(self.bridges, per)], [b.context() for b in self.bridges])
        return tuple(None if i < b.n_state else x for b, xs in zip(self.bridges, per) for i, x in enumerate(xs))

    def restore(self, saved, context):
        step, counts, _ = context
        per = self._split(saved, counts)
        if all(x is not None for xs in per for x in xs):
            return per
        states = self.buffer.get(step)
        return [list(s) + xs[b.n_state:] for b, s, xs in zip(self.bridges, states, per)]

    def _load(self, per, contexts):
        for b, xs, c in zip(self.bridges, per, contexts):
            b.load(xs, c)

    def forward_step(self):
        self._run(grad=True)
        return tuple(o for b in self.bridges for o in b.read_outputs())

    def _replay_step(self, states, t):
        """Re-run step t forward from `states` with the inputs it had (checkpoint windows)."""
        rests, contexts = self._step_inputs[t]
        per = [list(s) + list(rest) for s, rest in zip(states, rests)]
        self._load(per, contexts)
        outs = self.forward_step()
        return tuple(tuple(b.state_from_outputs(o))
                     for b, o in zip(self.bridges, self._split(outs, [b.n_outputs for b in self.bridges])))

    def substep_states(self):
        """What a step node keeps besides its inputs: the MPM substeps of the step just run (MPMSim.substep_states)
        when nothing couples them to rigid bodies and no checkpoints are asked for, else None. A coupled
        step's backward recomputes its substeps (the coupler's wrench feeds the rigid substeps recorded
        with them); a checkpointed rollout keeps nothing per step by request."""
        if self.mpm is None or self.coupler is not None or self.buffer.every is not None:
            return None
        return self.mpm.substep_states()

    def backward_step(self, per, context, grads, needs, substeps=None):
        """Gradients of one step's inputs given the gradients of its outputs (`substeps`: the step's kept
        MPM substeps, substep_states, recorded on the Tape without being computed again)."""
        step, counts, contexts = context
        self._load(per, contexts)
        for b in self.bridges:
            b.clear_grads()
        out_grads = self._split(grads, [b.n_outputs for b in self.bridges])
        if substeps is not None:
            self.mpm.load_substeps(substeps)
        try:
            with ti.ad.Tape(loss=self.loss, clear_gradients=False):
                self._run(grad=True)
                for b, g in zip(self.bridges, out_grads):
                    b.vjp(g, self.loss)
        finally:
            if substeps is not None:
                self.mpm.substeps_done()
        result, state_grads = [], []
        with incoming_grads(grads, self.nan_watch):
            for b, n in zip(self.bridges, self._split(needs, counts)):
                g = b.input_grads(n, step)
                result.extend(g)
                state_grads.extend(g[:b.n_state])
        self.growth.record(step, grads, state_grads)
        return result

    # ---------------------------------------------------------------- getters (OutputFunction)
    def getter_to_save(self, bridge, state):
        """A getter node keeps its bridge's state, or, when checkpointing, offers the whole scene's
        state at this step to the buffer and keeps nothing."""
        if self.buffer.every is None:
            return state
        full = tuple(tuple(x.detach() for x in b.state()) for b in self.bridges)
        self.buffer.record(self.step_count, full)
        return tuple(None for _ in state)

    def getter_restore(self, bridge, saved, step):
        if all(x is not None for x in saved):
            return saved
        return self.buffer.get(step)[self.bridges.index(bridge)]

    # ---------------------------------------------------------------- rollouts
    def new_rollout(self, states):
        self.rollout_token += 1
        self.view_nodes = {}
        self._backward_done = False
        self.step_count = 0
        if self.buffer is not None:
            self.buffer.clear()
        self._step_inputs = {}
        self.growth.reset()
        for b, s in zip(self.bridges, states):
            b.new_rollout(s)
