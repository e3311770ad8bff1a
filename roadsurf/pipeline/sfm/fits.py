"""The SfM baseline's robust placement fit: camera centres onto GPS by a 2D rigid or similarity
transform (``roadsurf.core.fits.fit_rigid_2d``), refitted without the pairs whose residual is
more than k robust sigmas (MAD) off."""

from __future__ import annotations

import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA, Rigid2D, fit_rigid_2d


def robust_fit_2d(
    src: np.ndarray, dst: np.ndarray, with_scale: bool, k: float
) -> tuple[Rigid2D, np.ndarray]:
    """Iteratively reweighted (trimmed) 2D fit dst ≈ s R src + t of (N, 2) points (metres):
    refit without pairs whose residual exceeds k robust sigmas (MAD), at most 5 rounds.
    Returns (the fit, inlier mask (N,))."""
    inl = np.ones(len(src), bool)
    fit = fit_rigid_2d(src, dst, with_scale=with_scale)
    for _ in range(5):
        r = np.linalg.norm(dst - (fit.scale * src @ fit.R.T + fit.t), axis=1)
        sigma = MAD_TO_SIGMA * float(np.median(r[inl])) + 1e-9
        new = r <= max(k * sigma, 1e-6)
        if new.sum() < 2 or np.array_equal(new, inl):
            break
        inl = new
        fit = fit_rigid_2d(src[inl], dst[inl], with_scale=with_scale)
    return fit, inl
