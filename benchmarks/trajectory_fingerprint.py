"""Bitwise fingerprint of three scenes' trajectories and gradients, for refactors that must not change a number.

    python benchmarks/trajectory_fingerprint.py [--out FILE]

Scenes (all at the default build options: collision on, default integrator, float64 on the CPU backend):
  contact  three boxes and a sphere on a plane and on each other, 4 envs, per-env initial velocities, 40 steps,
           requires_grad; loss.backward() to the initial velocities, a mass and a friction coefficient
  anymal   ANYmal B (example-robot-data) on a plane, 8 envs, PD control towards per-env targets, 40 steps
  coupling a rigid box pushing an elastic MPM cube (two-way coupling), 10 steps, gradient to the box's
           initial velocity and mass
  mpm      no gradients: elastic, neo-Hookean, plasticine, sand and liquid bodies falling and colliding in
           2 envs with different initial velocities, 25 steps (the solver's no-gradient substep)
  coupling_nograd  the coupling scene's box and cube without gradients, 10 steps
  hull     no gradients: plank meshes crossed ridge on ridge, a box flat on plank meshes, a pile of plank meshes
           and a box on a plane, 150 steps each; the Panda (example-robot-data) with self-collision, 4 envs
--precision 32 runs the scenes in float32 (only mpm and coupling_nograd take no float64 inputs).
Prints the sha256 of the raw float64 bytes of every recorded tensor, then one line per scene (a hash of
the tensors' hashes). Two runs on one tree must print the same lines; a refactor that claims to change no
numerics must too (diff the output).
"""
import argparse
import hashlib
import os
import sys

import numpy as np
import torch

import genesis_lite as gs

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import find_robots_dir  # noqa: E402

F64 = dict(dtype=torch.float64)


def _digest(x) -> str:
    a = np.ascontiguousarray((x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)).astype(np.float64))
    return hashlib.sha256(a.tobytes()).hexdigest()


def contact_scene():
    B = 4
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True))
    scene.add_entity(gs.morphs.Plane())
    lower = scene.add_entity(gs.morphs.Box(size=(0.2, 0.2, 0.2), pos=(0.0, 0.0, 0.1)))
    upper = scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1), pos=(0.03, 0.0, 0.25), quat=(0.995, 0.0, 0.0, 0.1)))
    # (a fifth free body, box or sphere, makes the backward pass of this scene segfault at 52d1430: reported)
    ball = scene.add_entity(gs.morphs.Sphere(radius=0.04, pos=(0.02, 0.01, 0.4)))
    slider = scene.add_entity(gs.morphs.Box(size=(0.2, 0.1, 0.1), pos=(-0.6, 0.0, 0.06), quat=(0.999, 0.02, 0.03, 0.01)))
    scene.build(n_envs=B)
    rng = np.random.default_rng(7)
    v_upper = torch.tensor(rng.normal(0, 0.5, (B, 6)), **F64).requires_grad_(True)
    v_ball = torch.tensor(rng.normal(0, 1.0, (B, 6)), **F64).requires_grad_(True)
    v_slider = torch.tensor(np.c_[rng.uniform(0.5, 2.0, (B, 1)), rng.normal(0, 0.3, (B, 4)), rng.normal(0, 2.0, (B, 1))], **F64).requires_grad_(True)
    mass = torch.tensor(0.7, **F64).requires_grad_(True)
    mu = torch.tensor(0.6, **F64).requires_grad_(True)
    upper.set_links_mass(mass.reshape(1))
    slider.set_friction(mu)
    upper.set_dofs_velocity(v_upper)
    ball.set_dofs_velocity(v_ball)
    slider.set_dofs_velocity(v_slider)
    traj = []
    for _ in range(40):
        scene.step()
        traj.append(torch.cat([b.get_qpos() for b in (lower, upper, ball, slider)], dim=-1))
    traj = torch.stack(traj)
    w = torch.tensor(np.random.default_rng(3).normal(0, 1, tuple(traj.shape)), **F64)
    loss = (w * traj).sum()
    loss.backward()
    return {"qpos": traj, "loss": loss.reshape(1), "grad_v_upper": v_upper.grad, "grad_v_ball": v_ball.grad,
            "grad_v_slider": v_slider.grad, "grad_mass": mass.grad.reshape(1), "grad_mu": mu.grad.reshape(1)}


def anymal_scene():
    B = 8
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01))
    scene.add_entity(gs.morphs.Plane())
    urdf = find_robots_dir() / "anymal_b_simple_description" / "robots" / "anymal.urdf"
    robot = scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=False, pos=(0.0, 0.0, 0.62)))
    scene.build(n_envs=B)
    names = [j.name for j in robot.joints if j.n_dofs == 1]
    dofs = [j.dof_start_local for j in robot.joints if j.n_dofs == 1]
    q0 = torch.tensor([0.0 if "HAA" in n else (0.4 if n[1] == "F" else -0.4) if "HFE" in n else (-0.8 if n[1] == "F" else 0.8)
                       for n in names], **F64)
    rng = np.random.default_rng(11)
    robot.set_dofs_kp(torch.full((12,), 300.0, **F64), dofs)
    robot.set_dofs_kv(torch.full((12,), 10.0, **F64), dofs)
    robot.set_dofs_position(q0.expand(B, 12).clone(), dofs)
    target = q0 + torch.tensor(rng.normal(0, 0.2, (B, 12)), **F64)
    robot.control_dofs_position(target, dofs)
    traj, vel = [], []
    for _ in range(40):
        scene.step()
        traj.append(robot.get_qpos())
        vel.append(robot.get_dofs_velocity())
    return {"qpos": torch.stack(traj), "qvel": torch.stack(vel)}


