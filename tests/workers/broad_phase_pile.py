"""Worker of tests/test_many_bodies.py: a pile of long planks, boxes, cylinders and spheres thrown at
each other and at the ground (random poses, 2 m/s, 6 rad/s), 100 steps in float64, default options.
With the argument `spheres`, the broad phase's bounding-box test (collision/narrow.py: func_gap_boxes)
is replaced by one that never separates a pair, before anything is compiled (the bounding spheres
alone, as before the test existed). Argument 2: the seeds (comma-separated; 14 by default). Prints one
JSON line per seed: the sha256 of the trajectory's float64 bytes, the number of pair activations over
the steps, the lowest final height and the fastest body speed."""
import hashlib
import json
import sys

import numpy as np
import taichi as ti

if sys.argv[1] == "spheres":
    from solvers.rigid.collision import narrow

    @ti.func
    def _never_apart(c: ti.template(), ga, gb, Ra, Rb, ca, cb, branch: ti.template()):
        return -1e30

    narrow.func_gap_boxes = _never_apart

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


# seeds (argument 2, comma-separated): 14 by default; one JSON line each
for seed in (sys.argv[2] if len(sys.argv) > 2 else "14").split(","):
    print(json.dumps(run(int(seed))), flush=True)
