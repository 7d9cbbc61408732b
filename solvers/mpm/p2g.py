"""Stage 2 of an MLS-MPM substep (quadratic B-splines, APIC), particle to grid: each particle adds its
mass, its momentum m v plus its external impulse dt f, and the affine momentum
(m C - dt V 4/dx^2 tau)(x_node - x_p) to the 27 nodes around it.

The scatter adds with plain adds (`atomic=False`) from a loop in which one thread owns each env's grid
where threads are few (solver.py func_p2g_all, `plain_p2g`), else with atomic adds: on the CPU a float
atomic add is a compare-and-swap loop, and the 108 of them per particle cost five times the rest of the
particle-to-grid transfer. Its adjoint (func_p2g_adjoint) is a gather, written out.
"""
import taichi as ti


@ti.func
def func_stencil(s: ti.template(), x):
    """Lower corner `base` of the 3x3x3 stencil around x, the offset fx of x from it (cells) and the
    quadratic B-spline weights per axis. The corner is clamped so that the stencil stays on the grid
    whatever x is (a NaN, a position set outside the domain): the setters refuse those and g2p keeps
    particles inside, so for every particle that may be there the clamp changes nothing; it only
    keeps a bad value from writing outside the grid's memory."""
    xg = (x - s.lower) * s.inv_dx
    top = ti.Vector([s.grid_res[0] - 3, s.grid_res[1] - 3, s.grid_res[2] - 3])
    base = ti.min(ti.max(ti.cast(ti.floor(xg - 0.5), ti.i32), 0), top)
    fx = xg - ti.cast(base, float)
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
    return base, fx, w


@ti.func
def func_stencil_dw(fx):
    """The weights' derivatives d w_n / d fx of func_stencil, per axis (for the written-out adjoints)."""
    return [fx - 1.5, -2.0 * (fx - 1.0), fx - 0.5]


@ti.func
def func_weight_grad(w, dw, i: ti.template(), j: ti.template(), k: ti.template()):
    """d W_o / d fx of node o = (i, j, k)'s weight W_o = w_i(fx_0) w_j(fx_1) w_k(fx_2)."""
    return ti.Vector([dw[i][0] * w[j][1] * w[k][2], w[i][0] * dw[j][1] * w[k][2], w[i][0] * w[j][1] * dw[k][2]])


@ti.func
def func_p2g(s: ti.template(), i_b, i_p, src, dt, atomic: ti.template()):
    x = s.x[src, i_b, i_p]
    m = s.p_mass[i_p]
    base, fx, w = func_stencil(s, x)
    stress = (-dt * s.p_vol[i_p] * 4.0 * s.inv_dx * s.inv_dx) * s.tau[src, i_b, i_p]
    affine = stress + m * s.C[src, i_b, i_p]
    # momentum at node base + o: m v + dt f + affine (o - fx) dx = q + dx (o_0 a_0 + o_1 a_1 + o_2 a_2)
    # with a_k the columns of affine: o's entries are the constants 0, 1, 2, so each node costs a few
    # vector adds instead of a matrix product (a smaller kernel, and an adjoint that compiles faster)
    q = m * s.v[src, i_b, i_p] + dt * s.f_ext[i_b, i_p] - affine @ (fx * s.dx)
    a0 = ti.Vector([affine[0, 0], affine[1, 0], affine[2, 0]]) * s.dx
    a1 = ti.Vector([affine[0, 1], affine[1, 1], affine[2, 1]]) * s.dx
    a2 = ti.Vector([affine[0, 2], affine[1, 2], affine[2, 2]]) * s.dx
    for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
        weight = w[i][0] * w[j][1] * w[k][2]
        I = base + ti.Vector([i, j, k])
        if ti.static(atomic):
            s.grid_mv[i_b, I] += weight * (q + float(i) * a0 + float(j) * a1 + float(k) * a2)
            s.grid_m[i_b, I] += weight * m
        else:  # (a load and a store: the caller guarantees no other thread adds to this env's grid)
            s.grid_mv[i_b, I] = s.grid_mv[i_b, I] + weight * (q + float(i) * a0 + float(j) * a1 + float(k) * a2)
            s.grid_m[i_b, I] = s.grid_m[i_b, I] + weight * m


@ti.func
def func_p2g_adjoint(s: ti.template(), i_b, i_p, src, dt):
    """Adjoint of func_p2g, written out: the particle gathers the adjoints of the 27 nodes' momenta and
    masses (no atomics: each particle writes only its own adjoints) into those of its position, velocity,
    C, stress tau (slot src) and external force. Taichi's adjoint of the atomic scatter computes the same
    sums with the stencil recomputed per node (solver.py kernel_p2g_grad: ~2x faster on the CPU).

    Forward (func_p2g): node o gets W_o (q + sum_c o_c a_c) and W_o m, with q = m v + dt f - A fx dx,
    a_c = A[:, c] dx, A = k tau + m C, k = -dt V 4/dx^2, W_o the product of the B-spline weights of fx."""
    x = s.x[src, i_b, i_p]
    m = s.p_mass[i_p]
    base, fx, w = func_stencil(s, x)
    dw = func_stencil_dw(fx)
    ks = -dt * s.p_vol[i_p] * 4.0 * s.inv_dx * s.inv_dx
    affine = ks * s.tau[src, i_b, i_p] + m * s.C[src, i_b, i_p]
    q = m * s.v[src, i_b, i_p] + dt * s.f_ext[i_b, i_p] - affine @ (fx * s.dx)
    a0 = ti.Vector([affine[0, 0], affine[1, 0], affine[2, 0]]) * s.dx
    a1 = ti.Vector([affine[0, 1], affine[1, 1], affine[2, 1]]) * s.dx
    a2 = ti.Vector([affine[0, 2], affine[1, 2], affine[2, 2]]) * s.dx
    g_q = ti.Vector.zero(float, 3)
    g0 = ti.Vector.zero(float, 3)
    g1 = ti.Vector.zero(float, 3)
    g2 = ti.Vector.zero(float, 3)
    g_fx = ti.Vector.zero(float, 3)
    for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
        I = base + ti.Vector([i, j, k])
        G = s.grid_mv.grad[i_b, I]
        wt = w[i][0] * w[j][1] * w[k][2]
        wG = wt * G
        g_q += wG
        g0 += float(i) * wG
        g1 += float(j) * wG
        g2 += float(k) * wG
        gW = G.dot(q + float(i) * a0 + float(j) * a1 + float(k) * a2) + s.grid_m.grad[i_b, I] * m
        g_fx += gW * func_weight_grad(w, dw, i, j, k)
    # q = ... - A (fx dx) and a_c = A[:, c] dx: the adjoint of A, column by column
    fxd = fx * s.dx
    gA = ti.Matrix.cols([s.dx * g0 - fxd[0] * g_q, s.dx * g1 - fxd[1] * g_q, s.dx * g2 - fxd[2] * g_q])
    g_fx -= s.dx * (affine.transpose() @ g_q)
    s.v.grad[src, i_b, i_p] = s.v.grad[src, i_b, i_p] + m * g_q
    s.f_ext.grad[i_b, i_p] = s.f_ext.grad[i_b, i_p] + dt * g_q
    s.C.grad[src, i_b, i_p] = s.C.grad[src, i_b, i_p] + m * gA
    s.tau.grad[src, i_b, i_p] = s.tau.grad[src, i_b, i_p] + ks * gA
    s.x.grad[src, i_b, i_p] = s.x.grad[src, i_b, i_p] + s.inv_dx * g_fx
