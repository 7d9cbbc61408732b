"""The scene's side of each solver: one module per solver, one protocol (the simulator, simulator.py,
calls nothing else of them).

    rigid.py    RigidSim: the rigid solver (solvers/rigid)
    mpm.py      MPMSim: the MPM solver (solvers/mpm)
    coupler.py  CouplerBridge: the rigid-MPM coupler (solvers/coupling.py), a stage with no state

A solver's bridge holds torch mirrors of its solver's state, controls and parameters, moves them in and
out of the solver's Taichi fields, and is the solver's part of the scene's step node:

    n_state, n_outputs             its leading state inputs, its outputs
    inputs(), context()            the step node's inputs (state first) and what else a step remembers
    upload()                       the current values into the fields before a step
    load(values, context)          a recorded step's inputs back into the fields (backward, replays)
    <its stages>                   called by Simulator._substep in the step's one order
    untracked_step_done()          a step without gradients ran: the state now lives in the fields
    read_outputs(), state_from_outputs(outs), set_state(*state), state()
    clear_grads(), vjp(grads, loss), input_grads(needs, step)    the step node's backward
    (MPMSim alone: substep_states(), load_substeps(kept), substeps_done(): the substeps a step node keeps,
    Simulator.substep_states)
    new_rollout(state)             scene.reset()

A new solver is a new module here (and its stage in Simulator._substep).
"""