def _coupling_build(requires_grad):
    """An elastic cube and a tilted rigid pusher (coupled), built: (scene, cube, pusher)."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=5, requires_grad=requires_grad),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.5, 0.5, 0.5), grid_density=32))
    cube = scene.add_entity(gs.morphs.Box(pos=(0.3, 0.25, 0.25), size=(0.1, 0.1, 0.1)),
                            material=gs.materials.MPM.Elastic(E=2e4, nu=0.3))
    pusher = scene.add_entity(gs.morphs.Box(pos=(0.215, 0.26, 0.24), size=(0.05, 0.12, 0.1), quat=(0.99, 0.05, 0.1, 0.0)),
                              material=gs.materials.Rigid(rho=2000, coup_friction=0.4))
    scene.build()
    return scene, cube, pusher


def _coupling_rollout(scene, cube, pusher):
    """10 steps: the pusher's qpos and the cube's particles at each, stacked."""
    traj, parts = [], []
    for _ in range(10):
        scene.step()
        traj.append(pusher.get_qpos())
        parts.append(cube.get_particles_pos())
    return torch.stack(traj), torch.stack(parts)


def coupling_scene():
    scene, cube, pusher = _coupling_build(True)
    vel = torch.tensor([1.2, 0.1, -0.05, 0.5, -0.3, 1.0], **F64).requires_grad_(True)
    mass = torch.tensor([pusher.get_mass()], **F64).requires_grad_(True)
    pusher.set_links_mass(mass)
    pusher.set_dofs_velocity(vel)
    traj, parts = _coupling_rollout(scene, cube, pusher)
    loss = (torch.tensor([1.0, -0.7, 0.4], **F64) * parts[-1].mean(0)).sum() + traj[:, :3].sum()
    loss.backward()
    return {"pusher_qpos": traj, "particles": parts, "loss": loss.reshape(1), "grad_vel": vel.grad, "grad_mass": mass.grad}


def mpm_scene():
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=8),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.6, 0.6, 0.6), grid_density=40))
    M = gs.materials.MPM
    ents = [scene.add_entity(gs.morphs.Box(pos=(0.15, 0.15, 0.12), size=(0.08, 0.08, 0.08)), material=M.Elastic(E=3e4, nu=0.3)),
            scene.add_entity(gs.morphs.Box(pos=(0.15, 0.18, 0.3), size=(0.06, 0.06, 0.06)), material=M.Elastic(E=2e4, nu=0.25, model="neohooken")),
            scene.add_entity(gs.morphs.Sphere(pos=(0.4, 0.4, 0.15), radius=0.05), material=M.ElastoPlastic(E=5e4, nu=0.3)),
            scene.add_entity(gs.morphs.Box(pos=(0.42, 0.2, 0.1), size=(0.08, 0.06, 0.06)), material=M.Sand()),
            scene.add_entity(gs.morphs.Sphere(pos=(0.2, 0.42, 0.2), radius=0.05), material=M.Liquid())]
    scene.build(n_envs=2)
    for k, e in enumerate(ents):
        v = torch.tensor([[0.3 * (k - 2), 0.2, -0.5], [-0.4, 0.1 * k, 0.6]], dtype=gs.tc_float)
        e.set_velocity(v)
    out = {}
    for t in range(25):
        scene.step()
    for k, e in enumerate(ents):
        out[f"x{k}"] = e.get_particles_pos()
        out[f"v{k}"] = e.get_particles_vel()
    return out


def coupling_nograd_scene():
    """The coupling scene without gradients (the MPM substep's no-gradient path, coupled)."""
    scene, cube, pusher = _coupling_build(False)
    pusher.set_dofs_velocity(torch.tensor([1.2, 0.1, -0.05, 0.5, -0.3, 1.0], dtype=gs.tc_float))
    traj, parts = _coupling_rollout(scene, cube, pusher)
    return {"pusher_qpos": traj, "particles": parts}


def _turn(yaw_deg, roll_deg):
    """A plank's quaternion (w, x, y, z): roll_deg about its length (x), then yaw_deg about z."""
    y, r = np.radians(yaw_deg) / 2, np.radians(roll_deg) / 2
    return (np.cos(y) * np.cos(r), np.cos(y) * np.sin(r), np.sin(y) * np.sin(r), np.sin(y) * np.cos(r))


def hull_scene():
    """Convex volumes meeting through the hull pair test's slots (collision/narrow.func_hull_pair_test): a plank
    mesh (0.6 x 0.08 x 0.08 m) dropped across two fixed ones at 70 degrees, ridges up (edge on edge), then a box
    dropped flat across two fixed plank meshes (face on face), then five plank meshes and a box thrown onto a
    plane, 150 steps each; and example-robot-data's Panda with self-collision holding a bent pose, 4 envs."""
    plank = os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir, "assets", "meshes", "plank.obj")
    out = {}
    for name, roll, top in (("ridge", 45.0, "mesh"), ("flat", 0.0, "box")):
        scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.005))
        for y in (-0.15, 0.15):
            scene.add_entity(gs.morphs.Mesh(file=plank, pos=(0.0, y, 0.2), quat=_turn(0.0, roll), fixed=True))
        z = 0.2 + (0.08 * np.sqrt(2.0) if roll else 0.08) + 0.01
        morph = (gs.morphs.Mesh(file=plank, pos=(0.01, 0.02, z), quat=_turn(70.0, roll)) if top == "mesh" else
                 gs.morphs.Box(size=(0.6, 0.08, 0.08), pos=(0.01, 0.02, z), quat=_turn(70.0, roll)))
        body = scene.add_entity(morph)
        scene.build()
        traj = []
        for _ in range(150):
            scene.step()
            traj.append(body.get_qpos())
        out[f"{name}_qpos"] = torch.stack(traj)
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.005))
    scene.add_entity(gs.morphs.Plane())
    rng = np.random.default_rng(0)
    bodies = []
    for i in range(5):
        q = rng.normal(size=4)
        bodies.append(scene.add_entity(gs.morphs.Mesh(file=plank, pos=(0.05 * i, 0.03 * i, 0.15 + 0.12 * i),
                                                      quat=tuple(q / np.linalg.norm(q)))))
    bodies.append(scene.add_entity(gs.morphs.Box(size=(0.2, 0.1, 0.05), pos=(0.0, 0.0, 0.9))))
    scene.build()
    for _ in range(150):
        scene.step()
    out["pile_qpos"] = torch.cat([b.get_qpos() for b in bodies])
    scene = gs.Scene(rigid_options=gs.options.RigidOptions(enable_self_collision=True))
    scene.add_entity(gs.morphs.Plane())
    urdf = find_robots_dir() / "panda_description" / "urdf" / "panda.urdf"
    arm = scene.add_entity(gs.morphs.URDF(file=str(urdf), fixed=True))
    scene.build(n_envs=4)
    n = arm.n_dofs
    q = np.zeros((4, n))
    q[:, :7] = [0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8]
    q[:, 1] += np.linspace(0.0, 0.3, 4)
    arm.set_dofs_kp(np.full(n, 100.0))
    arm.set_dofs_kv(np.full(n, 10.0))
    arm.set_dofs_position(q)
    arm.control_dofs_position(q)
    for _ in range(150):
        scene.step()
    out["panda_selfcol_qpos"] = arm.get_dofs_position()
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=None, help="also write the lines to this file")
    ap.add_argument("--scenes", default="contact,anymal,coupling,mpm,coupling_nograd,hull",
                    help="comma-separated subset")
    ap.add_argument("--precision", default="64", choices=("32", "64"))
    ap.add_argument("--npz", default=None, help="also save the tensors to this .npz file; --compare the npz of "
                    "another tree prints how far each tensor moved (for a change that moves rounding only)")
    ap.add_argument("--compare", default=None, help="an .npz written by --npz: print each tensor's largest "
                    "difference from it, relative to the tensor's largest magnitude")
    args = ap.parse_args()
    gs.init(backend=gs.cpu, precision=args.precision, logging_level="warning")
    lines, arrays = [], {}
    for name in args.scenes.split(","):
        tensors = {"contact": contact_scene, "anymal": anymal_scene, "coupling": coupling_scene, "mpm": mpm_scene,
                   "coupling_nograd": coupling_nograd_scene, "hull": hull_scene}[name]()
        hashes = []
        for k, v in tensors.items():
            h = _digest(v)
            hashes.append(h)
            lines.append(f"  {name}.{k} {tuple(v.shape)} {h}")
            arrays[f"{name}.{k}"] = np.asarray(v.detach().cpu().numpy() if isinstance(v, torch.Tensor) else v, dtype=np.float64)
        lines.append(f"{name} {hashlib.sha256(''.join(hashes).encode()).hexdigest()}")
        print("\n".join(lines[-len(hashes) - 1:]), flush=True)
    if args.out:
        with open(args.out, "w") as f:
            f.write("\n".join(lines) + "\n")
    if args.npz:
        np.savez(args.npz, **arrays)
    if args.compare:
        ref = np.load(args.compare)
        for k, a in arrays.items():
            b = ref[k]
            rel = np.abs(a - b).max() / max(np.abs(b).max(), 1e-300)
            print(f"  {k}: largest difference {rel:.2e} of its largest magnitude")


if __name__ == "__main__":
    main()
