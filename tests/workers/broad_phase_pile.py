"""Worker of tests/test_many_bodies.py: a pile of long planks, boxes, cylinders and spheres thrown at
each other and at the ground (random poses, 2 m/s, 6 rad/s), 100 steps in float64, default options.
With the argument `spheres`, the broad phase's bounding-box tests (collision/narrow.py: func_gap_boxes,
the world-axis boxes, func_gap_obbs, the oriented ones, and func_gap_mesh_planes) are replaced by ones
that never separate a pair, before anything is compiled (the bounding spheres alone, as before those
tests existed). Argument 2: the seeds (comma-separated; 14 by default). Prints one JSON line per seed:
the sha256 of the trajectory's float64 bytes, the number of pair activations over the steps, the lowest
final height and the fastest body speed. Argument 3, `arm`: then a line of a robot's own meshes (arm())."""
import hashlib
import json
import os
import sys

import numpy as np
import taichi as ti

if sys.argv[1] == "spheres":
    from solvers.rigid.collision import narrow

    @ti.func
    def _never_apart(c: ti.template(), i_b, ga, gb, ca, cb):
        return -1e30

    @ti.func
    def _never_apart_oriented(c: ti.template(), i_b, ga, gb, Ra, Rb):
        return -1e30

    @ti.func
    def _never_apart_meshes(c: ti.template(), i_b, i_p, ga, gb, Ra, Rb, thr):
        return -1e30

    narrow.func_gap_boxes = _never_apart
    narrow.func_gap_obbs = _never_apart_oriented
    narrow.func_gap_mesh_planes = _never_apart_meshes

import genesis_lite as gs  # noqa: E402

gs.init(backend=gs.cpu, precision="64", logging_level="warning")


def run(seed):
    """The pile of `seed` over 100 steps: its trajectory's sha256, pair activations, lowest final height
    and fastest body speed."""
    rng = np.random.default_rng(seed)
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
    scene.add_entity(gs.morphs.Plane())
    bodies = []
    for i in range(14):
        # one above the other, turned about z and tilted a little (the 1 m cylinders stand upright: they
        # overlap the levels around them, the lowest starts 15 cm into the ground)
        pos = (*rng.uniform(-0.4, 0.4, 2), 0.15 + 0.2 * i)
        yaw, tilt = rng.uniform(0, np.pi), rng.uniform(-0.15, 0.15)
        quat = (np.cos(yaw / 2) * np.cos(tilt / 2), np.sin(tilt / 2) * np.cos(yaw / 2), np.sin(tilt / 2) * np.sin(yaw / 2),
                np.sin(yaw / 2) * np.cos(tilt / 2))
        kind = i % 4
        if kind == 0:
            morph = gs.morphs.Box(size=(1.2, 0.15, 0.08), pos=pos, quat=quat)
        elif kind == 1:
            morph = gs.morphs.Cylinder(radius=0.06, height=1.0, pos=pos, quat=quat)
        elif kind == 2:
            morph = gs.morphs.Box(size=(0.1, 0.9, 0.1), pos=pos, quat=quat)
        else:
            morph = gs.morphs.Sphere(radius=0.08, pos=pos)
        bodies.append(scene.add_entity(morph))
    scene.build()
    for b in bodies:
        b.set_dofs_velocity(np.concatenate([rng.uniform(-2, 2, 3), rng.uniform(-6, 6, 3)]))
    c = scene.sim.rigid_solver.contact
    n_pairs = c.plan.n_pairs
    states, active = [], 0
    for _ in range(100):
        scene.step()
        active += int(c.pair_active.to_numpy()[0, :n_pairs].sum())
        states.append(np.concatenate([np.concatenate([b.get_qpos().numpy(), b.get_dofs_velocity().numpy()])
                                      for b in bodies]))
    traj = np.asarray(states, dtype=np.float64)
    return {"seed": seed, "sha": hashlib.sha256(traj.tobytes()).hexdigest(), "active": active, "pairs": n_pairs,
            "z_min": float(traj[-1, 2::13].min()),
            "v_max": float(np.abs(traj.reshape(len(states), len(bodies), 13)[:, :, 7:10]).max())}


def arm():
    """example-robot-data's Panda with self-collision on, over a plane, swung by its PD from a bent pose into
    one that folds its hand onto its forearm (its fingers and link 5 touch, link 6 the plane): its joint
    angles' sha256 over 100 steps, the pair activations, and how many slot contacts two of its own links
    made."""
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from conftest import robot_urdf

    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01),
                     rigid_options=gs.options.RigidOptions(enable_self_collision=True))
    scene.add_entity(gs.morphs.Plane())
    robot = scene.add_entity(gs.morphs.URDF(file=str(robot_urdf("panda")), fixed=True))
    scene.build()
    n = robot.n_dofs
    robot.set_dofs_kp(np.full(n, 200.0))
    robot.set_dofs_kv(np.full(n, 20.0))
    q0 = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8, 0.02, 0.02])
    q1 = np.array([0.0, 1.2, 0.0, -3.0, 2.5, 0.5, 0.0, 0.0, 0.0])
    robot.set_dofs_position(q0)
    c = scene.sim.rigid_solver.contact
    own = np.array([a != 0 and b != 0 for a, b in zip(c.plan.geoms.entity[c.plan.np_slot_ga],
                                                     c.plan.geoms.entity[c.plan.np_slot_gb])])
    active, own_on, states = 0, 0, []
    for k in range(100):
        robot.control_dofs_position(q0 + (q1 - q0) * min(1.0, k / 60))
        scene.step()
        pairs = c.pair_active.to_numpy()[0, :c.plan.n_pairs]
        active += int(pairs.sum())
        on = (c.sl_on.to_numpy()[0, :c.plan.n_slots] == 1) & (pairs[c.plan.np_slot_pair] == 1)
        own_on += int((on & own).sum())
        states.append(robot.get_dofs_position().numpy())
    traj = np.asarray(states, dtype=np.float64)
    return {"case": "arm", "sha": hashlib.sha256(traj.tobytes()).hexdigest(), "active": active,
            "pairs": c.plan.n_pairs, "own_contacts": own_on}


# seeds (argument 2, comma-separated): 14 by default; one JSON line each; then the arm's (argument 3: "arm")
for seed in (sys.argv[2] if len(sys.argv) > 2 else "14").split(","):
    print(json.dumps(run(int(seed))), flush=True)
if len(sys.argv) > 3 and sys.argv[3] == "arm":
    print(json.dumps(arm()), flush=True)
