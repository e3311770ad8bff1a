"""Plane + parallax geometry of one pair: the road plane's homography, and the exact relation
between a pixel's residual parallax after the plane warp and its height above the plane.

Camera a at the origin, X_b = R X_a + t. The road plane n·X = d (n unit, pointing away from
camera a, d = h_a > 0 its distance); a point's height above the road is η = d - n·X_a (negative
below). With H = K (R + t nᵀ/d) K⁻¹ (the road homography a -> b), warping image b onto image a
by H (I_w(x) = I_b(H x)) leaves the road in place; a pixel x_a (ray r = K⁻¹ x_a, depth Z_a) of a
point at height η appears in I_w at

    x_w = x_a + s ŵ,   ŵ = w / |w|,   w = E₃ x_a - (E₁, E₂),   E = K C_b,
    s = k |w| / (1 - k E₃),   k = η / (h_b Z_a),   Z_a = (h_a - η) / (n·r),

with C_b = -Rᵀ t the centre of camera b in camera a and h_b = d - n·C_b its height: the
displacement lies on the line through the epipole E (the image of camera b's centre in a),
whatever its position (at infinity for a nadir camera moving parallel to the road). Inverting,

    k = s / (|w| + s E₃),   η = k h_a h_b / (n·r + k h_b).

Derivation: X_b = (R + t nᵀ/d) X_a + t η / d, and (R + t nᵀ/d)⁻¹ t = -C_b d / h_b.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from roadsurf.core.errors import RoadsurfError


def plane_normal_distance(plane: np.ndarray) -> tuple[np.ndarray, float]:
    """(3,) unit normal n (pointing away from the camera) and distance d (m) of the plane
    z = p0 x + p1 y + p2 (camera coordinates, PairResult.plane), so that n·X = d on it."""
    p = np.asarray(plane, float).reshape(3)
    if not np.all(np.isfinite(p)) or p[2] <= 0:
        raise RoadsurfError(
            f"road plane {p.tolist()} is not in front of the camera (needs finite p0, p1 and "
            "p2 > 0 m): a failed pair has no dense height"
        )
    m = np.array([-p[0], -p[1], 1.0])
    norm = float(np.linalg.norm(m))
    return m / norm, float(p[2] / norm)


@dataclass(frozen=True)
class PlaneParallax:
    """The plane + parallax model of one pair in ideal (undistorted) pixels of intrinsics K."""

    K: np.ndarray  # (3, 3) intrinsics of the pixel grid the model works in
    n: np.ndarray  # (3,) unit road normal in camera a, pointing away from the camera
    h_a: float  # distance of camera a from the road plane, d (m)
    h_b: float  # distance of camera b from the road plane (m)
    C_b: np.ndarray  # (3,) centre of camera b in camera a (m)
    H: np.ndarray  # (3, 3) road homography a -> b (ideal px of K)
    E: np.ndarray  # (3,) K C_b: the epipole of b in a, homogeneous, not normalised

    @classmethod
    def from_pair(
        cls, R_b_from_a: np.ndarray, t_b_from_a_m: np.ndarray, plane: np.ndarray, K: np.ndarray
    ) -> PlaneParallax:
        R = np.asarray(R_b_from_a, float).reshape(3, 3)
        t = np.asarray(t_b_from_a_m, float).reshape(3)
        K = np.asarray(K, float).reshape(3, 3)
        n, d = plane_normal_distance(plane)
        C_b = -R.T @ t
        h_b = d - float(n @ C_b)
        if h_b <= 0:
            raise RoadsurfError(f"camera b is {h_b:.3f} m from the road plane (not above it)")
        if float(np.linalg.norm(t)) < 1e-9:
            raise RoadsurfError("the pair has no baseline: no parallax, no dense height")
        Hm = K @ (R + np.outer(t, n) / d) @ np.linalg.inv(K)
        return cls(K, n, d, h_b, C_b, Hm / Hm[2, 2], K @ C_b)

    def scaled(self, s: float) -> PlaneParallax:
        """The same model on a pixel grid resized by ``s`` (pixel centres kept: u' = s (u +
        0.5) - 0.5)."""
        S = np.array([[s, 0.0, 0.5 * s - 0.5], [0.0, s, 0.5 * s - 0.5], [0.0, 0.0, 1.0]])
        K = S @ self.K
        Hm = S @ self.H @ np.linalg.inv(S)
        return PlaneParallax(K, self.n, self.h_a, self.h_b, self.C_b, Hm / Hm[2, 2], K @ self.C_b)

    def cropped(self, c0: int, r0: int) -> PlaneParallax:
        """The same model on the sub-grid whose pixel (0, 0) is this grid's (c0, r0) (a crop:
        u' = u - c0, v' = v - r0)."""
        T = np.array([[1.0, 0.0, -c0], [0.0, 1.0, -r0], [0.0, 0.0, 1.0]])
        K = T @ self.K
        Hm = T @ self.H @ np.linalg.inv(T)
        return PlaneParallax(K, self.n, self.h_a, self.h_b, self.C_b, Hm / Hm[2, 2], K @ self.C_b)

    # ------------------------------------------------------------------ per pixel
    def direction(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit epipolar direction (ŵx, ŵy) of positive height and |w| at pixels u, v (any
        shape, ideal px)."""
        E = self.E
        wx = E[2] * u - E[0]
        wy = E[2] * v - E[1]
        nw = np.hypot(wx, wy)
        with np.errstate(invalid="ignore", divide="ignore"):
            return wx / nw, wy / nw, nw

    def n_dot_ray(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """n·r with r = K⁻¹ (u, v, 1): the ray's rate of approach to the plane."""
        Ki = np.linalg.inv(self.K)
        m = self.n @ Ki  # n·K⁻¹ (u, v, 1)
        return m[0] * u + m[1] * v + m[2]

    def shift_from_height(
        self, eta_m: np.ndarray, u: np.ndarray, v: np.ndarray, nw: np.ndarray | None = None
    ) -> np.ndarray:
        """Parallax s (px, along ŵ) of a point at height η (m) above the plane seen at u, v."""
        if nw is None:
            nw = self.direction(u, v)[2]
        nr = self.n_dot_ray(u, v)
        eta = np.asarray(eta_m, float)
        with np.errstate(invalid="ignore", divide="ignore"):
            k = eta * nr / (self.h_b * (self.h_a - eta))
            return k * nw / (1.0 - k * self.E[2])

    def height_from_shift(
        self, s_px: np.ndarray, u: np.ndarray, v: np.ndarray, nw: np.ndarray | None = None
    ) -> np.ndarray:
        """Height η (m) above the plane of a pixel u, v whose parallax along ŵ is s (px)."""
        if nw is None:
            nw = self.direction(u, v)[2]
        nr = self.n_dot_ray(u, v)
        s = np.asarray(s_px, float)
        with np.errstate(invalid="ignore", divide="ignore"):
            k = s / (nw + s * self.E[2])
            return k * self.h_a * self.h_b / (nr + k * self.h_b)

    def dheight_dshift(
        self, s_px: np.ndarray, u: np.ndarray, v: np.ndarray, nw: np.ndarray | None = None
    ) -> np.ndarray:
        """dη/ds (m/px) at parallax s: propagates the parallax's variance to the height."""
        if nw is None:
            nw = self.direction(u, v)[2]
        nr = self.n_dot_ray(u, v)
        s = np.asarray(s_px, float)
        with np.errstate(invalid="ignore", divide="ignore"):
            den = nw + s * self.E[2]
            k = s / den
            dk = nw / (den * den)
            q = nr + k * self.h_b
            return dk * self.h_a * self.h_b * nr / (q * q)

    def points_cam_a(self, eta_m: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(..., 3) camera-a points of pixels u, v at heights η above the plane (m)."""
        Ki = np.linalg.inv(self.K)
        r = np.stack([u, v, np.ones_like(u)], axis=-1) @ Ki.T
        with np.errstate(invalid="ignore", divide="ignore"):
            Z = (self.h_a - np.asarray(eta_m, float)) / self.n_dot_ray(u, v)
        return r * Z[..., None]
