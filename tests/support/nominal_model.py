"""The nominal model of the visual feedback system in plain NumPy, eq. (1)-(18) and (25): the
readable oracle the compiled kernels (:mod:`rt_controller.control.model_kernels`, the C/GMRES
problem of :mod:`rt_controller.control.rhc.dynamics`) are held to. Product code never imports
it.

States are arrays of shape (2,): joint angles ``q`` (rad), velocities ``dq`` (rad/s) and image
features ``f`` (px).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from rt_controller.control.model import NominalModel

_SKEW = np.array([[0.0, -1.0], [1.0, 0.0]])


@dataclasses.dataclass(frozen=True)
class NumpyModel(NominalModel):
    """:class:`~rt_controller.control.model.NominalModel`'s parameters with the model's terms
    as NumPy functions."""

    @classmethod
    def of(cls, model: NominalModel) -> NumpyModel:
        """The same parameters as ``model``."""
        return cls(**{f.name: getattr(model, f.name) for f in dataclasses.fields(model)})

    # --- manipulator, eq. (1)-(3) -------------------------------------------------------------
    def M(self, q: np.ndarray) -> np.ndarray:
        """Inertia matrix, eq. (2)."""
        c2 = np.cos(q[1])
        m12 = self.theta2 + self.theta3 * c2
        return np.array(
            [[self.theta1 + self.theta2 + 2 * self.theta3 * c2, m12], [m12, self.theta2]]
        )

    def M_dot(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """Time derivative of M along the motion."""
        d = -self.theta3 * np.sin(q[1]) * dq[1]
        return np.array([[2 * d, d], [d, 0.0]])

    def C(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """Coriolis/centrifugal matrix, eq. (3)."""
        h = self.theta3 * np.sin(q[1])
        return np.array([[-h * dq[1], -h * (dq[0] + dq[1])], [h * dq[0], 0.0]])

    def g(self, q: np.ndarray) -> np.ndarray:
        """Gravity torques (zero in the horizontal plane)."""
        c12 = np.cos(q[0] + q[1])
        return np.array([self.gravity1 * np.cos(q[0]) + self.gravity2 * c12, self.gravity2 * c12])

    # --- camera kinematics, eq. (6)-(10) ------------------------------------------------------
    def camera_position(self, q: np.ndarray) -> np.ndarray:
        """Position p_wc of the camera (end effector) in the X_w-Y_w plane, m."""
        q12 = q[0] + q[1]
        return np.array(
            [
                self.l1 * np.cos(q[0]) + self.l2 * np.cos(q12),
                self.l1 * np.sin(q[0]) + self.l2 * np.sin(q12),
            ]
        )

    def R_wc(self, q: np.ndarray) -> np.ndarray:
        """Camera rotation, eq. (9)."""
        c, s = np.cos(q[0] + q[1]), np.sin(q[0] + q[1])
        return np.array([[c, -s], [s, c]])

    def R_wc_dot(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """Time derivative of R_wc."""
        c, s = np.cos(q[0] + q[1]), np.sin(q[0] + q[1])
        w = dq[0] + dq[1]
        return w * np.array([[-s, -c], [c, -s]])

    def J_b(self, q: np.ndarray) -> np.ndarray:
        """Manipulator Jacobian, eq. (10)."""
        s1, c1 = np.sin(q[0]), np.cos(q[0])
        s12, c12 = np.sin(q[0] + q[1]), np.cos(q[0] + q[1])
        return np.array(
            [
                [-self.l1 * s1 - self.l2 * s12, -self.l2 * s12],
                [self.l1 * c1 + self.l2 * c12, self.l2 * c12],
            ]
        )

    def J_b_dot(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """Time derivative of J_b."""
        s1, c1 = np.sin(q[0]), np.cos(q[0])
        s12, c12 = np.sin(q[0] + q[1]), np.cos(q[0] + q[1])
        w = dq[0] + dq[1]
        return np.array(
            [
                [-self.l1 * c1 * dq[0] - self.l2 * c12 * w, -self.l2 * c12 * w],
                [-self.l1 * s1 * dq[0] - self.l2 * s12 * w, -self.l2 * s12 * w],
            ]
        )

    def features(self, q: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Image features of a target at ``target`` (x_wo, y_wo), eq. (6)."""
        return self.gain * self.R_wc(q).T @ (np.asarray(target) - self.camera_position(q))

    def f_dot(self, q: np.ndarray, dq: np.ndarray, f: np.ndarray) -> np.ndarray:
        """Image feature dynamics for a static target, eq. (8)."""
        w = dq[0] + dq[1]
        return -self.gain * self.R_wc(q).T @ self.J_b(q) @ dq - w * (_SKEW @ f)

    # --- the visual feedback system, eq. (11)-(12) --------------------------------------------
    def eta(self, q: np.ndarray, f: np.ndarray) -> np.ndarray:
        """eta = J_b^T R_wc f."""
        return self.J_b(q).T @ self.R_wc(q) @ f

    def eta_dot(self, q: np.ndarray, dq: np.ndarray, f: np.ndarray) -> np.ndarray:
        """Analytic time derivative of eta, using eq. (8) for f_dot."""
        Jb, Rwc = self.J_b(q), self.R_wc(q)
        return (
            self.J_b_dot(q, dq).T @ Rwc @ f
            + Jb.T @ self.R_wc_dot(q, dq) @ f
            + Jb.T @ Rwc @ self.f_dot(q, dq, f)
        )

    def xi(self, q: np.ndarray, dq: np.ndarray, f: np.ndarray) -> np.ndarray:
        """xi = dq - alpha eta."""
        return dq - self.alpha @ self.eta(q, f)

    def torque(self, q: np.ndarray, dq: np.ndarray, f: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Control torque, eq. (11): tau = M alpha eta_dot + C alpha eta + g + u."""
        return (
            self.M(q) @ self.alpha @ self.eta_dot(q, dq, f)
            + self.C(q, dq) @ self.alpha @ self.eta(q, f)
            + self.g(q)
            + u
        )

    def closed_loop_rhs(
        self, q: np.ndarray, xi: np.ndarray, f: np.ndarray, u: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Right-hand side of eq. (12) in (q, xi, f) coordinates: (dq, xi_dot, f_dot)."""
        Rwc, Jb = self.R_wc(q), self.J_b(q)
        dq = xi + self.alpha @ (Jb.T @ Rwc @ f)
        xi_dot = np.linalg.solve(self.M(q), u - self.C(q, dq) @ xi)
        w = dq[0] + dq[1]
        f_dot = (
            -self.gain * Rwc.T @ Jb @ xi
            - (self.gain * Rwc.T @ Jb @ self.alpha @ Jb.T @ Rwc + w * _SKEW) @ f
        )
        return dq, xi_dot, f_dot

    # --- energy function and costs, eq. (13), (17), (25) -------------------------------------
    def V(self, q: np.ndarray, xi: np.ndarray, f: np.ndarray) -> float:
        """Energy function, eq. (13)."""
        return float(0.5 * xi @ self.M(q) @ xi + self.kp / (2 * self.gain) * (f @ f))

    def V_dot(self, q: np.ndarray, xi: np.ndarray, f: np.ndarray, u: np.ndarray) -> float:
        """dV/dt along eq. (12), in the form of eq. (14)."""
        A = self.R_wc(q).T @ self.J_b(q)
        return float(xi @ u - self.kp * f @ A @ xi - self.kp * f @ A @ self.alpha @ A.T @ f)

    def Q(self, q: np.ndarray) -> np.ndarray:
        """Weight matrix of eq. (17) (4x4, acting on x = [xi, f])."""
        A = self.R_wc(q).T @ self.J_b(q)
        return np.block(
            [[self.R, 0.5 * self.kp * A.T], [0.5 * self.kp * A, self.kp * A @ self.alpha @ A.T]]
        )

    def stage_cost(self, q: np.ndarray, xi: np.ndarray, f: np.ndarray, u: np.ndarray) -> float:
        """l(x, u) = 4 x^T Q x + u^T R^-1 u, eq. (25)."""
        x = np.concatenate([xi, f])
        return float(4.0 * x @ self.Q(q) @ x + u @ self.R_inv @ u)
