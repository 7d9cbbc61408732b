"""Stage 1 of an MLS-MPM substep, constitutive update: the deformation gradient moves with the particle's
velocity gradient C, materials return it to their yield surface, and the Kirchhoff stress follows.

    F_trial = (I + dt C) F,   F_new = plastic return of F_trial,   tau = Kirchhoff stress of F_new

Materials (codes in MAT_*), with Lame parameters mu, lam (Pa):
- ELASTIC, corotated:    F_new = F_trial,  tau = 2 mu (F - R) F^T + lam (J - 1) J I   (R: rotation of F)
- NEOHOOKEAN:            F_new = F_trial,  tau = mu (F F^T - I) + lam log(J) I
- PLASTIC (plasticine):  von Mises return in Hencky strain (yield stress ys, Pa), corotated elasticity
- SAND:                  Drucker-Prager return in Hencky strain (Klar et al. 2016; alpha from the friction
                         angle), St. Venant-Kirchhoff elasticity in Hencky strain
- LIQUID:                F_new = J^(1/3) I,  tau = lam J (J - 1) I + eta J (C + C^T)   (viscosity eta, Pa s)

The three that need the singular values of F_trial (ELASTIC, PLASTIC, SAND) are isotropic maps
F_trial = U diag(s) V^T -> F_new = U diag(h(s)) V^T, tau = U diag(t(s)) U^T. ELASTIC's forward needs only
the rotation R = U V^T, which svd.func_polar finds in a third to a fifth of the SVD's time (solver.py,
func_constitutive_svd); the SVD stays its fallback (inverted particles). Its adjoint likewise goes
through R (func_corotated_polar_adjoint) where the forward did. Taichi's reverse mode
cannot differentiate an SVD where singular values coincide (every particle at rest), so their adjoint
is written out here (`func_svd_adjoint`) from the derivatives of isotropic matrix functions: with
dF~ = U^T dF V split into its symmetric part S and skew part A,
    U^T dF_new V = diag(Jh ds) + S o (h_i - h_j)/(s_i - s_j) + A o (h_i + h_j)/(s_i + s_j)
    U^T dtau  U  = diag(Jt ds) + S o (t_i - t_j)/(s_i - s_j) + A o (t_j - t_i)/(s_i + s_j)
(o: entrywise, off the diagonal), whose divided differences stay finite as s_i -> s_j (their limit
is taken from the Jacobians Jh = dh/ds, Jt = dt/ds, which each material supplies with the
derivatives of h and t with respect to its parameters). The other two materials are polynomial in F
and C and go through Taichi's autodiff.
"""
import taichi as ti

from .svd import func_cofactor

MAT_ELASTIC, MAT_NEOHOOKEAN, MAT_PLASTIC, MAT_SAND, MAT_LIQUID = 0, 1, 2, 3, 4
SVD_MATERIALS = (MAT_ELASTIC, MAT_PLASTIC, MAT_SAND)
AD_MATERIALS = (MAT_NEOHOOKEAN, MAT_LIQUID)

PLASTIC_MIN_STRETCH = 0.05  # singular values clamped below (as Genesis does) so log strains stay finite
SAND_MIN_STRETCH = 1e-4
DEGENERATE = 1e-6  # |s_i - s_j| below which a divided difference is taken from the Jacobian
TINY = 1e-20


@ti.func
def func_others(s):
    """(s1 s2, s0 s2, s0 s1): dJ/ds for J = s0 s1 s2, without dividing by a singular value."""
    return ti.Vector([s[1] * s[2], s[0] * s[2], s[0] * s[1]])


@ti.func
def func_corotated(s, mu, lam):
    """Principal Kirchhoff stresses of corotated elasticity at stretches s, their Jacobian and
    derivatives with respect to (mu, lam)."""
    J = s[0] * s[1] * s[2]
    Jk = func_others(s)
    t = 2.0 * mu * (s - 1.0) * s + lam * (J - 1.0) * J
    Jt = ti.Matrix.zero(float, 3, 3)
    for i, k in ti.static(ti.ndrange(3, 3)):
        Jt[i, k] = lam * (2.0 * J - 1.0) * Jk[k]
        if ti.static(i == k):
            Jt[i, k] += 2.0 * mu * (2.0 * s[i] - 1.0)
    dmu = 2.0 * (s - 1.0) * s
    dlam = ti.Vector([1.0, 1.0, 1.0]) * (J - 1.0) * J
    return t, Jt, dmu, dlam


@ti.func
def func_hencky(s, mu, lam):
    """Principal Kirchhoff stresses of St. Venant-Kirchhoff elasticity in Hencky strain log(s)."""
    e = ti.log(s)
    tr = e.sum()
    t = 2.0 * mu * e + lam * tr
    Jt = ti.Matrix.zero(float, 3, 3)
    for i, k in ti.static(ti.ndrange(3, 3)):
        Jt[i, k] = lam / s[k]
        if ti.static(i == k):
            Jt[i, k] += 2.0 * mu / s[k]
    dmu = 2.0 * e
    dlam = ti.Vector([tr, tr, tr])
    return t, Jt, dmu, dlam


