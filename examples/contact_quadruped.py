"""A quadruped (ANYmal B from example-robot-data) dropped onto the ground and held by PD control, next
to a stack of boxes; prints and plots the base height, the feet's contact forces and the stack.

    python examples/contact_quadruped.py [--seconds 5] [--out out/contact_quadruped]
"""
import argparse
import os
import site
import sys
import sysconfig
import time
from pathlib import Path

import numpy as np
import torch

import genesis_lite as gs

ap = argparse.ArgumentParser()
ap.add_argument("--seconds", type=float, default=5.0)
ap.add_argument("--out", default="out/contact_quadruped")
args = ap.parse_args()
os.makedirs(args.out, exist_ok=True)


def robots_dir():
    for base in list(site.getsitepackages()) + [sysconfig.get_paths()["purelib"], sys.prefix]:
        d = Path(base) / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
        if d.is_dir():
            return d
    raise SystemExit("example-robot-data is not installed: pip install example-robot-data")


gs.init(backend=gs.cpu, precision="64")
scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
scene.add_entity(gs.morphs.Plane())
robot = scene.add_entity(gs.morphs.URDF(file=str(robots_dir() / "anymal_b_simple_description/robots/anymal.urdf"),
                                        fixed=False, pos=(0.0, 0.0, 0.62)))
boxes = [scene.add_entity(gs.morphs.Box(size=(0.15, 0.15, 0.15), pos=(1.0, 0.0, 0.075 + 0.155 * i))) for i in range(4)]
scene.build()

names = [j.name for j in robot.joints if j.n_dofs == 1]
dofs = [j.dof_start_local for j in robot.joints if j.n_dofs == 1]
q0 = torch.tensor([0.0 if "HAA" in n else (0.4 if n[1] == "F" else -0.4) if "HFE" in n else (-0.8 if n[1] == "F" else 0.8)
                   for n in names], dtype=torch.float64)
robot.set_dofs_kp(torch.full((12,), 300.0, dtype=torch.float64), dofs)
robot.set_dofs_kv(torch.full((12,), 10.0, dtype=torch.float64), dofs)
robot.set_dofs_position(q0, dofs)
robot.control_dofs_position(q0, dofs)
feet = [robot.get_link(n).idx_local for n in ("LF_SHANK", "RF_SHANK", "LH_SHANK", "RH_SHANK")]

steps = int(args.seconds / 0.01)
t_log, z_log, f_log, stack_log = [], [], [], []
t0 = time.time()
for i in range(steps):
    scene.step()
    t_log.append((i + 1) * 0.01)
    z_log.append(float(robot.get_pos()[2]))
    f_log.append(robot.get_links_net_contact_force()[feet, 2].detach().numpy().copy())
    stack_log.append(float(boxes[-1].get_pos()[2]))
    if (i + 1) % 100 == 0:
        print(f"t = {(i + 1) * 0.01:5.2f} s  base z {z_log[-1]:.4f} m  feet Fz {np.round(f_log[-1], 1)} N  "
              f"top box z {stack_log[-1]:.4f} m  ({time.time() - t0:.1f} s)", flush=True)
contacts = robot.get_contacts()
print(f"{len(contacts['position'])} contact points on the robot; total ground force "
      f"{robot.get_links_net_contact_force().sum(0).numpy().round(2)} N for a weight of {float(robot.get_mass()) * 9.81:.2f} N")

csv = os.path.join(args.out, "quadruped_contacts.csv")
np.savetxt(csv, np.column_stack([t_log, z_log, np.array(f_log), stack_log]), delimiter=",",
           header="t,base_z,Fz_LF,Fz_RF,Fz_LH,Fz_RH,top_box_z", comments="")
print(f"wrote {csv}")
try:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(14, 3.8))
    ax[0].plot(t_log, z_log)
    ax[0].set_ylabel("base height (m)")
    ax[1].plot(t_log, np.array(f_log), label=["LF", "RF", "LH", "RH"])
    ax[1].set_ylabel("foot normal force (N)")
    ax[1].legend()
    ax[2].plot(t_log, stack_log)
    ax[2].set_ylabel("top box height (m)")
    for a in ax:
        a.set_xlabel("t (s)")
    fig.tight_layout()
    fig.savefig(os.path.join(args.out, "quadruped_contacts.png"), dpi=110)
    print(f"wrote {os.path.join(args.out, 'quadruped_contacts.png')}")
except ImportError:
    print("matplotlib is not installed: no figure")
