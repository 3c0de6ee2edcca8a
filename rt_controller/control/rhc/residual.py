"""F(U, x, T) of C/GMRES and what works on U directly: the sweeps, the per-stage block
preconditioner of F_U, the projections of the dummy inputs and bounds, and the initial guess.

``F(U, x, T)``: Euler forward sweep ``x_{r+1} = x_r + h f(x_r, u_k)`` (S substeps of
``h = dtau / S`` per stage), backward sweep ``lam = phi_x(x_N)``,
``lam_r = lam_{r+1} + h H_x(x_r, u_k, lam_{r+1})``, and per stage
``(mean H_u + 2 mu u, -r_v + 2 mu v, u^2 + v^2 - umax^2)``. ``F = 0`` are the KKT conditions of
the discretised problem (``dtau`` times the first rows is its exact gradient).
"""

from __future__ import annotations

import math

from numba import njit

from rt_controller.control import numba_cache  # noqa: F401  (before any cached kernel)
from rt_controller.control.rhc.dynamics import JIT, rhs, stage_adjoint, stage_forward, terminal_grad
from rt_controller.control.state import NPRE, NS, NX, PAR, PRE, STAGE, XS


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
        u = U[NS * k + STAGE.U : NS * k + STAGE.U + 2]
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
        u = U[j + STAGE.U : j + STAGE.U + 2]
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
            ui, vi, mi = U[j + STAGE.U + i], U[j + STAGE.V + i], U[j + STAGE.MU + i]
            F[j + STAGE.U + i] = (g0 if i == 0 else g1) + 2.0 * mi * ui
            F[j + STAGE.V + i] = -rv + 2.0 * mi * vi
            F[j + STAGE.MU + i] = ui * ui + vi * vi - P[PAR.U_MAX + i] * P[PAR.U_MAX + i]
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
            u, v = U[j + STAGE.U], U[j + STAGE.V]
            if v < vmin:
                v = vmin
            r = math.sqrt(u * u + v * v)
            if r > 0.0 and math.isfinite(r):
                u *= um / r
                v *= um / r
            if v < vmin:
                v = vmin
                u = math.copysign(math.sqrt(um * um - vmin * vmin), u)
            U[j + STAGE.U] = u
            U[j + STAGE.V] = v


@njit(inline="always", **JIT)
def norm(a):
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * a[i]
    return math.sqrt(s)


@njit(inline="always", **JIT)
def _inside(P, U, j, i, u):
    """Input ``i`` of the stage at ``j`` in U set to ``u`` (0 if not finite) clipped to 90 % of
    its bound, with its dummy input and multiplier on the central path (``u^2 + v^2 = umax^2``,
    ``mu = r_v / (2 v)``)."""
    lim = 0.9 * P[PAR.U_MAX + i]
    if not math.isfinite(u):
        u = 0.0
    u = min(max(u, -lim), lim)
    v = math.sqrt(P[PAR.U_MAX + i] * P[PAR.U_MAX + i] - u * u)
    U[j + STAGE.U + i] = u
    U[j + STAGE.V + i] = v
    U[j + STAGE.MU + i] = P[PAR.RV] / (2.0 * v)


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
            mu = U[j + STAGE.MU + i]
            if mu >= 0.0:
                continue
            ui = U[j + STAGE.U + i]
            g = F[j + STAGE.U + i] - 2.0 * mu * ui
            _inside(P, U, j, i, ui - g / (2.0 * P[PAR.R_INV + 3 * i]))
            count += 1
    return count


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
    c2 = math.cos(x0[XS.Q + 1])
    m11 = t1 + t2 + 2.0 * t3 * c2
    m12 = t2 + t3 * c2
    det = m11 * t2 - m12 * m12
    trace = 2.0 * (t2 * rw0 - m12 * rw2 - m12 * rw1 + m11 * rw3) / det
    gain = 2.0 / max(1.0, dtau * trace)
    for k in range(N):
        xk = X[k * S]
        j = NS * k
        ua = -gain * (rw0 * xk[XS.XI] + rw1 * xk[XS.XI + 1])
        ub = -gain * (rw2 * xk[XS.XI] + rw3 * xk[XS.XI + 1])
        _inside(P, U, j, 0, ua)
        _inside(P, U, j, 1, ub)
        for s in range(S):
            r = k * S + s
            rhs(P, X[r], U[j + STAGE.U : j + STAGE.U + 2], xd)
            for i in range(NX):
                X[r + 1, i] = X[r, i] + h * xd[i]


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
        c2 = math.cos(X[k * S, XS.Q + 1])
        m11 = t1 + t2 + 2.0 * t3 * c2
        m12 = t2 + t3 * c2
        det = m11 * t2 - m12 * m12
        c = 4.0 * dtau / det
        s11 = P[PAR.R_INV] + P[PAR.R_INV] + c * t2
        s12 = P[PAR.R_INV + 1] + P[PAR.R_INV + 2] - c * m12
        s22 = P[PAR.R_INV + 3] + P[PAR.R_INV + 3] + c * m11
        o = NPRE * k
        for i in range(2):
            ui, vi, mi = U[j + STAGE.U + i], U[j + STAGE.V + i], U[j + STAGE.MU + i]
            iv = 1.0 / vi
            pre[o + PRE.UV + i] = ui * iv
            pre[o + PRE.MV + i] = mi * iv
            pre[o + PRE.IV + i] = iv
            dgl = 2.0 * mi + 2.0 * ui * ui * mi * iv * iv
            if i == 0:
                s11 += dgl
            else:
                s22 += dgl
        sdet = s11 * s22 - s12 * s12
        pre[o + PRE.S_INV] = s22 / sdet
        pre[o + PRE.S_INV + 1] = -s12 / sdet
        pre[o + PRE.S_INV + 2] = -s12 / sdet
        pre[o + PRE.S_INV + 3] = s11 / sdet


@njit(inline="always", **JIT)
def precond_apply(N, pre, r, d):
    """d = P^-1 r with the factors of :func:`precond_setup`."""
    for k in range(N):
        j = NS * k
        o = NPRE * k
        # Reduced right-hand side of the du system.
        uv0, uv1 = pre[o + PRE.UV], pre[o + PRE.UV + 1]
        q0 = r[j + STAGE.U] - uv0 * r[j + STAGE.V] + uv0 * pre[o + PRE.MV] * r[j + STAGE.MU]
        q1 = (
            r[j + STAGE.U + 1]
            - uv1 * r[j + STAGE.V + 1]
            + uv1 * pre[o + PRE.MV + 1] * r[j + STAGE.MU + 1]
        )
        du0 = pre[o + PRE.S_INV] * q0 + pre[o + PRE.S_INV + 1] * q1
        du1 = pre[o + PRE.S_INV + 2] * q0 + pre[o + PRE.S_INV + 3] * q1
        for i in range(2):
            dui = du0 if i == 0 else du1
            uv, mv, iv = pre[o + PRE.UV + i], pre[o + PRE.MV + i], pre[o + PRE.IV + i]
            dvi = 0.5 * iv * r[j + STAGE.MU + i] - uv * dui
            d[j + STAGE.U + i] = dui
            d[j + STAGE.V + i] = dvi
            d[j + STAGE.MU + i] = 0.5 * iv * r[j + STAGE.V + i] - mv * dvi
