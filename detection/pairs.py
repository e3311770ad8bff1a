"""Per-pair defect points (dissertation Ch. 4): recursive plane fit, then 2D + 3D refinement."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from roadsurf.detection.config import DetectionConfig
from roadsurf.detection.cracks import PairCracks, PairView, detect_pair_cracks
from roadsurf.detection.planefit import recursive_plane_fit
from roadsurf.detection.refine import binarise, correct_defects, refined_mask
from roadsurf.io.drive import Camera
from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)


@dataclass
class PairDefects:
    """Refined defect points of one pair (camera-a coordinates)."""

    index_a: int
    frame_a: str
    candidate: np.ndarray  # (N,) bool, X^rd from the plane fit
    refined: np.ndarray  # (N,) bool, after CORRECT_DEFECTS
    dist_m: np.ndarray  # (N,) signed distance to the final plane (m)
    threshold_m: float  # T_d used (m)
    noise_m: float  # σ of the road points (m)
    deep_area_m2: float  # footprint area covered by refined points deeper than the frame depth
    score: float  # p_defect from this pair alone, in [0, 1]
    area_per_point_m2: float = float("nan")  # road area one point stands for (m²)
    mask: np.ndarray | None = None  # (H, W) bool refined 2D defect mask of image a (with gray)
    cracks: PairCracks | None = None  # cracks confirmed by 3D (with gray and m_per_px)

    @property
    def label(self) -> int:
        return int(self.score >= 0.5)


def analyse_pair(
    pair: PairResult,
    gray: np.ndarray | None,
    cfg: DetectionConfig,
    m_per_px: float | None = None,
    gray_b: np.ndarray | None = None,
    camera: Camera | None = None,
) -> PairDefects | None:
    """Plane fit + CORRECT_DEFECTS for one ok pair; None when the pair has no usable points.

    With ``gray`` and ``m_per_px`` (ground size of a pixel, m) cracks are detected too; with
    image b (``gray_b``, raw pixels) and the ``camera`` their depth is also measured densely
    from the parallax across each crack (``detection.cracks.dense_crack_depth``).
    """
    if not pair.ok or pair.n_points < max(3, cfg.plane.min_points):
        return None
    P = np.asarray(pair.points_cam_a_m, float)
    fit = recursive_plane_fit(P, cfg.plane)
    if not np.isfinite(fit.threshold_m):
        return None
    refined = fit.candidate.copy()
    mask = None if gray is None else np.zeros(np.asarray(gray).shape[:2], bool)
    # The image is raw (as captured); the pair's pixels are ideal (undistorted). Image work
    # reads the image where each point really is.
    px_img = _raw_px(np.asarray(pair.px_a, float), camera) if gray is not None else None
    if cfg.refine.enabled and gray is not None and refined.any():
        road = ~fit.candidate & (np.abs(fit.dist_m) < fit.threshold_m)
        dark = binarise(gray, cfg.refine, road_px=px_img[road])
        refined = correct_defects(
            fit.dist_m, px_img, fit.candidate, dark, fit.threshold_m, cfg.refine
        )
        mask = refined_mask(dark, px_img, refined, max(1, cfg.refine.window_px))
    cracks = None
    if cfg.crack.enabled and gray is not None and m_per_px:
        road = ~fit.candidate & (np.abs(fit.dist_m) < fit.threshold_m)
        view = None
        if gray_b is not None and camera is not None:
            view = PairView.of(pair, gray_b, camera)
        cracks = detect_pair_cracks(
            gray, px_img, P, fit.dist_m, road, fit.noise_m, m_per_px, cfg.crack, view, camera,
            px_ideal=np.asarray(pair.px_a, float),
        )  # fmt: skip
    app = _area_per_point(P)
    deep = refined & (-fit.dist_m >= cfg.map.frame_depth_m)
    area = float(deep.sum()) * app if deep.sum() >= 3 else 0.0
    a_min = cfg.map.frame_min_area_m2
    return PairDefects(
        index_a=pair.index_a,
        frame_a=pair.frame_a,
        candidate=fit.candidate,
        refined=refined,
        dist_m=fit.dist_m,
        threshold_m=fit.threshold_m,
        noise_m=fit.noise_m,
        deep_area_m2=area,
        score=float(area / (area + a_min)) if area > 0 else 0.0,
        area_per_point_m2=app,
        mask=mask,
        cracks=cracks,
    )


def _raw_px(px: np.ndarray, camera: Camera | None) -> np.ndarray:
    """(N, 2) ideal pinhole pixels -> raw image pixels (unchanged without lens distortion)."""
    if camera is None or not camera.has_distortion:
        return px
    from roadsurf.detection.dense import _distort

    return _distort(px, camera)


def _area_per_point(P: np.ndarray) -> float:
    """Road area (m²) one point stands for: the area the points span (1-99 % box in camera X, Y)
    over their count (the reconstruction spreads points over the image with a feature grid)."""
    lo, hi = np.percentile(P[:, :2], [1, 99], axis=0)
    return float(np.prod(np.maximum(hi - lo, 1e-6))) / len(P)
