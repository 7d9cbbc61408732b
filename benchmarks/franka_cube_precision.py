"""Genesis's rigid/franka_cube.py scene on genesis_lite, in float32 and float64 (issue #25): the MJCF
Panda (Genesis's asset, found through GS_ASSETS_DIR or a Genesis install) holds its fingers over a 4 cm
cube for 1 s, closes them for 1 s, lifts for 2 s, as the script does. Prints the cube's final position
per precision, each run in a fresh process (one gs.init per process). Genesis 0.4.5 ends the script with
the cube at (0.652, -0.0004, 0.1832) (results/genesis_scripts_genesis045.json)."""
import argparse
import json
import subprocess
import sys

import numpy as np


def run(precision):
    import genesis_lite as gs

    gs.init(backend=gs.cpu, precision=precision, logging_level="warning")
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
    scene.add_entity(gs.morphs.Plane())
    franka = scene.add_entity(gs.morphs.MJCF(file="xml/franka_emika_panda/panda.xml"))
    cube = scene.add_entity(gs.morphs.Box(size=(0.04, 0.04, 0.04), pos=(0.65, 0.0, 0.02)))
    scene.build()
    motors, fingers = np.arange(7), np.arange(7, 9)
    franka.set_dofs_kp([100.0, 100.0], fingers)
    franka.set_dofs_kv([10.0, 10.0], fingers)
    franka.set_qpos(np.array([-1.0124, 1.5559, 1.3662, -1.6878, -1.5799, 1.7757, 1.4602, 0.04, 0.04]))
    scene.step()
    hand = franka.get_link("hand")
    q = franka.inverse_kinematics(link=hand, pos=np.array([0.65, 0.0, 0.135]), quat=np.array([0, 1, 0, 0]))
    franka.control_dofs_position(q[:-2], motors)
    for _ in range(100):
        scene.step()
    for _ in range(100):
        franka.control_dofs_position(q[:-2], motors)
        franka.control_dofs_position(np.array([0.0, 0.0]), fingers)
        scene.step()
    q = franka.inverse_kinematics(link=hand, pos=np.array([0.65, 0.0, 0.3]), quat=np.array([0, 1, 0, 0]))
    for _ in range(200):
        franka.control_dofs_position(q[:-2], motors)
        franka.control_dofs_position(np.array([0.0, 0.0]), fingers)
        scene.step()
    return [float(v) for v in np.asarray(cube.get_pos().detach().cpu().numpy(), dtype=float)]


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--precision", choices=["32", "64"], default=None, help="one run in this process")
    args = ap.parse_args()
    if args.precision:
        print(json.dumps({"precision": args.precision, "cube_pos": run(args.precision)}))
        return
    print("| precision | cube's final position (m) |\n|---|---|")
    for p in ("32", "64"):
        done = subprocess.run([sys.executable, __file__, "--precision", p], capture_output=True, text=True)
        if done.returncode != 0:
            print(f"| {p} | failed: {done.stderr.strip().splitlines()[-1]} |")
            continue
        pos = json.loads(done.stdout.strip().splitlines()[-1])["cube_pos"]
        print(f"| {p} | ({pos[0]:.4f}, {pos[1]:.4f}, {pos[2]:.4f}) |")


if __name__ == "__main__":
    main()
