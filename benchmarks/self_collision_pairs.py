"""Self-collision pairs against Genesis's (issue #25): with RigidOptions(enable_self_collision=True), which of
a robot's own geom pairs may collide, after Genesis's two filters (adjacent links, walking up through
fixed-joint links; shapes that overlap or touch with every joint at zero). Genesis's MJCF Panda and its
Go2 URDF (Genesis's assets: GS_ASSETS_DIR or a Genesis install), ours in this process, Genesis's in the
python of its own venv (--genesis-python), in a child process. Prints a Markdown table: geom pairs and the
set of link pairs on each side, and the link pairs only one side has; then what self-collision costs ours:
the MJCF Panda over a plane, float64, PD holding a bent pose (links apart) and a folded one (--poses; some of
its own pairs active), at 1 env and 1,024 envs: both scenes built in this process, 5 alternated rounds of 400
(1 env) and 20 (1,024 envs) steps, the medians of the rounds' mean time an env-step, self-collision off and on
(kernels compiled or loaded before the rounds), and how many of its own pairs are active at the end.

    GS_ASSETS_DIR=<genesis>/assets python benchmarks/self_collision_pairs.py [--genesis-python <venv>/bin/python]
        [--poses bent,folded]
"""
import argparse
import json
import subprocess

ROBOTS = {"mjcf_panda": ("MJCF", "xml/franka_emika_panda/panda.xml"), "go2": ("URDF", "urdf/go2/urdf/go2.urdf")}

GENESIS_SIDE = r"""
import json, sys, numpy as np, genesis as gs
gs.init(backend=gs.cpu, logging_level="error")
out = {}
for key, (kind, file) in json.loads(sys.argv[1]).items():
    scene = gs.Scene(show_viewer=False)
    scene.add_entity(getattr(gs.morphs, kind)(file=file))
    scene.build()
    geoms = scene.sim.rigid_solver.geoms
    idx = np.argwhere(np.asarray(scene.sim.rigid_solver.collider._collision_pair_idx) >= 0)
    out[key] = {"n_geom_pairs": int(len(idx)),
                "link_pairs": sorted({tuple(sorted((geoms[i].link.name, geoms[j].link.name))) for i, j in idx})}
print(json.dumps(out))
"""


def ours():
    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision="64", logging_level="error")
    out = {}
    for key, (kind, file) in ROBOTS.items():
        scene = gs.Scene(rigid_options=gs.options.RigidOptions(enable_self_collision=True))
        ent = scene.add_entity(getattr(gs.morphs, kind)(file=file))
        scene.build()
        plan = scene._rigid.solver.contact.plan
        names = [link.name for link in ent.links]
        link = plan.geoms.link - ent.link_start
        out[key] = {"n_geom_pairs": len(plan.pairs), "n_slots": plan.n_slots,
                    "link_pairs": sorted({tuple(sorted((names[link[a]], names[link[b]]))) for a, b in plan.pairs})}
    return out


# PD targets: "bent" keeps the links apart (link 5 20 mm from link 7); "folded" turns the hand back towards the
# forearm, where some of the robot's own pairs stay active
POSES = {"bent": [0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8, 0.02, 0.02],
         "folded": [0.3, 0.4, -0.2, -2.9, 0.4, 3.4, 2.5, 0.0, 0.0]}


def step_cost(n_envs: int, steps: int, pose: str = "bent", rounds: int = 5):
    """({False: us, True: us} an env-step of the MJCF Panda over a plane (float64, n_envs envs, PD holding a
    pose of POSES, reached from the bent one over 200 steps), without and with self-collision, the self-colliding
    scene's active pairs in env 0 at the end): both scenes built in this process, then `rounds` alternated
    rounds of `steps` steps each, medians."""
    import statistics
    import time

    import numpy as np

    import genesis_lite as gs

    scenes = {}
    for on in (False, True):
        scene = gs.Scene(rigid_options=gs.options.RigidOptions(enable_self_collision=on))
        scene.add_entity(gs.morphs.Plane())
        arm = scene.add_entity(gs.morphs.MJCF(file=ROBOTS["mjcf_panda"][1]))
        if n_envs > 1:
            scene.build(n_envs=n_envs)
        else:
            scene.build()
        q0, q = (np.array(POSES[k]) for k in ("bent", pose))
        q0, q = ((np.tile(x, (n_envs, 1)) if n_envs > 1 else x) for x in (q0, q))
        arm.set_dofs_position(q0)
        arm.control_dofs_position(q)
        for _ in range(200 if pose != "bent" else 20):
            scene.step()
        scenes[on] = scene
    times = {False: [], True: []}
    for _ in range(rounds):
        for on in (False, True):
            t0 = time.perf_counter()
            for _ in range(steps):
                scenes[on].step()
            times[on].append((time.perf_counter() - t0) / steps / n_envs * 1e6)
    c = scenes[True]._rigid.solver.contact
    active = int(c.pair_active.to_numpy()[0, :c.plan.n_pairs].sum())
    return {on: statistics.median(t) for on, t in times.items()}, active


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--genesis-python", help="python of a venv with genesis-world (without it: our side alone, "
                                             "the pairs' columns of Genesis's side empty)")
    ap.add_argument("--poses", default="bent,folded", help="comma-separated, of " + ", ".join(POSES))
    args = ap.parse_args()
    mine = ours()
    cost = {(pose, n): step_cost(n, steps, pose)
            for pose in args.poses.split(",") for n, steps in ((1, 400), (1024, 20))}
    theirs = {key: {"n_geom_pairs": "-", "link_pairs": []} for key in ROBOTS}
    if args.genesis_python:
        done = subprocess.run([args.genesis_python, "-c", GENESIS_SIDE, json.dumps(ROBOTS)], capture_output=True,
                              text=True, timeout=1800)
        if done.returncode != 0:
            raise SystemExit(f"Genesis's side failed: {done.stderr.strip().splitlines()[-1]}")
        theirs = json.loads(done.stdout.strip().splitlines()[-1])
    print("| robot | geom pairs, ours / Genesis | link pairs, ours / Genesis | only ours | only Genesis's | our slots |")
    print("|---|---|---|---|---|---|")
    for key in ROBOTS:
        a, b = mine[key], theirs[key]
        sa, sb = {tuple(p) for p in a["link_pairs"]}, {tuple(p) for p in b["link_pairs"]}
        print(f"| {key} | {a['n_geom_pairs']} / {b['n_geom_pairs']} | {len(sa)} / {len(sb)} | "
              f"{sorted(sa - sb) or '-'} | {sorted(sb - sa) or '-'} | {a['n_slots']} |")
    for (pose, n), (c, active) in cost.items():
        print(f"\nOurs, MJCF Panda over a plane, {pose} pose, {n} env(s), float64: an env-step {c[False]:.2f} us "
              f"without self-collision, {c[True]:.2f} us with it ({c[True] / c[False]:.1f}x); {active} of its own "
              f"pairs active at the end (env 0).")


if __name__ == "__main__":
    main()
