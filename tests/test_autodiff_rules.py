"""The loop shape Taichi 1.7.4 differentiates wrongly, shown on a small kernel, and a guard that no stage
whose adjoint Taichi computes has it (tests/sibling_loops.py says what the shape is and how it is found)."""
import numpy as np
import pytest
import taichi as ti

from sibling_loops import loop_count, scan
from solvers import taichi_compat
from solvers.rigid.math3d import func_add

B, N = 2, 5


@pytest.fixture
def fields():
    # (gs.init, float64, by conftest.py)
    f = ti.types.f64
    x, p, q = (ti.field(f, shape=(B, N), needs_grad=True) for _ in range(3))
    loss = ti.field(f, shape=(), needs_grad=True)
    x.from_numpy(np.random.default_rng(3).standard_normal((B, N)))
    return x, p, q, loss


@ti.func
def _first(x: ti.template(), p: ti.template(), b):
    for i in range(N):
        p[b, i] = ti.sin(x[b, i])


@ti.func
def _second(p: ti.template(), q: ti.template(), b):
    for i in range(N):
        q[b, i] = p[b, i] * p[b, i]


@ti.func
def _both(x: ti.template(), p: ti.template(), q: ti.template(), b):
    """Two sibling loops, the second reading what the first writes: the shape Taichi gets wrong."""
    _first(x, p, b)
    _second(p, q, b)


@ti.func
def _both_locals(x: ti.template(), q: ti.template(), b):
    """Two sibling loops sharing a local only: differentiated correctly."""
    s = 0.0
    for i in range(N):
        s += ti.sin(x[b, i])
    for i in range(N):
        q[b, i] = s * (i + 1)


@ti.kernel
def _one_body(x: ti.template(), p: ti.template(), q: ti.template()):
    for b in range(B):
        _both(x, p, q, b)


@ti.kernel
def _two_loops(x: ti.template(), p: ti.template(), q: ti.template()):
    for b in range(B):
        _first(x, p, b)
    for b in range(B):
        _second(p, q, b)


@ti.kernel
def _weighted(q: ti.template(), loss: ti.template()):
    for b, i in q:
        loss[None] += q[b, i] * (i + 1)


def _grad(kernel, x, p, q, loss):
    for f in (x, p, q, loss):
        f.grad.fill(0)
    loss.fill(0)
    kernel(x, p, q)
    _weighted(q, loss)
    loss.grad[None] = 1.0
    _weighted.grad(q, loss)
    kernel.grad(x, p, q)
    return x.grad.to_numpy()


def test_taichi_loses_the_gradient_between_sibling_loops_of_one_body(fields):
    """loss = sum_i (i + 1) sin(x_i)^2: d/dx_i = 2 (i + 1) sin(x_i) cos(x_i), all through p. As two top-level
    loops Taichi gives it; as two loops of one loop body (a stage's loops inside the loop over envs) it gives
    0, silently. If a later Taichi gives the right number here, the rule of sibling_loops.py can go."""
    x = fields[0].to_numpy()
    exact = 2 * (np.arange(N) + 1) * np.sin(x) * np.cos(x)
    assert np.abs(exact).max() > 0.1
    np.testing.assert_allclose(_grad(_two_loops, *fields), exact, rtol=1e-13, atol=1e-13)
    np.testing.assert_array_equal(_grad(_one_body, *fields), np.zeros_like(x))


def test_the_scan_flags_that_shape_and_nothing_Taichi_differentiates_correctly():
    found = scan(_both)
    assert len(found) == 1 and found[0][2] == ("p",), found
    assert "_first" in found[0][0] and "_second" in found[0][1]
    assert scan(_both_locals) == []
    assert scan(_first) == [] and scan(_second) == []
    # a kernel's own top-level loops are separate tasks (correct); inside its loop over b they are siblings
    assert scan(_two_loops, inside_loop=False) == []
    assert len(scan(_one_body, inside_loop=False)) == 1


