"""A quadruped (ANYmal B from example-robot-data) dropped onto the ground and held by PD control, next
to a stack of boxes; prints and plots the base height, the feet's contact forces and the stack.

    python examples/contact_quadruped.py [--quick] [--seconds 5] [--out out/contact_quadruped]

Writes quadruped_contacts.csv and quadruped_contacts.png (base height, feet normal forces, top box).
"""
import os
import sys
import time

import numpy as np
import genesis_lite as gs  # before torch: its OpenMP threads then sleep between ops (README)
import torch


sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from example_utils import parse_args, progress, pyplot, robots_dir, save_figure, summary, write_csv  # noqa: E402

t_start = time.time()
args = parse_args("contact_quadruped", __doc__, lambda ap: ap.add_argument(
    "--seconds", type=float, default=5.0, help="simulated time (--quick: 0.5 s)"))
seconds = 0.5 if args.quick else args.seconds

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

steps = int(round(seconds / 0.01))
t_log, z_log, f_log, stack_log = [], [], [], []
t0 = time.time()
for i in progress(range(steps), desc="simulate", total=steps):
    scene.step()
    t_log.append((i + 1) * 0.01)
    z_log.append(float(robot.get_pos()[2]))
    f_log.append(robot.get_links_net_contact_force()[feet, 2].detach().numpy().copy())
    stack_log.append(float(boxes[-1].get_pos()[2]))
contacts = robot.get_contacts()
weight = float(robot.get_mass()) * 9.81
ground = robot.get_links_net_contact_force().sum(0).numpy()
written = []
write_csv(args.out, "quadruped_contacts.csv", ["t", "base_z", "Fz_LF", "Fz_RF", "Fz_LH", "Fz_RH", "top_box_z"],
          [t_log, z_log] + [np.array(f_log)[:, k] for k in range(4)] + [stack_log], written)
plt = pyplot()
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
save_figure(fig, args.out, "quadruped_contacts.png", written)
summary("contact_quadruped", [f"{steps} steps of 0.01 s in {time.time() - t0:.1f} s",
                              f"base height {z_log[-1]:.4f} m, top box {stack_log[-1]:.4f} m",
                              f"{len(contacts['position'])} contact points on the robot; total ground force "
                              f"{np.round(ground, 2).tolist()} N for a weight of {weight:.2f} N"], written, t_start)
