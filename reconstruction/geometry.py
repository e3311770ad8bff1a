"""Pure numpy two-view geometry helpers (dissertation eq. 3.9-3.34).

Conventions: camera a is the reference, X_b = R_b_from_a @ X_a + t_b_from_a. Pixels are
(u right, v down); "normalised" coordinates are K^-1 [u, v, 1]. Camera z points down at the road,
so road points have Z > 0 and a point below the road surface has a larger Z than the plane.
"""

from __future__ import annotations

import numpy as np

from roadsurf.core.geometry import check_shape, skew


def rotation_from_axis_angle(w: np.ndarray) -> np.ndarray:
    """Rodrigues: (3,) axis*angle (rad) -> (3, 3) rotation."""
    w = np.asarray(w, dtype=float)
    th = float(np.linalg.norm(w))
    if th < 1e-12:
        return np.eye(3) + skew(w)
    k = skew(w / th)
    return np.eye(3) + np.sin(th) * k + (1.0 - np.cos(th)) * (k @ k)


def fundamental_from_pose(R: np.ndarray, t: np.ndarray, K: np.ndarray) -> np.ndarray:
    """F = K^-T [t]x R K^-1, so that x_b^T F x_a = 0 in pixels (eq. 3.9)."""
    Ki = np.linalg.inv(K)
    F = Ki.T @ skew(np.asarray(t, float)) @ R @ Ki
    return F / (np.linalg.norm(F) + 1e-300)


def sampson_px(F: np.ndarray, px_a: np.ndarray, px_b: np.ndarray) -> np.ndarray:
    """(N,) signed Sampson distance (px) of matches to the epipolar geometry F."""
    n = px_a.shape[0]
    xa = np.hstack([px_a, np.ones((n, 1))])
    xb = np.hstack([px_b, np.ones((n, 1))])
    Fxa = xa @ F.T
    Ftxb = xb @ F
    num = np.sum(xb * Fxa, axis=1)
    den = np.sqrt(Fxa[:, 0] ** 2 + Fxa[:, 1] ** 2 + Ftxb[:, 0] ** 2 + Ftxb[:, 1] ** 2) + 1e-300
    return num / den


def triangulate(xa: np.ndarray, xb: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear (inhomogeneous DLT) triangulation in normalised coordinates (eq. 3.11-3.12).

    xa, xb: (N, 2) normalised coordinates in a and b; R (3, 3), t (3,) with X_b = R X_a + t.
    Returns (N, 3) points in camera a (same length unit as t).
    """
    xa = check_shape("xa", xa, (None, 2))
    xb = check_shape("xb", xb, (None, 2))
    n = xa.shape[0]
    A = np.zeros((n, 4, 3))
    b = np.zeros((n, 4))
    A[:, 0] = [1.0, 0.0, 0.0]
    A[:, 0, 2] = -xa[:, 0]
    A[:, 1] = [0.0, 1.0, 0.0]
    A[:, 1, 2] = -xa[:, 1]
    A[:, 2] = R[0] - xb[:, :1] * R[2]
    A[:, 3] = R[1] - xb[:, 1:2] * R[2]
    b[:, 2] = xb[:, 0] * t[2] - t[0]
    b[:, 3] = xb[:, 1] * t[2] - t[1]
    AtA = np.einsum("nki,nkj->nij", A, A)
    Atb = np.einsum("nki,nk->ni", A, b)
    return np.linalg.solve(AtA, Atb[..., None])[..., 0]


def point_covariance(
    X: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray, sigma_px: float
) -> np.ndarray:
    """(N, 3, 3) first-order covariance of triangulated points (eq. 3.27-3.30), pose fixed.

    Σ_X = σ² (Gᵀ G)⁻¹ with G = ∂(u_a, v_a, u_b, v_b)/∂X (4x3), i.e. the P⁺ Σ_x P⁺ᵀ of the
    dissertation for the optimal (reprojection-error) triangulation; analytic, so cheap.
    """
    X = check_shape("X", X, (None, 3))
    fx, fy = K[0, 0], K[1, 1]

    def proj_jac(P: np.ndarray) -> np.ndarray:
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        J = np.zeros((P.shape[0], 2, 3))
        J[:, 0, 0] = fx / z
        J[:, 0, 2] = -fx * x / z**2
        J[:, 1, 1] = fy / z
        J[:, 1, 2] = -fy * y / z**2
        return J

    G = np.concatenate([proj_jac(X), proj_jac(X @ R.T + t) @ R], axis=1)
    return sigma_px**2 * np.linalg.inv(np.einsum("nki,nkj->nij", G, G))


def decompose_essential(
    E: np.ndarray, xa: np.ndarray, xb: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:
    """SVD of E (eq. 3.10) -> (R, unit t, n_in_front) keeping the cheirality-valid combination."""
    U, _, Vt = np.linalg.svd(E)
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    best: tuple[np.ndarray, np.ndarray, int] = (np.eye(3), np.zeros(3), -1)
    if len(xa) > 200:  # cheirality is decided by any sizeable subset; keeps the loop cheap
        sel = np.linspace(0, len(xa) - 1, 200).astype(int)
        xa, xb = xa[sel], xb[sel]
    for R in (U @ W @ Vt, U @ W.T @ Vt):
        for t in (U[:, 2], -U[:, 2]):
            X = triangulate(xa, xb, R, t)
            Xb = X @ R.T + t
            n_front = int(np.sum((X[:, 2] > 0) & (Xb[:, 2] > 0)))
            if n_front > best[2]:
                best = (R, t / np.linalg.norm(t), n_front)
    return best
