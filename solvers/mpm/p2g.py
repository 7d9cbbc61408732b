"""Stage 2 of an MLS-MPM substep (quadratic B-splines, APIC), particle to grid: each particle adds its
mass, its momentum m v plus its external impulse dt f, and the affine momentum
(m C - dt V 4/dx^2 tau)(x_node - x_p) to the 27 nodes around it.

Written for Taichi's reverse mode: every local is assigned once, the scatter is an atomic add (its
adjoint is a gather). The no-gradient substep scatters with plain adds instead (`atomic=False`), from a
loop in which one thread owns each env's grid (solver.py kernel_substep_nograd): on the CPU a float
atomic add is a compare-and-swap loop, and the 108 of them per particle cost five times the rest of the
particle-to-grid transfer.
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
