"""Compiled C/GMRES kernels (Ohtsuka 2004): sweeps, F(U, x, t), forward-difference GMRES, a tick.

Everything a tick needs runs inside the single call :func:`rhc_tick` on preallocated arrays:

* ``F(U, x, T)``: Euler forward sweep ``x_{r+1} = x_r + h f(x_r, u_k)`` (S substeps of
  ``h = dtau / S`` per stage, S = 1 unless ``T/N`` is too long for the plant's ~40 /s modes),
  backward sweep ``lam = phi_x(x_N)``, ``lam_r = lam_{r+1} + h H_x(x_r, u_k, lam_{r+1})``, and per
  stage ``(mean H_u + 2 mu u, -r_v + 2 mu v, u^2 + v^2 - umax^2)``. ``F = 0`` are the KKT
  conditions of the discretised problem (``dtau`` times the first rows is its exact gradient).
* One linear solve per tick: Ohtsuka's ``F_U Udot = -zeta F - F_x xdot - F_t`` at the *measured*
  state, its two right-hand sides kept apart in one block Krylov basis (:func:`block_gmres`):
  ``d1 = -c F_U^-1 F`` (``c = min(zeta dt, 1)``, the correction to the measured state) and
  ``d2 = -dt F_U^-1 (F_x xdot + F_t)`` (the prediction, by one forward difference). The input
  applied at this tick is the first one of ``U + d1``; the next tick starts from
  ``U + d1 + d2``. F is evaluated kmax + 3 times per tick (the two-solve tick it replaces took 14
  for kmax = 5, at the same closed-loop cost J).

Applying the corrected input rather than the predicted one matters for a loop sampled at 50 Hz:
the plant's fast modes are ~40 /s, comparable to 1 / period.

Each GMRES solve runs (at most) ``kmax`` iterations with forward-difference products
``(F(U + h v) - F(U)) / h`` and Givens rotations, right-preconditioned by a per-stage block
inverse (:func:`precond_setup`): the dummy/multiplier rows are eliminated exactly, the input block
uses ``2 R^-1 + 4 dtau M^-1`` (the Hessian of the cost-to-go 4V). After every update the dummy
inputs are put back on their circles with ``v >= vmin`` (:func:`clip_dummies`) and bounds whose
multiplier turned negative are restarted inside the box (:func:`release_bounds`). The initial
solution (first tick, and after a fallback) is found by Newton-GMRES with backtracking.

All compiled code lives in this one module on purpose: numba's cache is keyed on the source file
of each function, so a compiled function calling into another module would keep stale machine
code when only that other module changed. The OCP itself is documented in
:mod:`rt_controller.control.rhc.problem`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from rt_controller.control.state import IP, NAUX, NPRE, NS, NX, PAR, ST, W, work_offsets

# ============================================================================================
# Parameter layout and the optimal control problem (see rt_controller.control.rhc.problem)
# ============================================================================================

JIT = {"cache": True, "error_model": "numpy", "fastmath": {"nsz", "arcp", "contract", "reassoc"}}
"""numba options: cached, IEEE NaN/inf semantics kept (the fallback relies on them)."""


@njit(inline="always", **JIT)
def horizon_at(P, t):
    """T(t) = Tf (1 - exp(-a t)), or Tf when a = 0."""
    a = P[PAR.GROWTH]
    if a <= 0.0:
        return P[PAR.TF]
    return P[PAR.TF] * (1.0 - math.exp(-a * max(t, 0.0)))


@njit(inline="always", **JIT)
def stage_forward(P, x, u, aux, out):
    """Right-hand side of eq. (12) in (q, xi, f) coordinates into ``out`` (6).

    ``aux`` (NAUX) receives s2, c2, eta, dq, xi', M11, M12, 1/det M and C(q, dq) xi / (t3 s2).
    """
    t1, t2, t3, l1, l2, g = P[PAR.TH1], P[PAR.TH2], P[PAR.TH3], P[PAR.L1], P[PAR.L2], P[PAR.GAIN]
    s2, c2 = math.sin(x[1]), math.cos(x[1])
    xi1, xi2, f1, f2 = x[2], x[3], x[4], x[5]
    a11, a21, a22 = l1 * s2, l1 * c2 + l2, l2
    e1 = a11 * f1 + a21 * f2
    e2 = a22 * f2
    dq1 = xi1 + P[PAR.ALPHA] * e1 + P[PAR.ALPHA + 1] * e2
    dq2 = xi2 + P[PAR.ALPHA + 2] * e1 + P[PAR.ALPHA + 3] * e2
    w = dq1 + dq2
    hh = t3 * s2
    k1 = -dq2 * xi1 - w * xi2
    k2 = dq1 * xi1
    r1 = u[0] - hh * k1
    r2 = u[1] - hh * k2
    m11 = t1 + t2 + 2.0 * t3 * c2
    m12 = t2 + t3 * c2
    idet = 1.0 / (m11 * t2 - m12 * m12)
    y1 = (t2 * r1 - m12 * r2) * idet
    y2 = (-m12 * r1 + m11 * r2) * idet
    out[0] = dq1
    out[1] = dq2
    out[2] = y1
    out[3] = y2
    out[4] = -g * a11 * dq1 + w * f2
    out[5] = -g * (a21 * dq1 + a22 * dq2) - w * f1
    aux[0], aux[1], aux[2], aux[3], aux[4], aux[5] = s2, c2, e1, e2, dq1, dq2
    aux[6], aux[7], aux[8], aux[9], aux[10], aux[11], aux[12] = y1, y2, m11, m12, idet, k1, k2


@njit(**JIT)
def rhs(P, x, u, out):
    """Right-hand side of eq. (12) in (q, xi, f) coordinates into ``out`` (6)."""
    aux = np.empty(NAUX)
    stage_forward(P, x, u, aux, out)


@njit(**JIT)
def stage_cost(P, x, u):
    """l(x, u) of eq. (25) (without the dummy term)."""
    l1, l2, kp = P[PAR.L1], P[PAR.L2], P[PAR.KP]
    s2, c2 = math.sin(x[1]), math.cos(x[1])
    xi1, xi2, f1, f2 = x[2], x[3], x[4], x[5]
    e1 = l1 * s2 * f1 + (l1 * c2 + l2) * f2
    e2 = l2 * f2
    dq1 = xi1 + P[PAR.ALPHA] * e1 + P[PAR.ALPHA + 1] * e2
    dq2 = xi2 + P[PAR.ALPHA + 2] * e1 + P[PAR.ALPHA + 3] * e2
    xrx = xi1 * (P[PAR.R] * xi1 + P[PAR.R + 1] * xi2) + xi2 * (
        P[PAR.R + 2] * xi1 + P[PAR.R + 3] * xi2
    )
    uru = u[0] * (P[PAR.R_INV] * u[0] + P[PAR.R_INV + 1] * u[1]) + u[1] * (
        P[PAR.R_INV + 2] * u[0] + P[PAR.R_INV + 3] * u[1]
    )
    return 4.0 * xrx + 4.0 * kp * (e1 * dq1 + e2 * dq2) + uru


@njit(**JIT)
def terminal_cost(P, x):
    """phi = 4 V(x) of eq. (13)."""
    t1, t2, t3 = P[PAR.TH1], P[PAR.TH2], P[PAR.TH3]
    c2 = math.cos(x[1])
    xi1, xi2, f1, f2 = x[2], x[3], x[4], x[5]
    m11 = t1 + t2 + 2.0 * t3 * c2
    m12 = t2 + t3 * c2
    xmx = m11 * xi1 * xi1 + 2.0 * m12 * xi1 * xi2 + t2 * xi2 * xi2
    return 2.0 * xmx + 2.0 * P[PAR.KP] / P[PAR.GAIN] * (f1 * f1 + f2 * f2)


@njit(inline="always", **JIT)
def terminal_grad(P, x, out):
    """Gradient of phi = 4 V(x) with respect to x into ``out`` (6)."""
    t1, t2, t3 = P[PAR.TH1], P[PAR.TH2], P[PAR.TH3]
    s2, c2 = math.sin(x[1]), math.cos(x[1])
    xi1, xi2 = x[2], x[3]
    m11 = t1 + t2 + 2.0 * t3 * c2
    m12 = t2 + t3 * c2
    out[0] = 0.0
    out[1] = -4.0 * t3 * s2 * xi1 * (xi1 + xi2)
    out[2] = 4.0 * (m11 * xi1 + m12 * xi2)
    out[3] = 4.0 * (m12 * xi1 + t2 * xi2)
    c = 4.0 * P[PAR.KP] / P[PAR.GAIN]
    out[4] = c * x[4]
    out[5] = c * x[5]


@njit(**JIT)
def hamiltonian_grad(P, x, u, lam, hx, hu):
    """H_x (6) into ``hx`` and the cost-plus-dynamics part of H_u (2) into ``hu``.

    With z = M^-1 lam_xi, y = xi', sigma = lam_f1 f2 - lam_f2 f1 and dq, eta as intermediates:
    G = dH/ddq = 4 kp eta + lam_q - g A^T lam_f + sigma (1, 1) - d(z^T C(dq) xi)/ddq,
    E = dH/deta (total) = 4 kp dq + alpha^T G; then
    H_xi = 4 (R + R^T) xi - C^T z + G,  H_f = w (-lam_f2, lam_f1) + A E,
    H_q2 = -z^T M' y - z^T C' xi - g lam_f^T A' dq + f^T A' E,  H_q1 = 0,
    H_u = (R^-1 + R^-T) u + z   (the bound term 2 mu u is added by the caller).
    """
    aux = np.empty(NAUX)
    xd = np.empty(NX)
    stage_forward(P, x, u, aux, xd)
    stage_adjoint(P, x, u, lam, aux, hx, hu)


@njit(inline="always", **JIT)
def stage_adjoint(P, x, u, lam, aux, hx, hu):
    """:func:`hamiltonian_grad` from the intermediates ``aux`` of :func:`stage_forward`."""
    t3, l1, l2, g, kp = P[PAR.TH3], P[PAR.L1], P[PAR.L2], P[PAR.GAIN], P[PAR.KP]
    s2, c2, e1, e2, dq1, dq2 = aux[0], aux[1], aux[2], aux[3], aux[4], aux[5]
    y1, y2, m11, m12, idet, k1, k2 = aux[6], aux[7], aux[8], aux[9], aux[10], aux[11], aux[12]
    m22 = P[PAR.TH2]
    xi1, xi2, f1, f2 = x[2], x[3], x[4], x[5]
    lq1, lq2, lx1, lx2, lf1, lf2 = lam[0], lam[1], lam[2], lam[3], lam[4], lam[5]
    al11, al12, al21, al22 = P[PAR.ALPHA], P[PAR.ALPHA + 1], P[PAR.ALPHA + 2], P[PAR.ALPHA + 3]
    a11, a21, a22 = l1 * s2, l1 * c2 + l2, l2
    w = dq1 + dq2
    hh = t3 * s2
    z1 = (m22 * lx1 - m12 * lx2) * idet
    z2 = (-m12 * lx1 + m11 * lx2) * idet
    sigma = lf1 * f2 - lf2 * f1
    # G = dH/d(dq) with eta, xi, f, q held.
    g1 = 4.0 * kp * e1 + lq1 - g * (a11 * lf1 + a21 * lf2) + sigma - hh * (-z1 * xi2 + z2 * xi1)
    g2 = 4.0 * kp * e2 + lq2 - g * (a22 * lf2) + sigma - hh * (-z1 * (xi1 + xi2))
    # E = total dH/d(eta) = 4 kp dq + alpha^T G.
    E1 = 4.0 * kp * dq1 + al11 * g1 + al21 * g2
    E2 = 4.0 * kp * dq2 + al12 * g1 + al22 * g2
    # H_q2: M' = -t3 s2 [[2, 1], [1, 0]], C' = t3 c2 K(dq), A' = [[l1 c2, 0], [-l1 s2, 0]].
    zMy = -t3 * s2 * (2.0 * z1 * y1 + z1 * y2 + z2 * y1)
    zCxi = t3 * c2 * (z1 * k1 + z2 * k2)
    lAdq = dq1 * l1 * (c2 * lf1 - s2 * lf2)
    fAE = E1 * l1 * (c2 * f1 - s2 * f2)
    hx[0] = 0.0
    hx[1] = -zMy - zCxi - g * lAdq + fAE
    # H_xi = 4 (R + R^T) xi - C^T z + G, C^T z = hh * (-dq2 z1 + dq1 z2, -w z1).
    hx[2] = (
        4.0 * ((P[PAR.R] + P[PAR.R]) * xi1 + (P[PAR.R + 1] + P[PAR.R + 2]) * xi2)
        - hh * (-dq2 * z1 + dq1 * z2)
        + g1
    )
    hx[3] = (
        4.0 * ((P[PAR.R + 2] + P[PAR.R + 1]) * xi1 + (P[PAR.R + 3] + P[PAR.R + 3]) * xi2)
        + hh * w * z1
        + g2
    )
    # H_f = w (-lam_f2, lam_f1) + A E.
    hx[4] = -w * lf2 + a11 * E1
    hx[5] = w * lf1 + a21 * E1 + a22 * E2
    hu[0] = (P[PAR.R_INV] + P[PAR.R_INV]) * u[0] + (P[PAR.R_INV + 1] + P[PAR.R_INV + 2]) * u[1] + z1
    hu[1] = (
        (P[PAR.R_INV + 2] + P[PAR.R_INV + 1]) * u[0]
        + (P[PAR.R_INV + 3] + P[PAR.R_INV + 3]) * u[1]
        + z2
    )


# ============================================================================================
# C/GMRES: sweeps, preconditioner, forward-difference GMRES, Newton, one tick
# ============================================================================================

# Result codes of rhc_tick.
OK = 0
NOT_FINITE = 1


@njit(**JIT)
def eval_F(P, N, U, x0, T, sw, F):
    """F(U, x0, T) into ``F`` (6N); ``sw = (X, Lam, Aux, hx, hu, cnt)`` receives the predicted
    states X (N S + 1, 6), costates Lam (N S + 1, 6) and the intermediates Aux (N S, NAUX), where
    S = (rows of X - 1) / N is the number of Euler substeps per stage; ``cnt[0]`` counts the calls.

    Stage k holds u_k over S substeps of h = T / (N S); its input rows are the average of H_u over
    the substeps (times dtau they are the exact gradient of the discretised cost)."""
    X, Lam, Aux, hx, hu, cnt = sw
    S = (X.shape[0] - 1) // N
    ns = N * S
    h = T / ns
    for i in range(NX):
        X[0, i] = x0[i]
    for k in range(N):
        u = U[NS * k : NS * k + 2]
        for s in range(S):
            r = k * S + s
            stage_forward(P, X[r], u, Aux[r], hx)
            for i in range(NX):
                X[r + 1, i] = X[r, i] + h * hx[i]
    terminal_grad(P, X[ns], Lam[ns])
    rv = P[PAR.RV]
    inv_s = 1.0 / S
    for k in range(N - 1, -1, -1):
        j = NS * k
        u = U[j : j + 2]
        g0 = 0.0
        g1 = 0.0
        for s in range(S - 1, -1, -1):
            r = k * S + s
            stage_adjoint(P, X[r], u, Lam[r + 1], Aux[r], hx, hu)
            g0 += hu[0]
            g1 += hu[1]
            if r > 0:
                for i in range(NX):
                    Lam[r, i] = Lam[r + 1, i] + h * hx[i]
        if S > 1:
            g0 *= inv_s
            g1 *= inv_s
        for i in range(2):
            ui, vi, mi = U[j + i], U[j + 2 + i], U[j + 4 + i]
            F[j + i] = (g0 if i == 0 else g1) + 2.0 * mi * ui
            F[j + 2 + i] = -rv + 2.0 * mi * vi
            F[j + 4 + i] = ui * ui + vi * vi - P[PAR.U_MAX + i] * P[PAR.U_MAX + i]
    cnt[0] += 1


@njit(**JIT)
def clip_dummies(P, N, U):
    """Put every (u_i, v_i) back on its circle ``u_i^2 + v_i^2 = umax_i^2``, with ``v_i >= vmin_i``.

    The projection is radial (well conditioned at the bound, where v is tiny, and in the middle);
    the floor on v selects the minimising branch (v > 0) and keeps ``mu_i = r_v / (2 v_i)``
    finite. At a solution the constraint holds, so this changes nothing there; after a
    linearised step it removes the second-order drift off the circle.
    """
    for k in range(N):
        for i in range(2):
            j = NS * k + i
            um = P[PAR.U_MAX + i]
            vmin = P[PAR.VMIN + i]
            u, v = U[j], U[j + 2]
            if v < vmin:
                v = vmin
            r = math.sqrt(u * u + v * v)
            if r > 0.0 and math.isfinite(r):
                u *= um / r
                v *= um / r
            if v < vmin:
                v = vmin
                u = math.copysign(math.sqrt(um * um - vmin * vmin), u)
            U[j] = u
            U[j + 2] = v


@njit(inline="always", **JIT)
def norm(a):
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * a[i]
    return math.sqrt(s)


@njit(**JIT)
def precond_setup(P, N, U, X, T, pre):
    """Per-stage block-Jacobi preconditioner of F_U around U (X: the states of U's forward sweep).

    The diagonal block of stage k is approximated by ``H_uu = 2 R^-1 + 4 dtau M(q_k)^-1`` (the
    Hessian of the cost-to-go 4V, exact for the continuous problem, eq. 31) with the exact bound
    rows; the (v, mu) unknowns are eliminated analytically, leaving a 2x2 system in du.
    """
    dtau = T / N
    S = (X.shape[0] - 1) // N
    t1, t2, t3 = P[PAR.TH1], P[PAR.TH2], P[PAR.TH3]
    for k in range(N):
        j = NS * k
        c2 = math.cos(X[k * S, 1])
        m11 = t1 + t2 + 2.0 * t3 * c2
        m12 = t2 + t3 * c2
        det = m11 * t2 - m12 * m12
        c = 4.0 * dtau / det
        s11 = P[PAR.R_INV] + P[PAR.R_INV] + c * t2
        s12 = P[PAR.R_INV + 1] + P[PAR.R_INV + 2] - c * m12
        s22 = P[PAR.R_INV + 3] + P[PAR.R_INV + 3] + c * m11
        o = NPRE * k
        for i in range(2):
            ui, vi, mi = U[j + i], U[j + 2 + i], U[j + 4 + i]
            iv = 1.0 / vi
            pre[o + 4 + i] = ui * iv  # u / v
            pre[o + 6 + i] = mi * iv  # mu / v
            pre[o + 8 + i] = iv
            dgl = 2.0 * mi + 2.0 * ui * ui * mi * iv * iv
            if i == 0:
                s11 += dgl
            else:
                s22 += dgl
        sdet = s11 * s22 - s12 * s12
        pre[o + 0] = s22 / sdet
        pre[o + 1] = -s12 / sdet
        pre[o + 2] = -s12 / sdet
        pre[o + 3] = s11 / sdet


@njit(inline="always", **JIT)
def precond_apply(N, pre, r, d):
    """d = P^-1 r with the factors of :func:`precond_setup`."""
    for k in range(N):
        j = NS * k
        o = NPRE * k
        # Reduced right-hand side of the du system.
        q0 = r[j] - pre[o + 4] * r[j + 2] + pre[o + 4] * pre[o + 6] * r[j + 4]
        q1 = r[j + 1] - pre[o + 5] * r[j + 3] + pre[o + 5] * pre[o + 7] * r[j + 5]
        du0 = pre[o] * q0 + pre[o + 1] * q1
        du1 = pre[o + 2] * q0 + pre[o + 3] * q1
        for i in range(2):
            dui = du0 if i == 0 else du1
            uv, mv, iv = pre[o + 4 + i], pre[o + 6 + i], pre[o + 8 + i]
            dvi = 0.5 * iv * r[j + 4 + i] - uv * dui
            d[j + i] = dui
            d[j + 2 + i] = dvi
            d[j + 4 + i] = 0.5 * iv * r[j + 2 + i] - mv * dvi


@njit(**JIT)
def _jvp(P, N, U, x0, T, F0, v, scale, out, Ut, sw):
    """out = (F(U + h v, x0, T) - F0) / h, a forward-difference Jacobian-vector product."""
    h = P[PAR.HFD] * scale
    n = U.shape[0]
    for i in range(n):
        Ut[i] = U[i] + h * v[i]
    eval_F(P, N, Ut, x0, T, sw, out)
    for i in range(n):
        out[i] = (out[i] - F0[i]) / h


@njit(inline="always", **JIT)
def _orthogonalise(v, Vb, nv, coef, col):
    """Modified Gram-Schmidt: take out of ``v`` its component along each of the first ``nv``
    (orthonormal) rows of ``Vb`` in turn, storing the ``i``-th in ``coef[i, col]``."""
    n = v.shape[0]
    for i in range(nv):
        vi = Vb[i]
        sdot = 0.0
        for p in range(n):
            sdot += v[p] * vi[p]
        coef[i, col] = sdot
        for p in range(n):
            v[p] -= sdot * vi[p]


@njit(**JIT)
def fd_gmres(P, N, U, x0, T, F0, b, sol, use_guess, m, tol, pre, ws, sw):
    """Solve F_U(U, x0, T) sol = b by right-preconditioned GMRES(m), forward-difference products.

    ``sol`` is the initial guess when ``use_guess`` (else it starts at 0) and receives the
    solution. Stops after ``m`` iterations, at breakdown, or when the residual falls to
    ``tol * ||b - F_U sol0||`` (``tol = 0``: always ``m`` iterations). ``pre`` holds the factors of
    :func:`precond_setup`; ``ws`` is a :class:`GmresWork` tuple. Returns the iteration count.
    """
    Vb, Hs, cs, sn, g, y, Ut, z, zz = ws[0], ws[1], ws[2], ws[3], ws[4], ws[5], ws[6], ws[7], ws[8]
    n = U.shape[0]
    r = Vb[0]
    if use_guess:
        sn2 = norm(sol)
        if sn2 > 0.0:
            _jvp(P, N, U, x0, T, F0, sol, 1.0 / sn2, r, Ut, sw)
            for i in range(n):
                r[i] = b[i] - r[i]
        else:
            for i in range(n):
                r[i] = b[i]
    else:
        for i in range(n):
            sol[i] = 0.0
            r[i] = b[i]
    beta = norm(r)
    if not (beta > 0.0) or not math.isfinite(beta):
        return 0
    for i in range(n):
        r[i] /= beta
    for i in range(m + 1):
        g[i] = 0.0
    g[0] = beta
    k = 0
    for j in range(m):
        w = Vb[j + 1]
        precond_apply(N, pre, Vb[j], z)
        zn = norm(z)
        if not (zn > 0.0) or not math.isfinite(zn):
            break
        _jvp(P, N, U, x0, T, F0, z, 1.0 / zn, w, Ut, sw)
        _orthogonalise(w, Vb, j + 1, Hs, j)
        hnext = norm(w)
        Hs[j + 1, j] = hnext
        for i in range(j):
            a = cs[i] * Hs[i, j] + sn[i] * Hs[i + 1, j]
            Hs[i + 1, j] = -sn[i] * Hs[i, j] + cs[i] * Hs[i + 1, j]
            Hs[i, j] = a
        d = math.sqrt(Hs[j, j] * Hs[j, j] + hnext * hnext)
        if not (d > 0.0):
            break
        cs[j] = Hs[j, j] / d
        sn[j] = hnext / d
        Hs[j, j] = d
        Hs[j + 1, j] = 0.0
        g[j + 1] = -sn[j] * g[j]
        g[j] = cs[j] * g[j]
        k = j + 1
        if not (hnext > 1e-300) or abs(g[j + 1]) <= tol * beta:
            break
        for p in range(n):
            w[p] /= hnext
    # Back substitution of the k x k triangular system, then sol += P^-1 V_k y.
    for i in range(k - 1, -1, -1):
        s = g[i]
        for p in range(i + 1, k):
            s -= Hs[i, p] * y[p]
        y[i] = s / Hs[i, i]
    for p in range(n):
        z[p] = 0.0
    for i in range(k):
        vi = Vb[i]
        for p in range(n):
            z[p] += y[i] * vi[p]
    precond_apply(N, pre, z, zz)
    for p in range(n):
        sol[p] += zz[p]
    return k


@njit(**JIT)
def initial_guess(P, N, U, x0, T, X, xd):
    """U from a rollout of the inverse-optimal law u = -2 R xi (clipped inside the bounds).

    When an input held over a stage cannot follow that feedback (``dtau tr(2 M^-1 R) > 1``, a
    stage too long for the plant's fast modes) the gain is scaled down by that factor so that the
    rollout does not explode. The rollout itself takes the S substeps of :func:`eval_F`.
    """
    S = (X.shape[0] - 1) // N
    dtau = T / N
    h = dtau / S
    for i in range(NX):
        X[0, i] = x0[i]
    rw0, rw1, rw2, rw3 = P[PAR.R], P[PAR.R + 1], P[PAR.R + 2], P[PAR.R + 3]
    t1, t2, t3 = P[PAR.TH1], P[PAR.TH2], P[PAR.TH3]
    c2 = math.cos(x0[1])
    m11 = t1 + t2 + 2.0 * t3 * c2
    m12 = t2 + t3 * c2
    det = m11 * t2 - m12 * m12
    trace = 2.0 * (t2 * rw0 - m12 * rw2 - m12 * rw1 + m11 * rw3) / det
    gain = 2.0 / max(1.0, dtau * trace)
    for k in range(N):
        xk = X[k * S]
        j = NS * k
        ua = -gain * (rw0 * xk[2] + rw1 * xk[3])
        ub = -gain * (rw2 * xk[2] + rw3 * xk[3])
        for i in range(2):
            lim = 0.9 * P[PAR.U_MAX + i]
            ui = ua if i == 0 else ub
            if not math.isfinite(ui):
                ui = 0.0
            ui = min(max(ui, -lim), lim)
            vi = math.sqrt(P[PAR.U_MAX + i] * P[PAR.U_MAX + i] - ui * ui)
            U[j + i] = ui
            U[j + 2 + i] = vi
            U[j + 4 + i] = P[PAR.RV] / (2.0 * vi)
        for s in range(S):
            r = k * S + s
            rhs(P, X[r], U[j : j + 2], xd)
            for i in range(NX):
                X[r + 1, i] = X[r, i] + h * xd[i]


@njit(**JIT)
def newton(P, iP, U, x0, T, F, dU, Utry, Ftry, pre, ws, sw):
    """Newton-GMRES on F(U, x0, T) = 0 with backtracking; returns (||F||, GMRES iterations)."""
    N = iP[IP.N]
    n = U.shape[0]
    m = iP[IP.INIT_KRYLOV]
    iters = 0
    eval_F(P, N, U, x0, T, sw, F)
    fn = norm(F)
    for _ in range(iP[IP.INIT_ITERS]):
        if not math.isfinite(fn) or fn <= P[PAR.INIT_TOL]:
            break
        precond_setup(P, N, U, sw[0], T, pre)
        for i in range(n):
            Ftry[i] = -F[i]
        iters += fd_gmres(P, N, U, x0, T, F, Ftry, dU, False, m, 1e-6, pre, ws, sw)
        step = 1.0
        accepted = False
        for _ls in range(30):
            for i in range(n):
                Utry[i] = U[i] + step * dU[i]
            clip_dummies(P, N, Utry)
            eval_F(P, N, Utry, x0, T, sw, Ftry)
            ftry = norm(Ftry)
            if ftry < (1.0 - 1e-4 * step) * fn:
                accepted = True
                break
            step *= 0.5
        if not accepted:
            break
        for i in range(n):
            U[i] = Utry[i]
            F[i] = Ftry[i]
        fn = ftry
        if release_bounds(P, N, U, F) > 0:
            eval_F(P, N, U, x0, T, sw, F)
            fn = norm(F)
    return fn, iters


@njit(**JIT)
def release_bounds(P, N, U, F):
    """Restart the bounds whose multiplier turned negative; returns how many.

    The dummy-input equations have spurious roots: u_i at its bound with mu_i < 0 and v_i -> 0-
    (a maximum along the circle u^2 + v^2 = umax^2). When the optimum leaves a bound faster than
    the continuation follows, the Newton step at v ~ 0 lands next to such a root (the circle's
    tangent is vertical there, so u barely moves). Such a bound is restarted inside the box at a
    Newton step of the stage cost, ``u_i - g_i / (2 R^-1_ii)`` with ``g = H_u - 2 mu u`` (clipped to
    90 % of the bound), with ``v_i, mu_i`` on the central path.
    """
    count = 0
    for k in range(N):
        j = NS * k
        for i in range(2):
            mu = U[j + 4 + i]
            if mu >= 0.0:
                continue
            ui = U[j + i]
            g = F[j + i] - 2.0 * mu * ui
            un = ui - g / (2.0 * P[PAR.R_INV + 3 * i])
            lim = 0.9 * P[PAR.U_MAX + i]
            if not math.isfinite(un):
                un = 0.0
            un = min(max(un, -lim), lim)
            vn = math.sqrt(P[PAR.U_MAX + i] * P[PAR.U_MAX + i] - un * un)
            U[j + i] = un
            U[j + 2 + i] = vn
            U[j + 4 + i] = P[PAR.RV] / (2.0 * vn)
            count += 1
    return count


@njit(**JIT)
def _correct(P, N, kmax, c, U, x0, T, F, b, dU, pre, ws, sw):
    """One corrector pass ``F_U dU = -c F`` from U; F holds F(U) on entry and on exit."""
    precond_setup(P, N, U, sw[0], T, pre)
    n = U.shape[0]
    for i in range(n):
        b[i] = -c * F[i]
    k = fd_gmres(P, N, U, x0, T, F, b, dU, False, kmax, 0.0, pre, ws, sw)
    for i in range(n):
        U[i] += dU[i]
    clip_dummies(P, N, U)
    eval_F(P, N, U, x0, T, sw, F)
    return k


@njit(**JIT)
def block_gmres(P, N, U, x0, T, F0, b1, b2, d1, d2, m, pre, ws, sw):
    """Solve F_U d1 = b1 and F_U d2 = b2 together: m forward-difference products in all.

    Right-preconditioned block-Arnoldi (block size 2, one column at a time): the basis V starts
    with b1 and b2 (orthonormalised; a zero or dependent one is dropped), column j adds
    ``F_U P^-1 v_j``; with ``F_U P^-1 V_m = V_{m+2} H``, each ``d_i = P^-1 V_m y_i`` with
    ``y_i = argmin ||V^T b_i - H y||`` (Givens QR of H). With b2 = 0 this is GMRES(m) on b1.
    ``ws`` is the :func:`rhc_tick` tuple; returns the number of products.
    """
    Vb, Hs, G, Ys, Ut, z = ws[0], ws[1], ws[9], ws[10], ws[6], ws[7]
    n = U.shape[0]
    for i in range(m + 2):
        for p in range(m):
            Hs[i, p] = 0.0
        G[i, 0] = 0.0
        G[i, 1] = 0.0
    nv = 0
    for c in range(2):
        b = b1 if c == 0 else b2
        v = Vb[nv]
        for p in range(n):
            v[p] = b[p]
        bn = norm(v)
        if not (bn > 0.0) or not math.isfinite(bn):
            continue
        _orthogonalise(v, Vb, nv, G, c)
        vn = norm(v)
        if vn > 1e-12 * bn:
            G[nv, c] = vn
            for p in range(n):
                v[p] /= vn
            nv += 1
    k = 0
    j = 0
    while j < m and j < nv:
        precond_apply(N, pre, Vb[j], z)
        zn = norm(z)
        if not (zn > 0.0) or not math.isfinite(zn):
            break
        w = Vb[nv]
        _jvp(P, N, U, x0, T, F0, z, 1.0 / zn, w, Ut, sw)
        wn0 = norm(w)
        _orthogonalise(w, Vb, nv, Hs, j)
        hnext = norm(w)
        k = j + 1
        if not math.isfinite(hnext):
            k = j
            break
        if hnext > 1e-12 * wn0 and hnext > 1e-300:
            Hs[nv, j] = hnext
            for p in range(n):
                w[p] /= hnext
            nv += 1
        j += 1
    # Givens QR of the nv x k matrix H, applied to both right-hand sides.
    for c in range(k):
        for i in range(c + 1, nv):
            hb = Hs[i, c]
            if hb == 0.0:
                continue
            ha = Hs[c, c]
            d = math.sqrt(ha * ha + hb * hb)
            cs, sn = ha / d, hb / d
            for p in range(c, k):
                a0, a1 = Hs[c, p], Hs[i, p]
                Hs[c, p] = cs * a0 + sn * a1
                Hs[i, p] = -sn * a0 + cs * a1
            for q in range(2):
                a0, a1 = G[c, q], G[i, q]
                G[c, q] = cs * a0 + sn * a1
                G[i, q] = -sn * a0 + cs * a1
    for q in range(2):
        d = d1 if q == 0 else d2
        for i in range(k - 1, -1, -1):
            sacc = G[i, q]
            for p in range(i + 1, k):
                sacc -= Hs[i, p] * Ys[q, p]
            Ys[q, i] = sacc / Hs[i, i] if Hs[i, i] != 0.0 else 0.0
        for p in range(n):
            z[p] = 0.0
        for i in range(k):
            vi = Vb[i]
            yi = Ys[q, i]
            for p in range(n):
                z[p] += yi * vi[p]
        precond_apply(N, pre, z, d)
    return k


@njit(inline="always", **JIT)
def _cut2(iP, work, k):
    """Work array ``k`` of :data:`~rt_controller.control.state.WORK` (2-D)."""
    o = IP.WORK + 3 * k
    off, rows, cols = iP[o], iP[o + 1], iP[o + 2]
    return work[off : off + rows * cols].reshape((rows, cols))


@njit(inline="always", **JIT)
def _cut1(iP, work, k):
    """Work array ``k`` of :data:`~rt_controller.control.state.WORK` (one row)."""
    o = IP.WORK + 3 * k
    return work[iP[o] : iP[o] + iP[o + 2]]


@njit(**JIT)
def _views(iP, work):
    """The arrays of one tick cut out of ``work`` (:data:`~rt_controller.control.state.WORK`)."""
    X, Lam, Aux = _cut2(iP, work, W.X), _cut2(iP, work, W.LAM), _cut2(iP, work, W.AUX)
    Vb, Hs, small = _cut2(iP, work, W.VB), _cut2(iP, work, W.HS), _cut2(iP, work, W.SMALL)
    G, Ys, vecs = _cut2(iP, work, W.G), _cut2(iP, work, W.YS), _cut2(iP, work, W.VECS)
    hx, hu, cnt = _cut1(iP, work, W.HX), _cut1(iP, work, W.HU), _cut1(iP, work, W.CNT)
    sw = (X, Lam, Aux, hx, hu, cnt)
    ws = (Vb, Hs, small[0], small[1], small[2], small[3], vecs[6], vecs[7], vecs[8], G, Ys)
    return sw, ws, vecs, _cut1(iP, work, W.PRE), _cut1(iP, work, W.XS)


def workspace_size(n_steps: int, kmax: int, init_krylov: int, substeps: int = 1) -> int:
    """Length of the float64 work array :func:`rhc_tick` needs (:data:`~rt_controller.control.
    state.WORK`)."""
    return work_offsets(n_steps, substeps, max(kmax, init_krylov))[1]


@njit(**JIT)
def _apply_input(P, U, st):
    """u = the first input of U clipped to the bounds into st; False if it is not finite."""
    ok = True
    for i in range(2):
        ui = U[i]
        lim = P[PAR.U_MAX + i]
        st[ST.U + i] = min(max(ui, -lim), lim)
        ok = ok and math.isfinite(ui)
    return ok


@njit(**JIT)
def _prediction_rhs(P, N, U, x0, t, T, xdot, F, sw, xs, Fs, b2):
    """b2 = -dt (F(U, x0 + h xdot, T(t + h)) - F) / h: the prediction of dF over one period.

    Leaves the forward sweep of that evaluation in sw."""
    h = P[PAR.HFD]
    for i in range(NX):
        xs[i] = x0[i] + h * xdot[i]
    eval_F(P, N, U, xs, horizon_at(P, t + h), sw, Fs)
    c = P[PAR.DT] / h
    for i in range(U.shape[0]):
        b2[i] = -c * (Fs[i] - F[i])


@njit(**JIT)
def rhc_tick(P, iP, st, work):
    """One C/GMRES tick; inputs and outputs in the state vector ``st`` (see ``ST_*``).

    Continuation tick (one linear solve, Ohtsuka's ``F_U U' = -zeta F - F_x x' - F_t`` at the
    measured state x0, split into its two right-hand sides that share one Krylov basis):

    1. ``F = F(U, x0, T(t))`` and the prediction ``b2 = -dt (F_x xdot + F_t)`` by a forward
       difference, with xdot from eq. (12) under the warm start's first input (or the given one);
    2. :func:`block_gmres` gives ``d1 = -c F_U^-1 F`` (c = min(zeta dt, 1)) and
       ``d2 = F_U^-1 b2`` from kmax products;
    3. the applied input is the first of ``U + d1``, the solution continued to the *measured*
       state; ``F`` there is evaluated for the residual and to release bounds (when a bound is
       released, rarely, one more plain correction follows and the prediction is solved again);
    4. the warm start of the next tick is ``U + d1 + d2``.

    F is evaluated kmax + 3 times (8 for kmax = 5; the previous two-solve tick took 14). With
    ``init`` the solution is first found by Newton-GMRES and only the prediction is solved for.
    """
    N = iP[IP.N]
    kmax = iP[IP.KMAX]
    n = NS * N
    sw, ws, vecs, pre, xs = _views(iP, work)
    cnt = sw[5]
    cnt[0] = 0.0
    F, Fs, b, dU, Utry, Ftry, b2, d2 = (
        vecs[0],
        vecs[1],
        vecs[2],
        vecs[3],
        vecs[4],
        vecs[5],
        vecs[9],
        vecs[10],
    )
    U = st[ST.HEAD : ST.HEAD + n]
    Udot = st[ST.HEAD + n : ST.HEAD + 2 * n]
    x0 = st[ST.X : ST.X + NX]
    xdot = st[ST.XDOT : ST.XDOT + NX]
    t = st[ST.T]
    model_xdot = st[ST.MODEL_XDOT] != 0.0
    T = horizon_at(P, t)
    dt = P[PAR.DT]
    iters = 0
    if st[ST.INIT] != 0.0:
        initial_guess(P, N, U, x0, T, sw[0], sw[3])
        fn, iters = newton(P, iP, U, x0, T, F, dU, Utry, Ftry, pre, ws, sw)
        eval_F(P, N, U, x0, T, sw, F)
        fn = norm(F)
        ok = _apply_input(P, U, st) and math.isfinite(fn)
        if ok:
            precond_setup(P, N, U, sw[0], T, pre)
            if model_xdot:
                rhs(P, x0, st[ST.U : ST.U + 2], xdot)
            _prediction_rhs(P, N, U, x0, t, T, xdot, F, sw, xs, Fs, b2)
            for i in range(n):
                b[i] = 0.0
            iters += block_gmres(P, N, U, x0, T, F, b, b2, dU, d2, kmax, pre, ws, sw)
    else:
        if model_xdot:
            _apply_input(P, U, st)
            rhs(P, x0, st[ST.U : ST.U + 2], xdot)
        eval_F(P, N, U, x0, T, sw, F)
        precond_setup(P, N, U, sw[0], T, pre)
        _prediction_rhs(P, N, U, x0, t, T, xdot, F, sw, xs, Fs, b2)
        c = min(P[PAR.ZETA] * dt, 1.0)
        for i in range(n):
            b[i] = -c * F[i]
        iters += block_gmres(P, N, U, x0, T, F, b, b2, dU, d2, kmax, pre, ws, sw)
        for i in range(n):
            U[i] += dU[i]
        clip_dummies(P, N, U)
        eval_F(P, N, U, x0, T, sw, F)
        released = release_bounds(P, N, U, F) > 0
        if released:
            eval_F(P, N, U, x0, T, sw, F)
            iters += _correct(P, N, kmax, 1.0, U, x0, T, F, b, dU, pre, ws, sw)
        fn = norm(F)
        ok = _apply_input(P, U, st) and math.isfinite(fn)
        if ok and released:
            # The prediction d2 belongs to the bounds as they were: solve it again (rare).
            precond_setup(P, N, U, sw[0], T, pre)
            if model_xdot:
                rhs(P, x0, st[ST.U : ST.U + 2], xdot)
            _prediction_rhs(P, N, U, x0, t, T, xdot, F, sw, xs, Fs, b2)
            for i in range(n):
                b[i] = 0.0
            iters += block_gmres(P, N, U, x0, T, F, b, b2, dU, d2, kmax, pre, ws, sw)
    st[ST.RES] = fn
    st[ST.ITERS] = iters
    if not ok:
        st[ST.STATUS] = NOT_FINITE
        st[ST.FEVALS] = cnt[0]
        return
    inv_dt = 1.0 / dt
    for i in range(n):
        U[i] += d2[i]
        Udot[i] = d2[i] * inv_dt
    clip_dummies(P, N, U)
    st[ST.STATUS] = OK
    st[ST.FEVALS] = cnt[0]


@njit(**JIT)
def sweep_probe(P, iP, st, work, reps):
    """Evaluate F at the state's U, x and T(t) ``reps`` times (for the benchmark's profile)."""
    N = iP[IP.N]
    n = NS * N
    sw, _ws, vecs, _pre, _xs = _views(iP, work)
    U = st[ST.HEAD : ST.HEAD + n]
    x0 = st[ST.X : ST.X + NX]
    T = horizon_at(P, st[ST.T])
    for _ in range(reps):
        eval_F(P, N, U, x0, T, sw, vecs[1])


def new_workspace(n_steps: int, kmax: int, init_krylov: int, substeps: int = 1) -> np.ndarray:
    """A zeroed work array for :func:`rhc_tick`."""
    return np.zeros(workspace_size(n_steps, kmax, init_krylov, substeps))
