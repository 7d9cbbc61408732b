"""The integrator schedule: the one integrator enum, the one RK4 tableau, and the ops of a step.

A step is a fixed list of ops per substep: OP_DYN (the dynamics stages of evaluation e at a state slot),
OP_SOLVE (its factor-solve, qacc[e]), OP_INT (an integration between state slots, integrate.py), so
that every state slot and every qacc[e] is written once per step and Taichi's autodiff can replay the
step backwards. Euler and implicitfast take one evaluation per substep; RK4 four, at the stage times of
its tableau, and combines their accelerations and velocities with its weights (integrate.py for the
state, the scene's acceleration reader for the reported qacc).
"""
import enum


class Integrator(enum.IntEnum):
    """Time integrators of the rigid solver (gs.integrator is this enum, with Genesis's member names)."""

    Euler = 0          # semi-implicit (symplectic) Euler
    implicitfast = 1   # semi-implicit Euler, implicit in joint damping and in the unsaturated PD's kp and kv
    # Genesis's default: semi-implicit Euler implicit in joint damping and in the PD's kv (never kp),
    # saturated or not (actuation.py). The first three numbers are Genesis's.
    approximate_implicitfast = 2
    RK4 = 3            # classic 4th-order Runge-Kutta on (q, v)


# classic RK4: stage k's derivative is taken at the state advanced by RK4_STAGE_FRACTIONS[k] * h from
# the substep's start along stage k-1's (the last entry is the final combination's full step); the
# derivatives combine as sum(RK4_WEIGHTS[k] * k_k) / RK4_WEIGHT_SUM
RK4_STAGE_FRACTIONS = (0.5, 0.5, 1.0, 1.0)
RK4_WEIGHTS = (1.0, 2.0, 2.0, 1.0)
RK4_WEIGHT_SUM = 6.0


def rk4_combine(k0, k1, k2, k3):
    """The RK4 combination of four stage derivatives (numpy arrays or torch tensors; integrate.py has
    the Taichi spelling, func_rk4_combine, with the same weights and the same order of operations)."""
    w = RK4_WEIGHTS
    return (w[0] * k0 + w[1] * k1 + w[2] * k2 + w[3] * k3) / RK4_WEIGHT_SUM


OP_DYN, OP_SOLVE, OP_INT, OP_COPY = 0, 1, 2, 3
# the kinds of OP_INT (integrate.py)
INT_EULER, INT_RK_STAGE, INT_RK_FINAL = 0, 1, 2


# kernel_step_fused takes the ops it runs and whether it ends the step as one integer (pack_span)
SPAN_BITS = 15
SPAN_MASK = (1 << SPAN_BITS) - 1


def pack_span(k0: int, k1: int, finish: int) -> int:
    """Ops k0..k1-1 and `finish` (0 or 1) as kernel_step_fused's one argument."""
    return k0 | (k1 << SPAN_BITS) | (finish << (2 * SPAN_BITS))


class StepSchedule:
    """The ops of one step, (op, kind, e, base, src, dst, h), and where each substep's begin in that
    list (substep i moves the state from slot substep_slot[i] to substep_slot[i + 1])."""

    def __init__(self, integrator: int, dt: float, substeps: int):
        h = dt / substeps
        ops, first = [], []
        if integrator == Integrator.RK4:
            for i in range(substeps):
                first.append(len(ops))
                base = 4 * i
                for k, c in enumerate(RK4_STAGE_FRACTIONS):
                    e = 4 * i + k
                    ops.append((OP_DYN, 0, e, base, base + k, 0, c * h))
                    ops.append((OP_SOLVE, 0, e, base, base + k, 0, 0.0))
                    if k < 3:
                        ops.append((OP_INT, INT_RK_STAGE, e, base, base + k, base + k + 1, c * h))
                    else:
                        ops.append((OP_INT, INT_RK_FINAL, e, base, base + k, base + 4, h))
            self.n_slots, self.n_evals = 4 * substeps + 1, 4 * substeps
            self.evals_per_substep = 4
        else:
            for i in range(substeps):
                first.append(len(ops))
                ops.append((OP_DYN, 0, i, i, i, 0, h))
                ops.append((OP_SOLVE, 0, i, i, i, 0, 0.0))
                ops.append((OP_INT, INT_EULER, i, i, i, i + 1, h))
            self.n_slots, self.n_evals = substeps + 1, substeps
            self.evals_per_substep = 1
        if len(ops) > SPAN_MASK:
            raise ValueError(f"{substeps} substeps make {len(ops)} ops in a step, more than the {SPAN_MASK} one step "
                             "can hold: use fewer substeps and a smaller dt instead")
        self.ops = ops
        self.n_ops = len(ops)
        self.substep_first_op = first + [len(ops)]
        self.substep_ops = [ops[first[i]:self.substep_first_op[i + 1]] for i in range(substeps)]
        per = (self.n_slots - 1) // substeps
        self.substep_slot = [per * i for i in range(substeps + 1)]
        self.last_slot = self.n_slots - 1