def test_the_scan_flags_the_bound_round_that_once_gave_a_gradient_37_times_off():
    """passes.bound_round runs the bank's sums up the tree, onto the dofs and projected as three stages:
    as one stage, its gradient was off by a factor 37 against finite differences (passes.py). The scan finds
    that shape in the one-stage form, following the calls into banks.py."""
    from solvers.rigid.contact.banks import func_bank_dof, func_bank_project, func_bank_tree

    @ti.func
    def sums_in_one_stage(s: ti.template(), b: ti.template(), i_b):
        func_bank_tree(s, b, i_b)
        func_bank_dof(s, b, i_b)
        func_bank_project(s, b, i_b)

    found = scan(sums_in_one_stage)
    assert found and all("banks.py:func_bank_" in a and "banks.py:func_bank_" in b for a, b, _ in found), found
    for one in (func_bank_tree, func_bank_dof, func_bank_project):
        assert scan(one) == []


def _differentiated_stages():
    """Every stage whose adjoint Taichi computes: the rigid dynamics' (with the applied and external
    wrenches'), the contact stages and passes (ContactSolver.solve_grad: the relinearise, Coulomb and friction
    passes, the toggle and bound rounds; their rebuilds run forward only and are checked too), integration, and
    the MPM constitutive stage. The broad phase writes integers and has no adjoint run (collision.NO_ADJOINT)."""
    from solvers.mpm.solver import MPMSolver
    from solvers.rigid import external
    from solvers.rigid.collision import NO_ADJOINT
    from solvers.rigid.contact import passes, rounds, slots
    from solvers.rigid.core import DYNAMICS, func_applied_wrench
    from solvers.rigid.integrate import INTEGRATE

    lists = [DYNAMICS, (func_applied_wrench, external.func_external_dof), slots.CONTACT_STAGES, slots.CROSS_STAGES,
             passes.RELINEARISE_PASS_CROSS, passes.COULOMB_PASS, passes.FRICTION_PASS_CROSS, passes.BOUND_REBUILD,
             passes.bound_round(1), rounds.TOGGLE_REBUILD, rounds.toggle_round(1), INTEGRATE,
             (MPMSolver.func_constitutive_ad,)]
    stages = []
    for lst in lists:
        stages += [f for f in lst if f not in NO_ADJOINT and f not in stages]
    return stages


def test_no_stage_whose_adjoint_taichi_computes_has_sibling_loops_sharing_a_field():
    stages = _differentiated_stages()
    assert len(stages) > 60  # 70 today
    assert sum(loop_count(f) for f in stages) > 60  # the loops it read, their calls followed (74 today)
    found = {}
    for stage in stages:
        pairs = scan(stage)
        if pairs:
            found[stage] = pairs
    assert not found, ("sibling loops in one loop body where a later one reads a field an earlier one writes: "
                       "Taichi 1.7.4 drops the gradient through that field (tests/sibling_loops.py). Split the "
                       f"stage into stages (each one loop over envs). {found}")


# ---- plain read-modify-writes in primal kernels (solvers/rigid/math3d.plain_updates)

class _GradCore:
    """What math3d.func_add reads of a stage's `s`: a core with gradients."""
    requires_grad = True


@ti.kernel
def _sum_rows(s: ti.template(), x: ti.template(), acc: ti.template()):
    for b in range(B):
        for i in range(N):
            func_add(s, acc, b, 0, ti.sin(x[b, i]))


@ti.kernel
def _primal_two_adjoint_three(x: ti.template(), acc: ti.template()):
    for b in range(B):
        if ti.static(taichi_compat.compiling_adjoint()):
            acc[b, 0] = 3.0 * x[b, 0]
        else:
            acc[b, 0] = 2.0 * x[b, 0]


def _rows_grad(run, x, acc):
    """x.grad of loss = sum_b (b + 1) acc[b, 0] after run() (forward then, by the caller, the adjoint)."""
    x.grad.fill(0)
    acc.fill(0)
    acc.grad.fill(0)
    run(False)
    value = acc.to_numpy()[:, 0].copy()
    for b in range(B):
        acc.grad[b, 0] = b + 1.0
    run(True)
    return value, x.grad.to_numpy()


