"""Compiled per-tick terms of the nominal model: xi, the feedforward of eq. (11), l and V.

The loop calls these once per tick instead of a few dozen small NumPy operations. They compute
exactly what the NumPy model of ``tests/support/nominal_model.py`` computes (the tests compare
the two). Their parameter vector ``p`` is the model's part of
:data:`~rt_controller.control.state.PAR` (:func:`~rt_controller.control.state.pack_params`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from rt_controller.control import numba_cache  # noqa: F401  (before any cached kernel)
from rt_controller.control.state import PAR


@njit(cache=True, fastmath=False)
def prepare(p, q, dq, f):
    """(xi, tau_ff): xi = dq - alpha eta and tau_ff = M alpha eta_dot + C alpha eta + g."""
    s1, c1 = np.sin(q[0]), np.cos(q[0])
    s12, c12 = np.sin(q[0] + q[1]), np.cos(q[0] + q[1])
    l1, l2, g = p[PAR.L1], p[PAR.L2], p[PAR.GAIN]
    w = dq[0] + dq[1]
    # J_b, R_wc and their derivatives.
    j00, j01 = -l1 * s1 - l2 * s12, -l2 * s12
    j10, j11 = l1 * c1 + l2 * c12, l2 * c12
    jd00 = -l1 * c1 * dq[0] - l2 * c12 * w
    jd01 = -l2 * c12 * w
    jd10 = -l1 * s1 * dq[0] - l2 * s12 * w
    jd11 = -l2 * s12 * w
    # Rf = R_wc f, Rdf = R_wc_dot f.
    rf0, rf1 = c12 * f[0] - s12 * f[1], s12 * f[0] + c12 * f[1]
    rdf0, rdf1 = w * (-s12 * f[0] - c12 * f[1]), w * (c12 * f[0] - s12 * f[1])
    # f_dot = -g R^T J_b dq - w S f, S = [[0, -1], [1, 0]].
    v0 = j00 * dq[0] + j01 * dq[1]
    v1 = j10 * dq[0] + j11 * dq[1]
    fd0 = -g * (c12 * v0 + s12 * v1) + w * f[1]
    fd1 = -g * (-s12 * v0 + c12 * v1) - w * f[0]
    rfd0, rfd1 = c12 * fd0 - s12 * fd1, s12 * fd0 + c12 * fd1
    eta0 = j00 * rf0 + j10 * rf1
    eta1 = j01 * rf0 + j11 * rf1
    ed0 = jd00 * rf0 + jd10 * rf1 + j00 * rdf0 + j10 * rdf1 + j00 * rfd0 + j10 * rfd1
    ed1 = jd01 * rf0 + jd11 * rf1 + j01 * rdf0 + j11 * rdf1 + j01 * rfd0 + j11 * rfd1
    a = p[PAR.ALPHA : PAR.ALPHA + 4]
    ae0, ae1 = a[0] * eta0 + a[1] * eta1, a[2] * eta0 + a[3] * eta1
    aed0, aed1 = a[0] * ed0 + a[1] * ed1, a[2] * ed0 + a[3] * ed1
    c2, s2 = np.cos(q[1]), np.sin(q[1])
    m00 = p[PAR.TH1] + p[PAR.TH2] + 2 * p[PAR.TH3] * c2
    m01 = p[PAR.TH2] + p[PAR.TH3] * c2
    m11 = p[PAR.TH2]
    h = p[PAR.TH3] * s2
    c00, c01, c10 = -h * dq[1], -h * w, h * dq[0]
    xi = np.empty(2)
    xi[0], xi[1] = dq[0] - ae0, dq[1] - ae1
    tau = np.empty(2)
    tau[0] = m00 * aed0 + m01 * aed1 + c00 * ae0 + c01 * ae1 + p[PAR.G1] * c1 + p[PAR.G2] * c12
    tau[1] = m01 * aed0 + m11 * aed1 + c10 * ae0 + p[PAR.G2] * c12
    return xi, tau


@njit(cache=True, fastmath=False)
def torque(tau_ff, u, tau_max):
    """(tau, tau_raw, saturated): tau_raw = tau_ff + u (eq. 11) and tau, tau_raw clipped to
    +-tau_max per joint (a NaN stays NaN, as with ``np.clip``)."""
    raw = tau_ff + u
    tau = np.empty(2)
    saturated = False
    for j in range(2):
        v = raw[j]
        if v > tau_max[j]:
            v = tau_max[j]
        elif v < -tau_max[j]:
            v = -tau_max[j]
        tau[j] = v
        saturated = saturated or v != raw[j]
    return tau, raw, saturated


@njit(cache=True, fastmath=False)
def costs(p, q, xi, f, u):
    """(l, V): the stage cost of eq. (25) and the energy of eq. (13)."""
    l1, l2, kp, g = p[PAR.L1], p[PAR.L2], p[PAR.KP], p[PAR.GAIN]
    s2, c2 = np.sin(q[1]), np.cos(q[1])
    # A = R_wc^T J_b depends on q2 only.
    a00, a01, a10, a11 = l1 * s2, 0.0, l1 * c2 + l2, l2
    af0 = a00 * xi[0] + a01 * xi[1]
    af1 = a10 * xi[0] + a11 * xi[1]
    eta0, eta1 = a00 * f[0] + a10 * f[1], a01 * f[0] + a11 * f[1]  # A^T f
    al = p[PAR.ALPHA : PAR.ALPHA + 4]
    r = p[PAR.R : PAR.R + 4]
    ri = p[PAR.R_INV : PAR.R_INV + 4]
    xrx = xi[0] * (r[0] * xi[0] + r[1] * xi[1]) + xi[1] * (r[2] * xi[0] + r[3] * xi[1])
    cross = f[0] * af0 + f[1] * af1
    aeta0, aeta1 = al[0] * eta0 + al[1] * eta1, al[2] * eta0 + al[3] * eta1
    ff = eta0 * aeta0 + eta1 * aeta1
    uru = u[0] * (ri[0] * u[0] + ri[1] * u[1]) + u[1] * (ri[2] * u[0] + ri[3] * u[1])
    cost = 4.0 * (xrx + kp * cross + kp * ff) + uru
    m00 = p[PAR.TH1] + p[PAR.TH2] + 2 * p[PAR.TH3] * c2
    m01 = p[PAR.TH2] + p[PAR.TH3] * c2
    m11 = p[PAR.TH2]
    V = 0.5 * (m00 * xi[0] ** 2 + 2 * m01 * xi[0] * xi[1] + m11 * xi[1] ** 2)
    V += kp / (2.0 * g) * (f[0] ** 2 + f[1] ** 2)
    return cost, V


@njit(cache=True, fastmath=False, inline="always")
def _rhs(p, q0, q1, dq0, dq1, tau0, tau1):
    """d/dt (q, dq) of the nominal arm under the torque (tau0, tau1), as four scalars: ddq from
    M(q) ddq + C(q, dq) dq + g(q) = tau (eq. 1)."""
    c2, s2 = np.cos(q1), np.sin(q1)
    m00 = p[PAR.TH1] + p[PAR.TH2] + 2 * p[PAR.TH3] * c2
    m01 = p[PAR.TH2] + p[PAR.TH3] * c2
    m11 = p[PAR.TH2]
    h = p[PAR.TH3] * s2
    w = dq0 + dq1
    c12 = np.cos(q0 + q1)
    r0 = tau0 + h * dq1 * dq0 + h * w * dq1 - p[PAR.G1] * np.cos(q0) - p[PAR.G2] * c12
    r1 = tau1 - h * dq0 * dq0 - p[PAR.G2] * c12
    det = m00 * m11 - m01 * m01
    return dq0, dq1, (m11 * r0 - m01 * r1) / det, (m00 * r1 - m01 * r0) / det


@njit(cache=True, fastmath=False)
def predict(p, q, dq, taus, durations, h_max):
    """(q, dq) after holding ``taus[i]`` for ``durations[i]`` seconds in turn, from (q, dq):
    the nominal dynamics of eq. (1) integrated by classical Runge-Kutta, steps <= ``h_max``;
    a negative duration integrates backwards in time. In scalars: no temporaries per step."""
    x0, x1, x2, x3 = q[0], q[1], dq[0], dq[1]
    for i in range(durations.shape[0]):
        dur = durations[i]
        if dur == 0.0:
            continue
        n = int(np.ceil(abs(dur) / h_max))
        h = dur / n
        hh, h6 = 0.5 * h, h / 6.0
        t0, t1 = taus[i, 0], taus[i, 1]
        for _ in range(n):
            a0, a1, a2, a3 = _rhs(p, x0, x1, x2, x3, t0, t1)
            b0, b1, b2, b3 = _rhs(p, x0 + hh * a0, x1 + hh * a1, x2 + hh * a2, x3 + hh * a3, t0, t1)
            c0, c1, c2, c3 = _rhs(p, x0 + hh * b0, x1 + hh * b1, x2 + hh * b2, x3 + hh * b3, t0, t1)
            d0, d1, d2, d3 = _rhs(p, x0 + h * c0, x1 + h * c1, x2 + h * c2, x3 + h * c3, t0, t1)
            x0 = x0 + h6 * (((a0 + 2.0 * b0) + 2.0 * c0) + d0)
            x1 = x1 + h6 * (((a1 + 2.0 * b1) + 2.0 * c1) + d1)
            x2 = x2 + h6 * (((a2 + 2.0 * b2) + 2.0 * c2) + d2)
            x3 = x3 + h6 * (((a3 + 2.0 * b3) + 2.0 * c3) + d3)
    q_out, dq_out = np.empty(2), np.empty(2)
    q_out[0], q_out[1], dq_out[0], dq_out[1] = x0, x1, x2, x3
    return q_out, dq_out


@njit(cache=True, fastmath=False)
def reproject(p, q_then, q_now, f):
    """Features of eq. (6) seen from ``q_now`` of the target that showed as ``f`` from
    ``q_then`` (a static target: p_wo = p_wc + R_wc f / gain, then eq. 6 at ``q_now``)."""
    l1, l2, g = p[PAR.L1], p[PAR.L2], p[PAR.GAIN]
    c, s = np.cos(q_then[0] + q_then[1]), np.sin(q_then[0] + q_then[1])
    x = l1 * np.cos(q_then[0]) + l2 * c + (c * f[0] - s * f[1]) / g
    y = l1 * np.sin(q_then[0]) + l2 * s + (s * f[0] + c * f[1]) / g
    c, s = np.cos(q_now[0] + q_now[1]), np.sin(q_now[0] + q_now[1])
    dx = x - l1 * np.cos(q_now[0]) - l2 * c
    dy = y - l1 * np.sin(q_now[0]) - l2 * s
    out = np.empty(2)
    out[0], out[1] = g * (c * dx + s * dy), g * (-s * dx + c * dy)
    return out


@njit(cache=True, fastmath=False)
def held_torques(times, taus, n, start, end):
    """(torques, durations): what the drive held over [start, end] given the first ``n``
    torques sent (``taus[i]`` from ``times[i]`` on, times ascending; none before the first)."""
    out_tau = np.zeros((n + 1, 2))
    bounds = np.empty(n + 2)
    bounds[0] = start
    m = 1
    for i in range(n):
        ts = times[i]
        if ts >= end:
            break
        if ts <= start:
            out_tau[0, 0], out_tau[0, 1] = taus[i, 0], taus[i, 1]
        else:
            out_tau[m, 0], out_tau[m, 1] = taus[i, 0], taus[i, 1]
            bounds[m] = ts
            m += 1
    bounds[m] = end
    return out_tau[:m].copy(), np.diff(bounds[: m + 1])


@njit(cache=True, fastmath=False)
def advance(p, q, dq, times, taus, n, t_from, t_to, horizon, h_max):
    """(q, dq) at ``t_to`` of the state (q, dq) at ``t_from`` under the torques sent, forwards
    or backwards in time, over at most ``horizon`` seconds before the later end."""
    lo, hi = min(t_from, t_to), max(t_from, t_to)
    held, durations = held_torques(times, taus, n, max(lo, hi - horizon), hi)
    if t_to < t_from:
        held, durations = held[::-1].copy(), -durations[::-1]
    return predict(p, q, dq, held, durations, h_max)


@njit(cache=True, fastmath=False)
def compensate(p, q, dq, f, times, taus, n, now, state_age, f_age, horizon, h_max):
    """(q, dq, f) brought up to ``now``: the joint state measured ``state_age`` before (0: as
    measured) by the nominal dynamics under the torques sent; the features captured ``f_age``
    before (0: as measured) by seeing the static target from the pose of now instead of the
    pose at capture, which follows from the same trajectory."""
    t_state = now - min(max(state_age, 0.0), horizon)
    q_now, dq_now = q.copy(), dq.copy()
    if state_age > 0.0:
        q_now, dq_now = advance(p, q, dq, times, taus, n, t_state, now, horizon, h_max)
    f_now = f.copy()
    if f_age > 0.0:
        t_capture = now - min(f_age, horizon)
        q_capture, _ = advance(p, q, dq, times, taus, n, t_state, t_capture, horizon, h_max)
        f_now = reproject(p, q_capture, q_now, f)
    return q_now, dq_now, f_now
