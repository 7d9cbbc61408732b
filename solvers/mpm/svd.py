"""3x3 singular value decomposition by cyclic Jacobi rotations on F^T F.

Taichi's `ti.svd` (McAdams et al.'s approximate Givens iterations) costs about 2.5 us per matrix in
float64 on this project's CPUs and reassembles F only to ~1e-10; MPM calls it once per particle and
substep, forward and backward. Here: four sweeps of exact Jacobi rotations diagonalise A = F^T F
(quadratic convergence: round-off level for 3x3), V holds its eigenvectors, s = sqrt(eig), and U is
F V / s completed to a rotation. Convention as Taichi's: det U = det V = 1, s sorted descending, the
last singular value negative when det F < 0. Not differentiated: the adjoint of the maps built on it is
written out in constitutive.py.

Also the polar rotation R of F = R S by Newton's iteration (func_polar), which corotated elasticity
needs instead of the whole SVD: three to five iterations for the stretches of an elastic body, each
a few cross products, where the Jacobi SVD costs three to five times as much.
"""
import taichi as ti

SWEEPS = 4
TINY = 1e-30


@ti.func
def func_jacobi_rotate(A, V, p: ti.template(), q: ti.template()):
    """One Jacobi rotation zeroing A[p, q] of the symmetric A: returns (J^T A J, V J), touching only
    the entries that change (rows and columns p, q) to keep the unrolled sweeps small."""
    r = 3 - p - q
    apq = A[p, q]
    c = 1.0
    s = 0.0
    t = 0.0
    if ti.abs(apq) > TINY:
        theta = (A[q, q] - A[p, p]) / (2.0 * apq)
        t = ti.select(theta >= 0.0, 1.0, -1.0) / (ti.abs(theta) + ti.sqrt(theta * theta + 1.0))
        c = 1.0 / ti.sqrt(t * t + 1.0)
        s = t * c
    B = A
    B[p, p] = A[p, p] - t * apq
    B[q, q] = A[q, q] + t * apq
    B[p, q] = 0.0
    B[q, p] = 0.0
    arp = c * A[r, p] - s * A[r, q]
    arq = s * A[r, p] + c * A[r, q]
    B[r, p] = arp
    B[p, r] = arp
    B[r, q] = arq
    B[q, r] = arq
    W = V
    for i in ti.static(range(3)):
        W[i, p] = c * V[i, p] - s * V[i, q]
        W[i, q] = s * V[i, p] + c * V[i, q]
    return B, W


@ti.func
def func_swap_desc(e, V, i: ti.template(), j: ti.template()):
    """Order eigenpairs i < j so that e[i] >= e[j]."""
    e2 = e
    V2 = V
    if e[i] < e[j]:
        e2[i] = e[j]
        e2[j] = e[i]
        for r in ti.static(range(3)):
            V2[r, i] = V[r, j]
            V2[r, j] = V[r, i]
    return e2, V2


@ti.func
def func_any_perpendicular(u):
    """A unit vector perpendicular to the unit vector u."""
    a = ti.Vector([1.0, 0.0, 0.0])
    if ti.abs(u[0]) > 0.7:
        a = ti.Vector([0.0, 1.0, 0.0])
    w = a - a.dot(u) * u
    return w / w.norm()


@ti.func
def func_svd3(F):
    """(U, s, V) with F = U diag(s) V^T."""
    A = F.transpose() @ F
    V = ti.Matrix.identity(float, 3)
    for _ in ti.static(range(SWEEPS)):
        A, V = func_jacobi_rotate(A, V, 0, 1)
        A, V = func_jacobi_rotate(A, V, 0, 2)
        A, V = func_jacobi_rotate(A, V, 1, 2)
    e = ti.Vector([A[0, 0], A[1, 1], A[2, 2]])
    e, V = func_swap_desc(e, V, 0, 1)
    e, V = func_swap_desc(e, V, 0, 2)
    e, V = func_swap_desc(e, V, 1, 2)
    if V.determinant() < 0.0:
        for r in ti.static(range(3)):
            V[r, 2] = -V[r, 2]
    v0 = ti.Vector([V[0, 0], V[1, 0], V[2, 0]])
    v1 = ti.Vector([V[0, 1], V[1, 1], V[2, 1]])
    v2 = ti.Vector([V[0, 2], V[1, 2], V[2, 2]])
    f0 = F @ v0
    f1 = F @ v1
    n0 = f0.norm()
    u0 = ti.Vector([1.0, 0.0, 0.0])
    if n0 > TINY:
        u0 = f0 / n0
    w1 = f1 - f1.dot(u0) * u0
    n1 = w1.norm()
    u1 = func_any_perpendicular(u0)
    if n1 > 1e-12 * ti.max(n0, TINY):
        u1 = w1 / n1
    u2 = u0.cross(u1)
    s = ti.Vector([n0, u1.dot(f1), u2.dot(F @ v2)])
    U = ti.Matrix.cols([u0, u1, u2])
    return U, s, V


@ti.func
def func_cofactor(F):
    """d det(F) / dF = det(F) F^-T: the columns f1 x f2, f2 x f0, f0 x f1 of F's columns f0, f1, f2."""
    f0 = ti.Vector([F[0, 0], F[1, 0], F[2, 0]])
    f1 = ti.Vector([F[0, 1], F[1, 1], F[2, 1]])
    f2 = ti.Vector([F[0, 2], F[1, 2], F[2, 2]])
    return ti.Matrix.cols([f1.cross(f2), f2.cross(f0), f0.cross(f1)])


POLAR_MAX_ITERS = 20
# squared Frobenius norm of an iteration's change below which it has converged (the error after it is
# about the change squared), by the solver's precision in bits (MPMSolver.bits)
POLAR_TOL = {32: 1e-12, 64: 1e-26}


@ti.func
def func_polar(F, tol: ti.template()):
    """(R, ok): the rotation of the polar decomposition F = R S (S symmetric positive definite) by
    Newton's iteration X <- (X + X^-T) / 2 from X = F, whose fixed point is R and which converges
    quadratically once near it (Higham 1986; unscaled: F of an elastic body is near a rotation).
    X^-T is the cofactor matrix over det X (its first column dotted with X's). ok is False when det F
    <= 0 (an inverted particle: R would be a reflection) or the iteration has not converged in
    POLAR_MAX_ITERS; the caller then takes the SVD (func_svd3), whose U V^T is the same R."""
    X = F
    ok = F.determinant() > 0.0
    converged = False
    n = 0
    while ok and not converged:
        C = func_cofactor(X)
        Y = 0.5 * (X + C / (X[0, 0] * C[0, 0] + X[1, 0] * C[1, 0] + X[2, 0] * C[2, 0]))
        converged = (Y - X).norm_sqr() < tol
        X = Y
        n += 1
        if n >= POLAR_MAX_ITERS and not converged:
            ok = False
    return X, ok
