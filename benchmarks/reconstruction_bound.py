"""The physical floor of the parametric study: a first-order (Cramér–Rao-style) bound on ε
(eq. 3.36).

Derivation (see docs/reconstruction.md):
1. With the pose known, the Cramér–Rao bound of point X_j from its four pixel coordinates with
   i.i.d. Gaussian noise σ is Σ_j = σ² (G_jᵀ G_j)⁻¹, G_j = ∂(u_a, v_a, u_b, v_b)/∂X_j (4x3).
   (An estimator that must also find the pose can only do worse.)
2. The study's quantity is e_i = ĥ · d̂_i/d̂_c − d_i. With the least-squares plane
   Z = p0 X + p1 Y + p2 (eq. 3.31), d̂_i/d̂_c = (p0 X_i + p1 Y_i + p2 − Z_i)/p2, a function of
   every point. Its Jacobian J (N x 3N) is taken numerically at the true points, so
   e_i ≈ b_i + ĥ J_i δX with b_i the noise-free error (plane-fit sampling, ĥ ≠ Z_m) and
   var(e_i) = ĥ² Σ_j J_ij Σ_j J_ijᵀ (points are independent given the pose).
3. ε = mean_i |e_i|, and E|N(b, s²)| = s√(2/π)·exp(−b²/2s²) + b·(1 − 2Φ(−b/s)) (folded normal),
   so the bound is ε* = mean_i E|e_i|.
"""

from __future__ import annotations

import numpy as np
from scipy.special import erf

from roadsurf.core.geometry import check_shape
from roadsurf.reconstruction.geometry import point_covariance


def ratio_to_plane(X: np.ndarray) -> np.ndarray:
    """(..., N, 3) points -> (..., N) d_i/d_c for the least-squares plane of the same points."""
    A = np.concatenate([X[..., :2], np.ones(X.shape[:-1] + (1,))], axis=-1)
    AtA = np.einsum("...ni,...nj->...ij", A, A)
    Atz = np.einsum("...ni,...n->...i", A, X[..., 2])
    p = np.linalg.solve(AtA, Atz[..., None])[..., 0]
    num = np.einsum("...ni,...i->...n", A, p) - X[..., 2]
    return num / np.abs(p[..., 2:3])


def point_crb(
    X: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray, sigma_px: float
) -> np.ndarray:
    """(N, 3, 3) Cramér–Rao covariance of each point given the pose (X_b = R X + t)."""
    return point_covariance(X, R, t, K, sigma_px)


def epsilon_bound(
    X_true: np.ndarray,
    d_true: np.ndarray,
    h_measured: float,
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    sigma_px: float,
) -> float:
    """First-order bound ε* (m) on eq. 3.36's ε for this scene (see the module docstring)."""
    X = check_shape("X_true", X_true, (None, 3)).astype(float)
    n = X.shape[0]
    r0 = ratio_to_plane(X)
    b = h_measured * r0 - d_true
    # Numerical Jacobian of r (N) w.r.t. the 3N coordinates, all perturbations in one batch.
    step = 1e-7 * float(np.median(X[:, 2]))
    batch = np.repeat(X[None], 3 * n, axis=0)
    k = np.arange(3 * n)
    batch[k, k // 3, k % 3] += step
    rp = ratio_to_plane(batch)  # (3N, N)
    batch[k, k // 3, k % 3] -= 2 * step
    rm = ratio_to_plane(batch)
    J = ((rp - rm) / (2 * step)).T.reshape(n, n, 3)  # J[i, j, :] = dr_i / dX_j
    S = point_crb(X, R, t, K, sigma_px)
    var = h_measured**2 * np.einsum("ijk,jkl,ijl->i", J, S, J)
    s = np.sqrt(np.maximum(var, 1e-300))
    folded = s * np.sqrt(2 / np.pi) * np.exp(-(b**2) / (2 * s**2)) + b * erf(b / (s * np.sqrt(2)))
    return float(np.mean(folded))
