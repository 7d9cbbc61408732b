"""The substep order lives in one place (genesis_lite/simulator.py): MPM before coupling, coupling,
MPM after coupling, rigid. Checked on stand-in bridges that record their calls, so no kernel compiles."""
import pytest

import genesis_lite as gs
from genesis_lite.simulator import Simulator


class _Log(list):
    def bridge(self, name, n_state=0):
        log = self

        class Bridge:
            attached = False  # (the coupler's: particles attached to links, MPMEntity.set_particle_constraints)

            def __init__(self):
                self.n_state, self.n_outputs = n_state, n_state

            def __getattr__(self, stage):
                return lambda *args: log.append((name, stage) + tuple(a for a in args if not callable(a)))

            def record_substep(self, i, stages):  # as MPMSolver.record_substep: one Tape call running the stages
                log.append((name, "record_substep", i))
                stages(i, True, False)

        return Bridge()


def _simulator(log, rigid=True, mpm=True, coupler=True, substeps=2):
    opts = gs.options.SimOptions(dt=0.01, substeps=substeps)
    return Simulator(log.bridge("rigid") if rigid else None, log.bridge("mpm") if mpm else None,
                     log.bridge("coupler") if coupler else None, opts)


@pytest.mark.parametrize("grad", [False, True])
def test_a_coupled_substep_runs_mpm_coupling_mpm_then_rigid(grad):
    log = _Log()
    _simulator(log)._run(grad=grad)
    expected = []
    for i in range(2):
        if grad:
            expected.append(("mpm", "record_substep", i))
        expected += [("mpm", "substep_pre_coupling", i, grad, False), ("coupler", "couple", i, grad, False),
                     ("mpm", "substep_post_coupling", i, grad, False), ("rigid", "substep", i, grad, 1)]
    assert log == expected


@pytest.mark.parametrize("grad", [False, True])
def test_with_attached_particles_the_coupler_s_grid_to_particle_takes_the_mpm_one_s_place(grad):
    log = _Log()
    sim = _simulator(log, substeps=1)
    sim.coupler.attached = True
    sim._run(grad=grad)
    assert log == ([("mpm", "record_substep", 0)] if grad else []) + [
        ("mpm", "substep_pre_coupling", 0, grad, False), ("coupler", "couple", 0, grad, False),
        ("coupler", "g2p_attached", 0, grad), ("rigid", "substep", 0, grad, 1)]


@pytest.mark.parametrize("grad", [False, True])
def test_without_a_coupler_the_mpm_grid_update_takes_its_place(grad):
    """With gradients, the three MPM stages with the grid update between them; without, the same stages
    in one launch (substep_uncoupled: test_mpm.py checks it gives the staged path's numbers)."""
    log = _Log()
    _simulator(log, coupler=False, substeps=1)._run(grad=grad)
    if grad:
        assert log == [("mpm", "record_substep", 0), ("mpm", "substep_pre_coupling", 0, True, False),
                       ("mpm", "grid_update", 0, False), ("mpm", "substep_post_coupling", 0, True, False),
                       ("rigid", "substep", 0, True, 1)]
    else:
        assert log == [("mpm", "substep_uncoupled", 0), ("rigid", "substep", 0, False, 1)]


def test_rigid_bodies_alone_step_in_one_fused_launch_without_gradients():
    log = _Log()
    _simulator(log, mpm=False, coupler=False)._run(grad=False)
    assert log == [("rigid", "step_fused", 1)]
    log.clear()
    _simulator(log, mpm=False, coupler=False)._run(grad=True)
    assert log == [("rigid", "substep", 0, True, 1), ("rigid", "substep", 1, True, 1)]
