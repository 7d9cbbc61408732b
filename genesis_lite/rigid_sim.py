"""The scene's side of the rigid solver: torch mirrors of state, controls and parameters, their
upload to the solver's fields, and the gradient bridge (grad/functions.py) for rigid steps.

Invariant: slot 0 of the solver's state fields holds the current state. With gradients, the
current state is also a pair of torch tensors (qpos, qvel) in the autograd graph; controls and
parameters are torch tensors whose values are uploaded to the fields before the next launch.
"""
from __future__ import annotations

import numpy as np
import taichi as ti
import torch

from solvers.buffer import StepBuffer
from solvers.rigid.solver import RigidSolver

from .errors import GenesisException, SimulationNaNError
from .grad.functions import OutputFunction, StepFunction, require_token

# name -> (solver field, trailing shape, axis it is indexed by)
PARAMS = {
    "mass": ("link_mass", (), "link"),
    "com": ("link_com", (3,), "link"),
    "inertia": ("link_inertia", (3, 3), "link"),
    "damping": ("dof_damping", (), "dof"),
    "armature": ("dof_armature", (), "dof"),
    "frictionloss": ("dof_frictionloss", (), "dof"),
    "kp": ("dof_kp", (), "dof"),
    "kv": ("dof_kv", (), "dof"),
    "gravity": ("gravity", (3,), "env"),
    "friction": ("contact.geom_friction", (), "geom"),  # only when the scene has contacts
}
CTRL = ("force", "pos", "vel")  # rows of the packed control tensor (B, 3, n_dofs)


