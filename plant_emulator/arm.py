"""Rigid two-link planar arm, integrated with RK4: the emulator's "real" physics.

Written independently of the controller's nominal model on purpose: the inertia matrix is built
from the link centre-of-mass Jacobians, Coriolis/centrifugal torques from Christoffel symbols and
gravity from the potential energy, so a sign error in one cannot cancel itself out in the other.
The kernels are compiled with numba so that the 1 kHz physics costs a few microseconds a step.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from hal.config import RobotConfig
from plant_emulator.errors import PhysicsError

COULOMB_SMOOTHING = 0.05
"""Velocity (rad/s) over which Coulomb friction ramps through zero (tanh smoothing)."""

# Layout of the parameter vector handed to the kernels.
L1, LC1, LC2, M1, M2, I1, I2, G, VIS1, VIS2, COUL1, COUL2, TMAX1, TMAX2 = range(14)


@njit(cache=True)
def _com_jacobians(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a1, a12 = q[0], q[0] + q[1]
    jv1 = np.zeros((2, 2))
    jv1[0, 0] = -p[LC1] * np.sin(a1)
    jv1[1, 0] = p[LC1] * np.cos(a1)
    jv2 = np.empty((2, 2))
    jv2[0, 0] = -p[L1] * np.sin(a1) - p[LC2] * np.sin(a12)
    jv2[0, 1] = -p[LC2] * np.sin(a12)
    jv2[1, 0] = p[L1] * np.cos(a1) + p[LC2] * np.cos(a12)
    jv2[1, 1] = p[LC2] * np.cos(a12)
    return jv1, jv2


@njit(cache=True)
def _gram(j: np.ndarray) -> np.ndarray:
    """J^T J of a 2x2 matrix, written out: numba's ``@`` on arrays calls SciPy's BLAS, which is
    not a run-time dependency (without SciPy the compiled kernel aborts the process)."""
    g = np.empty((2, 2))
    for a in range(2):
        for b in range(2):
            g[a, b] = j[0, a] * j[0, b] + j[1, a] * j[1, b]
    return g


@njit(cache=True)
def inertia_kernel(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """M(q) = sum over links of m Jv^T Jv + I Jw^T Jw (Jw1 = [1, 0], Jw2 = [1, 1])."""
    jv1, jv2 = _com_jacobians(p, q)
    m = p[M1] * _gram(jv1) + p[M2] * _gram(jv2)
    m[0, 0] += p[I1] + p[I2]
    m[0, 1] += p[I2]
    m[1, 0] += p[I2]
    m[1, 1] += p[I2]
    return m


@njit(cache=True)
def inertia_gradient_kernel(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """dM/dq_k as an array [k, i, j]; only the m2 l1 lc2 cos(q2) cross term depends on q."""
    d = -p[M2] * p[L1] * p[LC2] * np.sin(q[1])
    grad = np.zeros((2, 2, 2))
    grad[1, 0, 0] = 2.0 * d
    grad[1, 0, 1] = d
    grad[1, 1, 0] = d
    return grad


@njit(cache=True)
def coriolis_kernel(p: np.ndarray, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """h_i = sum_jk (dM_ij/dq_k - 1/2 dM_jk/dq_i) dq_j dq_k (Christoffel symbols)."""
    dm = inertia_gradient_kernel(p, q)
    h = np.zeros(2)
    for i in range(2):
        for j in range(2):
            for k in range(2):
                h[i] += (dm[k, i, j] - 0.5 * dm[i, j, k]) * dq[j] * dq[k]
    return h


@njit(cache=True)
def gravity_kernel(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """G = dU/dq with U = g (m1 y_c1 + m2 y_c2)."""
    jv1, jv2 = _com_jacobians(p, q)
    return p[G] * (p[M1] * jv1[1] + p[M2] * jv2[1])


@njit(cache=True)
def friction_kernel(p: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """Viscous plus (smoothed) Coulomb friction torque."""
    out = np.empty(2)
    out[0] = p[VIS1] * dq[0] + p[COUL1] * np.tanh(dq[0] / COULOMB_SMOOTHING)
    out[1] = p[VIS2] * dq[1] + p[COUL2] * np.tanh(dq[1] / COULOMB_SMOOTHING)
    return out


@njit(cache=True)
def saturate_kernel(p: np.ndarray, tau: np.ndarray) -> np.ndarray:
    out = np.empty(2)
    out[0] = min(max(tau[0], -p[TMAX1]), p[TMAX1])
    out[1] = min(max(tau[1], -p[TMAX2]), p[TMAX2])
    return out


@njit(cache=True)
def acceleration_kernel(p: np.ndarray, q: np.ndarray, dq: np.ndarray, tau: np.ndarray):
    rhs = tau - coriolis_kernel(p, q, dq) - gravity_kernel(p, q) - friction_kernel(p, dq)
    m = inertia_kernel(p, q)
    det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    out = np.empty(2)
    out[0] = (m[1, 1] * rhs[0] - m[0, 1] * rhs[1]) / det
    out[1] = (m[0, 0] * rhs[1] - m[1, 0] * rhs[0]) / det
    return out


@njit(cache=True)
def integrate_kernel(
    p: np.ndarray, q: np.ndarray, dq: np.ndarray, tau: np.ndarray, dt: float, steps: int
):
    """``steps`` classical RK4 steps with the (saturated) torque held."""
    tau = saturate_kernel(p, tau)
    q = q.copy()
    dq = dq.copy()
    for _ in range(steps):
        k1q, k1v = dq, acceleration_kernel(p, q, dq, tau)
        k2q = dq + 0.5 * dt * k1v
        k2v = acceleration_kernel(p, q + 0.5 * dt * k1q, k2q, tau)
        k3q = dq + 0.5 * dt * k2v
        k3v = acceleration_kernel(p, q + 0.5 * dt * k2q, k3q, tau)
        k4q = dq + dt * k3v
        k4v = acceleration_kernel(p, q + dt * k3q, k4q, tau)
        q = q + dt / 6.0 * (k1q + 2.0 * k2q + 2.0 * k3q + k4q)
        dq = dq + dt / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
    return q, dq


@njit(cache=True)
def integrate_encoded_kernel(
    p: np.ndarray,
    q: np.ndarray,
    dq: np.ndarray,
    tau: np.ndarray,
    dt: float,
    steps: int,
    lsb: float,
    gain: float,
    q_enc: np.ndarray,
    dq_est: np.ndarray,
):
    """:func:`integrate_kernel` with the DSP's sensors sampled after every step: encoder
    quantisation (``lsb`` rad) and a first-order filtered difference velocity estimate."""
    q_enc = q_enc.copy()
    dq_est = dq_est.copy()
    for _ in range(steps):
        q, dq = integrate_kernel(p, q, dq, tau, dt, 1)
        for i in range(2):
            enc = np.round(q[i] / lsb) * lsb
            dq_est[i] += gain * ((enc - q_enc[i]) / dt - dq_est[i])
            q_enc[i] = enc
    return q, dq, q_enc, dq_est


class Encoder:
    """The DSP's joint sensors: quantised angles and a filtered difference velocity."""

    def __init__(self, q: np.ndarray, dq: np.ndarray, lsb: float, gain: float) -> None:
        self.lsb = lsb
        """Angle resolution, rad per count."""
        self.gain = gain
        """Per-step gain of the first-order velocity filter (1 = raw difference)."""
        self.q = np.round(np.asarray(q, dtype=float) / lsb) * lsb
        self.dq = np.array(dq, dtype=float)


