"""The optimal control problem of eq. (30) compiled: eq. (12) in (q, xi, f), the gradients of
the terminal cost and of the Hamiltonian, per horizon stage (the maths is documented in
:mod:`rt_controller.control.rhc.problem`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from rt_controller.control import numba_cache  # noqa: F401  (before any cached kernel)
from rt_controller.control.state import AUX, NAUX, PAR, XS

JIT = {"cache": True, "error_model": "numpy", "fastmath": {"nsz", "arcp", "contract", "reassoc"}}
"""numba options of every C/GMRES kernel: cached, IEEE NaN/inf semantics kept (the fallback
relies on them)."""


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
    s2, c2 = math.sin(x[XS.Q + 1]), math.cos(x[XS.Q + 1])
    xi1, xi2, f1, f2 = x[XS.XI], x[XS.XI + 1], x[XS.F], x[XS.F + 1]
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
    out[XS.Q] = dq1
    out[XS.Q + 1] = dq2
    out[XS.XI] = y1
    out[XS.XI + 1] = y2
    out[XS.F] = -g * a11 * dq1 + w * f2
    out[XS.F + 1] = -g * (a21 * dq1 + a22 * dq2) - w * f1
    aux[AUX.S2], aux[AUX.C2], aux[AUX.E1], aux[AUX.E2] = s2, c2, e1, e2
    aux[AUX.DQ1], aux[AUX.DQ2], aux[AUX.Y1], aux[AUX.Y2] = dq1, dq2, y1, y2
    aux[AUX.M11], aux[AUX.M12], aux[AUX.IDET], aux[AUX.K1], aux[AUX.K2] = m11, m12, idet, k1, k2


@njit(**JIT)
def rhs(P, x, u, out):
    """Right-hand side of eq. (12) in (q, xi, f) coordinates into ``out`` (6)."""
    aux = np.empty(NAUX)
    stage_forward(P, x, u, aux, out)


@njit(inline="always", **JIT)
def terminal_grad(P, x, out):
    """Gradient of phi = 4 V(x) with respect to x into ``out`` (6)."""
    t1, t2, t3 = P[PAR.TH1], P[PAR.TH2], P[PAR.TH3]
    s2, c2 = math.sin(x[XS.Q + 1]), math.cos(x[XS.Q + 1])
    xi1, xi2 = x[XS.XI], x[XS.XI + 1]
    m11 = t1 + t2 + 2.0 * t3 * c2
    m12 = t2 + t3 * c2
    out[XS.Q] = 0.0
    out[XS.Q + 1] = -4.0 * t3 * s2 * xi1 * (xi1 + xi2)
    out[XS.XI] = 4.0 * (m11 * xi1 + m12 * xi2)
    out[XS.XI + 1] = 4.0 * (m12 * xi1 + t2 * xi2)
    c = 4.0 * P[PAR.KP] / P[PAR.GAIN]
    out[XS.F] = c * x[XS.F]
    out[XS.F + 1] = c * x[XS.F + 1]


@njit(inline="always", **JIT)
def stage_adjoint(P, x, u, lam, aux, hx, hu):
    """H_x (6) into ``hx`` and the cost-plus-dynamics part of H_u (2) into ``hu``, from the
    intermediates ``aux`` of :func:`stage_forward` at the same ``x`` and ``u``.

    With z = M^-1 lam_xi, y = xi', sigma = lam_f1 f2 - lam_f2 f1 and dq, eta as intermediates:
    G = dH/ddq = 4 kp eta + lam_q - g A^T lam_f + sigma (1, 1) - d(z^T C(dq) xi)/ddq,
    E = dH/deta (total) = 4 kp dq + alpha^T G; then
    H_xi = 4 (R + R^T) xi - C^T z + G,  H_f = w (-lam_f2, lam_f1) + A E,
    H_q2 = -z^T M' y - z^T C' xi - g lam_f^T A' dq + f^T A' E,  H_q1 = 0,
    H_u = (R^-1 + R^-T) u + z   (the bound term 2 mu u is added by the caller).
    """
    t3, l1, l2, g, kp = P[PAR.TH3], P[PAR.L1], P[PAR.L2], P[PAR.GAIN], P[PAR.KP]
    s2, c2, e1, e2 = aux[AUX.S2], aux[AUX.C2], aux[AUX.E1], aux[AUX.E2]
    dq1, dq2, y1, y2 = aux[AUX.DQ1], aux[AUX.DQ2], aux[AUX.Y1], aux[AUX.Y2]
    m11, m12, idet, k1, k2 = aux[AUX.M11], aux[AUX.M12], aux[AUX.IDET], aux[AUX.K1], aux[AUX.K2]
    m22 = P[PAR.TH2]
    xi1, xi2, f1, f2 = x[XS.XI], x[XS.XI + 1], x[XS.F], x[XS.F + 1]
    lq1, lq2, lx1, lx2 = lam[XS.Q], lam[XS.Q + 1], lam[XS.XI], lam[XS.XI + 1]
    lf1, lf2 = lam[XS.F], lam[XS.F + 1]
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
    hx[XS.Q] = 0.0
    hx[XS.Q + 1] = -zMy - zCxi - g * lAdq + fAE
    # H_xi = 4 (R + R^T) xi - C^T z + G, C^T z = hh * (-dq2 z1 + dq1 z2, -w z1).
    hx[XS.XI] = (
        4.0 * ((P[PAR.R] + P[PAR.R]) * xi1 + (P[PAR.R + 1] + P[PAR.R + 2]) * xi2)
        - hh * (-dq2 * z1 + dq1 * z2)
        + g1
    )
    hx[XS.XI + 1] = (
        4.0 * ((P[PAR.R + 2] + P[PAR.R + 1]) * xi1 + (P[PAR.R + 3] + P[PAR.R + 3]) * xi2)
        + hh * w * z1
        + g2
    )
    # H_f = w (-lam_f2, lam_f1) + A E.
    hx[XS.F] = -w * lf2 + a11 * E1
    hx[XS.F + 1] = w * lf1 + a21 * E1 + a22 * E2
    hu[0] = (P[PAR.R_INV] + P[PAR.R_INV]) * u[0] + (P[PAR.R_INV + 1] + P[PAR.R_INV + 2]) * u[1] + z1
    hu[1] = (
        (P[PAR.R_INV + 2] + P[PAR.R_INV + 1]) * u[0]
        + (P[PAR.R_INV + 3] + P[PAR.R_INV + 3]) * u[1]
        + z2
    )
