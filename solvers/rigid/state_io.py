"""State, controls, parameters and link outputs in and out of a RigidCore: the kernels through which
the scene's side (genesis_lite/rigid_sim.py, via RigidSolver) exchanges arrays with the core's fields.

Each kernel takes the core `s` (a RigidCore, core.py) as a template argument, so it compiles once per
core, as the core's own kernels do, and the arrays as external arrays (numpy or torch: the caller's
buffers, filled or read in place). They loop over the scene's envs with the core's guard (see RigidCore).
"""
import taichi as ti

from .kinematics import func_point_velocity


# Every torch tensor passed to a kernel costs ~30 us here, so each crossing packs its data in one:
# state x = [qpos | qvel] (B, n_qs + n_dofs), controls c = [force; pos; vel] (B, 3, n_dofs),
# parameters p = [mass | com | inertia | damping | armature | frictionloss | kp | kv | stiffness | gravity |
# force_lo | force_hi | invweight] (B, 13 n_links + 9 n_dofs + 3), see param_layout.


@ti.kernel
def kernel_set_state(s: ti.template(), slot: ti.i32, x: ti.types.ndarray()):
    if ti.static(s.serial_light):
        ti.loop_config(serialize=True)
    for i_b in range(s.cap_envs):
        if i_b < s.n_envs:
            for i_q in range(s.n_qs):
                s.qpos[slot, i_b, i_q] = x[i_b, i_q]
            for i_d in range(s.n_dofs):
                s.qvel[slot, i_b, i_d] = x[i_b, s.n_qs + i_d]


@ti.kernel
def kernel_get_state(s: ti.template(), slot: ti.i32, x: ti.types.ndarray()):
    """Read the state in `slot` and make it the current state (slot 0)."""
    if ti.static(s.serial_light):
        ti.loop_config(serialize=True)
    for i_b in range(s.cap_envs):
        if i_b < s.n_envs:
            for i_q in range(s.n_qs):
                x[i_b, i_q] = s.qpos[slot, i_b, i_q]
                s.qpos[0, i_b, i_q] = s.qpos[slot, i_b, i_q]
            for i_d in range(s.n_dofs):
                x[i_b, s.n_qs + i_d] = s.qvel[slot, i_b, i_d]
                s.qvel[0, i_b, i_d] = s.qvel[slot, i_b, i_d]


@ti.kernel
def kernel_vjp(s: ti.template(), slot: ti.i32, g: ti.types.ndarray()):
    """vjp_loss += <g, state in `slot`>: the scalar whose adjoint a step's ti.ad.Tape propagates, g
    being the gradient torch hands the step's output state (packed like kernel_get_state). The
    scalar is the core's own, its adjoint seeded to 1 by kernel_clear_grads: the Tape's loss is a torch
    token no kernel reads (genesis_lite/simulator.py tape_loss)."""
    if ti.static(s.serial_light):
        ti.loop_config(serialize=True)
    for i_b in range(s.cap_envs):
        if i_b < s.n_envs:
            for i_q in range(s.n_qs):
                s.vjp_loss[None] += g[i_b, i_q] * s.qpos[slot, i_b, i_q]
            for i_d in range(s.n_dofs):
                s.vjp_loss[None] += g[i_b, s.n_qs + i_d] * s.qvel[slot, i_b, i_d]


@ti.kernel
def kernel_get_grads(s: ti.template(), g: ti.types.ndarray()):
    """g[:, :n_qs + n_dofs] <- adjoint of the state in slot 0, g[:, n_qs + n_dofs:] <- adjoint of
    the controls (force, pos, vel blocks of n_dofs)."""
    if ti.static(s.serial):
        ti.loop_config(serialize=True)
    for i_b in range(s.cap_envs):
        if i_b < s.n_envs:
            nx = s.n_qs + s.n_dofs
            nd = s.n_dofs
            for i_q in range(s.n_qs):
                g[i_b, i_q] = s.qpos.grad[0, i_b, i_q]
            for i_d in range(nd):
                g[i_b, s.n_qs + i_d] = s.qvel.grad[0, i_b, i_d]
                g[i_b, nx + i_d] = s.ctrl_force.grad[i_b, i_d]
                g[i_b, nx + nd + i_d] = s.ctrl_pos.grad[i_b, i_d]
                g[i_b, nx + 2 * nd + i_d] = s.ctrl_vel.grad[i_b, i_d]