class RigidSim:
    def __init__(self, scene, models, n_envs, sim_options, rigid_options):
        import genesis_lite as gs

        self.scene = scene
        self.B = max(n_envs, 1)
        self.dtype = gs.tc_float
        self.device = gs.device
        self.requires_grad = sim_options.requires_grad
        # a collision geom without its own friction (GeomDesc.friction None) takes its entity's material's
        for ent in scene.entities:
            for link in ent.model.links:
                for g in link.geoms:
                    if g.friction is None:
                        g.friction = float(ent.material.friction)
        self.solver = RigidSolver(models, self.B, sim_options.dt, sim_options.substeps, int(rigid_options.integrator),
                                  sim_options.gravity, gs.ti_float, self.requires_grad,
                                  rigid_options.enable_joint_limit, rigid_options.joint_limit_stiffness,
                                  rigid_options.joint_limit_damping,
                                  contact_options=rigid_options if rigid_options.enable_collision else None,
                                  mimic=rigid_options.enable_mimic)
        s = self.solver
        self.n_qs, self.n_dofs, self.n_links = s.n_qs, s.n_dofs, s.n_links
        self.rollout_token = 0
        self.step_count = 0
        self.buffer = StepBuffer(sim_options.checkpoint_every, self._replay_step) if self.requires_grad else None
        self._step_inputs = {}
        self._backward_done = False
        # parameters: base values from the model, then the user's setter calls replayed on top
        self.param_names = [k for k in PARAMS if not PARAMS[k][0].startswith("contact.") or s.contact is not None]
        self.param_base = {k: self._field_to_torch(self.param_field(k)) for k in self.param_names}
        self.param_ops = {k: [] for k in self.param_names}
        self.params = dict(self.param_base)
        self._loaded_params = dict(self.params)  # the tensors whose values are in the fields now
        self.force_lo = self._field_to_torch(s.dof_force_lo)
        self.force_hi = self._field_to_torch(s.dof_force_hi)
        self._params_dirty = set()
        self.reset_controls()
        q0 = torch.as_tensor(s.np_qpos0, dtype=self.dtype, device=self.device).reshape(1, -1).repeat(self.B, 1)
        self.init_state = (q0, torch.zeros(self.B, self.n_dofs, dtype=self.dtype, device=self.device))
        self.set_state(*self.init_state)
        self._outputs = None

    # ---------------------------------------------------------------- helpers
    def param_field(self, name):
        """The solver field behind a parameter (a dotted path, e.g. 'contact.geom_friction')."""
        obj = self.solver
        for part in PARAMS[name][0].split("."):
            obj = getattr(obj, part)
        return obj

    def _field_to_torch(self, field):
        return field.to_torch(device=self.device).to(self.dtype)

    def _c(self, t):
        return t.detach().to(self.dtype).contiguous()

    def grad_tracking(self):
        """True when this step must be recorded for torch (something upstream requires grad)."""
        if not (self.requires_grad and torch.is_grad_enabled()):
            return False
        q, v = self.get_state()  # after an untracked step the state lives only in the fields
        if q.requires_grad or v.requires_grad:
            return True
        if self.ctrl.requires_grad:
            return True
        return any(p.requires_grad for p in self.params.values())

    # ---------------------------------------------------------------- state
    def set_state(self, qpos, qvel):
        self.qpos, self.qvel = qpos, qvel
        self._state_on_device = False
        self._outputs = None

    def get_state(self):
        if self.qpos is None:
            self.qpos, self.qvel = self._split(self._read_state(0))
        return self.qpos, self.qvel

    def _read_state(self, slot):
        x = torch.empty(self.B, self.n_qs + self.n_dofs, dtype=self.dtype, device=self.device)
        if self.n_qs + self.n_dofs:
            self.solver.kernel_get_state(slot, x)
        return x

    def _split(self, x):
        return x[:, : self.n_qs], x[:, self.n_qs:]

    def _write_state(self, q, v):
        if self.n_qs + self.n_dofs:
            self.solver.kernel_set_state(0, self._c(torch.cat([q, v], -1)))

    def _upload(self):
        s = self.solver
        if not self._state_on_device:
            self._write_state(*self.get_state())
            self._state_on_device = True
        if self._ctrl_dirty:
            self._load_ctrl(self.ctrl, self.ctrl_mode)
            self._ctrl_dirty = False
        for k in self._params_dirty:
            if self._loaded_params.get(k) is not self.params[k]:
                self.param_field(k).from_torch(self._c(self.params[k]))
                self._loaded_params[k] = self.params[k]
        self._params_dirty = set()

    # ---------------------------------------------------------------- controls and parameters
    def reset_controls(self):
        self.ctrl = torch.zeros(self.B, 3, self.n_dofs, dtype=self.dtype, device=self.device)
        self.ctrl_mode = torch.zeros(self.B, self.n_dofs, dtype=torch.int32, device=self.device)
        self._loaded_mode = None
        self._ctrl_dirty = True

    def _load_ctrl(self, ctrl, mode):
        if not self.n_dofs:
            return
        self.solver.kernel_set_ctrl(self._c(ctrl))
        if self._loaded_mode is not mode:
            self.solver.kernel_set_ctrl_mode(mode)
            self._loaded_mode = mode

    def set_ctrl(self, kind, values, envs, idx, mode):
        row = CTRL.index(kind)
        values = values.to(self.dtype).reshape(len(envs), len(idx))
        out = self.ctrl.clone()
        full_envs, span = _as_slices(envs, self.B), _as_span(idx)
        if full_envs and span is not None:
            # basic slicing: autograd keeps no index tensors per step
            out[:, row, span] = values
        else:
            out[envs[:, None], row, idx[None, :]] = values
        self.ctrl = out
        if mode is not None:
            m = self.ctrl_mode.clone()
            m[envs[:, None], idx[None, :]] = mode
            if not torch.equal(m, self.ctrl_mode):
                self.ctrl_mode = m
        self._ctrl_dirty = True

    def set_param(self, name, values, envs, idx):
        # a later call on the same entries supersedes an earlier one (keeps the replay list short)
        self.param_ops[name] = [op for op in self.param_ops[name]
                                if not (torch.equal(op[1], envs) and torch.equal(op[2], idx))]
        self.param_ops[name].append((values, envs, idx))
        self.params[name] = _index_put(self.params[name], envs, idx, values)
        self._params_dirty.add(name)

    def rebuild_params(self):
        """A new rollout: parameter tensors are recomposed from the user's setter calls so a leaf
        parameter keeps receiving gradients epoch after epoch."""
        for name, ops in self.param_ops.items():
            if not ops:
                continue
            p = self.param_base[name]
            for values, envs, idx in ops:
                # a value made from a leaf is made again, so the leaf keeps receiving gradients; a
                # value computed in an earlier rollout keeps its value only (its graph belongs to
                # that rollout and has been freed by its backward)
                remake = getattr(values, "_gs_remake", None)
                p = _index_put(p, envs, idx, remake() if remake is not None else values.detach())
            self.params[name] = p
            self._params_dirty.add(name)

    def set_force_range(self, lo, hi, envs, idx):
        self.force_lo = _index_put(self.force_lo, envs, idx, lo.detach())
        self.force_hi = _index_put(self.force_hi, envs, idx, hi.detach())
        self.solver.dof_force_lo.from_torch(self._c(self.force_lo))
        self.solver.dof_force_hi.from_torch(self._c(self.force_hi))

    # ---------------------------------------------------------------- stepping
    def step(self):
        if self._backward_done:
            raise GenesisException("scene.step() after loss.backward(): this rollout's gradient buffers have been "
                                   "consumed. Call scene.reset() to start a new rollout.")
        self._upload()
        if self.grad_tracking():
            inputs = [self.qpos, self.qvel, self.ctrl] + [self.params[k] for k in self.param_names]
            self.qpos, self.qvel = self._split(StepFunction.apply(self, *inputs))
            self._state_on_device = True
        else:
            self.solver.step(self.step_count + 1)
            self.qpos = self.qvel = None
        self.step_count += 1
        self._outputs = None

    def first_nan_step(self):
        """The first step after which the (fused-path) state was not finite, or None."""
        k = self.solver.nan_step[None]
        return None if k == self.solver.NO_NAN else k

    def check_finite(self, entities, step=None):
        """Raise SimulationNaNError naming the entity, the quantity and the step if the state is not finite."""
        step = self.step_count if step is None else step
        q, v = self.get_state()
        for name, x in (("qpos", q), ("qvel", v)):
            bad = ~torch.isfinite(x.detach())
            if bad.any():
                i_b, i = [int(a) for a in torch.nonzero(bad)[0]]
                ent, local = _entity_of(entities, i, name)
                raise SimulationNaNError(
                    f"entity '{ent.name}': {name}[{local}] became {x[i_b, i].item()} at step {step}"
                    f"{f' in env {i_b}' if self.scene.n_envs else ''}. The simulation diverged: reduce dt or raise "
                    "substeps, lower gains/stiffness, or check the inputs set before this step.")

    # ---------------------------------------------------------------- gradient bridge (rigid side)
    def check_token(self, token, what):
        require_token(self.rollout_token, token, what)
        self._backward_done = True

    def step_context(self):
        """What a step or getter node remembers besides its tensors: the step index and control modes."""
        return (self.step_count, self.ctrl_mode)

    def to_save(self, inputs):
        """The tensors a node keeps: everything, or everything but the state when checkpointing
        (the state at a checkpoint goes to the buffer, others are recomputed in backward)."""
        t = self.step_count
        keep = self.buffer.record(t, (inputs[0].detach(), inputs[1].detach()))
        if len(inputs) > 2 and self.buffer.every is not None:
            # the parameter tensors themselves: replay recognises them and uploads nothing
            self._step_inputs[t] = (inputs[2].detach(), self.ctrl_mode, list(inputs[3:]))
        return inputs if keep else (None, None) + tuple(inputs[2:])

    def restore(self, saved, context):
        if saved[0] is not None:
            return saved
        q, v = self.buffer.get(context[0])
        return (q, v) + tuple(saved[2:])

    def _replay_step(self, state, t):
        """Re-run step t forward from `state` with the inputs it had (for checkpoint windows)."""
        ctrl, mode, params = self._step_inputs[t]
        self._replay_inputs(state[0], state[1], ctrl, mode, params, clear=False)
        return self._split(self.forward_step())

    def forward_step(self):
        self.solver.run_ops()
        return self._read_state(self.solver.last_slot)

    def _replay_inputs(self, qpos, qvel, ctrl=None, mode=None, params=None, clear=True):
        s = self.solver
        if clear:
            s.kernel_clear_grads()
        self._write_state(qpos, qvel)
        if ctrl is not None:
            self._load_ctrl(ctrl, mode)
            self._ctrl_dirty = True
        if params is not None:
            for k, p in zip(self.param_names, params):
                if self._loaded_params.get(k) is not p:
                    self.param_field(k).from_torch(self._c(p))
                    self._loaded_params[k] = p
                    self._params_dirty.add(k)
        self._state_on_device = False
        self._outputs = None

    def backward_step(self, saved, context, grads, needs):
        """Gradients of one step's inputs (qpos, qvel, ctrl, *params) given the gradient of its
        packed output state."""
        s = self.solver
        qpos, qvel, ctrl, params = saved[0], saved[1], saved[2], saved[3:]
        step, mode = context
        self._replay_inputs(qpos, qvel, ctrl, mode, params)
        (gx,) = grads
        if gx is None:
            gx = torch.zeros(self.B, self.n_qs + self.n_dofs, dtype=self.dtype, device=self.device)
        s.kernel_seed_state_grad(s.last_slot, self._c(gx))
        s.backward_ops()
        nx = self.n_qs + self.n_dofs
        g = torch.empty(self.B, nx + 3 * self.n_dofs, dtype=self.dtype, device=self.device)
        s.kernel_get_grads(g)
        out = [g[:, : self.n_qs] if needs[0] else None, g[:, self.n_qs: nx] if needs[1] else None,
               g[:, nx:].reshape(self.B, 3, self.n_dofs) if needs[2] else None]
        for k, n in zip(self.param_names, needs[3:]):
            if n:
                pg = torch.empty_like(self.params[k], dtype=self.dtype)
                s.get_param_grad(self.param_field(k), pg)
                out.append(pg)
            else:
                out.append(None)
        _raise_if_nan_grad(out, step)
        return out

    def outputs(self):
        """(links pos, quat, vel, ang) at the current state, each (B, n_links, 3 or 4)."""
        if self._outputs is None:
            self._upload()
            s = self.solver
            s.kernel_kinematics(0)
            L = self.n_links
            o = [torch.empty(self.B, L, k, dtype=self.dtype, device=self.device) for k in (3, 4, 3, 3)]
            s.kernel_link_outputs(*o)
            self._outputs = tuple(o)
        return self._outputs

    def link_outputs(self):
        q, v = self.get_state()
        if self.requires_grad and torch.is_grad_enabled() and (q.requires_grad or v.requires_grad):
            out = OutputFunction.apply(self, q, v)
            self._outputs = tuple(o.detach() for o in out)
            return out
        return self.outputs()

    def backward_outputs(self, saved, grads):
        s = self.solver
        self._replay_inputs(saved[0], saved[1])
        s.kernel_kinematics(0)
        L = self.n_links
        g = [self._c(x) if x is not None else torch.zeros(self.B, L, k, dtype=self.dtype, device=self.device)
             for x, k in zip(grads, (3, 4, 3, 3))]
        s.kernel_seed_link_grad(*g)
        s.kernel_kinematics.grad(0)
        g = torch.empty(self.B, self.n_qs + 4 * self.n_dofs, dtype=self.dtype, device=self.device)
        s.kernel_get_grads(g)
        gq, gv = g[:, : self.n_qs], g[:, self.n_qs: self.n_qs + self.n_dofs]
        _raise_if_nan_grad([gq, gv], self.step_count)
        return gq, gv

    # ---------------------------------------------------------------- rollouts
    def new_rollout(self, qpos, qvel):
        self.rollout_token += 1
        self._backward_done = False
        self.step_count = 0
        self.solver.nan_step[None] = self.solver.NO_NAN
        if self.buffer is not None:
            self.buffer.clear()
        self._step_inputs = {}
        self.reset_controls()
        self.rebuild_params()
        self.set_state(qpos, qvel)


