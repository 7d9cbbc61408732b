"""Fault injection at the API: what a user gets when the simulation or the input goes wrong (issue #21).

1. NaN / inf in the state is caught at the step where it appears, per env, for rigid (the fused
   no-gradient step and the gradient path) and MPM. The first non-finite step is observed
   independently, through the getters of a scene whose check is off (nan_policy="off"), and the
   default scene must raise exactly there, naming the env, the entity and the step (before, the fused
   path checked every 16 steps and blamed another step; a batched mean over envs went NaN silently).
   With nan_policy="mask" the failed env is reported and keeps going as NaN while the others are
   bitwise those of a clean run; scene.get_error_envs_mask() (and Genesis's
   scene.rigid_solver.get_error_envs_mask()) marks it and scene.reset(envs_idx=mask) restores its
   build-time state bitwise, leaving the other envs bitwise untouched. On the gradient path the other
   envs get exactly the gradients of a clean run, and a loss that depends on the failed env raises a
   clear error instead of returning NaN.
2. Physically impossible parameters are refused where they are set: an inertia that is not symmetric
   positive definite or breaks the triangle inequality (the user's case gained 0.23 J -> 693 J with no
   force), a zero mass (the user's NaN box), negative damping / armature / gains, at URDF load and in
   the setters; repeated indices in dofs_idx_local / envs_idx. A valid parameter that requires grad
   keeps its gradient (the checks read detached copies).
3. Clear messages: every getter before build(), and loss.backward() on a scene without gradients.

Cost (2 shared cores): 15 s on a warm kernel cache (the rigid scenes share one compiled core: a box or
an arm without contacts, <= 16 envs; the MPM scenes are test_mpm.py's cube); 29-36 s on the first runs
after the fused step's and the MPM check's kernels changed (their compiles).
"""
import inspect
import logging
import re
import textwrap

import numpy as np
import pytest
import torch

import genesis_lite as gs
from genesis_lite.errors import GenesisException, SimulationNaNError

from conftest import ASSETS_DIR

F64 = dict(dtype=torch.float64)
ARM = str(ASSETS_DIR / "urdf" / "arm.urdf")
TAU = 1e30  # N m on two axes of a flat box: its gyroscopic term overflows after a few steps


def _box_scene(n_envs=3, **sim):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, **sim),
                     rigid_options=gs.options.RigidOptions(enable_collision=False))
    box = scene.add_entity(gs.morphs.Box(size=(0.3, 0.2, 0.1), pos=(0.0, 0.0, 1.0)), name="box")
    scene.build(n_envs=n_envs)
    return scene, box


def _torque_env1(box, n_envs=3):
    f = torch.zeros(n_envs, 6, **F64)
    f[1, 3] = f[1, 4] = TAU
    box.control_dofs_force(f)


def _finite(box):
    return (torch.isfinite(box.get_qpos()).all(-1) & torch.isfinite(box.get_dofs_velocity()).all(-1)).tolist()


# --------------------------------------------------------------------------- 1. NaN per step, per env
@pytest.fixture(scope="module")
def observed():
    """The step at which env 1's state first becomes non-finite, seen through the getters with the
    scene's check off; and the clean trajectory of envs 0 and 2."""
    scene, box = _box_scene(nan_policy="off")
    clean = []
    for _ in range(8):
        scene.step()
        clean.append(box.get_qpos().clone())
    scene.reset()
    _torque_env1(box)
    first = None
    for k in range(1, 9):
        scene.step()
        ok = _finite(box)
        assert ok[0] and ok[2], "env 1's torque reached another env"
        if not ok[1] and first is None:
            first = k
    assert first is not None and first > 1, first
    return first, clean


def test_rigid_nan_raises_at_its_step_naming_env_entity_and_step(observed):
    first, _ = observed
    scene, box = _box_scene()  # default options: nan_policy="raise"
    _torque_env1(box)
    with pytest.raises(SimulationNaNError) as e:
        for _ in range(20):
            scene.step()
    msg = str(e.value)
    assert scene.t == first, f"raised after step {scene.t}; the state became non-finite at step {first}"
    assert re.search(rf"\bstep {first}\b", msg) and "env [1]" in msg and "'box'" in msg, msg
    assert re.search(r"q(pos|vel)\[\d\]", msg) and re.search(r"dt|substeps", msg), msg
    assert "nan_policy='mask'" in msg, msg  # says how to let the other envs go on
    assert scene.get_error_envs_mask().tolist() == [False, True, False]


