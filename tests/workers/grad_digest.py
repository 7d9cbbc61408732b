"""Worker for tests/test_determinism.py: the gradients of a contact scene (3 envs) and of a two-way
coupled MPM scene, each rollout run and differentiated twice in this process; prints one JSON line
{scene: [sha256 of the gradients and loss, first pass; second pass]}. With the argument `envs32`, for
tests/test_threads.py: the contact scene at 32 envs, once, and whether its env loops run serially
({"cpu_threads", "serial", "contact": the gradients and the loss as numbers})."""
import hashlib
import json
import sys

import torch

import genesis_lite as gs

F64 = dict(dtype=torch.float64)


def digest(*tensors):
    h = hashlib.sha256()
    for t in tensors:
        h.update(t.detach().contiguous().numpy().tobytes())
    return h.hexdigest()


def contact_scene(n_envs=3, passes=2, digest=digest):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=5e-3, requires_grad=True))
    scene.add_entity(gs.morphs.Plane())
    box = scene.add_entity(gs.morphs.Box(pos=(0, 0, 0.1), size=(0.2, 0.2, 0.2)))
    ball = scene.add_entity(gs.morphs.Sphere(pos=(0.05, 0.02, 0.35), radius=0.08))
    scene.build(n_envs=n_envs)
    scale = [1.0, 0.5, -0.7] if n_envs == 3 else torch.linspace(1.0, -0.7, n_envs).tolist()
    out = []
    for _ in range(passes):
        v = torch.tensor([0.5, 0.2, -0.3, 0.1, 0.2, 0.3], **F64) * torch.tensor(scale, **F64).reshape(n_envs, 1)
        v.requires_grad_(True)
        mass = torch.tensor([1.3, 0.9, 1.1] * n_envs, **F64)[:n_envs].reshape(n_envs, 1).requires_grad_(True)
        scene.reset()
        box.set_dofs_velocity(v)
        ball.set_links_mass(mass)
        for _ in range(30):
            scene.step()
        loss = (box.get_pos() * torch.tensor([1.0, 2.0, 3.0], **F64)).sum() + (ball.get_pos() ** 2).sum()
        loss.backward()
        out.append(digest(v.grad, mass.grad, loss))
    return scene, out


def coupled_scene():
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=10, requires_grad=True),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.4, 0.4, 0.4),
                                                       grid_density=32))
    block = scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 0.15), size=(0.15, 0.15, 0.1)),
                             material=gs.materials.MPM.Elastic(E=3e4, nu=0.2))
    ball = scene.add_entity(gs.morphs.Sphere(pos=(0.2, 0.2, 0.24), radius=0.03), material=gs.materials.Rigid(rho=500))
    scene.build()
    out = []
    for _ in range(2):
        E = torch.tensor(3e4, **F64, requires_grad=True)
        v0 = torch.tensor([0.1, -0.2, -0.5], **F64, requires_grad=True)
        scene.reset()
        block.set_material(E=E)
        ball.set_dofs_velocity(torch.cat([v0, torch.zeros(3, **F64)]))
        for _ in range(10):
            scene.step()
        loss = ball.get_pos()[2] + (block.get_particles_pos()[:, 2] ** 2).mean()
        loss.backward()
        out.append(digest(E.grad, v0.grad, loss))
    return out


if __name__ == "__main__":
    gs.init(backend=gs.cpu, precision="64")
    if sys.argv[1:] == ["envs32"]:
        def values(*tensors):
            return torch.cat([t.detach().reshape(-1) for t in tensors]).tolist()

        scene, out = contact_scene(32, passes=1, digest=values)
        print(json.dumps({"cpu_threads": gs.cpu_threads, "serial": scene.rigid_solver.core.serial, "contact": out[0]}))
    else:
        print(json.dumps({"contact": contact_scene()[1], "coupled": coupled_scene()}))
