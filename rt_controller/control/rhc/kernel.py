"""One C/GMRES tick (Ohtsuka 2004) as one compiled call, :func:`rhc_tick`, on preallocated arrays.

Everything a tick needs runs inside the single call :func:`rhc_tick` on preallocated arrays:
one linear solve per tick, Ohtsuka's ``F_U Udot = -zeta F - F_x xdot - F_t`` at the *measured*
state (``F(U, x, T)`` = 0 are the KKT conditions of the discretised problem,
:func:`~rt_controller.control.rhc.residual.eval_F`), its two right-hand sides kept apart in one
block Krylov basis (:func:`~rt_controller.control.rhc.gmres.block_gmres`): ``d1 = -c F_U^-1 F``
(``c = min(zeta dt, 1)``, the correction to the measured state) and
``d2 = -dt F_U^-1 (F_x xdot + F_t)`` (the prediction, by one forward difference). The input
applied at this tick is the first one of ``U + d1``; the next tick starts from ``U + d1 + d2``.
F is evaluated kmax + 3 times per tick.

Applying the corrected input rather than the predicted one matters for a loop sampled at 50 Hz:
the plant's fast modes are ~40 /s, comparable to 1 / period.

After every update the dummy inputs are put back on their circles with ``v >= vmin``
(:func:`clip_dummies`) and bounds whose multiplier turned negative are restarted inside the box
(:func:`release_bounds`). The initial solution (first tick, and after a fallback) is found by
Newton-GMRES with backtracking.

The kernels are split by concern: the OCP's functions (:mod:`~rt_controller.control.rhc.
dynamics`, documented in :mod:`~rt_controller.control.rhc.problem`), F and what works on U
(:mod:`~rt_controller.control.rhc.residual`), the GMRES solvers (:mod:`~rt_controller.control.
rhc.gmres`) and the tick here. numba's cache of each is invalidated by any change to the
package (:mod:`rt_controller.control.numba_cache`), so no module keeps stale code of another.
"""

from __future__ import annotations

import math

from numba import njit

from rt_controller.control import numba_cache  # noqa: F401  (before any cached kernel)
from rt_controller.control.rhc.dynamics import JIT, horizon_at, rhs
from rt_controller.control.rhc.gmres import block_gmres, correct, newton
from rt_controller.control.rhc.residual import (
    clip_dummies,
    eval_F,
    initial_guess,
    norm,
    precond_setup,
    release_bounds,
)
from rt_controller.control.state import CUT, IP, NS, NX, PAR, SMALL, ST, VEC, W


@njit(inline="always", **JIT)
def _cut(iP, work, k):
    """Work array ``k`` of :data:`~rt_controller.control.state.WORK` (2-D; ``[0]`` of a one-row
    array is the row)."""
    o = IP.WORK + CUT.SIZE * k
    off, rows, cols = iP[o + CUT.OFF], iP[o + CUT.ROWS], iP[o + CUT.COLS]
    return work[off : off + rows * cols].reshape((rows, cols))