def test_rigid_nan_mask_policy_reports_and_resets_the_failed_env_only(observed, caplog):
    first, clean = observed
    scene, box = _box_scene(nan_policy="mask")
    q0 = box.get_qpos().clone()
    _torque_env1(box)
    with caplog.at_level(logging.WARNING, logger="genesis_lite"):
        for k in range(1, 9):
            scene.step()
            assert scene.get_error_envs_mask().tolist() == [False, k >= first, False]
            q = box.get_qpos()
            assert torch.equal(q[[0, 2]], clean[k - 1][[0, 2]])  # the other envs: a clean run, bitwise
    warned = [r.getMessage() for r in caplog.records if "NaN" in r.getMessage()]
    assert len(warned) == 1 and f"step {first}" in warned[0] and "env [1]" in warned[0], warned
    mask = scene.rigid_solver.get_error_envs_mask()  # Genesis's name
    assert mask.dtype == torch.bool and mask.tolist() == [False, True, False]
    before = box.get_qpos().clone(), box.get_dofs_velocity().clone()
    scene.reset(envs_idx=mask)
    q, v = box.get_qpos(), box.get_dofs_velocity()
    assert torch.equal(q[1], q0[1]) and torch.equal(v[1], torch.zeros(6, **F64))  # build-time state
    assert torch.equal(q[[0, 2]], before[0][[0, 2]]) and torch.equal(v[[0, 2]], before[1][[0, 2]])
    assert scene.get_error_envs_mask().tolist() == [False, False, False]
    box.control_dofs_force(torch.zeros(6, **F64))
    scene.step()
    assert all(_finite(box))
    with pytest.raises(GenesisException, match="shape"):
        scene.reset(envs_idx=torch.tensor([True, False]))


def test_batched_mean_over_envs_is_never_silently_nan(observed):
    """The user's report: one NaN env made a mean over envs NaN with no error."""
    first, _ = observed
    scene, box = _box_scene()
    _torque_env1(box)
    with pytest.raises(SimulationNaNError, match=r"env \[1\]"):
        for _ in range(first + 1):
            scene.step()
            assert torch.isfinite(box.get_pos().mean(0)).all()  # every mean read before the error is finite


@pytest.fixture(scope="module")
def grad_box():
    return _box_scene(n_envs=2, requires_grad=True, nan_policy="mask")


def _grad_rollout(scene, box, bad, loss_envs, steps=3):
    scene.reset()
    v = torch.tensor([[0.3, 0.0, 0.1, 0.0, 0.2, 0.0]] * 2, **F64)
    if bad:
        v[1, 3:] = 1e200  # its squares overflow in the first step
    v.requires_grad_(True)
    box.set_dofs_velocity(v)
    for _ in range(steps):
        scene.step()
    loss = (box.get_pos()[loss_envs] ** 2).sum()
    return v, loss


def test_gradient_path_nan_is_caught_per_env_and_backward_is_clean_or_clear(grad_box):
    scene, box = grad_box
    v, loss = _grad_rollout(scene, box, False, [0])
    loss.backward()
    ref = v.grad.clone()
    assert torch.isfinite(ref).all() and ref[0].abs().sum() > 0
    v, loss = _grad_rollout(scene, box, True, [0])
    assert scene.get_error_envs_mask().tolist() == [False, True]
    assert _finite(box) == [True, False]
    loss.backward()
    assert torch.equal(v.grad, ref), (v.grad, ref)  # env 0 exactly as in a clean run, env 1 zero
    v, loss = _grad_rollout(scene, box, True, [0, 1])
    with pytest.raises(SimulationNaNError, match=r"env.*1.*NaN since step 1.*out of the loss"):
        loss.backward()
    # a valid inertia that requires grad passes the checks and receives its gradient
    scene.reset()
    inertia = torch.diag(torch.tensor([0.05, 0.08, 0.1], **F64)).requires_grad_(True)
    box.set_links_inertia(inertia.unsqueeze(0))
    box.set_dofs_velocity(torch.tensor([0.0, 0.0, 0.0, 1.0, 2.0, 0.5], **F64))
    for _ in range(3):
        scene.step()
    box.get_quat()[:, 1].sum().backward()
    assert inertia.grad is not None and torch.isfinite(inertia.grad).all() and inertia.grad.abs().sum() > 0


def test_gradient_path_raise_policy_names_env_and_step():
    scene, box = _box_scene(n_envs=2, requires_grad=True)
    v = torch.zeros(2, 6, **F64)
    v[1, 3:] = 1e200
    box.set_dofs_velocity(v.requires_grad_(True))
    with pytest.raises(SimulationNaNError, match=r"step 1 in env \[1\].*'box'"):
        scene.step()


