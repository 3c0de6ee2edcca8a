"""Plain-NumPy reference of the C/GMRES update: the same algorithm, no numba.

It doubles as an independent cross-check of the compiled kernels: the dynamics come from
:meth:`tests.support.nominal_model.NumpyModel.closed_loop_rhs` and the Hamiltonian gradients are
derived in matrix form from the model's own M, C, J_b, R_wc and their derivatives (generic in q1
and q2), not from the scalar expressions of :mod:`rt_controller.control.rhc.problem`. It is slow
(Python loops over the horizon); it is for tests and for the benchmark's "what compiling buys"
ratio.
"""

from __future__ import annotations

import math

import numpy as np

from hal.config import RigConfig
from rt_controller.control.model import NominalModel
from rt_controller.control.rhc.problem import DUMMY_FLOOR, INIT_KRYLOV, substeps
from rt_controller.control.rhc.solver import SolveReport
from rt_controller.control.state import NS, NX
from tests.support.nominal_model import NumpyModel

_SKEW = np.array([[0.0, -1.0], [1.0, 0.0]])
_E = np.eye(2)


class ReferenceProblem:
    """Dynamics, costs and Hamiltonian gradients of eq. (30) in matrix form."""

    def __init__(self, model: NominalModel, cfg: RigConfig) -> None:
        self.m = NumpyModel.of(model)
        self.umax = np.asarray(cfg.rhc.u_max, dtype=float)
        self.rv = cfg.rhc.dummy_weight
        self.vmin = DUMMY_FLOOR * self.umax

    def rhs(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        dq, xid, fd = self.m.closed_loop_rhs(x[0:2], x[2:4], x[4:6], u)
        return np.concatenate([dq, xid, fd])

    def stage_cost(self, x: np.ndarray, u: np.ndarray) -> float:
        return self.m.stage_cost(x[0:2], x[2:4], x[4:6], u)

    def terminal_cost(self, x: np.ndarray) -> float:
        return 4.0 * self.m.V(x[0:2], x[2:4], x[4:6])

    def _dA(self, q: np.ndarray, j: int) -> np.ndarray:
        """d(R_wc^T J_b)/dq_j."""
        m, e = self.m, _E[j]
        return m.R_wc_dot(q, e).T @ m.J_b(q) + m.R_wc(q).T @ m.J_b_dot(q, e)

    def _dC(self, q: np.ndarray, dq: np.ndarray, j: int) -> np.ndarray:
        """dC(q, dq)/dq_j (C depends on q through theta3 sin q2 only)."""
        if j == 0:
            return np.zeros((2, 2))
        h = self.m.theta3 * np.cos(q[1])
        return np.array([[-h * dq[1], -h * (dq[0] + dq[1])], [h * dq[0], 0.0]])

    def terminal_grad(self, x: np.ndarray) -> np.ndarray:
        m = self.m
        q, xi, f = x[0:2], x[2:4], x[4:6]
        gq = np.array([2.0 * xi @ m.M_dot(q, _E[j]) @ xi for j in range(2)])
        return np.concatenate([gq, 4.0 * m.M(q) @ xi, 4.0 * m.kp / m.gain * f])

    def hamiltonian_grad(
        self, x: np.ndarray, u: np.ndarray, lam: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(H_x, H_u) without the bound terms; H = l + lam^T f(x, u)."""
        m = self.m
        q, xi, f = x[0:2], x[2:4], x[4:6]
        lq, lx, lf = lam[0:2], lam[2:4], lam[4:6]
        A = m.R_wc(q).T @ m.J_b(q)
        eta = A.T @ f
        dq = xi + m.alpha @ eta
        w = dq[0] + dq[1]
        Mq = m.M(q)
        Cq = m.C(q, dq)
        z = np.linalg.solve(Mq, lx)
        y = np.linalg.solve(Mq, u - Cq @ xi)
        lSf = lf @ _SKEW @ f
        # dH/d(dq), with C(q, dq) linear in dq: C = sum_j dq_j C(q, e_j).
        dCxi = np.array([z @ m.C(q, _E[j]) @ xi for j in range(2)])
        G = 4.0 * m.kp * eta + lq - m.gain * A.T @ lf - lSf * np.ones(2) - dCxi
        E = 4.0 * m.kp * dq + m.alpha.T @ G
        R = m.R
        h_xi = 4.0 * (R + R.T) @ xi - Cq.T @ z + G
        h_f = -w * _SKEW.T @ lf + A @ E
        h_q = np.zeros(2)
        for j in range(2):
            dA = self._dA(q, j)
            h_q[j] = (
                -z @ m.M_dot(q, _E[j]) @ y
                - z @ self._dC(q, dq, j) @ xi
                - m.gain * lf @ dA @ dq
                + f @ dA @ E
            )
        h_u = (m.R_inv + m.R_inv.T) @ u + z
        return np.concatenate([h_q, h_xi, h_f]), h_u

    def hamiltonian(self, x: np.ndarray, u: np.ndarray, lam: np.ndarray) -> float:
        """H = l + lam^T f(x, u) (for finite-difference checks)."""
        return self.stage_cost(x, u) + lam @ self.rhs(x, u)


class ReferenceSolver:
    """The C/GMRES update of :mod:`rt_controller.control.rhc.kernel` in NumPy (same interface as
    :class:`~rt_controller.control.rhc.solver.CGMRESSolver`)."""

    def __init__(self, model: NominalModel, cfg: RigConfig) -> None:
        h = cfg.rhc
        self.prob = ReferenceProblem(model, cfg)
        self.model = self.prob.m
        self.N = h.steps
        self.kmax = h.kmax
        self.zeta = h.zeta
        self.dt = 1.0 / cfg.rates.control_hz
        self.h = h.fd_step
        self.Tf = h.horizon
        self.growth = h.horizon_growth
        self.residual_bound = h.residual_bound
        self.init_tol = h.init_tol
        self.init_iterations = h.init_iterations
        self.init_krylov = min(NS * h.steps, max(INIT_KRYLOV, h.kmax))
        self.S = substeps(h.horizon, h.steps)
        self.U = np.zeros(NS * self.N)
        self.Udot = np.zeros(NS * self.N)
        self.needs_init = True
        self._X = np.zeros((self.N * self.S + 1, NX))
        self.fevals = 0

    @property
    def last_fevals(self) -> int:
        """Evaluations of F in the last update (as CGMRESSolver.last_fevals)."""
        return self.fevals

    def reset(self) -> None:
        self.U[:] = 0.0
        self.Udot[:] = 0.0
        self.needs_init = True

    def horizon(self, t: float) -> float:
        if self.growth <= 0.0:
            return self.Tf
        return self.Tf * (1.0 - math.exp(-self.growth * max(t, 0.0)))

    # --- F(U, x, T) -----------------------------------------------------------------------
    def F(self, U: np.ndarray, x0: np.ndarray, T: float) -> np.ndarray:
        """Optimality residual; leaves the forward sweep's states in ``self._X``.

        Each stage holds its input over ``S`` Euler substeps; its input rows are the average of
        H_u over them (kernel.eval_F)."""
        p, N, S = self.prob, self.N, self.S
        h = T / (N * S)
        self.fevals += 1
        Us = U.reshape(N, NS)
        X = self._X
        X[0] = x0
        for r in range(N * S):
            X[r + 1] = X[r] + h * p.rhs(X[r], Us[r // S, 0:2])
        lam = p.terminal_grad(X[N * S])
        F = np.empty((N, NS))
        for k in range(N - 1, -1, -1):
            u, v, mu = Us[k, 0:2], Us[k, 2:4], Us[k, 4:6]
            g = np.zeros(2)
            for r in range(k * S + S - 1, k * S - 1, -1):
                hx, hu = p.hamiltonian_grad(X[r], u, lam)
                g += hu
                lam = lam + h * hx
            F[k, 0:2] = g / S + 2.0 * mu * u
            F[k, 2:4] = -p.rv + 2.0 * mu * v
            F[k, 4:6] = u * u + v * v - p.umax**2
        return F.ravel()

    def clip(self, U: np.ndarray) -> None:
        """Radial projection of (u, v) onto the bound circles, v >= vmin (kernel.clip_dummies)."""
        S = U.reshape(self.N, NS)
        umax, vmin = self.prob.umax, self.prob.vmin
        u, v = S[:, 0:2], np.maximum(S[:, 2:4], vmin)
        r = np.hypot(u, v)
        good = (r > 0) & np.isfinite(r)
        scale = np.where(good, umax / np.where(good, r, 1.0), 1.0)
        u, v = u * scale, v * scale
        low = v < vmin
        u = np.where(low, np.copysign(np.sqrt(umax**2 - vmin**2), u), u)
        S[:, 0:2], S[:, 2:4] = u, np.where(low, vmin, v)

    def release(self, U: np.ndarray, F: np.ndarray) -> int:
        """Restart bounds whose multiplier turned negative (kernel.release_bounds)."""
        S, G = U.reshape(self.N, NS), F.reshape(self.N, NS)
        p, m = self.prob, self.model
        u, mu = S[:, 0:2], S[:, 4:6]
        bad = mu < 0.0
        if not bad.any():
            return 0
        g = G[:, 0:2] - 2.0 * mu * u
        un = u - g / (2.0 * np.diag(m.R_inv))
        un = np.clip(np.where(np.isfinite(un), un, 0.0), -0.9 * p.umax, 0.9 * p.umax)
        vn = np.sqrt(p.umax**2 - un * un)
        S[:, 0:2] = np.where(bad, un, u)
        S[:, 2:4] = np.where(bad, vn, S[:, 2:4])
        S[:, 4:6] = np.where(bad, p.rv / (2.0 * vn), mu)
        return int(bad.sum())

    # --- block preconditioner (see kernel.precond_setup) ------------------------------------
    def precond(self, U: np.ndarray, T: float):
        """Returns d = P^-1 r as a function (uses the states of the last F evaluation)."""
        m, N = self.model, self.N
        dtau = T / N
        S = U.reshape(N, NS)
        u, v, mu = S[:, 0:2], S[:, 2:4], S[:, 4:6]
        Hs = np.empty((N, 2, 2))
        for k in range(N):
            Hs[k] = m.R_inv + m.R_inv.T + 4.0 * dtau * np.linalg.inv(m.M(self._X[k * self.S, 0:2]))
        Hs[:, [0, 1], [0, 1]] += 2.0 * mu + 2.0 * u * u * mu / (v * v)
        Hinv = np.linalg.inv(Hs)

        def apply(r: np.ndarray) -> np.ndarray:
            R = r.reshape(N, NS)
            ru, rv, rc = R[:, 0:2], R[:, 2:4], R[:, 4:6]
            qv = ru - u / v * rv + u * mu / (v * v) * rc
            du = np.einsum("kij,kj->ki", Hinv, qv)
            dv = 0.5 * rc / v - u / v * du
            dmu = 0.5 * rv / v - mu / v * dv
            return np.concatenate([du, dv, dmu], axis=1).ravel()

        return apply

    # --- forward-difference GMRES ---------------------------------------------------------
    def gmres(self, U, x0, T, F0, b, guess, m, tol, pre):
        """Right-preconditioned GMRES(m) on F_U d = b; returns (d, iterations)."""
        h = self.h

        def jvp(v: np.ndarray) -> np.ndarray:
            s = np.linalg.norm(v)
            return (self.F(U + (h / s) * v, x0, T) - F0) / (h / s)

        sol = np.zeros_like(b) if guess is None else guess.copy()
        r = b - jvp(sol) if guess is not None and np.linalg.norm(sol) > 0 else b.copy()
        beta = np.linalg.norm(r)
        if not (beta > 0.0) or not np.isfinite(beta):
            return sol, 0
        V = [r / beta]
        H = np.zeros((m + 1, m))
        cs, sn = np.zeros(m), np.zeros(m)
        g = np.zeros(m + 1)
        g[0] = beta
        k = 0
        for j in range(m):
            z = pre(V[j])
            zn = np.linalg.norm(z)
            if not (zn > 0.0) or not np.isfinite(zn):
                break
            w = jvp(z)
            for i in range(j + 1):
                H[i, j] = w @ V[i]
                w = w - H[i, j] * V[i]
            hnext = np.linalg.norm(w)
            H[j + 1, j] = hnext
            for i in range(j):
                a = cs[i] * H[i, j] + sn[i] * H[i + 1, j]
                H[i + 1, j] = -sn[i] * H[i, j] + cs[i] * H[i + 1, j]
                H[i, j] = a
            d = math.hypot(H[j, j], hnext)
            if not (d > 0.0):
                break
            cs[j], sn[j] = H[j, j] / d, hnext / d
            H[j, j], H[j + 1, j] = d, 0.0
            g[j + 1] = -sn[j] * g[j]
            g[j] = cs[j] * g[j]
            k = j + 1
            if not (hnext > 1e-300) or abs(g[j + 1]) <= tol * beta:
                break
            V.append(w / hnext)
        if k:
            y = np.linalg.solve(np.triu(H[:k, :k]), g[:k])
            sol = sol + pre(np.asarray(V[:k]).T @ y)
        return sol, k

    def block_gmres(self, U, x0, T, F0, b1, b2, m, pre):
        """F_U d1 = b1 and F_U d2 = b2 from one basis of m products (kernel.block_gmres)."""
        h = self.h

        def jvp(v: np.ndarray) -> np.ndarray:
            s = np.linalg.norm(v)
            return (self.F(U + (h / s) * v, x0, T) - F0) / (h / s)

        V: list[np.ndarray] = []
        G = np.zeros((m + 2, 2))
        for c, b in enumerate((b1, b2)):
            bn = np.linalg.norm(b)
            if not (bn > 0.0) or not np.isfinite(bn):
                continue
            v = b.copy()
            for i, vi in enumerate(V):
                G[i, c] = v @ vi
                v = v - G[i, c] * vi
            vn = np.linalg.norm(v)
            if vn > 1e-12 * bn:
                G[len(V), c] = vn
                V.append(v / vn)
        H = np.zeros((m + 2, m))
        k = 0
        while k < m and k < len(V):
            z = pre(V[k])
            zn = np.linalg.norm(z)
            if not (zn > 0.0) or not np.isfinite(zn):
                break
            w = jvp(z)
            wn0 = np.linalg.norm(w)
            for i, vi in enumerate(V):
                H[i, k] = w @ vi
                w = w - H[i, k] * vi
            hn = np.linalg.norm(w)
            if not np.isfinite(hn):
                break
            if hn > 1e-12 * wn0 and hn > 1e-300:
                H[len(V), k] = hn
                V.append(w / hn)
            k += 1
        nv = len(V)
        out = []
        for c in range(2):
            if k == 0:
                out.append(np.zeros_like(b1))
                continue
            y = np.linalg.lstsq(H[:nv, :k], G[:nv, c], rcond=None)[0]
            out.append(pre(np.asarray(V[:k]).T @ y))
        return out[0], out[1], k

    def _predict(self, U, x0, t, T, F, u, xdot):
        """d2 = F_U^-1 b2, b2 = -dt (F(U, x0 + h xdot, T(t + h)) - F) / h (b1 = 0)."""
        xd = self.prob.rhs(x0, u) if xdot is None else np.asarray(xdot, dtype=float)
        h = self.h
        b2 = -self.dt * (self.F(U, x0 + h * xd, self.horizon(t + h)) - F) / h
        return b2

    # --- initial solution -----------------------------------------------------------------
    def initial_guess(self, x0: np.ndarray, T: float) -> np.ndarray:
        """Rollout of u = -2 R xi held over each stage (S substeps), the gain scaled by
        1 / (dtau tr(2 M^-1 R)) when that is > 1."""
        p, N, m, S = self.prob, self.N, self.model, self.S
        dtau = T / N
        gain = 2.0 / max(1.0, dtau * np.trace(2.0 * np.linalg.solve(m.M(x0[0:2]), m.R)))
        Us = np.zeros((N, NS))
        x = x0.copy()
        for k in range(N):
            u = -gain * m.R @ x[2:4]
            u = np.where(np.isfinite(u), u, 0.0)
            u = np.clip(u, -0.9 * p.umax, 0.9 * p.umax)
            v = np.sqrt(p.umax**2 - u * u)
            Us[k] = np.concatenate([u, v, p.rv / (2.0 * v)])
            for _ in range(S):
                x = x + dtau / S * p.rhs(x, u)
        return Us.ravel()

    def newton(self, x0: np.ndarray, T: float) -> tuple[float, int]:
        U = self.U
        F = self.F(U, x0, T)
        fn = np.linalg.norm(F)
        iters = 0
        for _ in range(self.init_iterations):
            if not np.isfinite(fn) or fn <= self.init_tol:
                break
            pre = self.precond(U, T)
            d, k = self.gmres(U, x0, T, F, -F, None, self.init_krylov, 1e-6, pre)
            iters += k
            step, accepted = 1.0, False
            for _ls in range(30):
                Ut = U + step * d
                self.clip(Ut)
                Ft = self.F(Ut, x0, T)
                ft = np.linalg.norm(Ft)
                if ft < (1.0 - 1e-4 * step) * fn:
                    accepted = True
                    break
                step *= 0.5
            if not accepted:
                break
            U[:] = Ut
            F, fn = Ft, ft
            if self.release(U, F):
                F = self.F(U, x0, T)
                fn = np.linalg.norm(F)
        return float(fn), iters

    def _correct(self, U, x0, T, F, c):
        """One corrector pass F_U dU = -c F (U updated in place); returns (F(U), iterations)."""
        pre = self.precond(U, T)
        dU, k = self.gmres(U, x0, T, F, -c * F, None, self.kmax, 0.0, pre)
        U += dU
        self.clip(U)
        return self.F(U, x0, T), k

    # --- one tick -------------------------------------------------------------------------
    def update(self, x: np.ndarray, t: float, xdot: np.ndarray | None = None) -> SolveReport:
        """Same contract as :meth:`CGMRESSolver.update`."""
        x0 = np.asarray(x, dtype=float).copy()
        T = self.horizon(t)
        init = self.needs_init
        with np.errstate(all="ignore"):
            rep = self._tick(x0, t, T, init, xdot)
        self.needs_init = not rep.ok
        return rep

    def _tick(self, x0, t, T, init, xdot) -> SolveReport:
        U = self.U
        iters = 0
        umax = self.prob.umax
        zero = np.zeros_like(U)
        self.fevals = 0
        if init:
            U[:] = self.initial_guess(x0, T)
            fn, iters = self.newton(x0, T)
            F = self.F(U, x0, T)
            fn = float(np.linalg.norm(F))
            u = np.clip(U[0:2], -umax, umax)
            if not (np.isfinite(fn) and np.all(np.isfinite(U[0:2]))):
                return SolveReport(u, fn, iters, False, init)
            pre = self.precond(U, T)
            b2 = self._predict(U, x0, t, T, F, u, xdot)
            _, d2, k = self.block_gmres(U, x0, T, F, zero, b2, self.kmax, pre)
            iters += k
        else:
            u_warm = np.clip(U[0:2], -umax, umax)
            F = self.F(U, x0, T)
            pre = self.precond(U, T)
            b2 = self._predict(U, x0, t, T, F, u_warm, xdot)
            c = min(self.zeta * self.dt, 1.0)
            d1, d2, k = self.block_gmres(U, x0, T, F, -c * F, b2, self.kmax, pre)
            iters += k
            U += d1
            self.clip(U)
            F = self.F(U, x0, T)
            released = self.release(U, F) > 0
            if released:
                F, k = self._correct(U, x0, T, self.F(U, x0, T), 1.0)
                iters += k
            fn = float(np.linalg.norm(F))
            u = np.clip(U[0:2], -umax, umax)
            if not (np.isfinite(fn) and np.all(np.isfinite(U[0:2]))):
                return SolveReport(u, fn, iters, False, init)
            if released:
                pre = self.precond(U, T)
                b2 = self._predict(U, x0, t, T, F, u, xdot)
                _, d2, k = self.block_gmres(U, x0, T, F, zero, b2, self.kmax, pre)
                iters += k
        self.Udot[:] = d2 / self.dt
        U += d2
        self.clip(U)
        return SolveReport(u, fn, iters, bool(fn <= self.residual_bound), init)
