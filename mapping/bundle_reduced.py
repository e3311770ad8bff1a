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
        self._J: sp.csr_matrix | None = None

    def full_x(self, theta: np.ndarray) -> np.ndarray:
        self._update(theta)
        return np.concatenate([theta, self.dX])

    def fun(self, theta: np.ndarray) -> np.ndarray:
        self._update(theta)
        return self._r

    def jac(self, theta: np.ndarray) -> sp.csr_matrix:
        self._update(theta)
        if self._J is None:
            raise RuntimeError("bundle: no Jacobian after an update")
        return self._J

    def _update(self, theta: np.ndarray) -> None:
        key = theta.tobytes()
        if key == self._key:
            return
        P = len(self.dX) // 3
        nt = self.n
        dX = self.dX.copy()
        for it in range(INNER_STEPS + 1):
            r, J = self.full._build(np.concatenate([theta, dX]))
            J = J.tocsc()
            Jx = J[:, nt:]
            w = _robust_weights(r, self.loss, self.scale)
            WJx = Jx.multiply(w[:, None]).tocsc()
            H = _block_diag3(Jx.T @ WJx, P) + 1e-9 * np.eye(3)
            if it == INNER_STEPS:
                break
            g = (WJx.T @ r).reshape(P, 3)
            step = np.linalg.solve(H, -g[..., None])[..., 0].ravel()
            if not np.all(np.isfinite(step)):
                break
            dX += step
        self.dX = dX
        Jt = J[:, :nt].tocsr()
        Hinv = _block_diag_csr(np.linalg.inv(H))
        proj = Jx.tocsr() @ (Hinv @ (WJx.T.tocsr() @ Jt))
        self._J = (Jt - proj).tocsr()
        self._r = r
        self._key = key


def _block_diag_csr(B: np.ndarray) -> sp.csr_matrix:
    """(P, 3, 3) blocks -> (3P, 3P) block-diagonal CSR."""
    P = len(B)
    i = np.arange(3 * P)
    cols = (3 * (i // 3))[:, None] + np.arange(3)[None, :]
    return sp.csr_matrix(
        (B.reshape(-1), cols.reshape(-1), 3 * np.arange(3 * P + 1)), (3 * P, 3 * P)
    )


def _block_diag3(A: sp.spmatrix, P: int) -> np.ndarray:
    """The (P, 3, 3) diagonal blocks of a (3P, 3P) sparse matrix."""
    A = A.tocoo()
    i, j = A.row, A.col
    on = (i // 3) == (j // 3)
    out = np.zeros((P, 3, 3))
    np.add.at(out, (i[on] // 3, i[on] % 3, j[on] % 3), A.data[on])
    return out


def _whitened(J: sp.csr_matrix, T: np.ndarray) -> LinearOperator:
    """J T as an operator: two products a LSMR step instead of a dense (rows x n) matrix."""
    Jt = J.T.tocsr()
    return LinearOperator(
        (J.shape[0], T.shape[1]),
        matvec=lambda v: J @ (T @ v),
        rmatvec=lambda u: T.T @ (Jt @ u),
        matmat=lambda V: J @ (T @ V),
        rmatmat=lambda U: T.T @ (Jt @ U),
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
        return _whitened(red.jac(theta + T @ y), T)

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
