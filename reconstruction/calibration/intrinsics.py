"""Intrinsics and lens distortion from board images (OpenCV's calibrateCamera, k1 k2 p1 p2 k3),
with the checks that refuse a calibration too poor to use."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from roadsurf.reconstruction.calibration.board import BoardSpec
from roadsurf.reconstruction.calibration.detect import Detection, detect_board, read_gray
from roadsurf.reconstruction.calibration.errors import CalibrationError

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)


@dataclass(frozen=True)
class CalibrationLimits:
    """When a calibration is refused."""

    min_images: int = 5  # usable board views
    max_rms_px: float = 1.0  # overall RMS reprojection error
    min_coverage: float = 0.35  # fraction of the image area covered by the boards
    tilt_deg: float = 10.0  # a view counts as tilted when the board is this far from frontal
    min_tilted_views: int = 3
    max_focal_std: float = 0.005  # 1-sigma of fx, fy relative to fx, fy


@dataclass
class Intrinsics:
    """A calibrated camera and how it was obtained."""

    width: int
    height: int
    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (5,) k1, k2, p1, p2, k3
    rms_px: float
    per_image_rms_px: dict[str, float]  # used image -> its RMS reprojection error
    n_corners: dict[str, int]
    skipped: dict[str, str]  # image -> why it was not used
    coverage: float
    tilts_deg: dict[str, float]
    std_intrinsics: dict[str, float]  # 1-sigma of fx, fy, cx, cy (px) and k1..k3
    board_hulls: list[np.ndarray] = field(default_factory=list)  # (M, 2) per used view


def _coverage(hulls: Sequence[np.ndarray], width: int, height: int) -> float:
    """Fraction of the image covered by the union of the boards' convex hulls."""
    s = 4  # raster at 1/4 resolution: plenty for a coverage figure
    mask = np.zeros((height // s + 1, width // s + 1), np.uint8)
    for h in hulls:
        cv2.fillConvexPoly(mask, np.round(h / s).astype(np.int32), 1)
    return float(mask.mean())


def _hull(px: np.ndarray) -> np.ndarray:
    return cv2.convexHull(px.reshape(-1, 1, 2).astype(np.float32)).reshape(-1, 2)


def calibrate_detections(
    names: Sequence[str],
    detections: Sequence[Detection],
    size: tuple[int, int],
    limits: CalibrationLimits,
    skipped: dict[str, str] | None = None,
) -> Intrinsics:
    """Calibrate from board detections of images of ``size`` = (width, height) px.

    Raises CalibrationError (one line) when the views are too few, cover too little of the
    image, are not tilted enough, or the result is too uncertain or fits too poorly."""
    skipped = dict(skipped or {})
    w, h = size
    gone = f" ({len(skipped)} skipped: {', '.join(sorted(skipped))})" if skipped else ""
    if len(detections) < limits.min_images:
        raise CalibrationError(
            f"the board was found in {len(detections)} image(s){gone}; at least "
            f"{limits.min_images} are needed. Take more sharp, well-lit photographs of the whole "
            "board at different positions and tilts."
        )
    hulls = [_hull(d.image_px) for d in detections]
    coverage = _coverage(hulls, w, h)
    if coverage < limits.min_coverage:
        raise CalibrationError(
            f"the boards cover {coverage:.0%} of the image (at least {limits.min_coverage:.0%} "
            "needed). Add photographs with the board near the edges and corners of the image."
        )
    objs = [d.object_m.reshape(-1, 1, 3) for d in detections]
    imgs = [d.image_px.reshape(-1, 1, 2) for d in detections]
    rms, K, dist, rvecs, _tvecs, std_in, _std_ex, per_view = cv2.calibrateCameraExtended(
        objs, imgs, (w, h), None, None, criteria=_CRITERIA
    )
    normals = [cv2.Rodrigues(r)[0][:, 2] for r in rvecs]
    tilts = [math.degrees(math.acos(min(1.0, abs(float(n[2]))))) for n in normals]
    n_tilted = sum(t >= limits.tilt_deg for t in tilts)
    if n_tilted < limits.min_tilted_views:
        raise CalibrationError(
            f"only {n_tilted} view(s) show the board tilted by {limits.tilt_deg:g}° or more "
            f"({limits.min_tilted_views} needed): the focal length cannot be told from the "
            "distance. Add photographs with the board turned 20-45° away from the camera."
        )
    per = {n: float(e) for n, e in zip(names, np.asarray(per_view).ravel(), strict=True)}
    if rms > limits.max_rms_px:
        worst = sorted(per, key=per.get, reverse=True)[:3]
        raise CalibrationError(
            f"the RMS reprojection error is {rms:.2f} px (limit {limits.max_rms_px:g} px; worst "
            f"images: {', '.join(f'{n} {per[n]:.2f} px' for n in worst)}). Remove blurred or "
            "bent-board images, check the --board square size, or raise the limit."
        )
    std = np.asarray(std_in, float).ravel()
    fx_std, fy_std = std[0] / K[0, 0], std[1] / K[1, 1]
    if max(fx_std, fy_std) > limits.max_focal_std or not np.all(np.isfinite(std[:4])):
        raise CalibrationError(
            f"the focal length is uncertain by {max(fx_std, fy_std):.2%} (limit "
            f"{limits.max_focal_std:.2%}). Add photographs with more board tilt and coverage."
        )
    keys = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    return Intrinsics(
        width=w,
        height=h,
        K=K,
        dist=np.asarray(dist, float).ravel()[:5],
        rms_px=float(rms),
        per_image_rms_px=per,
        n_corners={n: len(d.image_px) for n, d in zip(names, detections, strict=True)},
        skipped=skipped,
        coverage=coverage,
        tilts_deg={n: float(t) for n, t in zip(names, tilts, strict=True)},
        std_intrinsics={k: float(v) for k, v in zip(keys, std, strict=False)},
        board_hulls=hulls,
    )


def calibrate_images(
    paths: Sequence[Path], spec: BoardSpec, limits: CalibrationLimits | None = None
) -> Intrinsics:
    """Detect the board in every image file and calibrate. Images where the board is not
    found (or that cannot be read) are skipped and listed in ``Intrinsics.skipped``."""
    limits = limits or CalibrationLimits()
    names: list[str] = []
    dets: list[Detection] = []
    skipped: dict[str, str] = {}
    size: tuple[int, int] | None = None
    for path in paths:
        name = str(path)
        try:
            gray = read_gray(Path(path))
        except CalibrationError:
            skipped[name] = "unreadable"
            continue
        shape = (gray.shape[1], gray.shape[0])
        if size is None:
            size = shape
        elif shape != size:
            raise CalibrationError(
                f"{path}: the image is {shape[0]}x{shape[1]} px but earlier ones are "
                f"{size[0]}x{size[1]}. Calibrate one camera at one resolution at a time."
            )
        det = detect_board(gray, spec)
        if det is None:
            skipped[name] = "board not found"
            continue
        names.append(name)
        dets.append(det)
    if size is None:
        raise CalibrationError("no readable image was given. Pass the board photographs.")
    return calibrate_detections(names, dets, size, limits, skipped)
