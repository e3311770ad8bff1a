"""The window's problem with the points eliminated (variable projection), for scipy.

Handing poses and points together to ``least_squares`` leaves LSMR with a badly conditioned
system: it fits the points in a few steps but hardly moves the poses (measured: 1 mm moved,
drift unchanged, unless run to 30 evaluations, 5 s per window). Here the solver sees only the
camera side (poses, planes, τ: ~9 unknowns a frame); for each camera-side value every point is
re-triangulated (a few batched 3x3 Gauss-Newton steps with the same robust weights), and the
Jacobian is the camera-side block projected off the points' (J_θ - J_X H⁻¹ J_Xᵀ W J_θ, with
H = J_Xᵀ W J_X block-diagonal per point): the Schur complement, built with sparse products.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
from scipy.linalg import solve_triangular
from scipy.optimize import least_squares
from scipy.sparse.linalg import LinearOperator

from roadsurf.mapping.bundle_problem import WindowProblem
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.pose_graph import _robust_weights

log = logging.getLogger(__name__)

INNER_STEPS = 3  # Gauss-Newton steps per point and evaluation (warm-started)


class ReducedProblem:
    def __init__(self, full: WindowProblem, loss: str, scale: float) -> None:
        self.full = full
        self.loss, self.scale = loss, scale
        self.n = full.point_col0  # camera-side unknowns
        self.dX = np.zeros(full.n - full.point_col0)  # latest point offsets (warm start)
        self._key: bytes | None = None
        self._r = np.zeros(0)
        self._op: ProjectedJacobian | None = None
        self._J: sp.csr_matrix | None = None

    def full_x(self, theta: np.ndarray) -> np.ndarray:
        self._update(theta)
        return np.concatenate([theta, self.dX])

    def fun(self, theta: np.ndarray) -> np.ndarray:
        self._update(theta)
        return self._r

    def jac(self, theta: np.ndarray) -> sp.csr_matrix:
        """The reduced Jacobian as an explicit sparse matrix (rows x n)."""
        op = self.jac_op(theta)
        if self._J is None:
            self._J = op.explicit()
        return self._J

    def jac_op(self, theta: np.ndarray) -> ProjectedJacobian:
        """The reduced Jacobian kept factored (products only: no fill-in)."""
        self._update(theta)
        if self._op is None:
            raise RuntimeError("bundle: no Jacobian after an update")
        return self._op

    def _update(self, theta: np.ndarray) -> None:
        key = theta.tobytes()
        if key == self._key:
            return
        full = self.full
        P = len(self.dX) // 3
        p = full.d.obs_p
        dX = self.dX.copy()
        # the points' steps need only their own dense (3 x 3) blocks per observation: the
        # window's sparse Jacobian is built once, at the final points
        for it in range(INNER_STEPS + 1):
            ot = full.point_terms(np.concatenate([theta, dX]))
            w = [_robust_weights(r, self.loss, self.scale) for r in ot.res]
            # H = Jxᵀ W Jx, block-diagonal per point, and the gradient Jxᵀ W r
            h = np.zeros((len(p), 3, 3))
            gm = np.zeros((len(p), 3))
            for wk, rk, a in zip(w, ot.res, ot.Ax, strict=True):
                h += wk[:, None, None] * a[:, :, None] * a[:, None, :]
                gm += (wk * rk)[:, None] * a
            H = _per_point(h, p, P) + 1e-9 * np.eye(3)
            if it == INNER_STEPS:
                break
            g = _per_point(gm, p, P)
            step = np.linalg.solve(H, -g[..., None])[..., 0].ravel()
            if not np.all(np.isfinite(step)):
                break
            dX += step
        self.dX = dX
        r, Jt = full._build(np.concatenate([theta, dX]), points=False)
        Hinv = np.linalg.inv(H)
        ax = np.concatenate(ot.Ax)  # (3M, 3): rows k M + i
        pk = np.tile(p, 3)
        wr = np.concatenate(w)[:, None] * np.einsum("mij,mj->mi", Hinv[pk], ax)
        self._op = ProjectedJacobian(Jt, ax, wr, pk, P)
        self._J = None
        self._r = r
        self._key = key


class ProjectedJacobian:
    """The camera-side Jacobian projected off the points, J = Jt - Jx M, kept factored: Jt
    (rows x n) sparse, Jx (rows x 3P) each observation row's point block (ax, (3M, 3), rows
    first), M = H⁻¹ Jxᵀ W (3P x rows) from its rows' (W Jx H⁻¹) (wr, (3M, 3)), pk (3M,) each
    observation row's point. A product costs one of Jt's and two of three entries a row; the
    explicit matrix (each row filled over every frame seeing its point) about three times as
    much."""

    def __init__(
        self, Jt: sp.csr_matrix, ax: np.ndarray, wr: np.ndarray, pk: np.ndarray, P: int
    ) -> None:
        self.Jt, self.shape = Jt, Jt.shape
        n3, rows = len(pk), Jt.shape[0]
        cols = ((3 * pk)[:, None] + np.arange(3)).ravel()
        ptr = np.r_[3 * np.arange(n3 + 1), np.full(rows - n3, 3 * n3)]
        self.Jx = sp.csr_matrix((ax.ravel(), cols, ptr), shape=(rows, 3 * P))
        self.Mt = sp.csr_matrix((wr.ravel(), cols, ptr), shape=(rows, 3 * P))  # Mᵀ
        self._JtT: sp.csr_matrix | None = None

    def matvec(self, v: np.ndarray) -> np.ndarray:
        y = self.Jt @ v
        return y - self.Jx @ (self.Mt.T @ y)

    def rmatvec(self, u: np.ndarray) -> np.ndarray:
        if self._JtT is None:
            self._JtT = self.Jt.T.tocsr()
        return self._JtT @ (u - self.Mt @ (self.Jx.T @ u))

    def explicit(self) -> sp.csr_matrix:
        return (self.Jt - self.Jx @ (self.Mt.T.tocsr() @ self.Jt)).tocsr()


def _per_point(v: np.ndarray, p: np.ndarray, P: int) -> np.ndarray:
    """Per-observation (M, ...) values summed over each of the P points (p: (M,) point index)."""
    flat = v.reshape(len(p), -1)
    out = np.stack([np.bincount(p, flat[:, j], minlength=P) for j in range(flat.shape[1])], 1)
    return out.reshape((P,) + v.shape[1:])


def _whitened(J: ProjectedJacobian, T: np.ndarray) -> LinearOperator:
    """J T as an operator: two products a LSMR step instead of a dense (rows x n) matrix."""
    return LinearOperator(
        (J.shape[0], T.shape[1]),
        matvec=lambda v: J.matvec(T @ np.ravel(v)),
        rmatvec=lambda u: T.T @ J.rmatvec(np.ravel(u)),
        dtype=float,
    )


def _whitening(red: ReducedProblem, theta: np.ndarray) -> np.ndarray:
    """(n, n) T = L⁻ᵀ with L Lᵀ = JᵀJ (+ a small ridge) at theta."""
    J = red.jac(theta)
    A = (J.T @ J).toarray()
    A += np.diag(1e-6 * np.maximum(np.diag(A), 1e-12) + 1e-9)
    L = np.linalg.cholesky(A)
    return solve_triangular(L, np.eye(len(A)), lower=True).T


def solve_reduced(red: ReducedProblem, theta: np.ndarray, cfg: MappingConfig) -> np.ndarray:
    """scipy least_squares (TRF, LSMR, robust loss) on the whitened camera-side unknowns
    y = Lᵀ(θ - θ0), LLᵀ = JᵀJ at θ0: on the raw θ LSMR needs hundreds of iterations a step
    (poses, planes and τ differ by orders of magnitude and are correlated); on y a few tens."""
    T = _whitening(red, theta)
    r0 = red.fun(theta)

    def fun(y: np.ndarray) -> np.ndarray:
        return red.fun(theta + T @ y)

    def jac(y: np.ndarray) -> LinearOperator:
        return _whitened(red.jac_op(theta + T @ y), T)

    sol = least_squares(
        fun,
        np.zeros(red.n),
        jac=jac,
        method="trf",
        loss=cfg.robust_loss,
        f_scale=cfg.robust_scale,
        # the first trust region as long as a full step can be (|r|): y is in σ units
        x_scale=max(1.0, float(np.linalg.norm(r0))),
        tr_solver="lsmr",
        max_nfev=cfg.bundle_max_nfev,
        ftol=1e-6,
        xtol=1e-8,
    )
    log.debug("bundle window: %s after %d evaluations", sol.message, sol.nfev)
    return theta + T @ sol.x
