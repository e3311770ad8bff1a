"""The baselines' poses: traditional SfM ("classic": 8-point F with RANSAC) and pycolmap's
calibrated two-view geometry ("colmap"). Failures raise ``PairFailure``.
"""

from __future__ import annotations

import cv2
import numpy as np

from roadsurf.core.camera import normalised_from_px
from roadsurf.reconstruction import geometry as g
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.types import PairFailure


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
    xa, xb = normalised_from_px(px_a[inl], K), normalised_from_px(px_b[inl], K)
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
