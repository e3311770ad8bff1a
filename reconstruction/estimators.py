"""Two-view estimators on matched, undistorted pixels: the dissertation's method ("proposed"),
its rotation-aware refinement, and the baselines (classic, colmap, stereo).

Every estimator returns a PairResult; failures are statuses with a reason, never exceptions.
All of them share the final steps: epipolar inlier test, triangulation (eq. 3.11-3.12), plane fit
(eq. 3.31), metric scale α = h / d_c (eq. 3.34), signed plane distances and covariances.
"""

from __future__ import annotations

import logging
import time

import cv2
import numpy as np
from scipy.optimize import least_squares

from roadsurf.core.geometry import check_shape
from roadsurf.reconstruction import geometry as g
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)


class PairFailure(Exception):
    """Internal: a pair cannot be reconstructed (turned into a status, never leaves this module)."""

    def __init__(self, status: str, reason: str) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason


# ----------------------------------------------------------------------------- rejection


def motion_prior_mask(
    px_a: np.ndarray, px_b: np.ndarray, cfg: ReconstructionConfig, *, affine: bool = False
) -> np.ndarray:
    """Motion-prior mismatch rejection (eq. 4.2-4.7): keep d inside d̄ ± λ·σ_d per axis.

    d̄ and σ_d are the median and 1.4826·MAD of the displacements, so mismatches cannot inflate
    the window; the half-width has a floor so genuine parallax (potholes, rotation) survives.

    affine=True (the rotation-aware estimator) centres the window on an affine displacement
    field d̄(x) = A·[x, 1] instead of a constant d̄. A constant d̄ is the R ≈ I assumption
    again: under vibration the plane's displacement field is a homography, whose spread over
    the image (e.g. ±45 px across 1024 px for θz = 5°) pushes genuine matches at the image
    edges out of the window. The affine field is its first-order model; it is fitted by
    least squares on the constant window's inliers (mismatches are already bounded there),
    then on its own inliers, and the window keeps the same λ·MAD half-width and floor.
    """
    d = px_b - px_a
    med = np.median(d, axis=0)
    floor = max(cfg.prior_min_halfwidth_px, cfg.prior_min_halfwidth_frac * float(np.hypot(*med)))

    def window(r: np.ndarray) -> np.ndarray:
        c = np.median(r, axis=0)
        mad = 1.4826 * np.median(np.abs(r - c), axis=0)
        return np.all(np.abs(r - c) <= np.maximum(cfg.lambda_prior * mad, floor), axis=1)

    keep = window(d)
    if not affine:
        return keep
    # Centred, scaled coordinates keep the 3-column least squares well conditioned.
    s = float(np.std(px_a)) + 1e-12
    A = np.column_stack([(px_a - px_a.mean(axis=0)) / s, np.ones(len(px_a))])
    for _ in range(2):
        if keep.sum() < 10:  # too few to fit 6 parameters robustly: the constant window stays
            break
        coef = np.linalg.lstsq(A[keep], d[keep], rcond=None)[0]
        keep = window(d - A @ coef)
    return keep


# ----------------------------------------------------------------------------- homography


def estimate_homography(
    px_a: np.ndarray, px_b: np.ndarray, cfg: ReconstructionConfig
) -> tuple[np.ndarray, np.ndarray, float]:
    """Road-plane homography by RANSAC -> (H (3, 3), inlier mask, outlier ratio)."""
    cv2.setRNGSeed(0)  # deterministic RANSAC
    disp = float(np.hypot(*np.median(px_b - px_a, axis=0)))
    thr = max(cfg.h_ransac_px, cfg.h_ransac_frac * disp)
    H, mask = cv2.findHomography(
        px_a.astype(np.float64),
        px_b.astype(np.float64),
        cv2.RANSAC,
        thr,
        maxIters=cfg.h_ransac_iters,
        confidence=0.999,
    )
    if H is None or mask is None:
        raise PairFailure("geometry_failed", "homography RANSAC found no model")
    inl = mask.ravel().astype(bool)
    # Re-fit on the inliers by least squares (RANSAC's model comes from a minimal sample).
    if inl.sum() >= 8:
        H2, _ = cv2.findHomography(px_a[inl].astype(np.float64), px_b[inl].astype(np.float64), 0)
        if H2 is not None:
            H = H2
    return H / H[2, 2], inl, 1.0 - float(inl.mean())


