"""Issue #25: Genesis's tool (gs.materials.Tool, as its examples/differentiable_push.py uses it): a body that
moves only as it is told and pushes MPM material, differentiably; and the scene state a Genesis script
takes its loss from (scene.get_state().solvers_state[scene.solvers.index(scene.mpm_solver)]).

Checks against kinematics and against central finite differences in float64, not against the code: a
tool spun about a skew axis keeps its linear and angular velocity exactly as Genesis's kinematic tool does
(a real box would precess), falls through nothing and pushes nothing rigid; it pushes an elastic cube
and keeps its velocity; the gradients of a loss on the cube to the tool's per-step velocities and its
start position; the solver state of get_state is in the graph in a requires_grad scene and in
scene.solvers' order; bad input.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import genesis_lite as gs

F64 = dict(dtype=torch.float64)


def _quat_mul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def test_a_tool_keeps_the_velocity_it_was_given_and_touches_no_rigid_body():
    """A long box tool, turned, spun about a skew axis and moving down through the ground and a resting
    box: after 40 steps its pose is the kinematic one (p0 + v t; exp(w t) q0 with w in the world frame), its
    velocity unchanged, and the box it went through did not move."""
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=5e-3))
    scene.add_entity(gs.morphs.Plane())
    q0 = np.array([0.9, 0.3, -0.2, 0.25])
    q0 /= np.linalg.norm(q0)
    tool = scene.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 0.3), quat=tuple(q0), size=(0.3, 0.04, 0.1)),
                            material=gs.materials.Tool(friction=0.5))
    box = scene.add_entity(gs.morphs.Box(pos=(0.0, 0.0, 0.05), size=(0.1, 0.1, 0.1)))
    scene.build()
    for _ in range(20):  # the box settles on the plane
        scene.step()
    box_pos = box.get_pos().clone()
    p0 = tool.get_pos().numpy().copy()
    q0 = tool.get_quat().numpy().copy()
    v, w = np.array([0.2, -0.1, -2.0]), np.array([1.0, 2.0, -3.0])
    tool.set_velocity(vel=torch.tensor(v, **F64), ang=torch.tensor(w, **F64))
    n, dt = 40, 5e-3
    for _ in range(n):
        scene.step()
    t = n * dt
    np.testing.assert_allclose(tool.get_pos().numpy(), p0 + v * t, atol=1e-9)
    a = np.linalg.norm(w) * t
    dq = np.concatenate([[math.cos(a / 2)], math.sin(a / 2) * w / np.linalg.norm(w)])
    q = tool.get_quat().numpy()
    want = _quat_mul(dq, q0)
    assert min(np.abs(q - want).max(), np.abs(q + want).max()) < 1e-6, (q, want)
    st = tool.get_state()
    np.testing.assert_allclose(st.vel.numpy(), v, atol=1e-9)
    np.testing.assert_allclose(st.ang.numpy(), w, atol=1e-9)
    assert float(tool.get_pos()[2]) < -0.05  # went through the ground (0.3 - 2.0 * 0.2 m)
    # and through the box without moving it (it still settles into the penalty contact by microns)
    assert float((box.get_pos() - box_pos).abs().max()) < 1e-4


def _push_scene(requires_grad=False):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=5, requires_grad=requires_grad),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0.0, 0.0, 0.0), upper_bound=(0.4, 0.4, 0.3),
                                                       grid_density=32))
    scene.add_entity(gs.morphs.Plane())
    cube = scene.add_entity(gs.morphs.Box(pos=(0.2, 0.2, 3 / 32 + 0.04), size=(0.08, 0.08, 0.08)),
                            material=gs.materials.MPM.Elastic(E=2e4, nu=0.3, rho=500))
    tool = scene.add_entity(gs.morphs.Cylinder(pos=(0.2, 0.125, 3 / 32 + 0.04), radius=0.015, height=0.1),
                            material=gs.materials.Tool(friction=0.5))
    scene.build()
    return scene, cube, tool


def test_a_tool_pushes_the_material_and_keeps_its_velocity():
    scene, cube, tool = _push_scene()
    c0 = cube.get_pos().clone()
    v = torch.tensor([0.0, 0.5, 0.0], **F64)
    for _ in range(30):
        tool.set_velocity(vel=v)
        scene.step()
    np.testing.assert_allclose(tool.get_state().vel.numpy(), v.numpy(), atol=1e-12)  # no reaction
    np.testing.assert_allclose(tool.get_pos()[1].item(), 0.125 + 0.5 * 30 * 2e-3, atol=1e-9)
    d = cube.get_pos() - c0
    assert float(d[1]) > 5e-3  # pushed along +y by the tool
    assert abs(float(d[0])) < 0.2 * float(d[1])


def test_gradients_to_a_tool_s_velocities_and_start_match_finite_differences():
    """differentiable_push's pattern: a velocity tensor per step and the tool's start position, leaves that
    require grad; a loss on the particles read from scene.get_state() and on the block's centre. The scene
    is the gradient matrix's tool_in_block (the same solver classes as ball_in_block).

    First, get_state in a requires_grad scene is part of torch's graph (a loss on it has Genesis's gradient,
    not a silent zero) and in scene.solvers' order: the same loss through scene.get_state() and through the
    entity's getter gives the same gradient."""
    import gradient_cases

    b = gradient_cases.build_tool_in_block(gradient_cases.V())
    scene, block, tool = b.scene, b.ents["block"], b.ents["ball"]
    assert scene.solvers == [scene.rigid_solver, scene.mpm_solver]
    w = torch.tensor(np.random.default_rng(2).normal(size=(block.n_particles, 3)), **F64)
    grads = []
    for via_state in (True, False):
        scene.reset()
        v = torch.tensor([0.1, -0.05, -0.8, 0.0, 0.0, 0.0], **F64).requires_grad_(True)
        tool.set_dofs_velocity(v)
        for _ in range(3):
            scene.step()
        if via_state:
            state = scene.get_state()
            st = state.solvers_state[scene.solvers.index(scene.mpm_solver)]
            assert st.pos.shape == (1, block.n_particles, 3) and st.active.shape == (1, block.n_particles)
            assert bool(st.active.all())
            assert state.solvers_state[scene.solvers.index(scene.rigid_solver)].qpos.shape[-1] == 7
            x = st.pos[0]
        else:
            x = block.get_particles_pos()
        (w * x).sum().backward()
        grads.append(v.grad.clone())
    assert float(grads[1][:3].abs().max()) > 1e-3
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-12, atol=0)

    rng = np.random.default_rng(5)
    T = 5
    goal = torch.tensor([0.2, 0.1, 0.05], **F64)
    p_start = tool.get_pos().detach().clone()

    def rollout(vs, p0):
        scene.reset()
        tool.set_position(p0)
        loss = 0.0
        for i in range(T):
            tool.set_velocity(vel=vs[i])
            scene.step()
            if i == 2:
                st = scene.get_state().solvers_state[scene.solvers.index(scene.mpm_solver)]
                loss = loss + ((st.pos[st.active] - goal) ** 2).sum()
        return loss + 10 * ((block.get_state().pos - goal) ** 2).sum()

    inputs = {"vs": torch.tensor(rng.normal(scale=0.2, size=(T, 3)) + [0.1, -0.05, -0.8], **F64),
              "p0": p_start + torch.tensor([0.002, -0.001, 0.0], **F64)}
    leaves = {k: x.clone().requires_grad_(True) for k, x in inputs.items()}
    rollout(**leaves).backward()
    for k, x in inputs.items():
        d = torch.tensor(rng.normal(size=x.shape), **F64)
        h = 1e-6
        with torch.no_grad():
            fd = (rollout(**{**inputs, k: x + h * d}).item() - rollout(**{**inputs, k: x - h * d}).item()) / (2 * h)
        ad = (leaves[k].grad * d).sum().item()
        assert abs(ad) > 1e-6, k
        assert abs(ad - fd) <= 2e-6 * abs(fd), (k, ad, fd)


def test_gs_tensor_zero_grad():
    g = gs.tensor([1.0, 2.0], requires_grad=True)
    (g * 3).sum().backward()
    assert float(g.grad.abs().sum()) == 6.0
    g.zero_grad()  # Genesis's gs.Tensor.zero_grad
    assert float(g.grad.abs().sum()) == 0.0


def test_bad_tools_are_clear_errors():
    with pytest.raises(ValueError, match="Tool"):
        gs.materials.Tool(friction=-1.0)
    with pytest.raises(TypeError, match="collision"):
        gs.materials.Tool(collision=1)
    scene = gs.Scene()
    with pytest.raises(gs.GenesisException, match="moves"):
        scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1), fixed=True), material=gs.materials.Tool())
    tool = scene.add_entity(gs.morphs.Box(size=(0.1, 0.1, 0.1)), material=gs.materials.Tool())
    scene.build()
    with pytest.raises(gs.GenesisException, match="vel= or ang="):
        tool.set_velocity()
