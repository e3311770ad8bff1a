"""Public API of the reconstruction package.

- ``reconstruct_pair(frame_a, frame_b, camera, cfg)``: images (arrays) or ``Frame``s -> PairResult.
- ``reconstruct_matches(px_a, px_b, camera, cfg)``: matched pixels -> PairResult (the study's
  point-level path).
- ``reconstruct_features(fa, fb, camera, cfg)``: precomputed ``Features`` -> PairResult (the stage
  reuses each frame's features for both of its pairs).
- ``retry_stretched(res, fa, image_b, camera, cfg)``: a pair that failed for want of matches,
  tried again with image b's features detected on vertically compressed views of it.

A bad pair never raises: the PairResult's ``status``/``reason`` say what went wrong.
"""

from __future__ import annotations

import time

import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.errors import FrameReadError
from roadsurf.core.geometry import up_in_cam
from roadsurf.io.drive import Frame, read_gray
from roadsurf.reconstruction import features as feat
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.estimators import estimate_matches
from roadsurf.reconstruction.rolling_shutter import estimate_rolling_shutter, row_times_s
from roadsurf.reconstruction.types import Features, PairResult


def reconstruct_matches(
    px_a: np.ndarray,
    px_b: np.ndarray,
    camera: Camera,
    cfg: ReconstructionConfig,
    *,
    frame_dt_s: float | None = None,
    road_normal_cam: np.ndarray | None = None,
) -> PairResult:
    """Matched raw pixels (N, 2) in a and b -> metric PairResult (undistorted when needed).

    A known mount (``camera.mount_deg``) tells the estimators where the road's normal is;
    road_normal_cam ((3,), downward, camera coordinates) overrides it (the drive's consensus
    normal, ``reconstruction.consensus``). With
    a rolling shutter (``camera.readout_s`` > 0, ``cfg.rolling_shutter``) each observation is
    moved to its frame's timestamp (``reconstruction.rolling_shutter``); frame_dt_s = the
    timestamp of b minus that of a (s), None = 1 / ``camera.fps``."""
    pa = camera.undistort_px(px_a)
    pb = camera.undistort_px(px_b)
    size = (camera.width, camera.height)
    normal = road_normal_in_cam(camera) if road_normal_cam is None else road_normal_cam
    if camera.readout_s > 0 and cfg.rolling_shutter:
        dt = 1.0 / camera.fps if frame_dt_s is None else float(frame_dt_s)
        rows_a = np.asarray(px_a, float).reshape(-1, 2)[:, 1]  # raw rows: the sensor's order
        rows_b = np.asarray(px_b, float).reshape(-1, 2)[:, 1]
        return estimate_rolling_shutter(
            pa,
            pb,
            camera.K,
            camera.height_m,
            cfg,
            tau_a_s=row_times_s(rows_a, camera.height, camera.readout_s),
            tau_b_s=row_times_s(rows_b, camera.height, camera.readout_s),
            frame_dt_s=dt,
            image_size=size,
            road_normal_cam=normal,
        )
    return estimate_matches(
        pa, pb, camera.K, camera.height_m, cfg, image_size=size, road_normal_cam=normal
    )


def road_normal_in_cam(camera: Camera) -> np.ndarray | None:
    """(3,) the road's downward normal in camera coordinates from the camera's mount (a level
    vehicle on the road), or None when the mount is unknown."""
    if camera.mount_deg is None:
        return None
    return -up_in_cam(camera.vehicle_from_cam)


def reconstruct_features(
    fa: Features,
    fb: Features,
    camera: Camera,
    cfg: ReconstructionConfig,
    *,
    frame_dt_s: float | None = None,
    road_normal_cam: np.ndarray | None = None,
) -> PairResult:
    """Match two frames' features and reconstruct. Fills counts and the matching time.
    frame_dt_s, road_normal_cam: as ``reconstruct_matches``."""
    na, nb = len(fa.keypoints_px), len(fb.keypoints_px)
    if min(na, nb) < cfg.min_features:
        res = PairResult("", "", -1, -1, cfg.method, "too_few_features")
        res.reason = (
            f"{na} and {nb} keypoints (< min_features={cfg.min_features}): textureless, "
            "blurred or over/under-exposed frame"
        )
        res.n_features_a, res.n_features_b = na, nb
        return res
    t0 = time.perf_counter()
    ia, ib = feat.match(fa, fb, cfg.features)
    t_match = time.perf_counter() - t0
    if len(ia) < cfg.min_matches:
        res = PairResult("", "", -1, -1, cfg.method, "no_overlap")
        res.reason = (
            f"only {len(ia)} mutual ratio-test matches between {na} and {nb} keypoints "
            f"(< min_matches={cfg.min_matches}): the views probably do not overlap"
        )
    else:
        res = reconstruct_matches(
            fa.keypoints_px[ia],
            fb.keypoints_px[ib],
            camera,
            cfg,
            frame_dt_s=frame_dt_s,
            road_normal_cam=road_normal_cam,
        )
        if res.ok and res.n_points >= 3:
            _check_overlap(res, camera, cfg)
        elif (
            res.status == "too_few_matches"
            and cfg.motion_prior
            and 0 < len(ia)
            and res.n_prior_inliers < cfg.min_matches
        ):
            # the same evidence as too few matches at all: of the ratio-test matches, fewer
            # than min_matches move like one road (the rest are chance matches between two
            # textured frames); a blurred frame gives too few keypoints or matches instead
            res.status = "no_overlap"
            res.reason = (
                f"only {res.n_prior_inliers} of {len(ia)} mutual ratio-test matches agree with "
                f"one motion of the road (motion prior; < min_matches={cfg.min_matches}): the "
                "views probably do not overlap"
            )
    res.n_features_a, res.n_features_b = na, nb
    res.n_matches = int(len(ia))
    res.timings_s["matching"] = t_match
    return res