def test_gradient_path_finite_state_whose_sum_overflows_is_not_reported():
    """The gradient path's NaN watch first sums the state (a NaN or an infinity makes the sum non-finite); a
    finite state whose sum overflows must go on to the per-entry check and pass it, not be reported."""
    scene, box = _box_scene(n_envs=2, requires_grad=True)
    q = torch.tensor([[1e308, 1e308, 1.0, 1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]], **F64)
    box.set_qpos(q.requires_grad_(True))  # an input that requires grad: the step takes the gradient path
    for _ in range(2):
        scene.step()
    p = box.get_pos().detach()
    assert torch.isfinite(p).all() and p[0, 0] == 1e308 and float(p.sum()) == float("inf")
    assert scene.get_error_envs_mask().tolist() == [False, False]


def _mpm_scene(n_envs=2, **sim):
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=2e-3, substeps=10, **sim),
                     mpm_options=gs.options.MPMOptions(lower_bound=(0, 0, 0), upper_bound=(0.5, 0.5, 0.5),
                                                       grid_density=32))
    cube = scene.add_entity(gs.morphs.Box(pos=(0.25, 0.25, 0.2), size=(0.06, 0.06, 0.06)),
                            material=gs.materials.MPM.Elastic(E=2e4, nu=0.3), name="jelly")
    scene.build(n_envs=n_envs)
    return scene, cube


def _mpm_finite(cube):
    return (torch.isfinite(cube.get_particles_pos()).all((-1, -2))
            & torch.isfinite(cube.get_particles_vel()).all((-1, -2))).tolist()


def test_mpm_nan_per_step_per_env_raise_and_mask():
    scene, cube = _mpm_scene(nan_policy="mask")
    x_build = cube.get_particles_pos().clone()
    clean = []
    for _ in range(4):
        scene.step()
        clean.append(cube.get_particles_pos().clone())
    scene.reset()
    cube.set_velocity(torch.tensor([[0.0, 0.0, 0.0], [1e200, 0.0, 0.0]], **F64))
    first = None
    for k in range(1, 5):
        scene.step()
        ok = _mpm_finite(cube)
        if not ok[1] and first is None:
            first = k
        assert ok[0] and torch.equal(cube.get_particles_pos()[0], clean[k - 1][0])  # env 0 bitwise clean
        assert scene.get_error_envs_mask().tolist() == [False, first is not None]
    assert first is not None
    x_before = cube.get_particles_pos().clone()
    scene.reset(envs_idx=[1])
    x = cube.get_particles_pos()
    assert torch.equal(x[1], x_build[1]) and torch.equal(x[0], x_before[0])
    assert scene.get_error_envs_mask().tolist() == [False, False] and _mpm_finite(cube) == [True, True]

    scene, cube = _mpm_scene()  # default: raise
    cube.set_velocity(torch.tensor([[0.0, 0.0, 0.0], [1e200, 0.0, 0.0]], **F64))
    with pytest.raises(SimulationNaNError, match=rf"step {first} in env \[1\].*MPM entity 'jelly'"):
        for _ in range(20):
            scene.step()
    assert scene.t == first

    # the gradient path (the state is a torch tensor in the graph): the same step, the same env
    scene, cube = _mpm_scene(requires_grad=True)
    cube.set_velocity(torch.tensor([[0.0, 0.0, 0.0], [1e200, 0.0, 0.0]], **F64, requires_grad=True))
    with pytest.raises(SimulationNaNError, match=rf"step {first} in env \[1\].*MPM entity 'jelly'"):
        for _ in range(20):
            scene.step()
    assert scene.t == first


def test_nan_policy_is_validated():
    with pytest.raises(ValueError, match="nan_policy.*'raise', 'mask' or 'off'"):
        gs.options.SimOptions(nan_policy="ignore")


# --------------------------------------------------------------------------- 2. nonsense refused
@pytest.fixture(scope="module")
def arm_box():
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01),
                     rigid_options=gs.options.RigidOptions(enable_collision=False))
    arm = scene.add_entity(gs.morphs.URDF(file=ARM, fixed=True), name="arm")
    box = scene.add_entity(gs.morphs.Box(size=(0.3, 0.2, 0.1), pos=(1.0, 0.0, 1.0)), name="box")
    scene.build(n_envs=2)
    return scene, arm, box


