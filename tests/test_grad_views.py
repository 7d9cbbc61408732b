"""Controls given as views of a larger tensor that requires grad (`controls[t]`): genesis_lite routes their
gradients to the base itself (genesis_lite/grad/views.py: one fill of the base per backward pass instead of
one per step). The reference is torch's own backward of the same views: each test feeds the views once
through `.clone()` (a copy, which the routing leaves alone, so torch's view backward runs) and once as they are,
in the same scene with the default options, and asks for the same gradients: the routing's bookkeeping (views
that share a base, several losses and backward passes, a pass that raised, a base written in place between
steps, hooks). One test holds routed gradients against central differences in float64 (those of small control
tensors, which keep torch's backward, are in tests/test_gradients.py)."""
import numpy as np
import pytest
import torch

import genesis_lite as gs
from genesis_lite.grad.views import ROUTE_MIN

from conftest import ASSETS_DIR

ARM = str(ASSETS_DIR / "urdf" / "skew_arm.urdf")  # 3 revolute joints on skewed axes, offset COMs
T = 8
F64 = dict(dtype=torch.float64)


def _wide(rows):
    """Columns for a (T, rows, cols) control tensor large enough for the routing (views.ROUTE_MIN)."""
    return -(-2 * ROUTE_MIN // (T * rows))


WIDE = _wide(1)  # columns of a (T, WIDE) control tensor


def _scene(n_envs):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True))
    arm = scene.add_entity(gs.morphs.URDF(file=ARM, fixed=True))
    scene.build(n_envs=n_envs)
    return scene, arm


@pytest.fixture(scope="module")
def scenes():
    return {}


def _get(scenes, n_envs):
    if n_envs not in scenes:
        scenes[n_envs] = _scene(n_envs)
    return scenes[n_envs]


def _names(t):
    """The names of the nodes of t's backward graph."""
    seen, todo, names = set(), [t.grad_fn], []
    while todo:
        f = todo.pop()
        if f is None or f in seen:
            continue
        seen.add(f)
        names.append(f.name())
        todo += [g for g, _ in f.next_functions]
    return names


def _controls(shape, seed=0):
    rng = np.random.default_rng(seed)
    return torch.tensor(rng.uniform(-2, 2, shape), **F64).requires_grad_()


def _grads(loss_fn, leaves, copy):
    for x in leaves:
        x.grad = None
    loss = loss_fn(copy)
    loss.backward()
    return loss, [x.grad.clone() for x in leaves]


@pytest.mark.parametrize("kind", ["torch leaf", "gs leaf", "computed"])
@pytest.mark.parametrize("n_envs", [0, 3])
def test_views_of_one_base_in_several_setters_and_the_loss(scenes, n_envs, kind):
    """Two slices of each row to two setters (forces on the first two dofs, a velocity target on the last), a
    fourth column no setter reads, the base also in the loss: the same gradients as torch's. The base a torch
    leaf, a gs.tensor leaf (an alias of a tensor without grad) or computed from a leaf (its gradient reaches
    the leaf through the computation)."""
    scene, arm = _get(scenes, n_envs)
    n = arm.n_dofs
    lead = (n_envs,) if n_envs else ()
    leaf = _controls((T,) + lead + (_wide(max(n_envs, 1)),))
    if kind == "gs leaf":
        leaf = gs.tensor(leaf.detach().clone(), dtype=torch.float64, requires_grad=True)
    q0 = torch.tensor(np.random.default_rng(1).uniform(-0.5, 0.5, n), **F64).requires_grad_()

    def loss_fn(copy):
        nonlocal c
        c = leaf * 1.5 - 0.25 if kind == "computed" else leaf
        own = (lambda v: v.clone()) if copy else (lambda v: v)
        scene.reset()
        arm.set_dofs_position(q0)
        for t in range(T):
            arm.control_dofs_force(own(c[t, ..., :2]), dofs_idx_local=[0, 1])
            arm.control_dofs_velocity(own(c[t, ..., 2:3]), dofs_idx_local=[2])
            scene.step()
        return (arm.get_links_pos()[..., -1, :] ** 2).sum() + 0.1 * (c ** 2).sum() + c[0].sum()

    c = None
    loss_ref, ref = _grads(loss_fn, [leaf, q0], copy=True)
    loss, got = _grads(loss_fn, [leaf, q0], copy=False)
    assert "_ViewNodeBackward" in _names(loss) and "_ViewNodeBackward" not in _names(loss_ref)
    assert float(loss) == float(loss_ref)
    for g, r in zip(got, ref):
        assert torch.allclose(g, r, rtol=1e-13, atol=1e-15), (g - r).abs().max()
    assert float(ref[0][:, ..., 2].abs().min()) > 0  # the velocity targets' slice gets a gradient
    row0 = (torch.arange(T) == 0).to(c.dtype).reshape((T,) + (1,) * (c.dim() - 1))
    scale = 1.5 if kind == "computed" else 1.0
    assert torch.allclose(got[0][:, ..., 3:], scale * (0.2 * c.detach()[:, ..., 3:] + row0), rtol=1e-14, atol=0)


