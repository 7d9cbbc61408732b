"""Genesis's rigid/control_mesh.py duck against MuJoCo (issue #25): the duck mesh (Genesis's asset
meshes/duck.obj, found through GS_ASSETS_DIR or a Genesis install) on a free joint without gravity, PD on its
six dofs (kp 0.3, kv 1) towards a yaw of 1 rad, 2 s. Ours with the Euler integrator; MuJoCo with the same
body (our mass, centre of mass and inertia tensor) and the same control law applied as generalised forces
(a world force kp (0 - p) - kv v at the body's origin, a world torque kp rotvec(q* q^-1) - kv w), Euler at
the same step. Prints both final (x, y, z, roll, pitch, yaw). Genesis 0.4.5's own run ends at (0.0003,
0.083, 0.002, -0.336, -0.0006, 0.476) (results/genesis_scripts_genesis045.json).

    python benchmarks/control_mesh_reference.py [--dt 0.01]"""
import argparse

import mujoco
import numpy as np
import torch
from scipy.spatial.transform import Rotation as Rot

import genesis_lite as gs

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--dt", type=float, default=0.01)
dt = ap.parse_args().dt
gs.init(backend=gs.cpu, precision="64", logging_level="warning")
T = 2.0
n = int(round(T / dt))
KP, KV = 0.3, 1.0
scene = gs.Scene(sim_options=gs.options.SimOptions(dt=dt, gravity=(0, 0, 0)),
                 rigid_options=gs.options.RigidOptions(integrator=gs.integrator.Euler))
duck = scene.add_entity(gs.morphs.Mesh(file="meshes/duck.obj", scale=0.1, pos=(0, 0, 0.0)))
scene.build()
m = float(duck.get_links_mass()[0]); com = duck.get_links_COM()[0].numpy(); I = duck.get_links_inertia()[0].numpy()
print("mass", m, "com", com, "I", I.round(8).tolist())
duck.set_dofs_kp([KP] * 6); duck.set_dofs_kv([KV] * 6)
tgt = torch.zeros(6, dtype=torch.float64); tgt[5] = 1.0
duck.control_dofs_position(tgt)
for _ in range(n):
    scene.step()
ours = duck.get_dofs_position().numpy()
print("ours (Euler, its PD)", ours.round(5))

# MuJoCo: same body, PD as generalised forces: world force at the origin, world torque kp rotvec(q* q^-1) - kv w
xml = f"""<mujoco><option timestep="{dt}" gravity="0 0 0" integrator="Euler"/>
<worldbody><body name="duck"><freejoint/>
<inertial pos="{com[0]} {com[1]} {com[2]}" mass="{m}" fullinertia="{I[0,0]} {I[1,1]} {I[2,2]} {I[0,1]} {I[0,2]} {I[1,2]}"/>
</body></worldbody></mujoco>"""
M = mujoco.MjModel.from_xml_string(xml); D = mujoco.MjData(M)
qt = Rot.from_euler("XYZ", [0, 0, 1.0])
for _ in range(n):
    p = D.qpos[:3].copy(); qw = D.qpos[3:7].copy()
    R = Rot.from_quat([qw[1], qw[2], qw[3], qw[0]])
    v = D.qvel[:3].copy(); w_local = D.qvel[3:6].copy(); w = R.apply(w_local)
    F = KP * (0 - p) - KV * v
    tau_w = KP * (qt * R.inv()).as_rotvec() - KV * w
    D.qfrc_applied[:3] = F
    D.qfrc_applied[3:6] = R.inv().apply(tau_w)
    mujoco.mj_step(M, D)
qw = D.qpos[3:7]
e = Rot.from_quat([qw[1], qw[2], qw[3], qw[0]]).as_euler("XYZ")
ref = np.r_[D.qpos[:3], e]
print("mujoco (same law)", ref.round(5))
print("max abs difference %.2e" % np.abs(ours - ref).max())