# ----------------------------------------------------------------------------- pose estimators


def _t_from_rotation(
    xa: np.ndarray, xb: np.ndarray, R: np.ndarray, t_ref: np.ndarray
) -> np.ndarray:
    """Unit t minimising Σ (t · (R x_a × x_b))², the epipolar constraint with R fixed."""
    ha = np.column_stack([xa, np.ones(len(xa))]) @ R.T
    hb = np.column_stack([xb, np.ones(len(xb))])
    A = np.cross(ha, hb)
    t = np.linalg.svd(A, full_matrices=False)[2][-1]
    return t if float(t @ t_ref) >= 0 else -t


def pose_proposed(
    px_a: np.ndarray, px_b: np.ndarray, H: np.ndarray, K: np.ndarray, cfg: ReconstructionConfig
) -> tuple[np.ndarray, np.ndarray, int]:
    """Dissertation method (eq. 3.18-3.26, Fig. 3.4): F = [x̄_b − x̄_a]x H, E = KᵀFK, SVD -> R, t.

    The epipole starts as the mean displacement (R ≈ I, t_z ≈ 0); each iteration rebuilds F from
    the current R and t (t re-solved from the epipolar constraint with R fixed) until t settles.
    Returns (R, unit t, iterations used).
    """
    xa, xb = g.normalised_from_px(px_a, K), g.normalised_from_px(px_b, K)
    e_px = np.append(px_b.mean(axis=0) - px_a.mean(axis=0), 0.0)  # homogeneous difference
    F = g.skew(e_px) @ H
    E = K.T @ F @ K
    R, t, n_front = g.decompose_essential(E, xa, xb)
    if n_front <= 0:
        raise PairFailure("geometry_failed", "no cheirality-valid pose from E = K^T F K")
    n_it = 0
    for it in range(1, cfg.f_iterations + 1):  # f_iterations = 0: the single pass (R ≈ I)
        n_it = it
        t_new = _t_from_rotation(xa, xb, R, t)
        converged = np.linalg.norm(t_new - t) < cfg.f_tol
        F = g.skew(K @ t_new) @ H  # F = [e']x H with the epipole e' = K t
        R, t, n_front = g.decompose_essential(K.T @ F @ K, xa, xb)
        if n_front <= 0:
            raise PairFailure("geometry_failed", "no cheirality-valid pose in the F rebuild loop")
        if converged:
            break
    return R, t / np.linalg.norm(t), n_it


def refine_homography_sampson(
    px_a: np.ndarray, px_b: np.ndarray, H0: np.ndarray, K: np.ndarray, max_nfev: int
) -> np.ndarray:
    """Maximum-likelihood homography for noise in both images: minimise the Sampson error of
    x_b × H x_a = 0 (Hartley & Zisserman §4.2.6) over the 8 entries (h33 = 1), in normalised
    coordinates. OpenCV's refinement only weighs the transfer error in image b."""
    Ki = np.linalg.inv(K)
    xa, xb = g.normalised_from_px(px_a, K), g.normalised_from_px(px_b, K)
    Hn0 = Ki @ H0 @ K
    Hn0 = Hn0 / Hn0[2, 2]
    u, v = xa[:, 0], xa[:, 1]
    up, vp = xb[:, 0], xb[:, 1]

    def resid(h: np.ndarray) -> np.ndarray:
        Hm = np.append(h, 1.0).reshape(3, 3)
        a = Hm[0, 0] * u + Hm[0, 1] * v + Hm[0, 2]
        b = Hm[1, 0] * u + Hm[1, 1] * v + Hm[1, 2]
        c = Hm[2, 0] * u + Hm[2, 1] * v + Hm[2, 2]
        e1 = vp * c - b
        e2 = a - up * c
        # J = d(e1, e2)/d(u, v, u', v'); S = J Jᵀ (2x2)
        j1 = np.stack([vp * Hm[2, 0] - Hm[1, 0], vp * Hm[2, 1] - Hm[1, 1], 0 * u, c], 1)
        j2 = np.stack([Hm[0, 0] - up * Hm[2, 0], Hm[0, 1] - up * Hm[2, 1], -c, 0 * u], 1)
        s11 = np.sum(j1 * j1, 1)
        s12 = np.sum(j1 * j2, 1)
        s22 = np.sum(j2 * j2, 1)
        # Whitening by the Cholesky factor of S: r = L^-1 e, |r|² = eᵀ S^-1 e.
        l11 = np.sqrt(s11)
        l21 = s12 / l11
        l22 = np.sqrt(np.maximum(s22 - l21**2, 1e-300))
        r1 = e1 / l11
        r2 = (e2 - l21 * r1) / l22
        return np.concatenate([r1, r2])

    sol = least_squares(resid, Hn0.ravel()[:8], method="lm", max_nfev=max_nfev * 9)
    Hn = np.append(sol.x, 1.0).reshape(3, 3)
    H = K @ Hn @ Ki
    return H / H[2, 2]