def test_two_losses_and_backward_passes_of_one_rollout(scenes):
    """Two backward passes over one rollout (a loss at step T/2 with retain_graph, then one at T): each pass
    adds the base's gradient, as torch's."""
    scene, arm = _get(scenes, 0)
    c = _controls((T, WIDE), seed=2)

    def run(copy):
        c.grad = None
        own = (lambda v: v.clone()) if copy else (lambda v: v)
        scene.reset()
        for t in range(T):
            arm.control_dofs_force(own(c[t, :arm.n_dofs]))
            scene.step()
            if t == T // 2:
                mid = (arm.get_dofs_position() ** 2).sum()
        end = (arm.get_links_pos()[-1] ** 2).sum()
        mid.backward(retain_graph=True)
        first = c.grad.clone()
        end.backward()
        return first, c.grad.clone()

    ref, got = run(True), run(False)
    for g, r in zip(got, ref):
        assert torch.allclose(g, r, rtol=1e-13, atol=1e-15), (g - r).abs().max()
    assert float(ref[0][T // 2 + 1:].abs().max()) == 0 and float(ref[1][T // 2 + 1:].abs().max()) > 0
    assert float(ref[1][:, arm.n_dofs:].abs().max()) == 0


def test_a_backward_pass_that_raised_leaves_nothing_in_the_next(scenes):
    """A hook raises half way through a backward pass (the later steps' views have added their rows by
    then): the next pass over the same graph gives torch's gradient, not that plus the stopped pass's rows."""
    scene, arm = _get(scenes, 0)
    c = _controls((T, WIDE), seed=3)
    k = torch.ones((), **F64).requires_grad_()
    fire = [True]

    def stop(g):
        if fire[0]:
            fire[0] = False
            raise RuntimeError("stop here")
        return g

    k.register_hook(stop)

    def run(copy):
        c.grad, k.grad, fire[0] = None, None, True
        own = (lambda v: v.clone()) if copy else (lambda v: v)
        scene.reset()
        for t in range(T):
            x = own(c[t, :arm.n_dofs])
            arm.control_dofs_force(x * k if t == 2 else x)
            scene.step()
        loss = (arm.get_links_pos()[-1] ** 2).sum()
        with pytest.raises(RuntimeError, match="stop here"):
            loss.backward(retain_graph=True)
        assert not fire[0]
        loss.backward()
        return c.grad.clone()

    ref, got = run(True), run(False)
    assert torch.allclose(got, ref, rtol=1e-13, atol=1e-15), (got - ref).abs().max()


def test_a_base_written_in_place_between_steps(scenes):
    """A policy writes each step's row into a preallocated tensor (u[t] = W s_t, in place) and the step takes
    the view u[t]: every version of u has its own history, so W's gradient must reach each row's."""
    scene, arm = _get(scenes, 0)
    n = arm.n_dofs
    W = torch.tensor(np.random.default_rng(4).uniform(-3, 3, (n, 2 * n)), **F64).requires_grad_()

    def run(copy):
        W.grad = None
        own = (lambda v: v.clone()) if copy else (lambda v: v)
        scene.reset()
        u = torch.zeros(T, WIDE, **F64)
        for t in range(T):
            s = torch.cat([arm.get_dofs_position(), arm.get_dofs_velocity()]).as_subclass(torch.Tensor)
            u[t, :n] = W @ s + 1.0
            arm.control_dofs_force(own(u[t, :n]))
            scene.step()
        (arm.get_links_pos()[-1] ** 2).sum().backward()
        return W.grad.clone()

    ref, got = run(True), run(False)
    assert float(ref.abs().max()) > 0
    assert torch.allclose(got, ref, rtol=1e-12, atol=1e-15), (got - ref).abs().max()


def test_a_hooked_view_stays_in_the_graph(scenes):
    """A view with a hook (or retain_grad) is the user's to watch: it keeps torch's own backward, and the hook
    sees each step's gradient."""
    scene, arm = _get(scenes, 0)
    c = _controls((T, WIDE), seed=5)
    seen = []
    scene.reset()
    for t in range(T):
        x = c[t, :arm.n_dofs]
        x.register_hook(lambda g: seen.append(g.clone()))
        arm.control_dofs_force(x)
        scene.step()
    (arm.get_links_pos()[-1] ** 2).sum().backward()
    assert len(seen) == T
    assert torch.allclose(torch.stack(seen[::-1]), c.grad[:, :arm.n_dofs], rtol=0, atol=0)


@pytest.mark.parametrize("view", [
    lambda c: c[1], lambda c: c[:, 2], lambda c: c[1:3, ::2], lambda c: c.transpose(0, 1)[1],
    lambda c: c[0:1, :2].expand(3, 2, 50), lambda c: c.unfold(2, 3, 1)[0], lambda c: c.unbind(1)[2]])
def test_any_view_geometry_gets_torchs_gradient(view):
    """routed() itself, on views of every kind (strided, transposed, and overlapping ones, which it must leave
    to torch): several views of one base, each weighted, give torch's gradient of the base."""
    from genesis_lite.grad.views import routed

    rng = np.random.default_rng(6)
    c = torch.tensor(rng.normal(size=(30, 40, 50)), **F64).requires_grad_()  # large enough to be routed
    xs = [view(c) for _ in range(3)]
    ws = [torch.tensor(rng.normal(size=x.shape), **F64) for x in xs]
    ref = torch.autograd.grad(sum((x * w).sum() for x, w in zip(xs, ws)), c)[0]
    nodes = {}
    got = torch.autograd.grad(sum((routed(x, nodes) * w).sum() for x, w in zip(xs, ws)), c)[0]
    assert torch.allclose(got, ref, rtol=1e-14, atol=1e-15), (got - ref).abs().max()


def test_a_small_base_keeps_torchs_backward(scenes):
    """Below views.ROUTE_MIN elements outside the view (the README's 100 x n controls at 1 env) torch's own
    backward of the view is cheaper than the routing's two nodes: the view stays in the graph."""
    scene, arm = _get(scenes, 0)
    c = _controls((T, arm.n_dofs), seed=7)
    scene.reset()
    for t in range(T):
        arm.control_dofs_force(c[t])
        scene.step()
    loss = (arm.get_links_pos()[-1] ** 2).sum()
    assert "_ViewNodeBackward" not in _names(loss) and "SelectBackward0" in _names(loss)
    loss.backward()
    assert float(c.grad.abs().min()) > 0


@pytest.mark.parametrize("n_envs", [0, 3])
def test_routed_gradients_match_finite_differences(scenes, n_envs):
    """Central differences in float64, default options: the controls are computed from two small leaves (a
    torque profile over the steps times a torque per dof, padded into a base large enough to be routed), fed as
    views c[t, ..., :n] each step; the loss reads the links' poses and velocities. gs.grad.check differences the
    leaves, so the routed views' gradients are checked through the computation to them."""
    scene, arm = _get(scenes, n_envs)
    n = arm.n_dofs
    lead = (n_envs,) if n_envs else ()
    pad = _wide(max(n_envs, 1)) - n
    rng = np.random.default_rng(8)
    S = torch.tensor(rng.uniform(0.5, 1.5, (T,) + lead), **F64)
    Wd = torch.tensor(rng.uniform(-2.0, 2.0, n), **F64)
    graphs = []

    def rollout(S, Wd):
        c = torch.cat([S[..., None] * Wd, torch.zeros((T,) + lead + (pad,), **F64)], -1)
        scene.reset()
        for t in range(T):
            arm.control_dofs_force(c[t, ..., :n])
            scene.step()
        loss = (arm.get_links_pos()[..., -1, :] ** 2).sum() + 0.1 * (arm.get_dofs_velocity() ** 2).sum()
        graphs.append(_names(loss))
        return loss

    report = gs.grad.check(rollout, {"S": S, "Wd": Wd}, tol=1e-6)
    print(report)
    assert report.ok, str(report)
    assert "_ViewNodeBackward" in graphs[0]  # the autograd rollout took the routing
