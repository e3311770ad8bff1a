"""Motion-prior mismatch rejection (dissertation eq. 4.2-4.7) for the planar estimators."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.reconstruction.config import PriorModel, ReconstructionConfig
from roadsurf.reconstruction.pose_planar import plane_solutions

MIN_H_MATCHES = 12  # fewer matches: no homography window, the affine one is used instead


def motion_prior_mask(
    px_a: np.ndarray,
    px_b: np.ndarray,
    cfg: ReconstructionConfig,
    *,
    affine: bool = False,
    model: PriorModel | None = None,
    K: np.ndarray | None = None,
    road_normal_cam: np.ndarray | None = None,
) -> np.ndarray:
    """Motion-prior mismatch rejection (eq. 4.2-4.7): keep d inside d̄ ± λ·σ_d per axis.

    d̄ and σ_d are the median and 1.4826·MAD of the displacements, so mismatches cannot inflate
    the window; the half-width has a floor so genuine parallax (potholes, rotation) survives.
    ``model`` says what d̄ is (None: "affine" if ``affine`` else "mean"):

    - "mean": a constant d̄, eq. 4.7 as published (the R ≈ I, nadir assumption).
    - "affine": an affine displacement field d̄(x) = A·[x, 1]. Under vibration the plane's
      displacement field is a homography, whose spread over the image (e.g. ±45 px across
      1024 px for θz = 5°) pushes genuine matches at the image edges out of a constant window.
      The affine field is its first-order model; it is fitted by least squares on the constant
      window's inliers (mismatches are already bounded there), then on its own inliers.
    - "homography": d̄(x) = π(H x) − x with H the road-plane homography, fitted by seeded RANSAC
      at the window's floor and refitted on its window. A tilted camera moving forward sees
      the road's displacement grow several-fold from the top of the image to the bottom (a
      perspective field no affine map follows). Falls back to "affine" with fewer than
      ``MIN_H_MATCHES`` matches or no homography. With the intrinsics K the floor's share
      applies to the displacement the camera's translation causes, not to the whole one:
      relief parallax scales with the translation (∝ |t| δ / Z²), while a turn moves every
      pixel without revealing depth. A hand-held camera turned 40° between shots moved the
      road 42 px in the median but its translation 0.26 m (spd2 18-19): a 6 px window cut a
      20 mm pothole's 17-24 px parallax. The translation's displacement is |π(H x) − π(K R
      K⁻¹ x)| with R from the decomposition the road priors prefer (``road_normal_cam`` as
      in ``pose_planar.plane_solutions``); the floor only grows, so a camera that does not
      turn keeps its window.

    Every model keeps the same λ·MAD half-width and floor around its d̄.
    """
    model = model or ("affine" if affine else "mean")
    if model not in ("mean", "affine", "homography"):
        raise ValueError(f"motion prior model {model!r}: expected mean, affine or homography")
    d = px_b - px_a
    med = np.median(d, axis=0)
    floor = max(cfg.prior_min_halfwidth_px, cfg.prior_min_halfwidth_frac * float(np.hypot(*med)))

    def window(r: np.ndarray, fl: float = floor) -> np.ndarray:
        c = np.median(r, axis=0)
        mad = MAD_TO_SIGMA * np.median(np.abs(r - c), axis=0)
        return np.all(np.abs(r - c) <= np.maximum(cfg.lambda_prior * mad, fl), axis=1)

    keep = window(d)
    if model == "mean":
        return keep
    if model == "homography":
        fit = _homography_window(px_a, px_b, floor, window, cfg.h_ransac_iters)
        if fit is not None and K is not None:
            keep_h, H, pred = fit
            f_t = cfg.prior_min_halfwidth_frac * _translation_flow_px(
                px_a[keep_h], H, K, road_normal_cam
            )
            if f_t > floor:  # the same plane, a window as wide as the translation allows
                return window(px_b - pred, f_t)
        if fit is not None:
            return fit[0]
    # Centred, scaled coordinates keep the 3-column least squares well conditioned.
    s = float(np.std(px_a)) + 1e-12
    A = np.column_stack([(px_a - px_a.mean(axis=0)) / s, np.ones(len(px_a))])
    for _ in range(2):
        if keep.sum() < 10:  # too few to fit 6 parameters robustly: the constant window stays
            break
        coef = np.linalg.lstsq(A[keep], d[keep], rcond=None)[0]
        keep = window(d - A @ coef)
    return keep


def _translation_flow_px(
    px_a: np.ndarray, H: np.ndarray, K: np.ndarray, road_normal_cam: np.ndarray | None
) -> float:
    """Median displacement (px) that the camera's translation causes on the road plane:
    |π(H x) − π(K R K⁻¹ x)| over the pixels px_a (N, 2) of image a, H (3, 3) the road
    homography and R its preferred decomposition's rotation. 0 when there is none."""
    a = px_a.astype(np.float64)
    sols = plane_solutions(a, H, K, road_normal_cam)
    if not sols:
        return 0.0
    Hr = K @ sols[0][0] @ np.linalg.inv(K)
    ph = cv2.perspectiveTransform(a.reshape(-1, 1, 2), H).reshape(-1, 2)
    pr = cv2.perspectiveTransform(a.reshape(-1, 1, 2), Hr).reshape(-1, 2)
    d = np.linalg.norm(ph - pr, axis=1)
    d = d[np.isfinite(d)]
    return float(np.median(d)) if len(d) else 0.0


def _homography_window(
    px_a: np.ndarray,
    px_b: np.ndarray,
    floor: float,
    window: Callable[[np.ndarray], np.ndarray],
    iters: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(window mask (N,), homography (3, 3), predicted pixels in b (N, 2)) around the
    homography-predicted displacement, or None (too few / no model)."""
    if len(px_a) < MIN_H_MATCHES:
        return None
    a, b = px_a.astype(np.float64), px_b.astype(np.float64)
    cv2.setRNGSeed(0)  # deterministic RANSAC
    H, mask = cv2.findHomography(a, b, cv2.RANSAC, floor, maxIters=iters, confidence=0.999)
    if H is None or mask is None or int(mask.sum()) < MIN_H_MATCHES:
        return None
    keep = mask.ravel().astype(bool)
    # Refit by least squares on the window (RANSAC's model comes from a minimal sample), twice:
    # the first window still holds mismatches up to the loose RANSAC threshold.
    for _ in range(2):
        H2, _ = cv2.findHomography(a[keep], b[keep], 0)
        if H2 is None:
            break
        H = H2
        pred = cv2.perspectiveTransform(a.reshape(-1, 1, 2), H).reshape(-1, 2)
        if not np.all(np.isfinite(pred)):
            return None
        new = window(b - pred)
        if new.sum() < MIN_H_MATCHES:
            return None
        keep = new
    return keep, H, pred