@njit(**JIT)
def work_views(iP, work):
    """The arrays of one tick cut out of ``work`` (:data:`~rt_controller.control.state.WORK`)."""
    X, Lam, Aux = _cut(iP, work, W.X), _cut(iP, work, W.LAM), _cut(iP, work, W.AUX)
    Vb, Hs, small = _cut(iP, work, W.VB), _cut(iP, work, W.HS), _cut(iP, work, W.SMALL)
    G, Ys, vecs = _cut(iP, work, W.G), _cut(iP, work, W.YS), _cut(iP, work, W.VECS)
    hx, hu, cnt = _cut(iP, work, W.HX)[0], _cut(iP, work, W.HU)[0], _cut(iP, work, W.CNT)[0]
    sw = (X, Lam, Aux, hx, hu, cnt)
    cs, sn, g, y = small[SMALL.CS], small[SMALL.SN], small[SMALL.G], small[SMALL.Y]
    ws = (Vb, Hs, cs, sn, g, y, vecs[VEC.UT], vecs[VEC.Z], vecs[VEC.ZZ], G, Ys)
    return sw, ws, vecs, _cut(iP, work, W.PRE)[0], _cut(iP, work, W.XS)[0]


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
    """One C/GMRES tick; inputs and outputs in the state vector ``st`` (layout
    :data:`~rt_controller.control.state.ST`).

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
    A solution that is not finite or whose residual exceeds ``rhc.residual_bound`` sets ``init``:
    it is not applied, and the next tick solves from scratch.
    """
    N = iP[IP.N]
    kmax = iP[IP.KMAX]
    n = NS * N
    sw, ws, vecs, pre, xs = work_views(iP, work)
    X, _Lam, _Aux, hx, _hu, cnt = sw
    cnt[0] = 0.0
    F, Fs, b, dU = vecs[VEC.F], vecs[VEC.FS], vecs[VEC.B], vecs[VEC.DU]
    Utry, Ftry, b2, d2 = vecs[VEC.UTRY], vecs[VEC.FTRY], vecs[VEC.B2], vecs[VEC.D2]
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
        initial_guess(P, N, U, x0, T, X, hx)
        iters = newton(P, iP, U, x0, T, F, dU, Utry, Ftry, pre, ws, sw)
        eval_F(P, N, U, x0, T, sw, F)
        predict_alone = True  # the solution is U: only the prediction is solved for
    else:
        if model_xdot:
            _apply_input(P, U, st)
            rhs(P, x0, st[ST.U : ST.U + 2], xdot)
        eval_F(P, N, U, x0, T, sw, F)
        precond_setup(P, N, U, X, T, pre)
        _prediction_rhs(P, N, U, x0, t, T, xdot, F, sw, xs, Fs, b2)
        c = min(P[PAR.ZETA] * dt, 1.0)
        for i in range(n):
            b[i] = -c * F[i]
        iters += block_gmres(P, N, U, x0, T, F, b, b2, dU, d2, kmax, pre, ws, sw)
        for i in range(n):
            U[i] += dU[i]
        clip_dummies(P, N, U)
        eval_F(P, N, U, x0, T, sw, F)
        # A released bound is corrected once more; the prediction d2 belongs to the bounds
        # as they were: it is solved again (rare).
        predict_alone = release_bounds(P, N, U, F) > 0
        if predict_alone:
            eval_F(P, N, U, x0, T, sw, F)
            iters += correct(P, N, kmax, 1.0, U, x0, T, F, b, dU, pre, ws, sw)
    fn = norm(F)
    ok = _apply_input(P, U, st) and math.isfinite(fn)
    if ok and predict_alone:
        precond_setup(P, N, U, X, T, pre)
        if model_xdot:
            rhs(P, x0, st[ST.U : ST.U + 2], xdot)
        _prediction_rhs(P, N, U, x0, t, T, xdot, F, sw, xs, Fs, b2)
        for i in range(n):
            b[i] = 0.0
        iters += block_gmres(P, N, U, x0, T, F, b, b2, dU, d2, kmax, pre, ws, sw)
    st[ST.RES] = fn
    st[ST.ITERS] = iters
    st[ST.INIT] = 0.0 if ok and fn <= P[PAR.RES_BOUND] else 1.0
    st[ST.FEVALS] = cnt[0]
    if ok:
        inv_dt = 1.0 / dt
        for i in range(n):
            U[i] += d2[i]
            Udot[i] = d2[i] * inv_dt
        clip_dummies(P, N, U)


@njit(**JIT)
def sweep_probe(P, iP, st, work, reps):
    """Evaluate F at the state's U, x and T(t) ``reps`` times (for the benchmark's profile)."""
    N = iP[IP.N]
    n = NS * N
    sw, _ws, vecs, _pre, _xs = work_views(iP, work)
    U = st[ST.HEAD : ST.HEAD + n]
    x0 = st[ST.X : ST.X + NX]
    T = horizon_at(P, st[ST.T])
    for _ in range(reps):
        eval_F(P, N, U, x0, T, sw, vecs[VEC.FS])