def pose_from_homography(
    px_a: np.ndarray, px_b: np.ndarray, H: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Homography decomposition with the plane-normal prior (road normal ≈ optical axis)."""
    R, t, _ = pose_plane_from_homography(px_a, H, K)
    return R, t


def pose_plane_from_homography(
    px_a: np.ndarray, H: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, unit t, m) with K⁻¹HK ∝ R + t mᵀ (m = plane normal / distance, in units of |t|),
    choosing the decomposition whose plane faces camera a along +z (the road prior)."""
    n_sol, Rs, ts, ns = cv2.decomposeHomographyMat(H, K)
    xa = g.normalised_from_px(px_a, K)
    best, best_score = None, -np.inf
    for R, t, n in zip(Rs, ts, ns, strict=True):
        n = n.ravel()
        t = t.ravel()
        if n[2] < 0:  # same plane, flipped sign convention
            n, t = -n, -t
        # Plane in front of camera a: n·x̂ > 0 for the observed points.
        front = np.mean(np.column_stack([xa, np.ones(len(xa))]) @ n > 0)
        score = front + n[2]  # prior: normal along +z (camera looks down at the road)
        if score > best_score and np.linalg.norm(t) > 1e-9:
            best, best_score = (R, t, n), score
    if best is None:
        raise PairFailure("geometry_failed", "homography decomposition gave no valid solution")
    R, t, n = best
    s = float(np.linalg.norm(t))  # cv2 returns t / d, so R + (t/d) nᵀ = R + t̂ (s n)ᵀ
    return R, t / s, s * n


def refine_pose_plane_parallax(
    px_a: np.ndarray,
    px_b: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    m0: np.ndarray,
    K: np.ndarray,
    max_iter: int = 10,
    outer: int = 2,
    kappa_z: float = 2.0,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Plane-plus-parallax maximum likelihood of the pose, with the road relief as a random
    effect. Returns (R, unit t, κ).

    A match is x_b = π(H x_a) + γ_i û_i + noise, with H = K (R + t mᵀ) K⁻¹ the road-plane
    homography and û_i the direction from π(H x_a) to the epipole K t: the parallax γ_i of a
    point off the plane runs along its epipolar line. Modelling γ_i ~ N(0, κσ² ĝ_i²) (ĝ_i: the
    distance to the epipole, normalised) and the pixel noise as N(0, σ²) in both images, each
    transfer residual has covariance σ² (I + J Jᵀ + κ ĝ² ûûᵀ), J = ∂π(Hx)/∂x. Minimising the
    whitened residuals over R, t, m (8 parameters) is then the generalised least squares of
    the pose. κ = 0 is the gold-standard homography (the plane prior used fully, the most
    precise pose on a flat road): the seed, which is that pose, is returned unchanged.
    κ → ∞ drops the along-line component and leaves the epipolar (Sampson-type) fit of a
    general scene. κ is estimated from the data by the method of moments (along-line against
    across-line residual power), less ``kappa_z`` standard errors so that a flat road's
    sampling scatter does not give away the plane, and re-estimated ``outer`` times. No
    threshold switches between the two models: the relief decides. Levenberg–Marquardt with
    an analytic Jacobian (covariance held at the linearisation point), ``max_iter`` steps
    per κ (the two t columns by forward differences); ~5-15 ms for 2000 matches.
    """
    xa = np.column_stack([g.normalised_from_px(px_a, K), np.ones(len(px_a))])
    xb = g.normalised_from_px(px_b, K)
    R, t, m = R0.copy(), t0 / np.linalg.norm(t0), np.asarray(m0, float).copy()

    def state(R: np.ndarray, t: np.ndarray, m: np.ndarray, kappa: float) -> dict:
        """Residual, its whitening (closed-form 2x2 Cholesky) and the pieces of the noise model."""
        Hn = R + np.outer(t, m)
        q = xa @ Hn.T
        w = q[:, 2]
        xp = q[:, :2] / w[:, None]
        r = xb - xp
        # J = ∂π(Hx)/∂(u, v) at x_a, C = I + J Jᵀ (noise of x_a carried into image b)
        j00 = (Hn[0, 0] - xp[:, 0] * Hn[2, 0]) / w
        j01 = (Hn[0, 1] - xp[:, 0] * Hn[2, 1]) / w
        j10 = (Hn[1, 0] - xp[:, 1] * Hn[2, 0]) / w
        j11 = (Hn[1, 1] - xp[:, 1] * Hn[2, 1]) / w
        c11, c12, c22 = 1 + j00**2 + j01**2, j00 * j10 + j01 * j11, 1 + j10**2 + j11**2
        u = t[None, :2] - t[2] * xp  # towards the epipole: the parallax direction
        gl = np.linalg.norm(u, axis=1) + 1e-300
        u = u / gl[:, None]
        g2 = gl**2 / np.mean(gl**2)
        s11 = c11 + kappa * g2 * u[:, 0] ** 2
        s12 = c12 + kappa * g2 * u[:, 0] * u[:, 1]
        s22 = c22 + kappa * g2 * u[:, 1] ** 2
        l11 = np.sqrt(s11)
        l21 = s12 / l11
        l22 = np.sqrt(np.maximum(s22 - l21**2, 1e-300))
        rw1 = r[:, 0] / l11
        rw2 = (r[:, 1] - l21 * rw1) / l22
        return dict(
            q=q, w=w, xp=xp, r=r, u=u, g2=g2, C=(c11, c12, c22), L=(l11, l21, l22),
            cost=float(np.sum(rw1**2) + np.sum(rw2**2)), rw=np.concatenate([rw1, rw2]),
        )  # fmt: skip

    def estimate_kappa(st: dict) -> float:
        u, r = st["u"], st["r"]
        c11, c12, c22 = st["C"]
        par = r[:, 0] * u[:, 0] + r[:, 1] * u[:, 1]
        perp = -r[:, 0] * u[:, 1] + r[:, 1] * u[:, 0]
        c_par = c11 * u[:, 0] ** 2 + 2 * c12 * u[:, 0] * u[:, 1] + c22 * u[:, 1] ** 2
        c_perp = c11 * u[:, 1] ** 2 - 2 * c12 * u[:, 0] * u[:, 1] + c22 * u[:, 0] ** 2
        sigma2 = float(np.mean(perp**2) / np.mean(c_perp)) + 1e-300
        k_i = (par**2 / sigma2 - c_par) / np.mean(st["g2"])  # per-point moment terms
        k_se = float(np.std(k_i) / np.sqrt(len(k_i)))
        return float(np.clip(np.mean(k_i) - kappa_z * k_se, 0.0, 1e8))

    def tangent(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a = np.array([1.0, 0, 0]) if abs(t[0]) < 0.9 else np.array([0, 1.0, 0])
        b1 = np.cross(t, a)
        b1 /= np.linalg.norm(b1)
        return b1, np.cross(t, b1)

    kappa = 0.0
    for _ in range(max(1, outer)):
        kappa = estimate_kappa(state(R, t, m, 0.0))
        if kappa == 0.0:  # the homography model explains the matches (the seed's own model)
            break
        st = state(R, t, m, kappa)
        lam = 1e-3
        for _ in range(max_iter):
            # Jacobian of q = (R + t mᵀ) x over (ω, τ1, τ2, m): ω rotates R on the left,
            # τ moves t in its tangent plane, m is free.
            b1, b2 = tangent(t)
            Rx = xa @ R.T
            mx = xa @ m
            Jq = np.empty((len(xa), 3, 8))
            Jq[:, :, 0] = np.stack([0 * mx, -Rx[:, 2], Rx[:, 1]], 1)  # e_k x (R x)
            Jq[:, :, 1] = np.stack([Rx[:, 2], 0 * mx, -Rx[:, 0]], 1)
            Jq[:, :, 2] = np.stack([-Rx[:, 1], Rx[:, 0], 0 * mx], 1)
            Jq[:, :, 3] = mx[:, None] * b1
            Jq[:, :, 4] = mx[:, None] * b2
            Jq[:, :, 5:8] = t[None, :, None] * xa[:, None, :]
            w, xp = st["w"], st["xp"]
            # r = x_b − π(q): ∂r/∂p = −(Jq[:, k] − π_k Jq[:, 2]) / w
            d1 = -(Jq[:, 0] - xp[:, :1] * Jq[:, 2]) / w[:, None]
            d2 = -(Jq[:, 1] - xp[:, 1:2] * Jq[:, 2]) / w[:, None]
            l11, l21, l22 = st["L"]
            a1 = d1 / l11[:, None]
            a2 = (d2 - l21[:, None] * a1) / l22[:, None]
            A = np.concatenate([a1, a2])
            # t also turns the epipolar lines (û, the split into along/across components):
            # with large κ that is where all of t's information is, so those two columns are
            # differentiated through the whole whitened residual (forward differences).
            for k, b in ((3, b1), (4, b2)):
                t_h = t + 1e-7 * b
                A[:, k] = (state(R, t_h / np.linalg.norm(t_h), m, kappa)["rw"] - st["rw"]) / 1e-7
            JtJ, Jtr = A.T @ A, A.T @ st["rw"]
            improved = False
            # Marquardt damping on the diagonal, floored so that a parameter the data barely
            # constrain (the plane m when κ is huge) cannot make the system singular.
            dg = np.diag(JtJ) + 1e-12 * float(np.max(np.diag(JtJ)))
            while lam < 1e8:
                delta = -np.linalg.solve(JtJ + lam * np.diag(dg), Jtr)
                R_n = g.rotation_from_axis_angle(delta[:3]) @ R
                t_n = t + delta[3] * b1 + delta[4] * b2
                t_n /= np.linalg.norm(t_n)
                m_n = m + delta[5:8]
                st_n = state(R_n, t_n, m_n, kappa)
                if st_n["cost"] < st["cost"]:
                    improved = st["cost"] - st_n["cost"] > 1e-8 * st["cost"]
                    R, t, m, st, lam = R_n, t_n, m_n, st_n, max(lam / 10, 1e-9)
                    break
                lam *= 10
            if not improved:
                break
    return R, t, kappa


def refine_pose_sampson(
    px_a: np.ndarray, px_b: np.ndarray, R0: np.ndarray, t0: np.ndarray, K: np.ndarray, max_nfev: int
) -> tuple[np.ndarray, np.ndarray]:
    """Two-view bundle adjustment reduced to the pose: minimise Sampson errors (first-order
    equal to the reprojection error with optimally triangulated points) over R (axis-angle
    update) and the unit t direction (2-D tangent update)."""
    t0 = t0 / np.linalg.norm(t0)
    a = np.array([1.0, 0, 0]) if abs(t0[0]) < 0.9 else np.array([0, 1.0, 0])
    b1 = np.cross(t0, a)
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(t0, b1)

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R = g.rotation_from_axis_angle(p[:3]) @ R0
        t = t0 + p[3] * b1 + p[4] * b2
        return R, t / np.linalg.norm(t)

    def resid(p: np.ndarray) -> np.ndarray:
        R, t = unpack(p)
        return g.sampson_px(g.fundamental_from_pose(R, t, K), px_a, px_b)

    sol = least_squares(resid, np.zeros(5), method="lm", max_nfev=max_nfev * 6, x_scale=1e-3)
    return unpack(sol.x)


def parallax_ratio(
    px_a: np.ndarray, px_b: np.ndarray, H: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray
) -> float:
    """mean ||x_b − H x_a||² / (4 · mean Sampson²): about 1 when the matches are planar up to
    noise (4 = two noisy images x two axes, against one constrained direction for Sampson)."""
    hx = np.column_stack([px_a, np.ones(len(px_a))]) @ H.T
    r_h = np.sum((px_b - hx[:, :2] / hx[:, 2:3]) ** 2, axis=1)
    s = g.sampson_px(g.fundamental_from_pose(R, t, K), px_a, px_b) ** 2
    return float(np.mean(r_h) / (4.0 * np.mean(s) + 1e-300))


def pose_classic(
    px_a: np.ndarray, px_b: np.ndarray, K: np.ndarray, cfg: ReconstructionConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Traditional SfM: F from all matches (RANSAC + 8-point), E = KᵀFK, SVD -> R, t."""
    cv2.setRNGSeed(0)
    F, mask = cv2.findFundamentalMat(
        px_a.astype(np.float64), px_b.astype(np.float64), cv2.FM_RANSAC, cfg.f_ransac_px, 0.999
    )
    if F is None or F.shape != (3, 3):
        raise PairFailure("geometry_failed", "8-point RANSAC found no fundamental matrix")
    inl = mask.ravel().astype(bool)
    E = K.T @ F @ K
    xa, xb = g.normalised_from_px(px_a[inl], K), g.normalised_from_px(px_b[inl], K)
    R, t, n_front = g.decompose_essential(E, xa, xb)
    if n_front <= 0:
        raise PairFailure("geometry_failed", "no cheirality-valid pose from the 8-point F")
    return R, t, F


def pose_colmap(
    px_a: np.ndarray,
    px_b: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    cfg: ReconstructionConfig,
) -> tuple[np.ndarray, np.ndarray, str, np.ndarray]:
    """pycolmap.estimate_calibrated_two_view_geometry with its relative pose.

    Returns (R, unit t, configuration name e.g. PLANAR / CALIBRATED, inlier mask).
    """
    import pycolmap

    cam = pycolmap.Camera(
        model="PINHOLE",
        width=int(width),
        height=int(height),
        params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
    )
    opts = pycolmap.TwoViewGeometryOptions()
    opts.compute_relative_pose = True
    opts.ransac.random_seed = 0
    opts.ransac.max_error = float(cfg.colmap_max_error_px)
    n = px_a.shape[0]
    matches = np.stack([np.arange(n), np.arange(n)], axis=1).astype(np.uint32)
    geo = pycolmap.estimate_calibrated_two_view_geometry(
        cam, px_a.astype(np.float64), cam, px_b.astype(np.float64), matches, opts
    )
    name = pycolmap.TwoViewGeometryConfiguration(geo.config).name
    if geo.cam2_from_cam1 is None:
        raise PairFailure("geometry_failed", f"pycolmap returned no relative pose (config {name})")
    R = np.asarray(geo.cam2_from_cam1.rotation.matrix())
    t = np.asarray(geo.cam2_from_cam1.translation, dtype=float)
    if np.linalg.norm(t) < 1e-12:
        raise PairFailure("geometry_failed", f"pycolmap pose has zero translation (config {name})")
    inl = np.zeros(n, dtype=bool)
    im = np.asarray(geo.inlier_matches)
    if im.size:
        inl[im[:, 0].astype(int)] = True
    return R, t / np.linalg.norm(t), name, inl


# ----------------------------------------------------------------------------- main entry


def estimate_matches(
    px_a: np.ndarray,
    px_b: np.ndarray,
    K: np.ndarray,
    height_m: float,
    cfg: ReconstructionConfig,
    *,
    image_size: tuple[int, int] = (1024, 768),
) -> PairResult:
    """Reconstruct one pair from matched undistorted pixels (N, 2) in a and b.

    height_m is h (camera height above the road, m); image_size = (width, height) px.
    Never raises for bad data: the returned PairResult carries status and reason.
    """
    px_a = check_shape("px_a", np.asarray(px_a, dtype=float), (None, 2))
    px_b = check_shape("px_b", np.asarray(px_b, dtype=float), (px_a.shape[0], 2))
    res = PairResult(frame_a="", frame_b="", index_a=-1, index_b=-1, method=cfg.method, status="ok")
    res.n_matches = int(px_a.shape[0])
    try:
        _estimate(px_a, px_b, K, height_m, cfg, image_size, res)
    except PairFailure as e:
        res.status, res.reason = e.status, e.reason
    except (np.linalg.LinAlgError, cv2.error, ValueError) as e:
        res.status, res.reason = "geometry_failed", f"{type(e).__name__}: {e}"
    return res


def _estimate(
    px_a: np.ndarray,
    px_b: np.ndarray,
    K: np.ndarray,
    height_m: float,
    cfg: ReconstructionConfig,
    image_size: tuple[int, int],
    res: PairResult,
) -> None:
    t0 = time.perf_counter()
    n = px_a.shape[0]
    idx = np.arange(n)
    if n < cfg.min_matches:
        raise PairFailure("too_few_matches", f"{n} matches < min_matches={cfg.min_matches}")
    method = cfg.method
    keep = np.ones(n, dtype=bool)
    if cfg.motion_prior and method in ("proposed", "rotation_aware"):
        keep = motion_prior_mask(px_a, px_b, cfg, affine=method == "rotation_aware")
    res.rejected_px_a, res.rejected_px_b = px_a[~keep], px_b[~keep]
    res.n_prior_inliers = int(keep.sum())
    t1 = time.perf_counter()
    res.timings_s["rejection"] = t1 - t0
    if keep.sum() < cfg.min_matches:
        raise PairFailure(
            "too_few_matches",
            f"{int(keep.sum())} matches left after motion-prior rejection (λ={cfg.lambda_prior})",
        )
    pa, pb, idx = px_a[keep], px_b[keep], idx[keep]
    disp = float(np.median(np.linalg.norm(pb - pa, axis=1)))
    if method != "stereo" and disp < cfg.min_displacement_px:
        raise PairFailure(
            "geometry_failed",
            f"median displacement {disp:.2f} px < {cfg.min_displacement_px} px: the camera did "
            "not move between the frames (vehicle stopped?), depth is unobservable",
        )

    if method == "stereo":
        # Rectified rig: pose is the calibration (R = I, t = (B, 0, 0)); any vibration of camera 2
        # goes uncorrected, which is what the study measures.
        R, t = np.eye(3), np.array([cfg.stereo_baseline_m, 0.0, 0.0])
        cand = np.ones(len(pa), dtype=bool)
    else:
        if method in ("proposed", "rotation_aware"):
            H, h_inl, out_ratio = estimate_homography(pa, pb, cfg)
            res.H, res.outlier_ratio_h = H, out_ratio
            if out_ratio >= cfg.near_planar_max_outlier:
                raise PairFailure(
                    "not_near_planar",
                    f"homography outlier ratio {out_ratio:.2f} >= {cfg.near_planar_max_outlier}",
                )
            if h_inl.sum() < cfg.min_matches:
                raise PairFailure("too_few_matches", f"{int(h_inl.sum())} homography inliers")
            if method == "proposed":
                R, t, _ = pose_proposed(pa[h_inl], pb[h_inl], H, K, cfg)
            else:
                H = refine_homography_sampson(pa[h_inl], pb[h_inl], H, K, cfg.ba_iterations)
                res.H = H
                R, t, m = pose_plane_from_homography(pa[h_inl], H, K)
                # Refine on every match consistent with the seed pose (plane + parallax points).
                s = np.abs(g.sampson_px(g.fundamental_from_pose(R, t, K), pa, pb))
                sel = s < max(cfg.epi_inlier_px, cfg.h_ransac_px)
                if sel.sum() >= 8 and cfg.pose_model == "plane_parallax":
                    R, t, kappa = refine_pose_plane_parallax(pa[sel], pb[sel], R, t, m, K)
                    res.config_name = f"kappa={kappa:.3g}"
                elif sel.sum() >= 8:
                    R2, t2 = refine_pose_sampson(pa[sel], pb[sel], R, t, K, cfg.ba_iterations)
                    ratio = parallax_ratio(pa[sel], pb[sel], H, R2, t2, K)
                    res.config_name = f"parallax_ratio={ratio:.2f}"
                    # Model selection: when the plane explains the matches to the noise level,
                    # the homography pose uses the planarity and is the more precise one.
                    if ratio >= cfg.planar_parallax_ratio:
                        R, t = R2, t2
        elif method == "classic":
            R, t, _ = pose_classic(pa, pb, K, cfg)
        elif method == "colmap":
            R, t, name, _ = pose_colmap(pa, pb, K, image_size[0], image_size[1], cfg)
            res.config_name = name
        else:
            raise PairFailure("geometry_failed", f"unknown method {method!r}")
        F = g.fundamental_from_pose(R, t, K)
        res.F = F
        cand = np.abs(g.sampson_px(F, pa, pb)) < cfg.epi_inlier_px
    t2 = time.perf_counter()
    res.timings_s["geometry"] = t2 - t1

    pa, pb, idx = pa[cand], pb[cand], idx[cand]
    xa, xb = g.normalised_from_px(pa, K), g.normalised_from_px(pb, K)
    X = g.triangulate(xa, xb, R, t)
    Xb = X @ R.T + t
    ok = (X[:, 2] > 0) & (Xb[:, 2] > 0)
    err = np.maximum(
        np.linalg.norm(g.px_from_cam(X, K) - pa, axis=1),
        np.linalg.norm(g.px_from_cam(Xb, K) - pb, axis=1),
    )
    if method != "stereo":  # the rig's calibrated pose is trusted as is (that is the baseline)
        ok &= err < cfg.max_reproj_px
    if ok.sum() < cfg.min_matches:
        raise PairFailure(
            "geometry_failed", f"only {int(ok.sum())} points triangulate in front of both cameras"
        )
    X, pa, pb, idx = X[ok], pa[ok], pb[ok], idx[ok]
    p, _ = g.fit_plane(X, cfg.plane_trim_k)
    d_c = g.camera_plane_distance(p)
    if not np.isfinite(d_c) or d_c <= 0:
        raise PairFailure("scale_failed", f"camera-to-plane distance d_c={d_c} is not positive")
    alpha = 1.0 if method == "stereo" else height_m / d_c
    Xm = alpha * X
    res.points_cam_a_m = Xm
    res.px_a, res.px_b, res.match_idx = pa, pb, idx.astype(np.int64)
    res.plane = np.array([p[0], p[1], alpha * p[2]])
    res.plane_dist_m = g.plane_distance(Xm, res.plane)
    sigma = cfg.pixel_sigma_px
    if cfg.estimate_sigma and method != "stereo" and len(pa) >= 8:
        s = g.sampson_px(g.fundamental_from_pose(R, t, K), pa, pb)
        sigma = float(1.4826 * np.median(np.abs(s))) or sigma
    res.cov_m2 = alpha**2 * g.point_covariance(X, R, t, K, sigma)
    res.R_b_from_a, res.t_b_from_a_m = R, alpha * t
    if method != "stereo" and res.F is not None:
        res.F = g.fundamental_from_pose(R, t, K)
    res.scale_alpha = float(alpha)
    res.n_inliers = int(len(idx))
    res.timings_s["triangulation"] = time.perf_counter() - t2