def _as_slices(envs, n):
    return len(envs) == n and bool((envs == torch.arange(n, device=envs.device)).all())


def _as_span(idx):
    """idx as a slice when it is a run of consecutive indices, else None."""
    if len(idx) == 0:
        return None
    start = int(idx[0])
    if bool((idx == torch.arange(start, start + len(idx), device=idx.device)).all()):
        return slice(start, start + len(idx))
    return None


def _index_put(base, envs, idx, values):
    """base with base[envs][:, idx] = values, out of place (differentiable in base and values)."""
    values = values.to(base.dtype).reshape((len(envs), len(idx)) + base.shape[2:])
    out = base.clone()
    span = _as_span(idx)
    if span is not None and _as_slices(envs, base.shape[0]):
        out[:, span] = values
    else:
        out[envs[:, None], idx[None, :]] = values
    return out


def _raise_if_nan_grad(grads, step):
    for g in grads:
        if g is not None and not torch.isfinite(g).all():
            raise SimulationNaNError(
                f"a gradient became NaN or infinite in the backward pass of step {step}: the rollout is not "
                "differentiable there (a diverging state, a singular pose, or a saturated quantity). Shorten the "
                "horizon, reduce dt, or check the loss.")


def _entity_of(entities, i, name):
    for ent in entities:
        start, n = (ent._q_start, ent.n_qs) if name == "qpos" else (ent._dof_start, ent.n_dofs)
        if start <= i < start + n:
            return ent, i - start
    return entities[0], i