@pytest.mark.parametrize("inertia, why", [
    (np.diag([0.01, 0.01, 0.05]), "triangle"),  # I1 + I2 < I3: the user's energy-gaining tensor
    (np.array([[0.02, 0.01, 0.0], [0.0, 0.02, 0.0], [0.0, 0.0, 0.02]]), "not symmetric"),
    (np.diag([0.02, -0.01, 0.02]), "not positive definite"),
    (np.zeros((3, 3)), "not positive definite"),  # with mass 0: the user's NaN box
])
def test_impossible_inertia_is_refused_in_the_setter(arm_box, inertia, why):
    scene, _, box = arm_box
    before = box.get_links_inertia().clone()
    with pytest.raises(GenesisException, match=rf"entity 'box': inertia of link 'box' in env 1.*{why}.*I1 \+ I2 >= I3"):
        box.set_links_inertia(torch.as_tensor(inertia, **F64)[None], envs_idx=[1])
    assert torch.equal(box.get_links_inertia(), before)
    box.set_links_inertia(torch.diag(torch.tensor([0.01, 0.02, 0.025], **F64))[None], envs_idx=[1])  # valid
    scene.reset()
    box.set_links_inertia(before[:, 0:1])


def test_impossible_masses_gains_and_damping_are_refused(arm_box):
    _, arm, box = arm_box
    with pytest.raises(GenesisException, match=r"entity 'box': link masses must be > 0 for a link that moves, got 0.0 for link 'box' \(free joint\) in env 0"):
        box.set_links_mass([0.0])
    with pytest.raises(GenesisException, match=r"'arm': link masses must be >= 0, got -1.0 for link '\w+' in env 1"):
        arm.set_links_mass([-1.0], links_idx_local=[2], envs_idx=[1])
    n = arm.n_links
    with pytest.raises(GenesisException, match=rf"'arm': link masses must be > 0 .* link '{arm.links[-1].name}' "
                                               r"\(revolute joint\) in env 0, which has no massive link below it"):
        arm.set_links_mass([0.0], links_idx_local=[n - 1])
    m = arm.get_links_mass(links_idx_local=[n - 2]).clone()
    arm.set_links_mass([0.0], links_idx_local=[n - 2])  # a massless intermediate link is allowed (as at load)
    arm.set_links_mass(m, links_idx_local=[n - 2])
    for setter in ("damping", "armature", "kp", "kv", "frictionloss", "stiffness"):
        with pytest.raises(GenesisException, match=rf"'arm': {setter} must be >= 0, got -0.5 for dof 2 "
                                                   r"\(joint '\w+'\) in env 0"):
            getattr(arm, f"set_dofs_{setter}")([0.1, 0.1, -0.5, 0.1])
    with pytest.raises(GenesisException, match=r"friction must be finite and >= 0"):
        box.set_friction(-0.2)
    with pytest.raises(GenesisException, match=r"'arm': force range of dof 1.*lower > upper"):
        arm.set_dofs_force_range([0.0, 2.0], [1.0, 1.0], dofs_idx_local=[0, 1])


def test_repeated_indices_are_refused_naming_them(arm_box):
    _, arm, _ = arm_box
    with pytest.raises(GenesisException, match=r"dofs_idx_local \[0, 2, 2\] repeats \[2\]"):
        arm.set_dofs_kp([1.0, 2.0, 3.0], dofs_idx_local=[0, 2, 2])
    with pytest.raises(GenesisException, match=r"envs_idx \[1, 1\] repeats \[1\]"):
        arm.set_dofs_velocity(torch.zeros(2, 4, **F64), envs_idx=[1, 1])
    with pytest.raises(GenesisException, match=r"dofs_idx_local \[1, 1\] repeats \[1\]"):
        arm.control_dofs_force([1.0, 2.0], dofs_idx_local=[1, 1])


def _urdf(tmp_path, inertial):
    text = f"""<robot name="probe">
      <link name="base"><inertial><mass value="1"/><inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/>
        </inertial></link>
      <link name="rod">{inertial}</link>
      <joint name="hinge" type="revolute"><parent link="base"/><child link="rod"/><axis xyz="0 0 1"/>
        <limit lower="-1" upper="1" effort="10" velocity="1"/></joint>
    </robot>"""
    path = tmp_path / "probe.urdf"
    path.write_text(textwrap.dedent(text))
    return str(path)


