"""Worker for tests/test_grasp.py: the grasp and lift of test_grasp._grasp_and_lift in a fresh process at
the precision given (gs.init once per process). Prints one JSON line: the cube's position, its angular
speed and the finger joints' positions at the end.

    python tests/workers/grasp_precision.py 32 RAMP_STEPS [INTEGRATOR]

INTEGRATOR (a gs.integrator name) replaces the default's."""
import json
import os
import sys

TESTS = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, TESTS)
sys.path.insert(0, os.path.dirname(TESTS))

import genesis_lite as gs  # noqa: E402

gs.init(backend=gs.cpu, precision=sys.argv[1], logging_level="warning")

from conftest import robot_urdf  # noqa: E402
from test_grasp import _grasp_and_lift  # noqa: E402

pos, spin, fingers = _grasp_and_lift(robot_urdf, ramp_steps=int(sys.argv[2]),
                                     integrator=sys.argv[3] if len(sys.argv) > 3 else None)
print(json.dumps({"pos": pos.tolist(), "spin": spin, "fingers": fingers.tolist()}))