class ArmPhysics:
    """Equations of motion M(q) qdd + h(q, qd) + G(q) + friction(qd) = sat(tau)."""

    def __init__(self, robot: RobotConfig) -> None:
        self.robot = robot
        r = robot
        inertial = (r.l1, r.lc1, r.lc2, r.m1, r.m2, r.I1, r.I2, r.gravity)
        self.params = np.array([*inertial, *r.viscous, *r.coulomb, *r.tau_max], dtype=float)

    def inertia(self, q: np.ndarray) -> np.ndarray:
        return inertia_kernel(self.params, np.asarray(q, dtype=float))

    def coriolis(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        return coriolis_kernel(self.params, np.asarray(q, float), np.asarray(dq, float))

    def gravity(self, q: np.ndarray) -> np.ndarray:
        return gravity_kernel(self.params, np.asarray(q, dtype=float))

    def saturate(self, tau: np.ndarray) -> np.ndarray:
        """Amplifier limits."""
        return saturate_kernel(self.params, np.asarray(tau, dtype=float))

    def integrate(
        self, q: np.ndarray, dq: np.ndarray, tau: np.ndarray, dt: float, steps: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """``steps`` RK4 steps with the torque held; raises on a non-finite state."""
        q_next, dq_next = integrate_kernel(
            self.params,
            np.asarray(q, dtype=float),
            np.asarray(dq, dtype=float),
            np.asarray(tau, dtype=float),
            dt,
            steps,
        )
        if not (np.all(np.isfinite(q_next)) and np.all(np.isfinite(dq_next))):
            raise PhysicsError(f"arm state diverged (q={q_next}, dq={dq_next}, tau={tau})")
        return q_next, dq_next

    def integrate_encoded(
        self,
        q: np.ndarray,
        dq: np.ndarray,
        tau: np.ndarray,
        dt: float,
        steps: int,
        encoder: Encoder,
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`integrate` that also updates ``encoder`` after every step."""
        q_next, dq_next, encoder.q, encoder.dq = integrate_encoded_kernel(
            self.params,
            np.asarray(q, dtype=float),
            np.asarray(dq, dtype=float),
            np.asarray(tau, dtype=float),
            dt,
            steps,
            encoder.lsb,
            encoder.gain,
            encoder.q,
            encoder.dq,
        )
        if not (np.all(np.isfinite(q_next)) and np.all(np.isfinite(dq_next))):
            raise PhysicsError(f"arm state diverged (q={q_next}, dq={dq_next}, tau={tau})")
        return q_next, dq_next
