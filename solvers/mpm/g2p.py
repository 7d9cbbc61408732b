"""Stage 4 of an MLS-MPM substep, grid to particle: each particle gathers its new velocity and affine
velocity C (APIC) from the 27 nodes around it and moves with the new velocity.
"""
import taichi as ti

from .p2g import func_stencil


@ti.func
def func_g2p(s: ti.template(), i_b, i_p, src, dst, dt):
    x = s.x[src, i_b, i_p]
    base, fx, w = func_stencil(s, x)
    new_v = ti.Vector.zero(float, 3)
    # C accumulated column by column: Taichi 1.7's reverse mode without advanced_optimization crashes
    # on a matrix-valued local accumulated in a loop (a segfault in the adjoint kernel)
    c0 = ti.Vector.zero(float, 3)
    c1 = ti.Vector.zero(float, 3)
    c2 = ti.Vector.zero(float, 3)
    for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
        dpos = ti.cast(offset, float) - fx
        g_v = s.grid_v[i_b, base + offset]
        weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2]
        new_v += weight * g_v
        wg = (4.0 * s.inv_dx * weight) * g_v
        c0 += wg * dpos[0]
        c1 += wg * dpos[1]
        c2 += wg * dpos[2]
    # a particle never leaves the grid (the walls stop it before; this guards against blow-ups)
    x_new = x + dt * new_v
    s.x[dst, i_b, i_p] = ti.Vector([ti.min(ti.max(x_new[a], s.x_min[a]), s.x_max[a]) for a in ti.static(range(3))])
    s.v[dst, i_b, i_p] = new_v
    s.C[dst, i_b, i_p] = ti.Matrix.cols([c0, c1, c2])
