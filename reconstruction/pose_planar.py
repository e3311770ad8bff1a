"""Pose from the road-plane homography: the dissertation's method ("proposed") and the seed of
its rotation-aware refinement.

The homography is found by RANSAC (``estimate_homography``); "proposed" builds F = [e]x H and
decomposes E = KᵀFK (eq. 3.18-3.26); "rotation_aware" refines H for noise in both images and
decomposes it with the road-normal prior, then refines the pose on every consistent match
(``roadsurf.reconstruction.pose_parallax``). Failures raise ``PairFailure``.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.optimize import least_squares

from roadsurf.core.camera import normalised_from_px
from roadsurf.core.geometry import check_shape, skew
from roadsurf.reconstruction import geometry as g
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.types import PairFailure


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
    px_a: np.ndarray,
    px_b: np.ndarray,
    H: np.ndarray,
    K: np.ndarray,
    cfg: ReconstructionConfig,
    *,
    road_normal_cam: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Dissertation method (eq. 3.18-3.26, Fig. 3.4): F = [x̄_b − x̄_a]x H, E = KᵀFK, SVD -> R, t.

    The epipole starts as the mean displacement (R ≈ I, t_z ≈ 0); each iteration rebuilds F from
    the current R and t (t re-solved from the epipolar constraint with R fixed) until t settles.
    Both plane decompositions of H satisfy F = [e']x H, so the loop settles on the one nearest
    its seed: for a tilted camera (finite epipole, t_z ≠ 0) that can be the wrong one. When the
    result is nearer the other decomposition than the one the road priors choose
    (``plane_solutions``; ``road_normal_cam`` as there), the loop is run again from
    the chosen one's epipole K t. A nadir camera keeps the dissertation's seed and result.
    Returns (R, unit t, iterations used).
    """
    xa, xb = normalised_from_px(px_a, K), normalised_from_px(px_b, K)
    e_px = np.append(px_b.mean(axis=0) - px_a.mean(axis=0), 0.0)  # homogeneous difference
    R, t, n_it = _f_loop(xa, xb, skew(e_px) @ H, H, K, cfg)
    sols = plane_solutions(px_a, H, K, road_normal_cam)
    if len(sols) > 1:
        dist = [_rotation_angle(R.T @ Rs) for Rs, _, _, _ in sols]
        if int(np.argmin(dist)) != 0:
            R, t, n_it2 = _f_loop(xa, xb, skew(K @ sols[0][1]) @ H, H, K, cfg)
            n_it += n_it2
    return R, t, n_it


def _rotation_angle(R: np.ndarray) -> float:
    """Angle (rad) of a rotation matrix."""
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def _f_loop(
    xa: np.ndarray,
    xb: np.ndarray,
    F: np.ndarray,
    H: np.ndarray,
    K: np.ndarray,
    cfg: ReconstructionConfig,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The F = [e']x H rebuild loop (Fig. 3.4) from a first F -> (R, unit t, iterations)."""
    R, t, n_front = g.decompose_essential(K.T @ F @ K, xa, xb)
    if n_front <= 0:
        raise PairFailure("geometry_failed", "no cheirality-valid pose from E = K^T F K")
    n_it = 0
    for it in range(1, cfg.f_iterations + 1):  # f_iterations = 0: the single pass (R ≈ I)
        n_it = it
        t_new = _t_from_rotation(xa, xb, R, t)
        converged = np.linalg.norm(t_new - t) < cfg.f_tol
        F = skew(K @ t_new) @ H  # F = [e']x H with the epipole e' = K t
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
    xa, xb = normalised_from_px(px_a, K), normalised_from_px(px_b, K)
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


def pose_plane_from_homography(
    px_a: np.ndarray, H: np.ndarray, K: np.ndarray, *, road_normal_cam: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, unit t, m) with K⁻¹HK ∝ R + t mᵀ (m = plane normal / distance, in units of |t|): the
    decomposition of H that the road priors prefer (``plane_solutions``)."""
    sols = plane_solutions(px_a, H, K, road_normal_cam)
    if not sols:
        raise PairFailure(
            "geometry_failed",
            "homography decomposition gave no valid solution: H is a pure rotation (the camera "
            "turned but did not move), depth is unobservable",
        )
    R, t, m, _ = sols[0]
    return R, t, m


def plane_solutions(
    px_a: np.ndarray, H: np.ndarray, K: np.ndarray, road_normal_cam: np.ndarray | None = None
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, float]]:
    """The physically distinct decompositions of H as (R, unit t, m, score), best score first.

    H alone has two: the road (normal n, motion t) and a mirror solution whose plane is nearly
    perpendicular to the road (its normal close to the true motion) and whose motion runs
    nearly along the road's normal. The score adds up priors on n̂ (unit normal, towards the
    plane) and t̂:
    - the plane is in front of camera a: the share of the points with n̂·x̂ > 0 (each
      solution's sign is chosen so that most are);
    - the road's normal: with a known mount n̂·``road_normal_cam`` ((3,), "down" in camera
      coordinates, -``core.geometry.up_in_cam``), ≈ 1 against ≈ 0 for the mirror. Without it,
      n̂·(ĝ, 1) with ĝ the image direction in which the road moves (unit 2-vector): the camera
      looks down (n̂_z, the nadir prior) or ahead (pitched forward by φ on a vehicle driving
      forward, it sees the road's normal lean along the flow, n̂_xy·ĝ = sin φ; the mirror
      leans against it). n̂_z alone cannot tell them apart from ~45° of pitch on (both ~45° off
      the optical axis). Reversing with a steep unknown mount would fool this term;
    - the vehicle moves parallel to the road: −|n̂·t̂|, ≈ 0 for the road and ≈ |t|/d (baseline
      over camera-to-plane distance) for the mirror.
    """
    xh = np.column_stack([normalised_from_px(px_a, K), np.ones(len(px_a))])
    if road_normal_cam is None:
        with np.errstate(divide="ignore", invalid="ignore"):
            flow = _transfer(px_a, H) - px_a
        flow = flow[np.all(np.isfinite(flow), axis=1)]
        g_img = np.median(flow, axis=0) if len(flow) else np.zeros(2)
        g_img = g_img / max(float(np.linalg.norm(g_img)), 1e-12)
        n_exp = np.array([g_img[0], g_img[1], 1.0])
    else:
        n_exp = check_shape("road_normal_cam", np.asarray(road_normal_cam, float), (3,))
        n_exp = n_exp / np.linalg.norm(n_exp)
    _, Rs, ts, ns = cv2.decomposeHomographyMat(H, K)
    out: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]] = []
    for R, t, n in zip(Rs, ts, ns, strict=True):
        n, t = n.ravel(), t.ravel()
        s = float(np.linalg.norm(t))  # cv2 returns t / d, so R + (t/d) nᵀ = R + t̂ (s n)ᵀ
        if s <= 1e-9:
            continue
        front = float(np.mean(xh @ n > 0))
        if front < 0.5:  # same plane, opposite sign convention
            n, t, front = -n, -t, 1.0 - front
        if any(np.allclose(R, o[0]) and np.allclose(t / s, o[1]) for o in out):
            continue  # the sign-flipped twin of a solution already kept
        score = front + float(n @ n_exp) - abs(float(n @ t)) / s
        out.append((R, t / s, s * n, score))
    out.sort(key=lambda o: -o[3])
    return out


def _transfer(px: np.ndarray, H: np.ndarray) -> np.ndarray:
    """(N, 2) pixels mapped by the homography H."""
    q = np.column_stack([px, np.ones(len(px))]) @ H.T
    return q[:, :2] / q[:, 2:3]