@ti.func
def func_deviatoric_direction(e):
    """Unit deviatoric direction m of strain e, its norm n and d(e_hat / n)/d e = (P - m m^T) / n."""
    e_hat = e - e.sum() / 3.0
    n = ti.sqrt(e_hat.dot(e_hat) + TINY)
    m = e_hat / n
    P = ti.Matrix.identity(float, 3) - 1.0 / 3.0
    return m, n, (P - m.outer_product(m)) / n


@ti.func
def func_principal(mat, s, mu, lam, ys, alpha, deriv: ti.template(), present: ti.template()):
    """For SVD materials: h (singular values of F_new) and t (principal Kirchhoff stresses) as
    functions of the trial singular values s; with `deriv` also their Jacobians Jh, Jt and their
    derivatives with respect to the parameters (mu, lam, ys, alpha) as the columns of 3x4 matrices
    (zero otherwise: the forward pass does not pay for them). Only the materials in `present` (the
    scene's) are compiled."""
    h = s
    Jh = ti.Matrix.identity(float, 3)
    dh = ti.Matrix.zero(float, 3, 4)
    if ti.static(MAT_PLASTIC in present) and mat == MAT_PLASTIC:
        sc = ti.max(s, PLASTIC_MIN_STRETCH)
        e = ti.log(sc)
        m, n, dm = func_deviatoric_direction(e)
        c = ys / (2.0 * mu)
        de = ti.Matrix.identity(float, 3)  # d e' / d e
        yields = n - c > 0.0
        if yields:  # back onto the von Mises cylinder
            e = e.sum() / 3.0 + c * m
            de = 1.0 / 3.0 + c * dm
        h = ti.exp(e)
        if ti.static(deriv):
            for i, k in ti.static(ti.ndrange(3, 3)):
                Jh[i, k] = h[i] * de[i, k] / sc[k] * ti.cast(s[k] > PLASTIC_MIN_STRETCH, float)
            if yields:
                for i in ti.static(range(3)):
                    dh[i, 0] = -h[i] * c / mu * m[i]
                    dh[i, 2] = h[i] * m[i] / (2.0 * mu)
    if ti.static(MAT_SAND in present) and mat == MAT_SAND:
        sc = ti.max(s, SAND_MIN_STRETCH)
        e = ti.log(sc)
        tr = e.sum()
        m, n, dm = func_deviatoric_direction(e)
        kappa = (3.0 * lam + 2.0 * mu) * alpha / (2.0 * mu)
        dgamma = n + kappa * tr
        Jh = ti.Matrix.zero(float, 3, 3)
        if tr >= 0.0:  # the grains separate: no elastic strain is kept
            h = ti.Vector([1.0, 1.0, 1.0])
        elif dgamma <= 0.0:  # inside the cone: elastic
            h = sc
            if ti.static(deriv):
                for k in ti.static(range(3)):
                    Jh[k, k] = ti.cast(s[k] > SAND_MIN_STRETCH, float)
        else:  # outside the cone: back onto it along the deviatoric direction
            h = ti.exp(e - dgamma * m)
            if ti.static(deriv):
                de = 1.0 / 3.0 - kappa * m.outer_product(ti.Vector([1.0, 1.0, 1.0])) - kappa * tr * dm
                for i, k in ti.static(ti.ndrange(3, 3)):
                    Jh[i, k] = h[i] * de[i, k] / sc[k] * ti.cast(s[k] > SAND_MIN_STRETCH, float)
                # d kappa / d (mu, lam, ys, alpha)
                dk = ti.Vector([-3.0 * lam * alpha / (2.0 * mu * mu), 3.0 * alpha / (2.0 * mu), 0.0,
                                (3.0 * lam + 2.0 * mu) / (2.0 * mu)])
                for i, j in ti.static(ti.ndrange(3, 4)):
                    dh[i, j] = -h[i] * tr * m[i] * dk[j]
    t = ti.Vector.zero(float, 3)
    Jt0 = ti.Matrix.zero(float, 3, 3)
    dmu = ti.Vector.zero(float, 3)
    dlam = ti.Vector.zero(float, 3)
    if ti.static(MAT_SAND in present) and mat == MAT_SAND:
        t, Jt0, dmu, dlam = func_hencky(h, mu, lam)
    if ti.static(MAT_ELASTIC in present or MAT_PLASTIC in present) and mat != MAT_SAND:
        t, Jt0, dmu, dlam = func_corotated(h, mu, lam)
    Jt = Jt0 @ Jh
    dt = Jt0 @ dh
    for i in ti.static(range(3)):
        dt[i, 0] += dmu[i]
        dt[i, 1] += dlam[i]
    return h, Jh, dh, t, Jt, dt


