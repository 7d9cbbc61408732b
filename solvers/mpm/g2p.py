"""Stage 4 of an MLS-MPM substep, grid to particle: each particle gathers its new velocity and affine
velocity C (APIC) from the 27 nodes around it and moves with the new velocity.
"""
import taichi as ti

from .p2g import func_stencil


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
