"""Non-convex meshes collide through convex parts (issue #25: Genesis's nonconvex_mesh script, a ball meant
to fall into a tank, rested on the tank's lid, its convex hull).

The tank (assets/meshes/tank.obj, written by assets/make_tank.py: 0.4 x 0.4 x 0.3 m outside, 5 cm walls, a
10 cm floor, open at the top) is split by CoACD; the checks are geometric facts about the tank, not our output:
- the parts' volume is the tank's (0.03 m^3), far below its hull's (0.048 m^3);
- its mass is its material's density times its own volume;
- a ball dropped over its middle comes to rest on the inner floor (10 cm above the outer bottom), not on
  the hull's top face 20 cm higher;
- with decompose_nonconvex=False it is one convex shape and a warning says so, on every load;
- in a URDF, Genesis's rules: an object's meshes (a file without hinge or slide joints) are split past
  decompose_object_error_threshold, a robot's past decompose_robot_error_threshold (never, by default);
- CoACD runs with Genesis's gs.options.CoacdOptions defaults, or the options given.
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


def _tank_urdf(tmp_path, inertial=True, hinge=False):
    """A one-link URDF whose collision shape is the tank's mesh (an object, by Genesis's rule: no hinge or
    slide joint), or with hinge=True the tank on a hinge below a small base link (a robot)."""
    inert = ('<inertial><mass value="10"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial>'
             if inertial else "")
    tank = (f'<link name="tank">{inert}<collision><geometry><mesh filename="{TANK}"/></geometry></collision>'
            '</link>')
    if hinge:
        tank = ('<link name="base"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" '
                'izz="1"/></inertial></link><joint name="hinge" type="revolute"><parent link="base"/><child '
                'link="tank"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
                + tank)
    path = tmp_path / ("tank_on_hinge.urdf" if hinge else "tank.urdf")
    path.write_text(f'<robot name="tank">{tank}</robot>')
    return path


def _parts_volume(link):
    return sum(trimesh.Trimesh(g.vertices, g.faces).convex_hull.volume for g in link.geoms)


def test_a_urdf_splits_meshes_by_genesis_s_rules(tmp_path):
    """Genesis's URDF morph: a file without hinge or slide joints is an object, whose non-convex meshes are
    split when their hull's volume is more than decompose_object_error_threshold (0.15) over the mesh's (the
    tank's: 60 % over); a robot's meshes only past decompose_robot_error_threshold (infinite by default);
    convexify=False (Genesis: the raw mesh) always."""
    rho = 500.0
    obj = _tank_urdf(tmp_path, inertial=False)
    robot = _tank_urdf(tmp_path, hinge=True)

    def tank_link(path, **kw):
        model = load_morph(gs.morphs.URDF(file=str(path), fixed=True, coacd_options=FAST, **kw),
                           gs.materials.Rigid(rho=rho), name="tank")
        return next(link for link in model.links if link.name == "tank")

    parts = tank_link(obj)
    assert len(parts.geoms) >= 5  # a floor and four walls at least
    assert abs(_parts_volume(parts) - 0.03) < 0.002  # the tank's own volume; its hull's is 0.048
    # no <inertial>: the link is filled at the material's density: the parts' volume
    assert parts.mass == pytest.approx(rho * _parts_volume(parts), rel=1e-6)
    hull = tank_link(obj, decompose_object_error_threshold=float("inf"))
    assert len(hull.geoms) == 1 and hull.mass == pytest.approx(rho * 0.03, rel=1e-6)  # the closed mesh's volume
    assert len(tank_link(obj, decompose_object_error_threshold=0.7).geoms) == 1  # 60 % is within 70 %
    assert len(tank_link(robot).geoms) == 1  # a robot's link collides as its hull, as in Genesis
    assert len(tank_link(robot, decompose_robot_error_threshold=0.5).geoms) >= 5
    assert len(tank_link(robot, convexify=False).geoms) >= 5
    assert len(tank_link(obj, decompose_object_error_threshold=float("inf"), convexify=False).geoms) >= 5
    # Genesis's older switch, on every file morph: True splits a robot's mesh too, False keeps an object's whole
    assert len(tank_link(robot, decompose_nonconvex=True).geoms) >= 5
    assert len(tank_link(obj, decompose_nonconvex=False).geoms) == 1
    for bad in (0.05, {"threshold": 0.1, "treshold": 0.1}):
        with pytest.raises(ValueError, match="coacd_options"):
            gs.morphs.URDF(file=str(obj), coacd_options=bad)
    with pytest.raises(ValueError, match="decompose_object_error_threshold"):
        gs.morphs.URDF(file=str(obj), decompose_object_error_threshold=-0.1)


def test_ball_falls_into_a_urdf_tank_or_onto_its_hull(tmp_path):
    path = _tank_urdf(tmp_path)
    r = 0.04
    heights = {}
    for split in (True, False):
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3))
        scene.add_entity(gs.morphs.URDF(file=str(path), fixed=True, pos=(0.0, 0.0, 0.15), coacd_options=FAST,
                                        decompose_object_error_threshold=0.15 if split else float("inf")))
        ball = scene.add_entity(gs.morphs.Sphere(radius=r, pos=(0.01, -0.02, 0.45)))
        scene.build()
        for _ in range(400):
            scene.step()
        heights[split] = ball.get_pos()[2].item()
        assert ball.get_vel().norm().item() < 1e-2
    # hull: on its top face, 0.30 m above the outer bottom (0.15 - 0.15 + 0.30 + r); parts: on the inner floor
    assert abs(heights[False] - (0.30 + r)) < 5e-3, heights
    assert abs(heights[True] - (0.10 + r)) < 5e-3, heights


# Genesis 0.4.5's gs.options.CoacdOptions defaults (genesis/options/misc.py), coarser than CoACD's own
GENESIS_COACD = {"threshold": 0.1, "max_convex_hull": -1, "preprocess_mode": "auto", "preprocess_resolution": 30,
                 "resolution": 1000, "mcts_nodes": 20, "mcts_iterations": 100, "mcts_max_depth": 3, "pca": False,
                 "merge": True, "decimate": False, "max_ch_vertex": 256, "extrude": False, "extrude_margin": 0.1,
                 "apx_mode": "ch", "seed": 0}


def test_coacd_options_are_genesis_s_and_reach_coacd():
    assert gs.options.CoacdOptions().kwargs() == GENESIS_COACD
    assert gs.morphs.Mesh(file=str(TANK)).coacd_options == gs.options.CoacdOptions()
    # a dict overrides some of Genesis's defaults, the same as the options object
    m = gs.morphs.Mesh(file=str(TANK), coacd_options={"threshold": 0.2})
    assert m.coacd_options == gs.options.CoacdOptions(threshold=0.2)
    # they reach CoACD: at most max_convex_hull parts (13 without the cap)
    capped = load_morph(gs.morphs.Mesh(file=str(TANK), fixed=True,
                                       coacd_options=gs.options.CoacdOptions(max_convex_hull=3, **FAST)),
                        gs.materials.Rigid(), name="tank")
    assert 1 < len(capped.links[0].geoms) <= 3
    for bad, what in (({"threshold": -1.0}, "threshold"), ({"resolution": 0}, "resolution"),
                      ({"preprocess_mode": "yes"}, "preprocess_mode")):
        with pytest.raises(ValueError, match=what):
            gs.options.CoacdOptions(**bad)
    with pytest.raises(ValueError, match="not CoACD options"):
        gs.morphs.Mesh(file=str(TANK), coacd_options={"mcts_iteration": 10})
    # genesis_lite's earlier name of the object threshold still sets it
    assert gs.morphs.Mesh(file=str(TANK), decompose_error_threshold=0.5).decompose_object_error_threshold == 0.5


def _tank_mjcf(tmp_path, free=True):
    """The tank's mesh as an MJCF body: a free body (an object, by Genesis's rule) or on a hinge (a robot)."""
    joint = "<freejoint/>" if free else '<joint type="hinge" axis="0 0 1"/>'
    path = tmp_path / ("tank_free.xml" if free else "tank_hinge.xml")
    path.write_text(f'<mujoco><asset><mesh name="tank" file="{TANK}"/></asset><worldbody><body name="tank" '
                    f'pos="0 0 0.15">{joint}<geom type="mesh" mesh="tank"/></body></worldbody></mujoco>')
    return path


def test_an_mjcf_splits_an_object_s_mesh_by_genesis_s_rules(tmp_path):
    """MuJoCo collides every mesh as its hull; Genesis splits an MJCF object's non-convex mesh (a free body with
    nothing articulated below it) past decompose_object_error_threshold, as a URDF's, and a robot's only past
    decompose_robot_error_threshold (never by default)."""
    def tank(path, **kw):
        model = load_morph(gs.morphs.MJCF(file=str(path), coacd_options=FAST, **kw), gs.materials.Rigid(), name="t")
        return next(link for link in model.links if link.name == "tank")

    obj = tank(_tank_mjcf(tmp_path))
    assert len(obj.geoms) >= 5 and abs(_parts_volume(obj) - 0.03) < 0.002
    assert len(tank(_tank_mjcf(tmp_path), decompose_object_error_threshold=float("inf")).geoms) == 1
    assert len(tank(_tank_mjcf(tmp_path, free=False)).geoms) == 1
    assert len(tank(_tank_mjcf(tmp_path, free=False), convexify=False).geoms) >= 5


def test_coacd_runs_once_a_mesh_and_options(tmp_path, monkeypatch):
    """CoACD's parts are cached by the mesh and the options (GS_CACHE_DIR/coacd): the tank placed elsewhere, or
    in an MJCF file (which has no model cache), does not run CoACD again; other options do."""
    import coacd

    monkeypatch.setenv("GS_CACHE_DIR", str(tmp_path / "cache"))
    calls = []
    run = coacd.run_coacd
    monkeypatch.setattr(coacd, "run_coacd", lambda *a, **k: calls.append(k) or run(*a, **k))
    first = load_morph(gs.morphs.Mesh(file=str(TANK), coacd_options=FAST), gs.materials.Rigid(), name="a")
    again = load_morph(gs.morphs.Mesh(file=str(TANK), pos=(1.0, 2.0, 3.0), coacd_options=FAST), gs.materials.Rigid(),
                       name="b")
    assert len(calls) == 1
    assert [g.vertices.tobytes() for g in first.links[0].geoms] == [g.vertices.tobytes() for g in again.links[0].geoms]
    load_morph(gs.morphs.Mesh(file=str(TANK), coacd_options={**FAST, "max_convex_hull": 4}), gs.materials.Rigid(),
               name="c")
    assert len(calls) == 2


def test_an_open_surface_is_measured_by_its_volume_as_genesis_measures_it(tmp_path):
    """The tank with one bottom triangle removed: open, its winding still consistent, its volume as trimesh
    closes it ~0.03 m^3 against the hull's 0.048 (60 % over): split, as Genesis splits it."""
    tank = trimesh.load(TANK, force="mesh", process=True)
    bottom = int(np.argmin(tank.triangles_center[:, 2]))
    open_tank = trimesh.Trimesh(tank.vertices, np.delete(tank.faces, bottom, axis=0), process=True)
    assert not open_tank.is_watertight and open_tank.is_winding_consistent
    path = tmp_path / "open_tank.obj"
    open_tank.export(path)
    model = load_morph(gs.morphs.Mesh(file=str(path), fixed=True, coacd_options=FAST), gs.materials.Rigid(), name="t")
    assert len(model.links[0].geoms) >= 5
