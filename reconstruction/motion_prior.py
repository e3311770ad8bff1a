"""Motion-prior mismatch rejection (dissertation eq. 4.2-4.7) for the planar estimators."""

from __future__ import annotations

import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.reconstruction.config import ReconstructionConfig


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
        mad = MAD_TO_SIGMA * np.median(np.abs(r - c), axis=0)
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