@ti.func
def func_divided(f, Jf, s, i: ti.template(), j: ti.template()):
    """(f_i - f_j) / (s_i - s_j), or its limit from the Jacobian when s_i and s_j (nearly) coincide."""
    ds = s[i] - s[j]
    out = 0.5 * (Jf[i, i] - Jf[i, j] + Jf[j, j] - Jf[j, i])
    if ti.abs(ds) > DEGENERATE:
        out = (f[i] - f[j]) / ds
    return out


@ti.func
def func_svd_adjoint(U, s, V, h, Jh, t, Jt, gF, gtau):
    """Gradient with respect to F_trial = U diag(s) V^T of <gF, U diag(h) V^T> + <gtau, U diag(t) U^T>
    (see the module docstring), and the diagonals of U^T gF V and U^T gtau U, which the parameter
    gradients need."""
    HG = U.transpose() @ gF @ V
    HT = U.transpose() @ gtau @ U
    G = ti.Matrix.zero(float, 3, 3)
    for i, j in ti.static(ti.ndrange(3, 3)):
        if ti.static(i == j):
            acc = 0.0
            for k in ti.static(range(3)):
                acc += HG[k, k] * Jh[k, i] + HT[k, k] * Jt[k, i]
            G[i, i] = acc
        else:
            symG = 0.5 * (HG[i, j] + HG[j, i])
            skwG = 0.5 * (HG[i, j] - HG[j, i])
            symT = 0.5 * (HT[i, j] + HT[j, i])
            den = s[i] + s[j]
            den = ti.select(ti.abs(den) > TINY, den, TINY)
            G[i, j] = (symG * func_divided(h, Jh, s, i, j) + skwG * (h[i] + h[j]) / den
                       + symT * (func_divided(t, Jt, s, i, j) + (t[j] - t[i]) / den))
    diagG = ti.Vector([HG[0, 0], HG[1, 1], HG[2, 2]])
    diagT = ti.Vector([HT[0, 0], HT[1, 1], HT[2, 2]])
    return U @ G @ V.transpose(), diagG, diagT


@ti.func
def func_ad_material(mat, F, C, dt, mu, lam, eta, present: ti.template()):
    """(F_new, tau) of the materials differentiated by Taichi (NEOHOOKEAN, LIQUID) from F_trial; only
    those in `present` are compiled. Single-assignment form with a 0/1 blend: Taichi's reverse mode
    wants no branches on data here (and crashed on a matrix local stored twice)."""
    J = F.determinant()
    I = ti.Matrix.identity(float, 3)
    Jc = ti.max(J, 1e-6)
    w = ti.cast(mat == MAT_NEOHOOKEAN, float) if ti.static(MAT_NEOHOOKEAN in present and MAT_LIQUID in present) \
        else (1.0 if ti.static(MAT_NEOHOOKEAN in present) else 0.0)
    F_new = w * F + (1.0 - w) * I * ti.pow(Jc, 1.0 / 3.0)
    tau = w * (mu * (F @ F.transpose() - I) + lam * ti.log(Jc) * I) + (1.0 - w) * (
        lam * J * (J - 1.0) * I + eta * J * (C + C.transpose()))
    return F_new, tau


@ti.func
def func_corotated_polar_adjoint(F, R, mu, lam, G):
    """(dL/dF, dL/dmu, dL/dlam) of corotated elasticity's tau = mu (Q + Q^T) + lam (J - 1) J I, Q = (F - R) F^T,
    from G = dL/dtau, with R the rotation of F = R S (svd.func_polar, det F > 0). With H = G + G^T:
        dL = mu <2 H F - H R, dF> - mu <H F, dR> + lam (2 J - 1) tr(G) <cof F, dF>,
    and R's variation dR = R [w]x, where (tr(S) I - S) w is the axial vector of R^T dF - dF^T R (from
    dF = dR S + R dS). So -mu <H F, dR> = <R [y]x, dF> for y = (tr(S) I - S)^-1 m, m the axial vector
    of M - M^T, M = -mu R^T H F. tr(S) I - S has the eigenvalues s_i + s_j > 0: no divided differences,
    nothing degenerate where singular values coincide (which the SVD's adjoint has to work around)."""
    H = G + G.transpose()
    J = F.determinant()
    HF = H @ F
    M = -mu * R.transpose() @ HF
    m = ti.Vector([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    S = R.transpose() @ F
    S = 0.5 * (S + S.transpose())
    y = (S.trace() * ti.Matrix.identity(float, 3) - S).inverse() @ m
    Y = ti.Matrix([[0.0, -y[2], y[1]], [y[2], 0.0, -y[0]], [-y[1], y[0], 0.0]])
    trG = G.trace()
    gF = mu * (2.0 * HF - H @ R) + R @ Y + lam * (2.0 * J - 1.0) * trG * func_cofactor(F)
    return gF, (H * ((F - R) @ F.transpose())).sum(), trG * (J - 1.0) * J
