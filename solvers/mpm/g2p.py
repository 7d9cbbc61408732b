"""Stage 4 of an MLS-MPM substep, grid to particle: each particle gathers its new velocity and affine
velocity C (APIC) from the 27 nodes around it and moves with the new velocity.
"""
import taichi as ti

from .p2g import func_stencil, func_stencil_dw, func_weight_grad


@ti.func
def func_g2p(s: ti.template(), i_b, i_p, src, dst, dt):
    x = s.x[src, i_b, i_p]
    new_v, C = func_g2p_gather(s, i_b, x)
    func_g2p_store(s, i_b, i_p, dst, x, new_v, C, dt)


@ti.func
def func_g2p_gather(s: ti.template(), i_b, x):
    """The new velocity and affine velocity C of a particle at x, gathered from the grid."""
    base, fx, w = func_stencil(s, x)
    # C = 4/dx sum_o w_o v_o (o - fx)^T = 4/dx (sum_o w_o v_o o^T - new_v fx^T), accumulated column by
    # column over the nodes with o_a > 0 (o's entries are the constants 0, 1, 2); also because Taichi
    # 1.7's reverse mode without advanced_optimization crashes on a matrix-valued local accumulated
    # in a loop
    new_v = ti.Vector.zero(float, 3)
    c0 = ti.Vector.zero(float, 3)
    c1 = ti.Vector.zero(float, 3)
    c2 = ti.Vector.zero(float, 3)
    for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
        wv = (w[i][0] * w[j][1] * w[k][2]) * s.grid_v[i_b, base + ti.Vector([i, j, k])]
        new_v += wv
        c0 += float(i) * wv
        c1 += float(j) * wv
        c2 += float(k) * wv
    scale = 4.0 * s.inv_dx
    C = ti.Matrix.cols([scale * (c0 - fx[0] * new_v), scale * (c1 - fx[1] * new_v), scale * (c2 - fx[2] * new_v)])
    return new_v, C


@ti.func
def func_g2p_store(s: ti.template(), i_b, i_p, dst, x, new_v, C, dt):
    """The particle moves from x with its new velocity (kept inside the walls) into slot dst."""
    x_new = x + dt * new_v
    s.x[dst, i_b, i_p] = ti.Vector([ti.min(ti.max(x_new[a], s.x_min[a]), s.x_max[a]) for a in ti.static(range(3))])
    s.v[dst, i_b, i_p] = new_v
    s.C[dst, i_b, i_p] = C


@ti.func
def func_g2p_adjoint(s: ti.template(), i_b, i_p, src, dst, dt, atomic: ti.template()):
    """Adjoint of func_g2p, written out: from the adjoints of the particle's new position, velocity and C
    (slot dst) into the adjoints of the grid velocities around it (a scatter: atomic adds, or plain adds
    where one thread owns the env's grid, as in p2g.py) and of its old position (slot src, through the
    clamp to the walls, the move and the weights). Taichi's own adjoint of the gather is the same sums
    with 81 atomic adds per particle and a recompute of the stencil per node; this one is ~5x faster on
    the CPU (solvers/mpm/solver.py kernel_g2p_grad). It reads the forward's new_v and x' from slot dst
    (the replay has just written them) rather than gathering again.

    Forward: new_v = sum_o W_o v_o, c_a = sum_o o_a W_o v_o, C[:, a] = 4/dx (c_a - fx_a new_v),
    x' = clamp(x + dt new_v), W_o = w_i(fx_0) w_j(fx_1) w_k(fx_2), fx = (x - lower)/dx - base."""
    x = s.x[src, i_b, i_p]
    base, fx, w = func_stencil(s, x)
    dw = func_stencil_dw(fx)
    # the forward's outputs are in slot dst: new_v itself, and x' inside the walls exactly where the clamp
    # left x + dt new_v alone, which is where it passes the adjoint (the walls are constants)
    new_v = s.v[dst, i_b, i_p]
    x_out = s.x[dst, i_b, i_p]
    gX = s.x.grad[dst, i_b, i_p]
    gxn = ti.Vector([ti.select((x_out[a] > s.x_min[a]) & (x_out[a] < s.x_max[a]), gX[a], 0.0)
                     for a in ti.static(range(3))])
    gC = s.C.grad[dst, i_b, i_p]
    scale = 4.0 * s.inv_dx
    g0 = scale * ti.Vector([gC[0, 0], gC[1, 0], gC[2, 0]])
    g1 = scale * ti.Vector([gC[0, 1], gC[1, 1], gC[2, 1]])
    g2 = scale * ti.Vector([gC[0, 2], gC[1, 2], gC[2, 2]])
    g_newv = s.v.grad[dst, i_b, i_p] + dt * gxn - (fx[0] * g0 + fx[1] * g1 + fx[2] * g2)
    g_fx = -ti.Vector([g0.dot(new_v), g1.dot(new_v), g2.dot(new_v)])
    for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
        I = base + ti.Vector([i, j, k])
        g_node = g_newv + float(i) * g0 + float(j) * g1 + float(k) * g2
        wt = w[i][0] * w[j][1] * w[k][2]
        if ti.static(atomic):
            s.grid_v.grad[i_b, I] += wt * g_node
        else:  # (the caller guarantees no other thread adds to this env's grid adjoints)
            s.grid_v.grad[i_b, I] = s.grid_v.grad[i_b, I] + wt * g_node
        sw = g_node.dot(s.grid_v[i_b, I])
        g_fx += sw * func_weight_grad(w, dw, i, j, k)
    s.x.grad[src, i_b, i_p] = s.x.grad[src, i_b, i_p] + gxn + s.inv_dx * g_fx