# failures that mean "not enough matches": the ones a stretched view of image b may cure
STRETCH_RETRY_STATUSES = ("too_few_matches", "no_overlap")


def wants_stretch_retry(res: PairResult, cfg: ReconstructionConfig) -> bool:
    """Whether ``retry_stretched`` would try the pair (so a caller reads image b only then)."""
    return not res.ok and res.status in STRETCH_RETRY_STATUSES and bool(cfg.features.stretch_retry)


def retry_stretched(
    res: PairResult,
    fa: Features,
    image_b: np.ndarray,
    camera: Camera,
    cfg: ReconstructionConfig,
    *,
    frame_dt_s: float | None = None,
    road_normal_cam: np.ndarray | None = None,
) -> PairResult:
    """A pair that failed for want of matches, tried again with image b's features detected at
    each vertical scale of ``cfg.features.stretch_retry`` (``features.detect_stretched``).
    Returns the ok result with the most inliers (its ``stretch_b`` says the scale), else ``res``
    unchanged; the time spent is in ``timings_s["stretch_retry"]`` either way."""
    if not wants_stretch_retry(res, cfg):
        return res
    t0 = time.perf_counter()
    best: PairResult | None = None
    for s in cfg.features.stretch_retry:
        fb = feat.detect_stretched(image_b, cfg.features, s, camera.mask)
        r = reconstruct_features(
            fa, fb, camera, cfg, frame_dt_s=frame_dt_s, road_normal_cam=road_normal_cam
        )
        if r.ok and (best is None or r.n_inliers > best.n_inliers):
            r.stretch_b = float(s)
            best = r
    out = best if best is not None else res
    out.timings_s["stretch_retry"] = time.perf_counter() - t0
    return out


def _check_overlap(res: PairResult, camera: Camera, cfg: ReconstructionConfig) -> None:
    """Mark pairs whose points cover too small a share of image a as no_overlap. The share is
    that of the convex hull without the outermost 2% (at least one point) of the points in
    each image direction: one stray point must not turn a strip of overlap into an area (a
    25-row strip and one point 170 rows away read 20%: a pose 37% off in scale)."""
    import cv2

    px = res.px_a
    k = max(1, int(round(0.02 * len(px))))
    if len(px) > 2 * k + 2:
        inside = np.ones(len(px), bool)
        for axis in (0, 1):
            lo, hi = np.sort(px[:, axis])[[k, len(px) - 1 - k]]
            inside &= (px[:, axis] >= lo) & (px[:, axis] <= hi)
        px = px[inside]
    hull = cv2.convexHull(px.astype(np.float32))
    usable = 1.0 if camera.mask is None else 1.0 - camera.mask.masked_share
    share = float(cv2.contourArea(hull)) / float(camera.width * camera.height * usable)
    if share < cfg.min_overlap:
        res.status = "no_overlap"
        of = "image a" if camera.mask is None else "image a's unmasked pixels"
        res.reason = f"matched points cover {share:.1%} of {of} (< min_overlap={cfg.min_overlap})"


def _as_gray(x: np.ndarray | Frame) -> np.ndarray:
    if isinstance(x, Frame):
        return read_gray(x)
    return feat.to_gray(np.asarray(x))


def reconstruct_pair(
    frame_a: np.ndarray | Frame,
    frame_b: np.ndarray | Frame,
    camera: Camera,
    cfg: ReconstructionConfig,
    *,
    frame_dt_s: float | None = None,
) -> PairResult:
    """Two images (arrays, RGB or grey) or Frames -> PairResult. Unreadable frames -> status.

    frame_dt_s: as ``reconstruct_matches``; None with two Frames = their timestamps' difference."""
    names = [x.filename if isinstance(x, Frame) else "" for x in (frame_a, frame_b)]
    idx = [x.index if isinstance(x, Frame) else -1 for x in (frame_a, frame_b)]
    try:
        ga, gb = _as_gray(frame_a), _as_gray(frame_b)
    except FrameReadError as e:
        return PairResult(
            names[0], names[1], idx[0], idx[1], cfg.method, "unreadable_frame", str(e)
        )
    t0 = time.perf_counter()
    fa = feat.detect(ga, cfg.features, camera.mask)
    fb = feat.detect(gb, cfg.features, camera.mask)
    t_feat = time.perf_counter() - t0
    if frame_dt_s is None and isinstance(frame_a, Frame) and isinstance(frame_b, Frame):
        frame_dt_s = frame_b.timestamp_s - frame_a.timestamp_s
    res = reconstruct_features(fa, fb, camera, cfg, frame_dt_s=frame_dt_s)
    res = retry_stretched(res, fa, gb, camera, cfg, frame_dt_s=frame_dt_s)
    res.frame_a, res.frame_b, res.index_a, res.index_b = names[0], names[1], idx[0], idx[1]
    res.timings_s["features"] = t_feat
    return res
