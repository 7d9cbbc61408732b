"""Non-convex meshes collide through convex parts (issue #25: Genesis's nonconvex_mesh script, a ball meant
to fall into a tank, rested on the tank's lid, its convex hull).

The tank (assets/meshes/tank.obj, written by assets/make_tank.py: 0.4 x 0.4 x 0.3 m outside, 5 cm walls, a
10 cm floor, open at the top) is split by CoACD; the checks are geometric facts about the tank, not our output:
- the parts' volume is the tank's (0.03 m^3), far below its hull's (0.048 m^3);
- its mass is its material's density times its own volume;
- a ball dropped over its middle comes to rest on the inner floor (10 cm above the outer bottom), not on
  the hull's top face 20 cm higher;
- with decompose_nonconvex=False it is one convex shape and a warning says so, on every load.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

import genesis_lite as gs
from genesis_lite.loaders import load_morph

TANK = Path(__file__).resolve().parents[1] / "assets" / "meshes" / "tank.obj"
FAST = {"mcts_iterations": 30, "mcts_nodes": 10, "mcts_max_depth": 2, "resolution": 500}  # coarse is enough here


def test_tank_splits_into_parts_with_its_own_volume_and_mass():
    rho = 500.0
    model = load_morph(gs.morphs.Mesh(file=str(TANK), fixed=True, coacd_options=FAST),
                       gs.materials.Rigid(rho=rho), name="tank")
    geoms = model.links[0].geoms
    assert len(geoms) >= 5  # a floor and four walls at least
    vol = sum(trimesh.Trimesh(g.vertices, g.faces).convex_hull.volume for g in geoms)
    assert abs(vol - 0.03) < 0.002, vol  # hull: 0.048
    assert model.links[0].mass == pytest.approx(rho * 0.03, rel=1e-6)


def test_ball_falls_into_the_tank_not_onto_its_hull():
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3))
    scene.add_entity(gs.morphs.Plane())
    scene.add_entity(gs.morphs.Mesh(file=str(TANK), fixed=True, pos=(0.0, 0.0, 0.15), coacd_options=FAST))
    r = 0.04
    ball = scene.add_entity(gs.morphs.Sphere(radius=r, pos=(0.01, -0.02, 0.45)))
    scene.build()
    for _ in range(400):
        scene.step()
    z = ball.get_pos()[2].item()
    # inner floor at 0.10 m: rests at 0.14 (the hull's top would hold it at 0.34)
    assert abs(z - (0.10 + r)) < 5e-3, z
    assert ball.get_vel().norm().item() < 1e-2


def test_decomposition_off_collides_as_the_hull_and_says_so_every_time():
    for _ in range(2):  # the second load comes from the model cache: it must warn too
        with pytest.warns(UserWarning, match="collides as its convex hull"):
            model = load_morph(gs.morphs.Mesh(file=str(TANK), decompose_nonconvex=False), gs.materials.Rigid(),
                               name="tank")
        assert len(model.links[0].geoms) == 1
    # a convex mesh is itself: no parts, no warning, no CoACD
    box = trimesh.creation.box(extents=(0.1, 0.2, 0.3))
    path = TANK.parent / "_test_box.obj"
    try:
        box.export(path)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            model = load_morph(gs.morphs.Mesh(file=str(path)), gs.materials.Rigid(), name="box")
        assert len(model.links[0].geoms) == 1
    finally:
        path.unlink(missing_ok=True)
    with pytest.raises(ValueError, match="decompose_nonconvex"):
        gs.morphs.Mesh(file=str(TANK), decompose_nonconvex="yes")


def _tank_urdf(tmp_path, inertial=True):
    """A one-link URDF whose collision shape is the tank's mesh (Genesis's water wheel is such a file: a
    paddled wheel, one non-convex mesh, loaded with convexify=False)."""
    inert = ('<inertial><mass value="10"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial>'
             if inertial else "")
    path = tmp_path / "tank.urdf"
    path.write_text(f'<robot name="tank"><link name="tank">{inert}<collision><geometry>'
                    f'<mesh filename="{TANK}"/></geometry></collision></link></robot>')
    return path


def test_urdf_convexify_false_splits_a_nonconvex_mesh_as_genesis_keeps_it_whole(tmp_path):
    path = _tank_urdf(tmp_path, inertial=False)
    rho = 500.0
    hull = load_morph(gs.morphs.URDF(file=str(path), fixed=True), gs.materials.Rigid(rho=rho), name="tank")
    assert len(hull.links[0].geoms) == 1  # a robot's mesh collides as its hull by default, as in Genesis
    parts = load_morph(gs.morphs.URDF(file=str(path), fixed=True, convexify=False, coacd_options=FAST),
                       gs.materials.Rigid(rho=rho), name="tank")
    geoms = parts.links[0].geoms
    assert len(geoms) >= 5
    vol = sum(trimesh.Trimesh(g.vertices, g.faces).convex_hull.volume for g in geoms)
    assert abs(vol - 0.03) < 0.002, vol  # the tank's own volume; its hull's is 0.048
    # no <inertial>: the link is filled at the material's density, the closed mesh's own volume (0.03 m^3)
    # either way (the parts: their hulls' volumes, as the Mesh morph's open surfaces)
    assert hull.links[0].mass == pytest.approx(rho * 0.03, rel=1e-6)
    assert parts.links[0].mass == pytest.approx(rho * vol, rel=1e-6)
    with pytest.raises(ValueError, match="coacd_options"):
        gs.morphs.URDF(file=str(path), convexify=False, coacd_options=0.05)


def test_ball_falls_into_a_urdf_tank_with_convexify_false(tmp_path):
    path = _tank_urdf(tmp_path)
    r = 0.04
    heights = {}
    for convexify in (True, False):
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3))
        scene.add_entity(gs.morphs.URDF(file=str(path), fixed=True, pos=(0.0, 0.0, 0.15), convexify=convexify,
                                        coacd_options=FAST))
        ball = scene.add_entity(gs.morphs.Sphere(radius=r, pos=(0.01, -0.02, 0.45)))
        scene.build()
        for _ in range(400):
            scene.step()
        heights[convexify] = ball.get_pos()[2].item()
        assert ball.get_vel().norm().item() < 1e-2
    # hull: on its top face, 0.30 m above the outer bottom (0.15 - 0.15 + 0.30 + r); parts: on the inner floor
    assert abs(heights[True] - (0.30 + r)) < 5e-3, heights
    assert abs(heights[False] - (0.10 + r)) < 5e-3, heights