@ti.kernel
def kernel_set_ctrl(s: ti.template(), c: ti.types.ndarray()):
    if ti.static(s.serial_light):
        ti.loop_config(serialize=True)
    for i_b in range(s.cap_envs):
        if i_b < s.n_envs:
            for i_d in range(s.n_dofs):
                s.ctrl_force[i_b, i_d] = c[i_b, 0, i_d]
                s.ctrl_pos[i_b, i_d] = c[i_b, 1, i_d]
                s.ctrl_vel[i_b, i_d] = c[i_b, 2, i_d]


@ti.kernel
def kernel_set_ctrl_mode(s: ti.template(), m: ti.types.ndarray()):
    if ti.static(s.serial_light):
        ti.loop_config(serialize=True)
    for i_b in range(s.cap_envs):
        if i_b < s.n_envs:
            for i_d in range(s.n_dofs):
                s.ctrl_mode[i_b, i_d] = m[i_b, i_d]


@ti.kernel
def kernel_set_params(s: ti.template(), p: ti.types.ndarray()):
    """All parameters of every env from the packed p (see param_layout)."""
    if ti.static(s.serial):
        ti.loop_config(serialize=True)
    for i_b in range(s.cap_envs):
        if i_b < s.n_envs:
            L = s.n_links
            D = s.n_dofs
            for i in range(L):
                s.link_mass[i_b, i] = p[i_b, i]
                for k in ti.static(range(3)):
                    s.link_com[i_b, i][k] = p[i_b, L + 3 * i + k]
                for k, l in ti.static(ti.ndrange(3, 3)):
                    s.link_inertia[i_b, i][k, l] = p[i_b, 4 * L + 9 * i + 3 * k + l]
            o = 13 * L
            for i in range(D):
                s.dof_damping[i_b, i] = p[i_b, o + i]
                s.dof_armature[i_b, i] = p[i_b, o + D + i]
                s.dof_frictionloss[i_b, i] = p[i_b, o + 2 * D + i]
                s.dof_kp[i_b, i] = p[i_b, o + 3 * D + i]
                s.dof_kv[i_b, i] = p[i_b, o + 4 * D + i]
                s.dof_stiffness[i_b, i] = p[i_b, o + 5 * D + i]
                s.dof_force_lo[i_b, i] = p[i_b, o + 6 * D + 3 + i]
                s.dof_force_hi[i_b, i] = p[i_b, o + 7 * D + 3 + i]
                s.dof_invweight[i_b, i] = p[i_b, o + 8 * D + 3 + i]
            for k in ti.static(range(3)):
                s.gravity[i_b][k] = p[i_b, o + 6 * D + k]


