"""The frame timeline of a recording: per frame the image with its matches, rejected
mismatches, deep points, projected defect outlines and mask, the camera pose, the per-frame
scalars and a frame card. Pixels: u right, v down."""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np
import rerun as rr
from tqdm import tqdm

from roadsurf.viewer.config import ViewerConfig
from roadsurf.viewer.derived import defect_rings_3d, project_to_image
from roadsurf.viewer.rundata import DefectView, RunData, severity_rgb
from roadsurf.viewer.scene import log_pose, pinhole

if TYPE_CHECKING:
    from roadsurf.core.camera import Camera
    from roadsurf.mapping.types import Trajectory
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)


def set_frame_time(rec: rr.RecordingStream, index: int, timestamp_s: float) -> None:
    """Put the stream on the frame timeline (index) and the capture time (seconds)."""
    rec.set_time("frame", sequence=int(index))
    ts = float(timestamp_s)
    if math.isfinite(ts):
        # epoch times become wall-clock timestamps, drive-relative times become durations
        if ts > 1e8:
            rec.set_time("time", timestamp=ts)
        else:
            rec.set_time("time", duration=ts)


def log_frames(
    rec: rr.RecordingStream, data: RunData, cfg: ViewerConfig, *, with_poses: bool = True
) -> int:
    """The frame timeline: image, overlays, mask, pose, per-frame scalars; returns frames logged.

    ``with_poses=False`` leaves the camera pose out (live mode logs it once the poses exist,
    with ``log_camera_poses``)."""
    drive = data.drive
    traj = data.trajectory
    pose_of = {}
    if traj is not None:
        pose_of = {int(i): k for k, i in enumerate(traj.frame_indices)}
    pair_a = {int(p.index_a): p for p in data.pairs}
    pair_b = {int(p.index_b): p for p in data.pairs}
    if drive is not None:
        frames = [(f.index, f.filename, f.timestamp_s, f.path) for f in drive.frames]
        cam = drive.camera
        rec.log("world/camera", pinhole(cam, cam.height_m, (255, 255, 255)), static=True)
    elif traj is not None:
        frames = [
            (int(i), n, float(ts), None)
            for i, n, ts in zip(traj.frame_indices, traj.filenames, traj.timestamp_s, strict=True)
        ]
        cam = None
    else:
        return 0
    rec.log("frames/p_defect", rr.SeriesLines(names="p_defect", colors=[220, 30, 30]), static=True)
    rec.log("frames/inliers", rr.SeriesLines(names="inliers", colors=[40, 160, 40]), static=True)
    rec.log("frames/matches", rr.SeriesLines(names="matches", colors=[120, 120, 120]), static=True)
    # class colours of the refined mask (looked up from the image entity downwards)
    rec.log(
        "world/camera/image",
        rr.AnnotationContext([(1, "defect", (255, 0, 255, 110))]),
        static=True,
    )
    outlines = defect_rings_3d(data)
    n = 0
    stride = max(1, cfg.frame_stride)
    for k, (index, name, ts, path) in enumerate(
        tqdm(frames, desc="viewer frames", disable=len(frames) < 50)
    ):
        if k % stride:
            continue
        set_frame_time(rec, index, ts)
        if with_poses and index in pose_of:
            log_pose(rec, "world/camera", traj.world_from_cam[pose_of[index]])
        if path is not None and path.exists():
            rec.log("world/camera/image", rr.EncodedImage(path=path))
        pair, side = (pair_a[index], "a") if index in pair_a else (pair_b.get(index), "b")
        log_frame_overlays(rec, pair, side, cfg)
        _log_mask(rec, data, name, cam)
        if cam is not None and index in pose_of and outlines:
            _log_projected_defects(rec, data, outlines, traj.world_from_cam[pose_of[index]], cam)
        row = data.frame_labels.get(name)
        p = _float_or_nan(row.get("p_defect")) if row else math.nan
        if math.isfinite(p):
            rec.log("frames/p_defect", rr.Scalars(p))
        if pair is not None:
            rec.log("frames/inliers", rr.Scalars(float(pair.n_inliers)))
            rec.log("frames/matches", rr.Scalars(float(pair.n_matches)))
            if not pair.ok and side == "a":
                rec.log(
                    "log",
                    rr.TextLog(
                        f"pair {pair.frame_a} -> {pair.frame_b} failed: {pair.status} "
                        f"{pair.reason}",
                        level=rr.TextLogLevel.WARN,
                    ),
                )
        rec.log(
            "frames/info",
            rr.TextDocument(
                _frame_card(index, name, ts, row, pair, traj, pose_of.get(index)),
                media_type=rr.MediaType.MARKDOWN,
            ),
        )
        n += 1
    return n


