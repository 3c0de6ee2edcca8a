"""Rigid two-link planar arm, integrated with RK4: the emulator's "real" physics.

Written independently of the controller's nominal model on purpose: the inertia matrix is built
from the link centre-of-mass Jacobians, Coriolis/centrifugal torques from Christoffel symbols and
gravity from the potential energy, so a sign error in one cannot cancel itself out in the other.
"""

from __future__ import annotations

import math

import numpy as np

from hal.config import RobotConfig
from plant_emulator.errors import PhysicsError

COULOMB_SMOOTHING = 0.05
"""Velocity (rad/s) over which Coulomb friction ramps through zero (tanh smoothing)."""


class ArmPhysics:
    """Equations of motion M(q) qdd + h(q, qd) + G(q) + friction(qd) = sat(tau)."""

    def __init__(self, robot: RobotConfig) -> None:
        self.robot = robot
        self.tau_max = np.array(robot.tau_max, dtype=float)
        self.viscous = np.array(robot.viscous, dtype=float)
        self.coulomb = np.array(robot.coulomb, dtype=float)

    def _com_jacobians(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = self.robot
        a1, a12 = q[0], q[0] + q[1]
        jv1 = np.array([[-r.lc1 * math.sin(a1), 0.0], [r.lc1 * math.cos(a1), 0.0]])
        jv2 = np.array(
            [
                [-r.l1 * math.sin(a1) - r.lc2 * math.sin(a12), -r.lc2 * math.sin(a12)],
                [r.l1 * math.cos(a1) + r.lc2 * math.cos(a12), r.lc2 * math.cos(a12)],
            ]
        )
        return jv1, jv2

    def inertia(self, q: np.ndarray) -> np.ndarray:
        """M(q) = sum over links of m Jv^T Jv + I Jw^T Jw."""
        r = self.robot
        jv1, jv2 = self._com_jacobians(q)
        jw1 = np.array([1.0, 0.0])
        jw2 = np.array([1.0, 1.0])
        return (
            r.m1 * jv1.T @ jv1
            + r.I1 * np.outer(jw1, jw1)
            + r.m2 * jv2.T @ jv2
            + r.I2 * np.outer(jw2, jw2)
        )

    def inertia_gradient(self, q: np.ndarray) -> np.ndarray:
        """dM/dq_k stacked as an array of shape (2, 2, 2), index [k, i, j]."""
        r = self.robot
        # Only the m2 l1 lc2 cos(q2) cross term of m2 Jv2^T Jv2 depends on q.
        d = -r.m2 * r.l1 * r.lc2 * math.sin(q[1])
        grad = np.zeros((2, 2, 2))
        grad[1] = np.array([[2.0 * d, d], [d, 0.0]])
        return grad

    def coriolis(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """h_i = sum_jk (dM_ij/dq_k - 1/2 dM_jk/dq_i) dq_j dq_k (Christoffel symbols)."""
        dm = self.inertia_gradient(q)
        first = np.einsum("kij,j,k->i", dm, dq, dq)
        second = 0.5 * np.einsum("ijk,j,k->i", dm, dq, dq)
        return first - second

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """G = dU/dq with U = g (m1 y_c1 + m2 y_c2)."""
        r = self.robot
        if r.gravity == 0.0:
            return np.zeros(2)
        jv1, jv2 = self._com_jacobians(q)
        return r.gravity * (r.m1 * jv1[1] + r.m2 * jv2[1])

    def friction(self, dq: np.ndarray) -> np.ndarray:
        """Viscous plus (smoothed) Coulomb friction torque."""
        return self.viscous * dq + self.coulomb * np.tanh(dq / COULOMB_SMOOTHING)

    def saturate(self, tau: np.ndarray) -> np.ndarray:
        """Amplifier limits."""
        return np.clip(tau, -self.tau_max, self.tau_max)

    def acceleration(self, q: np.ndarray, dq: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """qdd for an already saturated torque."""
        rhs = tau - self.coriolis(q, dq) - self.gravity(q) - self.friction(dq)
        return np.linalg.solve(self.inertia(q), rhs)

    def rk4_step(
        self, q: np.ndarray, dq: np.ndarray, tau: np.ndarray, dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """One classical Runge-Kutta step with the torque held; raises on a non-finite state."""
        tau = self.saturate(tau)
        k1q, k1v = dq, self.acceleration(q, dq, tau)
        k2q = dq + 0.5 * dt * k1v
        k2v = self.acceleration(q + 0.5 * dt * k1q, k2q, tau)
        k3q = dq + 0.5 * dt * k2v
        k3v = self.acceleration(q + 0.5 * dt * k2q, k3q, tau)
        k4q = dq + dt * k3v
        k4v = self.acceleration(q + dt * k3q, k4q, tau)
        q_next = q + dt / 6.0 * (k1q + 2 * k2q + 2 * k3q + k4q)
        dq_next = dq + dt / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
        if not (np.all(np.isfinite(q_next)) and np.all(np.isfinite(dq_next))):
            raise PhysicsError(f"arm state diverged (q={q_next}, dq={dq_next}, tau={tau})")
        return q_next, dq_next

    def kinetic_energy(self, q: np.ndarray, dq: np.ndarray) -> float:
        return float(0.5 * dq @ self.inertia(q) @ dq)
