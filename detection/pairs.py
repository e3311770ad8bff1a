"""Per-pair defect points (dissertation Ch. 4): recursive plane fit, then 2D + 3D refinement.

``analyse_pair`` does one pair; ``analyse_pairs`` every ok pair of a run, on threads, writing
each pair's refined 2D defect mask (RUN/masks/<frame stem>.png).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from roadsurf.core.atomic import atomic_path
from roadsurf.core.camera import Camera
from roadsurf.core.errors import OutputError
from roadsurf.core.parallel import ordered_map
from roadsurf.detection.config import DetectionConfig
from roadsurf.detection.cracks import PairCracks, PairView, detect_pair_cracks
from roadsurf.detection.planefit import recursive_plane_fit
from roadsurf.detection.refine import binarise, correct_defects, refined_mask
from roadsurf.io.drive import Drive, GrayFrames
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


def refines(cfg: DetectionConfig) -> bool:
    """Whether the 2D + 3D refinement runs: on request (``refine.enabled``), and always for the
    dissertation's per-pair frame decision (``frame_label`` "pair"), which is built on it."""
    return bool(cfg.refine.enabled or cfg.frame_label == "pair")


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
    from the parallax across each crack (``detection.crackdepth.dense_crack_depth``).
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
    # The camera's mask: its pixels filled with the median grey (the adaptive threshold's
    # blur, tens of pixels wide, would carry a black stamp's darkness onto the road around
    # it), and nothing within the refinement's window of it is dark (None: no mask)
    usable = None
    if gray is not None and camera is not None and camera.mask is not None:
        gray = camera.mask.fill(np.asarray(gray))
        usable = camera.mask.eroded(max(1, cfg.refine.window_px) // 2 + 1)
    if refines(cfg) and gray is not None and refined.any():
        road = ~fit.candidate & (np.abs(fit.dist_m) < fit.threshold_m)
        dark = binarise(gray, cfg.refine, road_px=px_img[road])
        if usable is not None:  # a burned-in stamp's black box is dark, not a defect
            dark &= usable
        refined = correct_defects(
            fit.dist_m, px_img, fit.candidate, dark, fit.threshold_m, cfg.refine
        )
        mask = refined_mask(dark, px_img, refined, max(1, cfg.refine.window_px))
        if usable is not None:
            mask &= usable
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
    return camera.distort_px(px)


def _area_per_point(P: np.ndarray) -> float:
    """Road area (m²) one point stands for: the area the points span (1-99 % box in camera X, Y)
    over their count (the reconstruction spreads points over the image with a feature grid)."""
    lo, hi = np.percentile(P[:, :2], [1, 99], axis=0)
    return float(np.prod(np.maximum(hi - lo, 1e-6))) / len(P)


def analyse_pairs(
    cfg: DetectionConfig,
    drive: Drive,
    pairs: list[PairResult],
    masks_dir: Path | None = None,
) -> dict[int, PairDefects]:
    """Plane fit + 2D/3D refinement of every ok pair; keyed by the pair's position in ``pairs``.

    With ``masks_dir`` the refined 2D defect mask of each pair's image a is written there as
    ``<frame stem>.png`` (uint8, 255 = defect, 0 = not) and not kept in memory.
    """
    out: dict[int, PairDefects] = {}
    ok = [(k, p) for k, p in enumerate(pairs) if p.ok]
    workers = max(1, int(cfg.pair_workers))
    # consecutive pairs share a frame (b, then a); each thread is a pair or two apart
    image = GrayFrames(
        drive.frames, 2 * workers + 2, "detection: pairs with this frame use 3D only"
    ).get

    def one(kp: tuple[int, PairResult]) -> PairDefects | None:
        _, p = kp
        gray = gray_b = None
        # the image serves the 2D refinement and the crack detector, each on its own switch
        if cfg.use_images and (refines(cfg) or cfg.crack.enabled):
            gray = image(p.frame_a)
            # Image b only for the dense crack depth (parallax across each crack).
            if gray is not None and cfg.crack.enabled and cfg.crack.dense:
                gray_b = image(p.frame_b)
        return analyse_pair(
            p, gray, cfg, m_per_px=drive.camera.ground_px_m(),
            gray_b=gray_b, camera=drive.camera,
        )  # fmt: skip

    # pairs are independent: threads analyse them (NumPy and OpenCV release the GIL), and the
    # results are taken in pair order, so they are the same on any thread count
    results = ordered_map(one, ok, workers)
    bar = tqdm(total=len(ok), desc="detection: pairs", unit="pair", disable=len(ok) < 20)
    with bar:
        for (k, _), res in zip(ok, results, strict=True):
            bar.update(1)
            if res is None:
                continue
            if masks_dir is not None and res.mask is not None:
                write_mask(Path(masks_dir) / f"{Path(res.frame_a).stem}.png", res.mask)
            res.mask = None  # bounded memory: a few image masks at a time
            out[k] = res
    return out


def write_mask(path: Path, mask: np.ndarray) -> None:
    """Write a refined 2D defect mask as an 8-bit PNG (255 = defect), atomically and checked:
    ``atomic_path`` fsyncs and refuses an empty file (cv2.imwrite reports success on a full
    disk after writing nothing), and a False from cv2.imwrite is an ``OutputError`` too."""
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.where(mask, 255, 0).astype(np.uint8)):
            raise OutputError(
                f"{path}: OpenCV could not write the defect mask PNG (disk full or unwritable "
                "output?). Free some space or choose another --out, then run the same command "
                "again to resume."
            )
