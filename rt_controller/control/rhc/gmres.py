"""Forward-difference GMRES on F_U: the single-right-hand-side solver of the Newton steps, the
block solver of a continuation tick, Newton-GMRES with backtracking, and one plain correction.

Each solve runs (at most) ``m`` iterations with forward-difference products
``(F(U + h v) - F(U)) / h`` and Givens rotations, right-preconditioned by the per-stage block
inverse of :func:`~rt_controller.control.rhc.residual.precond_setup`.
"""

from __future__ import annotations

import math

from numba import njit

from rt_controller.control import numba_cache  # noqa: F401  (before any cached kernel)
from rt_controller.control.rhc.dynamics import JIT
from rt_controller.control.rhc.residual import (
    clip_dummies,
    eval_F,
    norm,
    precond_apply,
    precond_setup,
    release_bounds,
)
from rt_controller.control.state import IP, PAR


@njit(**JIT)
def jvp(P, N, U, x0, T, F0, v, scale, out, Ut, sw):
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


@njit(inline="always", **JIT)
def _solution(N, pre, Vb, Hs, g, y, k, z, out):
    """GMRES's least-squares solution ``out = P^-1 V_k y``: ``y`` solves the k x k upper
    triangular system ``H y = g`` by back substitution (a zero pivot gives a zero component),
    ``z`` receives ``V_k y``."""
    for i in range(k - 1, -1, -1):
        s = g[i]
        for p in range(i + 1, k):
            s -= Hs[i, p] * y[p]
        y[i] = s / Hs[i, i] if Hs[i, i] != 0.0 else 0.0
    n = z.shape[0]
    for p in range(n):
        z[p] = 0.0
    for i in range(k):
        vi = Vb[i]
        for p in range(n):
            z[p] += y[i] * vi[p]
    precond_apply(N, pre, z, out)


@njit(**JIT)
def fd_gmres(P, N, U, x0, T, F0, b, sol, m, tol, pre, ws, sw):
    """Solve F_U(U, x0, T) sol = b by right-preconditioned GMRES(m), forward-difference products.

    ``sol`` receives the solution (GMRES starts from 0). Stops after ``m`` iterations, at
    breakdown, or when the residual falls to ``tol * ||b||`` (``tol = 0``: always ``m``
    iterations). ``pre`` holds the factors of :func:`precond_setup`; ``ws`` is the GMRES work
    tuple of :func:`~rt_controller.control.rhc.kernel.rhc_tick`. Returns the iteration count.
    """
    Vb, Hs, cs, sn, g, y, Ut, z, zz, _G, _Ys = ws
    n = U.shape[0]
    r = Vb[0]
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
        jvp(P, N, U, x0, T, F0, z, 1.0 / zn, w, Ut, sw)
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
    _solution(N, pre, Vb, Hs, g, y, k, z, zz)
    for p in range(n):
        sol[p] += zz[p]
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
    Vb, Hs, _cs, _sn, _g, _y, Ut, z, _zz, G, Ys = ws
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
        jvp(P, N, U, x0, T, F0, z, 1.0 / zn, w, Ut, sw)
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
        _solution(N, pre, Vb, Hs, G[:, q], Ys[q], k, z, d1 if q == 0 else d2)
    return k


@njit(**JIT)
def newton(P, iP, U, x0, T, F, dU, Utry, Ftry, pre, ws, sw):
    """Newton-GMRES on F(U, x0, T) = 0 with backtracking; returns the GMRES iterations."""
    N = iP[IP.N]
    n = U.shape[0]
    m = iP[IP.INIT_KRYLOV]
    X, _Lam, _Aux, _hx, _hu, _cnt = sw
    iters = 0
    eval_F(P, N, U, x0, T, sw, F)
    fn = norm(F)
    for _ in range(iP[IP.INIT_ITERS]):
        if not math.isfinite(fn) or fn <= P[PAR.INIT_TOL]:
            break
        precond_setup(P, N, U, X, T, pre)
        for i in range(n):
            Ftry[i] = -F[i]
        iters += fd_gmres(P, N, U, x0, T, F, Ftry, dU, m, 1e-6, pre, ws, sw)
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
    return iters


@njit(**JIT)
def correct(P, N, kmax, c, U, x0, T, F, b, dU, pre, ws, sw):
    """One corrector pass ``F_U dU = -c F`` from U; F holds F(U) on entry and on exit."""
    X, _Lam, _Aux, _hx, _hu, _cnt = sw
    precond_setup(P, N, U, X, T, pre)
    n = U.shape[0]
    for i in range(n):
        b[i] = -c * F[i]
    k = fd_gmres(P, N, U, x0, T, F, b, dU, kmax, 0.0, pre, ws, sw)
    for i in range(n):
        U[i] += dU[i]
    clip_dummies(P, N, U)
    eval_F(P, N, U, x0, T, sw, F)
    return k