@ti.kernel
def kernel_get_param_grads(s: ti.template(), g: ti.types.ndarray()):
    """Adjoints of the differentiable parameters into g, packed like kernel_set_params without the
    force range (B, 13 n_links + 7 n_dofs + 3)."""
    if ti.static(s.serial):
        ti.loop_config(serialize=True)
    for i_b in range(s.cap_envs):
        if i_b < s.n_envs:
            L = s.n_links
            D = s.n_dofs
            for i in range(L):
                g[i_b, i] = s.link_mass.grad[i_b, i]
                for k in ti.static(range(3)):
                    g[i_b, L + 3 * i + k] = s.link_com.grad[i_b, i][k]
                for k, l in ti.static(ti.ndrange(3, 3)):
                    g[i_b, 4 * L + 9 * i + 3 * k + l] = s.link_inertia.grad[i_b, i][k, l]
            o = 13 * L
            for i in range(D):
                g[i_b, o + i] = s.dof_damping.grad[i_b, i]
                g[i_b, o + D + i] = s.dof_armature.grad[i_b, i]
                g[i_b, o + 2 * D + i] = s.dof_frictionloss.grad[i_b, i]
                g[i_b, o + 3 * D + i] = s.dof_kp.grad[i_b, i]
                g[i_b, o + 4 * D + i] = s.dof_kv.grad[i_b, i]
                g[i_b, o + 5 * D + i] = s.dof_stiffness.grad[i_b, i]
                g[i_b, o + 6 * D + 3 + i] = s.dof_invweight.grad[i_b, i]
            for k in ti.static(range(3)):
                g[i_b, o + 6 * D + k] = s.gravity.grad[i_b][k]


@ti.kernel
def kernel_get_result(s: ti.template(), which: ti.i32, out: ti.types.ndarray()):
    """The scene's block of a per-env result (RigidSolver.RESULTS[which]): 0 the mass matrix into out
    (B, n, n), 1 the qacc of every evaluation into out (B, n_evals, n), 2 the actuator forces into out
    (B, 1, n)."""
    for i_b in range(s.cap_envs):
        if i_b < s.n_envs:
            n = s.n_dofs
            if which == 0:
                for i, j in ti.ndrange(n, n):
                    out[i_b, i, j] = s.mass_mat[i_b, i, j]
            elif which == 1:
                for e, i in ti.ndrange(out.shape[1], n):
                    out[i_b, e, i] = s.qacc[e, i_b, i]
            elif which == 2:
                for i in range(n):
                    out[i_b, 0, i] = s.dof_tau[i_b, i]
            else:
                for i in range(n):
                    out[i_b, 0, i] = s.dof_qf[i_b, i]


@ti.kernel
def kernel_param_grad(s: ti.template(), x: ti.template(), g: ti.types.ndarray()):
    """Adjoint of a scalar parameter field that is not the core's (contact friction), the scene's
    (B, n) block of it (the field may be larger: pooled by capacity)."""
    for i, j in ti.ndrange(g.shape[0], g.shape[1]):
        g[i, j] = x.grad[i, j]

# ------------------------------------------------------------------ getters


@ti.kernel
def kernel_link_outputs(s: ti.template(), pos: ti.types.ndarray(), quat: ti.types.ndarray(), vel: ti.types.ndarray(),
                        ang: ti.types.ndarray(), vjp: ti.template()):
    """Link origin poses and velocities (world frame) from the last kinematics evaluation into the
    arrays; with `vjp` the arrays hold gradients of those outputs instead and vjp_loss += <gradients,
    outputs>, for a getter's ti.ad.Tape (see kernel_vjp)."""
    if ti.static(s.serial):
        ti.loop_config(serialize=True)
    for i_b in range(s.cap_envs):
        if i_b < s.n_envs:
            for i_l in range(s.n_links):
                p = s.link_pos[i_b, i_l]
                w = s.cvel_w[i_b, i_l]
                v = func_point_velocity(s, s.cvel_w, s.cvel_v, i_b, i_l, p)
                q = s.link_quat[i_b, i_l]
                if ti.static(vjp):
                    acc = 0.0
                    for k in ti.static(range(3)):
                        acc += pos[i_b, i_l, k] * p[k] + vel[i_b, i_l, k] * v[k] + ang[i_b, i_l, k] * w[k]
                    for k in ti.static(range(4)):
                        acc += quat[i_b, i_l, k] * q[k]
                    s.vjp_loss[None] += acc
                else:
                    for k in ti.static(range(3)):
                        pos[i_b, i_l, k] = p[k]
                        vel[i_b, i_l, k] = v[k]
                        ang[i_b, i_l, k] = w[k]
                    for k in ti.static(range(4)):
                        quat[i_b, i_l, k] = q[k]
