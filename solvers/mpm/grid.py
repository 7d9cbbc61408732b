"""Stage 3 of an MLS-MPM substep, grid update, one node each: momentum -> velocity, gravity, then the
walls at the domain's faces (Coulomb friction); the rigid boundaries of solvers/coupling.py come after
these when a scene couples rigid bodies to MPM.

Single-assignment form with 0/1 masks for Taichi's reverse mode (no branches on differentiable data). The
update's adjoint is also written out (func_grid_velocity_adjoint, func_wall_adjoint): Taichi's adds every node's
share of gravity's adjoint atomically into one vector, which costs more than the rest of the update's adjoint.
"""
import taichi as ti

TINY = 1e-18  # squared in adjoints (d(1/m)/dm): must stay finite in float32


@ti.func
def func_grid_velocity(s: ti.template(), i_b, I, dt):
    """Velocity of node I from its momentum and mass, with gravity, before boundaries."""
    m = s.grid_m[i_b, I]
    inv_m = ti.cast(m > 0.0, float) / ti.max(m, TINY)
    return s.grid_mv[i_b, I] * inv_m + dt * s.gravity[i_b]


@ti.func
def func_wall(s: ti.template(), v, I, d: ti.template()):
    """Grid velocity v at node I after the walls normal to axis d: a node at most `bound` cells from a
    face (up to the plane that particles are kept behind, solver.BOUND) loses its velocity into the
    wall, and Coulomb friction (the coefficient wall_friction[d] of the faces normal to axis d, 0 by
    default as in Genesis) slows its tangential velocity by mu |v_n|, never reversing it."""
    n, vn, into, vt, vt_norm = func_wall_frame(s, v, I, d)
    slide = vt * ti.max(0.0, 1.0 + ti.static(s.wall_friction[d]) * vn / vt_norm)
    return into * slide + (1.0 - into) * v


@ti.func
def func_wall_frame(s: ti.template(), v, I, d: ti.template()):
    """The wall's inward normal n at node I (0 away from the faces normal to axis d), v's normal part vn,
    whether v goes into the wall (`into`, a 0/1 mask), v's tangential part vt and its smoothed norm."""
    low = ti.cast(I[d] <= s.bound, float)
    high = ti.cast(I[d] >= s.grid_res[d] - 1 - s.bound, float)
    n = ti.Vector([1.0 if d == 0 else 0.0, 1.0 if d == 1 else 0.0, 1.0 if d == 2 else 0.0]) * (low - high)
    vn = v.dot(n)
    into = ti.cast(vn < 0.0, float) * (low + high)
    vt = v - vn * n
    vt_norm = ti.sqrt(vt.dot(vt) + 1e-12)  # 1e-6 m/s smoothing keeps 1/vt_norm^2 finite in float32
    return n, vn, into, vt, vt_norm


@ti.func
def func_walls(s: ti.template(), v, I):
    v1 = func_wall(s, v, I, 0)
    v2 = func_wall(s, v1, I, 1)
    return func_wall(s, v2, I, 2)


@ti.func
def func_wall_adjoint(s: ti.template(), v, g_out, I, d: ti.template()):
    """Adjoint of func_wall: the adjoint of its input v from that of its output, with the same choices of
    branch as Taichi's reverse mode (the 0/1 masks are constants; max(0, r) passes to r where r > 0)."""
    n, vn, into, vt, vt_norm = func_wall_frame(s, v, I, d)
    mu = ti.static(s.wall_friction[d])
    r = 1.0 + mu * vn / vt_norm
    g_slide = into * g_out
    g_vt = g_slide * ti.max(0.0, r)
    g_vn = 0.0
    if ti.static(mu != 0.0):
        g_r = ti.cast(r > 0.0, float) * g_slide.dot(vt)
        g_vn = mu * g_r / vt_norm
        g_vt += (-mu * vn * g_r / (vt_norm * vt_norm * vt_norm)) * vt
    g_vn -= g_vt.dot(n)
    return (1.0 - into) * g_out + g_vt + g_vn * n


@ti.func
def func_grid_velocity_adjoint(s: ti.template(), i_b, I, dt):
    """Adjoint of node I's velocity (func_walls of func_grid_velocity) into the adjoints of its momentum and
    mass (plain adds: one thread per node); returns its share dt g_v0 of gravity's adjoint, which the caller
    sums."""
    m = s.grid_m[i_b, I]
    inv_m = ti.cast(m > 0.0, float) / ti.max(m, TINY)
    mv = s.grid_mv[i_b, I]
    v0 = mv * inv_m + dt * s.gravity[i_b]
    v1 = func_wall(s, v0, I, 0)
    v2 = func_wall(s, v1, I, 1)
    g2 = func_wall_adjoint(s, v2, s.grid_v.grad[i_b, I], I, 2)
    g1 = func_wall_adjoint(s, v1, g2, I, 1)
    g0 = func_wall_adjoint(s, v0, g1, I, 0)
    s.grid_mv.grad[i_b, I] = s.grid_mv.grad[i_b, I] + inv_m * g0
    s.grid_m.grad[i_b, I] = s.grid_m.grad[i_b, I] - ti.cast(m > TINY, float) * inv_m * inv_m * g0.dot(mv)
    return dt * g0