def _float_or_nan(v: object) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def log_camera_poses(rec: rr.RecordingStream, data: RunData, cfg: ViewerConfig) -> int:
    """The current-camera pose on the frame timeline (every ``frame_stride``-th posed frame)."""
    t = data.trajectory
    if t is None:
        return 0
    n = 0
    for k in range(0, len(t), max(1, cfg.frame_stride)):
        set_frame_time(rec, int(t.frame_indices[k]), float(t.timestamp_s[k]))
        log_pose(rec, "world/camera", t.world_from_cam[k])
        n += 1
    return n


def log_frame_overlays(
    rec: rr.RecordingStream, pair: PairResult | None, side: str, cfg: ViewerConfig
) -> None:
    """Matched features, rejected mismatches and defect points of one frame (pixels)."""
    if pair is None:
        rec.log("world/camera/image/matches", rr.Clear(recursive=False))
        rec.log("world/camera/image/rejected", rr.Clear(recursive=False))
        rec.log("world/camera/image/defect_points", rr.Clear(recursive=False))
        return
    px = np.asarray(pair.px_a if side == "a" else pair.px_b, float).reshape(-1, 2)
    rej = np.asarray(pair.rejected_px_a if side == "a" else pair.rejected_px_b, float).reshape(
        -1, 2
    )
    rng = np.random.default_rng(0)
    keep = _subsample(len(px), cfg.max_overlay_points, rng)
    rec.log(
        "world/camera/image/matches",
        rr.Points2D(px[keep], colors=[60, 230, 60], radii=rr.Radius.ui_points(2.0)),
    )
    keep_r = _subsample(len(rej), cfg.max_overlay_points, rng)
    rec.log(
        "world/camera/image/rejected",
        rr.Points2D(rej[keep_r], colors=[255, 60, 60], radii=rr.Radius.ui_points(2.0)),
    )
    d = np.asarray(pair.plane_dist_m, float).reshape(-1)
    if len(d) == len(px) and len(px):
        deep = d < -cfg.defect_point_depth_m
        labels = [f"{-1000 * v:.0f} mm" for v in d[deep]]
        rec.log(
            "world/camera/image/defect_points",
            rr.Points2D(
                px[deep],
                colors=[255, 0, 255],
                radii=rr.Radius.ui_points(3.5),
                labels=labels,
                show_labels=False,
            ),
        )
    else:
        rec.log("world/camera/image/defect_points", rr.Clear(recursive=False))


def _log_projected_defects(
    rec: rr.RecordingStream,
    data: RunData,
    outlines: list[tuple[DefectView, np.ndarray]],
    world_from_cam: np.ndarray,
    cam: Camera,
) -> None:
    """Final (map) defect outlines projected into the current frame, where they are visible."""
    strips, colors, labels = [], [], []
    for d, ring in outlines:
        uv = project_to_image(world_from_cam, cam, ring)
        if uv is None:
            continue
        strips.append(uv.astype(np.float32))
        colors.append(severity_rgb(d.severity))
        labels.append(d.label)
    if strips:
        rec.log(
            "world/camera/image/defect_outlines",
            rr.LineStrips2D(strips, colors=colors, labels=labels, radii=rr.Radius.ui_points(2.0)),
        )
    else:
        rec.log("world/camera/image/defect_outlines", rr.Clear(recursive=False))


def _subsample(n: int, k: int, rng: np.random.Generator) -> np.ndarray:
    return np.arange(n) if n <= k else np.sort(rng.choice(n, k, replace=False))


def _log_mask(rec: rr.RecordingStream, data: RunData, name: str, cam: Camera | None) -> None:
    from pathlib import PurePath

    path = data.masks.get(PurePath(name).stem)
    if path is None:
        if data.masks:
            rec.log("world/camera/image/mask", rr.Clear(recursive=False))
        return
    import cv2

    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        log.warning("%s: unreadable mask; skipped", path)
        return
    if m.ndim == 3:
        m = m[..., 0]
    m = (m > 0).astype(np.uint8)
    if cam is not None and m.shape != (cam.height, cam.width):
        m = cv2.resize(m, (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)
    rec.log("world/camera/image/mask", rr.SegmentationImage(m, opacity=0.45))


def _frame_card(
    index: int,
    name: str,
    ts: float,
    row: dict[str, str] | None,
    pair: PairResult | None,
    traj: Trajectory | None,
    k: int | None,
) -> str:
    lines = [f"### Frame {index}: `{name}`", f"- time: {ts:.3f} s"]
    if k is not None:
        lines.append(f"- pose source: {traj.source[k]}")
    if row:
        lines.append(
            f"- detection: defect={row.get('defect')} p={row.get('p_defect')} ({row.get('source')})"
        )
    if pair is not None:
        lines.append(f"- pair {pair.frame_a} → {pair.frame_b}: **{pair.status}** {pair.reason}")
        lines.append(
            f"- matches {pair.n_matches}, prior inliers {pair.n_prior_inliers}, "
            f"inliers {pair.n_inliers}, 3D points {pair.n_points}"
        )
    return "\n".join(lines)