def test_compiling_adjoint_tells_a_primal_kernel_from_its_adjoint(fields):
    """A primal kernel and its adjoint (`.grad`) compile separately from one source, each in its own mode:
    what a ti.static branch on taichi_compat.compiling_adjoint() emits in the primal is never differentiated."""
    x, acc = fields[0], fields[1]
    run = lambda adjoint: (_primal_two_adjoint_three.grad if adjoint else _primal_two_adjoint_three)(x, acc)  # noqa: E731
    value, grad = _rows_grad(run, x, acc)
    x0 = x.to_numpy()[:, 0]
    np.testing.assert_array_equal(value, 2.0 * x0)
    np.testing.assert_array_equal(grad[:, 0], 3.0 * (np.arange(B) + 1.0))
    assert taichi_compat.compiling_adjoint()  # outside a kernel: unknown, so True (the `+=` form)


def test_func_add_is_plain_in_the_primal_and_differentiable_in_the_adjoint(fields):
    """func_add on a core with gradients: the primal kernel's plain read-modify-write gives the sum, and the
    adjoint (`+=` there) the exact gradient (b + 1) cos(x)."""
    x, acc = fields[0], fields[1]
    xs = x.to_numpy()
    exact = (np.arange(B) + 1.0)[:, None] * np.cos(xs)
    run = lambda adjoint: (_sum_rows.grad if adjoint else _sum_rows)(_GradCore, x, acc)  # noqa: E731
    value, grad = _rows_grad(run, x, acc)
    np.testing.assert_allclose(value, np.sin(xs).sum(axis=1), rtol=1e-14)
    np.testing.assert_allclose(grad, exact, rtol=1e-13, atol=1e-13)


HAND_RUNS = ["inertia", "kinematics_inertia", "link_state", "forces", "accumulate_project", "generalized",
             "generalized_springs_implicitfast", "generalized_euler", "before_applied", "after_applied", "dynamics"]


def _hand_adjoint_scene(integrator, springs):
    """A scene with every joint type and three trees: the skewed arm (offset centres of mass, rotated non-diagonal
    inertia, skewed axes) on a free base whose quaternion is not of unit norm, spinning at 1, 150 and 300 rad/s in
    the three envs (the implicit gyroscopic moment's theta at 1/2, on its smooth step and at 1), the mimic gripper
    (prismatic fingers) and the small arm (a fixed joint), both fixed; a random state, random gains, damping,
    friction losses, springs, force limits that saturate some dofs, every control mode, joints past their limits,
    and in env 2 the free base's position target at its own orientation (the rotation error's series branch).
    Returns the core after an evaluation at slot 0 (h = 0.01)."""
    import genesis_lite as gs
    from gradient_cases import URDF_DIR

    rigid = dict(integrator=getattr(gs.integrator, integrator))
    if springs:
        rigid["joint_limit_stiffness"] = 3e3
    scene = gs.Scene(sim_options=gs.options.SimOptions(dt=0.01, requires_grad=True),
                     rigid_options=gs.options.RigidOptions(**rigid), show_viewer=False)
    scene.add_entity(gs.morphs.URDF(file=str(URDF_DIR / "skew_arm.urdf"), fixed=False, pos=(0.3, -0.2, 1.0)))
    scene.add_entity(gs.morphs.URDF(file=str(URDF_DIR / "mimic_gripper.urdf"), fixed=True, pos=(1.0, 0.5, 0.5)))
    scene.add_entity(gs.morphs.URDF(file=str(URDF_DIR / "arm.urdf"), fixed=True, pos=(-1.0, 0.2, 0.3)))
    scene.build(n_envs=3)
    solver = scene.rigid_solver
    core = solver.core
    rng = np.random.default_rng(7)
    nq, nv = solver.n_qs, solver.n_dofs

    def update(field, fn):
        x = field.to_numpy()
        fn(x)
        field.from_numpy(x)

    def state(qpos):
        qpos[0, :3, :nq] += rng.uniform(-0.8, 0.8, (3, nq))
        qpos[0, :3, 3:7] = rng.uniform(-1.0, 1.0, (3, 4)) * 1.3  # the free base's quaternion, not normalised
        dof_q, lo, hi = core.dof_q.to_numpy(), core.dof_limit_lo.to_numpy(), core.dof_limit_hi.to_numpy()
        for d in range(nv):  # some joints past a limit: by up to 3 cm or rad, or within the impedance's width
            if dof_q[d] >= 0 and np.isfinite(lo[d]) and rng.uniform() < 0.6:
                depth = np.where(rng.uniform(size=2) < 0.5, 0.03, 1.2e-3) * rng.uniform(-1.0, 1.0, 2)
                qpos[0, :2, dof_q[d]] = np.where(rng.uniform(size=2) < 0.5, lo[d], hi[d]) + depth
    update(core.qpos, state)

    def velocity(qvel):
        qvel[0, :3, :nv] = rng.uniform(-2.0, 2.0, (3, nv))
        spin = rng.standard_normal((3, 3))
        qvel[0, :3, 3:6] = spin / np.linalg.norm(spin, axis=1, keepdims=True) * np.array([[1.0], [150.0], [300.0]])
    update(core.qvel, velocity)
    for name, lo_, hi_ in (("ctrl_force", -5, 5), ("ctrl_vel", -1, 1), ("dof_kp", 10, 200), ("dof_kv", 1, 20),
                           ("dof_damping", 0.1, 2), ("dof_frictionloss", 0.0, 0.5), ("dof_stiffness", 0.0, 30)):
        update(getattr(core, name), lambda x, a=lo_, b=hi_: x.__setitem__((slice(0, 3), slice(0, nv)),
                                                                           rng.uniform(a, b, (3, nv))))
    update(core.ctrl_mode, lambda x: x.__setitem__((slice(0, 3), slice(0, nv)), rng.integers(0, 3, (3, nv))))
    update(core.dof_force_lo, lambda x: x.__setitem__((slice(0, 3), slice(0, nv)), -rng.uniform(2, 60, (3, nv))))
    update(core.dof_force_hi, lambda x: x.__setitem__((slice(0, 3), slice(0, nv)), rng.uniform(2, 60, (3, nv))))

    def targets(ctrl_pos):
        ctrl_pos[:3, :nv] = rng.uniform(-1.0, 1.0, (3, nv))
        q = core.qpos.to_numpy()[0, 2, 3:7]
        w, x, y, z = q / np.linalg.norm(q)
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        # intrinsic x-y-z Euler angles of R = Rx(a) Ry(b) Rz(c)
        ctrl_pos[2, 3:6] = np.arctan2(-R[1, 2], R[2, 2]), np.arcsin(R[0, 2]), np.arctan2(-R[0, 1], R[0, 0])
    update(core.ctrl_pos, targets)
    update(core.ctrl_mode, lambda x: x.__setitem__((2, slice(3, 6)), 1))  # env 2's base under position control
    core.kernel_evaluate(0, 0, 0.01)
    return core, rng


