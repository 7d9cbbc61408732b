"""Scenes of many bodies in contact with each other (issue #25, the 100-box tower): the broad phase's
bounding boxes (collision/narrow.py: func_gap_boxes) and the envelope factorisation of the coupled
contact system (contact/linalg.py: func_factor_dense_to) make them fast; neither may change the motion.
Default options (collision on, the default integrator), float64."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

import genesis_lite as gs

WORKERS = Path(__file__).parent / "workers"
PLANK = (1.0, 0.12, 0.06)


def _yaw(deg):
    a = np.deg2rad(deg) / 2
    return (np.cos(a), 0.0, 0.0, np.sin(a))


def _log_cabin(order):
    """Four courses of crossed planks (two per course), a sphere and a capsule dropped on them, the
    bodies added to the scene in `order` (indices into the list of bodies); their poses after 0.6 s
    in the list's order."""
    L, W, H = PLANK
    specs = []
    for k in range(4):
        for side in (-1, 1):
            pos = (side * 0.35, 0.0, (k + 0.5) * H + k * 1e-3) if k % 2 == 0 else (0.0, side * 0.35, (k + 0.5) * H + k * 1e-3)
            specs.append(gs.morphs.Box(size=PLANK, pos=pos, quat=_yaw(90.0 if k % 2 == 0 else 0.0)))
    specs.append(gs.morphs.Sphere(radius=0.08, pos=(0.3, 0.05, 0.5)))
    specs.append(gs.morphs.Cylinder(radius=0.05, height=0.6, pos=(-0.1, 0.3, 0.62), quat=_yaw(30.0)))
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
    scene.add_entity(gs.morphs.Plane())
    added = {i: scene.add_entity(specs[i]) for i in order}
    scene.build()
    for _ in range(60):
        scene.step()
    return np.stack([np.concatenate([added[i].get_qpos().numpy(), added[i].get_dofs_velocity().numpy()])
                     for i in range(len(specs))])


def test_the_order_bodies_are_added_in_does_not_change_their_motion():
    """The coupled contact system is factorised over its envelope in dof order: bodies added course by
    course give a narrow band, a shuffled order a ragged envelope whose rows start out of order. Both
    must be the same system solved: the same motion to the rounding of the sums' order (the slots'
    forces are summed in another order too)."""
    stacked = _log_cabin(list(range(10)))
    shuffled = _log_cabin([9, 3, 6, 0, 8, 5, 1, 7, 2, 4])
    # the scene moves: the sphere and the cylinder land, the planks settle
    assert stacked[8, 2] < 0.5 - 0.2 and stacked[9, 2] < 0.62 - 0.05
    np.testing.assert_allclose(shuffled, stacked, rtol=0, atol=1e-9)


def test_the_broad_phase_boxes_change_no_number():
    """A pile of long planks, cylinders, boxes and spheres thrown onto each other, in two fresh processes:
    with the broad phase as it is, and with its bounding-box test replaced by one that never separates
    a pair (bounding spheres alone). The trajectories are the same to the bit, with far fewer pair
    activations."""
    out = {}
    for mode in ("boxes", "spheres"):
        done = subprocess.run([sys.executable, str(WORKERS / "broad_phase_pile.py"), mode], capture_output=True,
                              text=True, timeout=900)
        assert done.returncode == 0, (mode, done.stderr[-3000:])
        out[mode] = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["boxes"]["sha"] == out["spheres"]["sha"], out
    assert out["boxes"]["active"] < 0.7 * out["spheres"]["active"], out
    assert out["boxes"]["z_min"] > 0.0, out  # nothing went through the ground
