"""Writes assets/meshes/tank.obj: an open-topped tank (0.4 x 0.4 x 0.3 m outside, walls 5 cm thick, floor
10 cm), a non-convex mesh for tests/test_convex_decomposition.py. Run once; the OBJ is committed."""
import os

import trimesh

outer = trimesh.creation.box(extents=(0.4, 0.4, 0.3))
cavity = trimesh.creation.box(extents=(0.3, 0.3, 0.3))
cavity.apply_translation((0.0, 0.0, 0.1))  # floor 10 cm thick, open at the top
tank = outer.difference(cavity)
assert tank.is_volume
tank.export(os.path.join(os.path.dirname(os.path.abspath(__file__)), "meshes", "tank.obj"))