@pytest.mark.parametrize("inertial, match", [
    ('<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.05" ixy="0" ixz="0" iyz="0"/></inertial>',
     r"link 'rod'.*I1 \+ I2 < I3"),
    ('<inertial><mass value="0"/><inertia ixx="0" iyy="0" izz="0" ixy="0" ixz="0" iyz="0"/></inertial>',
     r"link 'rod'.*mass 0.0 kg.*positive"),
])
def test_impossible_urdf_inertial_is_refused_at_load(tmp_path, inertial, match):
    scene = gs.Scene()
    with pytest.raises(GenesisException, match=match):
        scene.add_entity(gs.morphs.URDF(file=_urdf(tmp_path, inertial), fixed=True))


def test_massless_intermediate_link_and_point_mass_are_accepted_at_load(tmp_path):
    """A gimbal's massless middle link (massive links below it) and a point-mass pendulum bob (inertia
    0 about its COM, off the axis) are valid models."""
    text = """<robot name="gimbal">
      <link name="base"><inertial><mass value="1"/><inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/>
        </inertial></link>
      <link name="mid"/>
      <link name="bob"><inertial><origin xyz="0 0 -0.5"/><mass value="1"/>
        <inertia ixx="0" iyy="0" izz="0" ixy="0" ixz="0" iyz="0"/></inertial></link>
      <joint name="a" type="revolute"><parent link="base"/><child link="mid"/><axis xyz="1 0 0"/>
        <limit lower="-1" upper="1" effort="10" velocity="1"/></joint>
      <joint name="b" type="revolute"><parent link="mid"/><child link="bob"/><axis xyz="0 1 0"/>
        <limit lower="-1" upper="1" effort="10" velocity="1"/></joint>
    </robot>"""
    path = tmp_path / "gimbal.urdf"
    path.write_text(textwrap.dedent(text))
    ent = gs.Scene().add_entity(gs.morphs.URDF(file=str(path), fixed=True))
    assert ent.n_dofs == 2


# --------------------------------------------------------------------------- 3. clear messages
def test_every_getter_before_build_says_to_build():
    scene = gs.Scene()
    ent = scene.add_entity(gs.morphs.URDF(file=ARM, fixed=True), name="arm")
    getters = [n for n, f in inspect.getmembers(type(ent), inspect.isfunction)
               if n.startswith("get_") and n not in ("get_joint", "get_link")]
    assert len(getters) >= 25, getters
    args = {"get_jacobian": (ent.links[-1],)}  # getters with a required argument
    for name in getters:
        with pytest.raises(GenesisException, match=r"scene\.build\(\)"):
            getattr(ent, name)(*args.get(name, ()))
    jelly = scene.add_entity(gs.morphs.Box(pos=(0.5, 0.5, 0.4), size=(0.1, 0.1, 0.1)),
                             material=gs.materials.MPM.Elastic(), name="jelly")
    for name, f in inspect.getmembers(type(jelly), inspect.isfunction):
        if name.startswith("get_"):
            with pytest.raises(GenesisException, match=r"'jelly'.*scene\.build\(\)"):
                f(jelly, *{"get_material": ["E"], "get_particles_in_bbox": [(0, 0, 0), (1, 1, 1)]}.get(name, []))
    for name in ("get_state", "get_error_envs_mask", "step", "reset"):
        with pytest.raises(GenesisException, match=r"scene\.build\(\)"):
            getattr(scene, name)()


def test_backward_without_gradients_says_how_to_get_them(arm_box):
    scene, _, box = arm_box
    scene.reset()
    scene.step()
    loss = box.get_pos().sum()
    with pytest.raises(GenesisException, match=r"SimOptions\(requires_grad=True\)"):
        loss.backward()
    with pytest.raises(GenesisException, match=r"requires grad but the scene was built without gradients.*"
                                               r"SimOptions\(requires_grad=True\)"):
        box.set_links_mass(torch.tensor([2.0], **F64, requires_grad=True))


def test_fast_launch_returns_a_kernel_s_integer():
    """The rigid step returns its count of failed envs through taichi_compat's fast launch (the read
    after every step costs ~0.5 us there, against ~10 us through Taichi's own call): repeated
    launches, the fast path, must return the kernel's value, not None."""
    import taichi as ti

    counter = ti.field(ti.i32, shape=())

    @ti.kernel
    def bump(k: ti.i32) -> ti.i32:
        counter[None] += k
        return counter[None]

    got = [bump(k) for k in (1, 2, 3, 4)]
    assert got == [1, 3, 6, 10] and all(type(g) is int for g in got), got
    from solvers.taichi_compat import frontend

    if frontend.installed().get("fast_launch"):
        assert bump._primal.__dict__.get("_gs_plan") is not None  # it went through the fast path