@pytest.mark.parametrize("run", HAND_RUNS)
def test_written_out_adjoints_match_taichis(run):
    """solver.HAND_ADJOINTS: the written-out adjoints (core.kernel_hand_adjoint) against Taichi's adjoints of the same
    stages (kernel_dynamics_part(k0, k1).grad, in the groups adjoint_groups made before they were written out), in 3
    envs (_hand_adjoint_scene), from random adjoints in every field the stages write or read: the same adjoints to
    rounding, the stored fields' adjoints zeroed alike. `run`: the INERTIA stages, KINEMATICS + INERTIA, LINK_STATE
    (the getters'), the link forces with the gyroscopic moments, the forces' accumulation and projection, the
    generalised force with the free joint's rotation error (with each integrator's implicit terms, the limit
    constraint and the limit springs), the two runs a scene with applied wrenches takes, and all the dynamics'
    stages (the runs HAND_ADJOINTS lists)."""
    from solvers.rigid.bias import BIAS
    from solvers.rigid.core import DYNAMICS, LINK_STATE_ADJOINT, PLAIN_ADJOINT, HandAdjoint
    from solvers.rigid.inertia import INERTIA
    from solvers.rigid.kinematics import KINEMATICS, LINK_STATE
    from solvers.rigid.solver import HAND_ADJOINTS, MERGED_STAGES as GENERALIZED
    from solvers.taichi_compat.compile_options import AdjointCompile

    ki, kb, kg = DYNAMICS.index(INERTIA[0]), DYNAMICS.index(BIAS[0]), DYNAMICS.index(GENERALIZED[0])
    assert DYNAMICS == KINEMATICS + INERTIA + BIAS + GENERALIZED
    integrator = {"generalized_springs_implicitfast": "implicitfast", "generalized_euler": "Euler"}.get(
        run, "approximate_implicitfast")
    core, rng = _hand_adjoint_scene(integrator, springs=run == "generalized_springs_implicitfast")
    h = 0.01
    inertia = ["mass_mat", "dof_n", "dof_f", "crb_m", "crb_h", "crb_J", "link_mass", "link_h", "link_J", "cdof_w",
               "cdof_v"]
    link_state = ["link_pos", "link_quat", "link_R", "cdof_w", "cdof_v", "cvel_w", "cvel_v", "qpos", "qvel"]
    kinematics = link_state + ["link_cpos", "link_h", "link_J", "cdofd_w", "cdofd_v", "link_mass", "link_com",
                               "link_inertia"]
    forces = ["cfrc_n", "cfrc_f", "cacc_w", "cacc_v", "gravity", "link_mass", "link_h", "link_J", "cvel_w", "cvel_v",
              "cdofd_w", "cdofd_v", "qvel"]
    project = ["bias", "cfrc_n", "cfrc_f", "cdof_w", "cdof_v"]
    generalized = ["force", "dof_lim_f", "dof_lim_D", "mass_mat", "qpos", "qvel", "dof_stiffness", "dof_armature",
                   "bias", "ctrl_force", "ctrl_vel", "ctrl_pos", "dof_kp", "dof_kv", "dof_damping",
                   "dof_frictionloss", "dof_rot_err"]
    if integrator != "Euler" and run != "generalized_springs_implicitfast":
        generalized.append("dof_invweight")  # (the limit constraint's; springs have none, Euler damps nothing)
    kin_inertia = inertia[:6] + kinematics
    gen = (generalized, [(kg, kg + 2)], HandAdjoint(generalized=True))
    cases = {  # the fields, Taichi's groups (last first), the written-out adjoint
        "inertia": (inertia, [(ki, ki + 4)], HandAdjoint(inertia=True)),
        "kinematics_inertia": (kin_inertia, [(ki + 2, ki + 4), (0, ki + 2)], HandAdjoint(kinematics=True, inertia=True)),
        "link_state": (link_state, [(0, len(LINK_STATE))], LINK_STATE_ADJOINT),
        "forces": (forces, [(kb, kb + 2)], HandAdjoint(forces=True)),
        "accumulate_project": (project, [(kb + 3, kb + 4), (kb + 2, kb + 3)],
                               HandAdjoint(accumulate=True, project=True)),
        "generalized": gen, "generalized_springs_implicitfast": gen, "generalized_euler": gen,
        "before_applied": (kin_inertia + forces, [(kb, kb + 2), (ki + 2, ki + 4), (0, ki + 2)],
                           HAND_ADJOINTS[KINEMATICS + INERTIA + BIAS[:2]]),
        "after_applied": (project + generalized, [(kb + 3, kg + 2), (kb + 2, kb + 3)],
                          HAND_ADJOINTS[BIAS[2:] + GENERALIZED]),
        "dynamics": (kin_inertia + forces + project + generalized,
                     [(kb + 3, kg + 2), (kb, kb + 3), (ki + 2, ki + 4), (0, ki + 2)], HAND_ADJOINTS[DYNAMICS]),
    }
    names, groups, spec = cases[run]
    names = list(dict.fromkeys(names))
    fs = [getattr(core, n) for n in names]
    seeds = [rng.standard_normal(f.grad.to_numpy().shape) for f in fs]

    def adjoints(launch):
        for f, x in zip(fs, seeds):
            f.grad.from_numpy(x)
        launch()
        return [f.grad.to_numpy() for f in fs]

    def taichi_adjoints():
        for k0, k1 in groups:  # each group's stages under its compile option
            with AdjointCompile(all(f in PLAIN_ADJOINT for f in DYNAMICS[k0:k1])):
                core.kernel_dynamics_part.grad(k0, k1, 0, 0, h)

    taichi = adjoints(taichi_adjoints)
    hand = adjoints(lambda: core.hand_adjoint(spec, 0, 0, h))
    for name, a, b, x in zip(names, taichi, hand, seeds):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * np.abs(a).max(), err_msg=name)
        if not (run in ("generalized", "generalized_springs_implicitfast", "generalized_euler", "after_applied")
                and name == "mass_mat"):  # (its diagonal's adjoint is only read)
            assert np.abs(b - x).max() > 0.1, name  # every field's adjoint took part
