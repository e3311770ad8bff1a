"""Log a run folder to a Rerun recording, with a blueprint that lays it out.

Entity tree (all 3D in local ENU metres, x east, y north, z up; see docs/viewer.md):

- ``world/cloud``            global point cloud coloured by residual_m (diverging colormap)
- ``world/defects``          defect outlines at the road surface, labelled id/type/depth/area/severity
- ``world/defect_boxes``     depth boxes of each defect (outline bbox x max depth)
- ``world/trajectory``       fused camera path; ``world/gps`` GPS fixes in ENU
- ``world/frusta/f<idx>``    static camera frusta every ``frustum_stride`` frames
- ``world/camera``           current camera (timeline): pose + pinhole; ``world/camera/image`` the
                             frame, with ``matches``, ``rejected``, ``defect_points``,
                             ``defect_outlines`` (map defects projected in), ``mask``
- ``map/*``                  GeoLineStrings / GeoPoints for the map view (tiles are the viewer's)
- ``mosaic/*``, ``surface/*``  ortho-mosaic and residual surface images with defect outlines
- ``frames/*``               per-frame scalars (p_defect, matches, inliers) and a frame card
- ``profiles/<id>``          depth profile of each defect along its long axis (bar chart)
- ``legend``, ``summary``, ``log``  colour legend, run summary, warnings (failed pairs)
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from tqdm import tqdm

from roadsurf.viewer.colors import legend_png, residual_half_range_m, residual_rgb
from roadsurf.viewer.config import ViewerConfig
from roadsurf.viewer.runfolder import (
    DefectView,
    RunData,
    defect_rings_3d,
    depth_profile,
    gps_enu_m,
    project_to_image,
    road_height_near,
    rowcol_from_enu,
    severity_rgb,
)

log = logging.getLogger(__name__)

APP_ID = "roadsurf"
MAX_PROFILE_TABS = 6  # more defects still get a profile entity, just no tab of their own


def _latlon(lonlat: np.ndarray) -> np.ndarray:
    return np.asarray(lonlat, float)[:, ::-1]


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


def log_setup(rec: rr.RecordingStream) -> None:
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)


def log_cloud(rec: rr.RecordingStream, data: RunData, cfg: ViewerConfig) -> int:
    """The global cloud, coloured by residual; returns the number of points logged."""
    xyz = data.cloud_enu_m
    if xyz is None or len(xyz) == 0:
        return 0
    idx = np.arange(len(xyz))
    if len(xyz) > cfg.max_cloud_points:
        idx = np.sort(np.random.default_rng(0).choice(len(xyz), cfg.max_cloud_points, False))
    res = data.cloud_residual_m
    if res is not None:
        half = residual_half_range_m(res, cfg.residual_range_percentile, cfg.min_residual_range_m)
        colors = residual_rgb(res[idx], half, cfg.colormap)
        rec.log(
            "legend",
            rr.EncodedImage(contents=legend_png(half, cfg.colormap), media_type="image/png"),
            static=True,
        )
    else:
        colors = data.cloud_rgb[idx] if data.cloud_rgb is not None else None
    spacing = _point_spacing_m(xyz[idx, :2])
    rec.log(
        "world/cloud",
        rr.Points3D(
            xyz[idx].astype(np.float32),
            colors=colors,
            radii=0.5 * spacing,
            point_shading="flat",  # true colormap colours (no sphere shading)
        ),
        static=True,
    )
    if data.cloud_rgb is not None:
        # the photo colours too, hidden behind the residual colours unless toggled
        rec.log(
            "world/cloud_rgb",
            rr.Points3D(
                xyz[idx].astype(np.float32), colors=data.cloud_rgb[idx], radii=0.5 * spacing
            ),
            static=True,
        )
    return len(idx)


def _point_spacing_m(xy: np.ndarray) -> float:
    """Typical nearest-neighbour spacing (m) of a point set, from a sample."""
    if len(xy) < 2:
        return 0.005
    from scipy.spatial import cKDTree

    sample = xy[np.random.default_rng(1).choice(len(xy), min(2000, len(xy)), False)]
    d, _ = cKDTree(xy).query(sample, k=2)
    s = float(np.median(d[:, 1]))
    return float(np.clip(s, 0.001, 0.05))


def log_defects(rec: rr.RecordingStream, data: RunData, cfg: ViewerConfig) -> int:
    """Defect outlines + depth boxes in 3D, GeoPoints/outlines on the map, and profiles."""
    defects = data.defects
    if not defects:
        return 0
    strips, boxes_c, boxes_h, colors, labels = [], [], [], [], []
    for d in defects:
        z = road_height_near(data, d.centroid_enu_m)
        ring = d.ring_enu_m
        strips.append(np.column_stack([ring, np.full(len(ring), z)]).astype(np.float32))
        lo, hi = ring.min(axis=0), ring.max(axis=0)
        depth = d.max_depth_m if math.isfinite(d.max_depth_m) else 0.0
        boxes_c.append([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, z - depth / 2])
        boxes_h.append([(hi[0] - lo[0]) / 2, (hi[1] - lo[1]) / 2, max(depth / 2, 1e-4)])
        colors.append(severity_rgb(d.severity))
        labels.append(d.label)
    rec.log(
        "world/defects",
        rr.LineStrips3D(
            strips, colors=colors, labels=labels, show_labels=True, radii=rr.Radius.ui_points(2.0)
        ),
        static=True,
    )
    rec.log(
        "world/defect_boxes",
        rr.Boxes3D(
            centers=boxes_c, half_sizes=boxes_h, colors=colors, radii=rr.Radius.ui_points(1.0)
        ),
        static=True,
    )
    geo = [d for d in defects if d.ring_lonlat is not None]
    if geo:
        cent = np.array(
            [
                d.ring_lonlat[:-1].mean(axis=0) if len(d.ring_lonlat) > 1 else d.ring_lonlat[0]
                for d in geo
            ]
        )
        rec.log(
            "map/defects",
            rr.GeoPoints(
                lat_lon=_latlon(cent),
                colors=[severity_rgb(d.severity) for d in geo],
                radii=rr.Radius.ui_points(7.0),
            ),
            static=True,
        )
        rec.log(
            "map/defect_outlines",
            rr.GeoLineStrings(
                lat_lon=[_latlon(d.ring_lonlat) for d in geo],
                colors=[severity_rgb(d.severity) for d in geo],
                radii=rr.Radius.ui_points(2.0),
            ),
            static=True,
        )
    for d in defects:
        prof = depth_profile(data, d, cfg.profile_samples)
        if prof is None:
            continue
        dist_m, res_m = prof
        rec.log(
            f"profiles/{_safe(d.id)}",
            rr.BarChart(
                np.nan_to_num(1000.0 * res_m),
                abscissa=100.0 * dist_m,
                color=severity_rgb(d.severity),
            ),
            static=True,
        )
    return len(defects)


def _safe(s: str) -> str:
    return rr.escape_entity_path_part(str(s))


def log_trajectory(rec: rr.RecordingStream, data: RunData, cfg: ViewerConfig) -> int:
    """Fused path in 3D and on the map, GPS fixes, static frusta; returns posed frame count."""
    gps = gps_enu_m(data)
    if gps is not None:
        rec.log(
            "world/gps",
            rr.Points3D(
                gps.astype(np.float32), colors=[0, 200, 255], radii=rr.Radius.ui_points(3.0)
            ),
            static=True,
        )
        d = data.drive.gps
        rec.log(
            "map/gps_track",
            rr.GeoLineStrings(
                lat_lon=[np.column_stack([d.lat_deg, d.lon_deg])],
                colors=[0, 200, 255],
                radii=rr.Radius.ui_points(2.0),
            ),
            static=True,
        )
        rec.log(
            "map/gps_fixes",
            rr.GeoPoints(
                lat_lon=np.column_stack([d.lat_deg, d.lon_deg]),
                colors=[0, 200, 255],
                radii=rr.Radius.ui_points(3.0),
            ),
            static=True,
        )
    t = data.trajectory
    if t is None or len(t) == 0:
        return 0
    pos = t.positions_enu_m
    rec.log(
        "world/trajectory",
        rr.LineStrips3D(
            [pos.astype(np.float32)],
            colors=[40, 220, 60],
            radii=rr.Radius.ui_points(2.0),
            labels=["fused trajectory"],
        ),
        static=True,
    )
    ll = data.lonlat_from_enu(pos)
    if ll is not None:
        rec.log(
            "map/trajectory",
            rr.GeoLineStrings(
                lat_lon=[_latlon(ll)], colors=[40, 220, 60], radii=rr.Radius.ui_points(2.5)
            ),
            static=True,
        )
    cam = data.drive.camera if data.drive is not None else None
    if cam is not None:
        for k in range(0, len(t), max(1, cfg.frustum_stride)):
            path = f"world/frusta/f{int(t.frame_indices[k]):06d}"
            _log_pose(rec, path, t.world_from_cam[k], static=True)
            rec.log(path, _pinhole(cam, cfg.frustum_size_m, (160, 160, 160)), static=True)
    return len(t)


def _pinhole(cam: Any, plane_m: float, color: Iterable[int] | None = None) -> rr.Pinhole:
    return rr.Pinhole(
        image_from_camera=cam.K,
        resolution=[cam.width, cam.height],
        camera_xyz=rr.ViewCoordinates.RDF,  # x right, y down the image (backward), z optical axis
        image_plane_distance=plane_m,
        color=color,
    )


def _log_pose(rec: rr.RecordingStream, path: str, T: np.ndarray, static: bool = False) -> None:
    rec.log(path, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=static)


def log_mosaic(rec: rr.RecordingStream, data: RunData, cfg: ViewerConfig) -> bool:
    """Mosaic and colour-mapped surface, each with the defect outlines in pixel coordinates."""
    done = False
    if data.mosaic is not None:
        rec.log("mosaic/image", rr.Image(data.mosaic.data), static=True)
        _log_raster_outlines(rec, "mosaic/defects", data, data.mosaic.grid)
        done = True
    if data.surface is not None:
        surf = data.surface.data
        half = residual_half_range_m(surf, cfg.residual_range_percentile, cfg.min_residual_range_m)
        rgb = residual_rgb(surf.ravel(), half, cfg.colormap).reshape(*surf.shape, 3)
        rgb[~np.isfinite(surf)] = 0
        rec.log("surface/image", rr.Image(rgb), static=True)
        _log_raster_outlines(rec, "surface/defects", data, data.surface.grid)
        done = True
    return done


def _log_raster_outlines(rec: rr.RecordingStream, path: str, data: RunData, grid: Any) -> None:
    if not data.defects:
        return
    strips = []
    for d in data.defects:
        rc = rowcol_from_enu(data, grid, d.ring_enu_m)
        strips.append(rc[:, ::-1].astype(np.float32))  # (x=col, y=row)
    rec.log(
        path,
        rr.LineStrips2D(
            strips,
            colors=[severity_rgb(d.severity) for d in data.defects],
            labels=[d.label for d in data.defects],
            radii=rr.Radius.ui_points(1.5),
        ),
        static=True,
    )


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
        rec.log("world/camera", _pinhole(cam, cam.height_m, (255, 255, 255)), static=True)
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
            _log_pose(rec, "world/camera", traj.world_from_cam[pose_of[index]])
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


def _float_or_nan(v: Any) -> float:
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
        _log_pose(rec, "world/camera", t.world_from_cam[k])
        n += 1
    return n


def log_frame_overlays(rec: rr.RecordingStream, pair: Any, side: str, cfg: ViewerConfig) -> None:
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
    outlines: list[tuple[Any, np.ndarray]],
    world_from_cam: np.ndarray,
    cam: Any,
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


def _log_mask(rec: rr.RecordingStream, data: RunData, name: str, cam: Any) -> None:
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
    pair: Any,
    traj: Any,
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


def summary_markdown(data: RunData, counts: dict[str, int]) -> str:
    r = data.report
    c = r.get("counts", {})
    lines = [
        "# roadsurf run",
        f"- run folder: `{data.run_dir}`",
        f"- drive: `{r.get('drive', '?')}`",
        f"- CRS: {data.crs or 'local ENU (no GPS)'}",
        f"- frames: {c.get('frames', '?')}, posed: {counts.get('posed_frames', 0)}, "
        f"pairs ok/failed: {c.get('pairs_ok', '?')}/{c.get('pairs_failed', '?')}",
        f"- cloud points shown: {counts.get('cloud_points', 0)}",
        f"- defects: {counts.get('defects', 0)}",
        "",
        "Colours: the cloud is coloured by residual height (red below the road, blue above; "
        "see the legend). Defects: red high, orange medium, yellow low severity.",
    ]
    if data.defects:
        lines += ["", "| id | type | depth mm | area m² | severity |", "|---|---|---|---|---|"]
        for d in data.defects[:50]:
            lines.append(
                f"| {d.id} | {d.type} | {1000 * d.max_depth_m:.1f} | "
                f"{d.area_m2:.3f} | {d.severity} |"
            )
    if data.missing:
        lines += ["", "Not in this run folder: " + ", ".join(data.missing)]
    return "\n".join(lines)


def log_run(rec: rr.RecordingStream, data: RunData, cfg: ViewerConfig) -> dict[str, int]:
    """Log everything in ``data``; returns counts of what was logged."""
    log_setup(rec)
    counts = {
        "cloud_points": log_cloud(rec, data, cfg),
        "defects": log_defects(rec, data, cfg),
        "posed_frames": log_trajectory(rec, data, cfg),
        "mosaic": int(log_mosaic(rec, data, cfg)),
    }
    counts["frames"] = log_frames(rec, data, cfg)
    rec.log(
        "summary",
        rr.TextDocument(summary_markdown(data, counts), media_type=rr.MediaType.MARKDOWN),
        static=True,
    )
    return counts


def overview_eye(data: RunData) -> rrb.EyeControls3D | None:
    """A 3D camera that looks at the whole cloud (or path) obliquely from the south."""
    pts = data.cloud_enu_m
    if pts is None or len(pts) == 0:
        pts = data.trajectory.positions_enu_m if data.trajectory is not None else None
    if pts is None or len(pts) == 0:
        return None
    lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
    centre = (lo + hi) / 2
    span = float(np.clip(np.max(hi[:2] - lo[:2]), 2.0, 40.0))
    return rrb.EyeControls3D(
        kind=rrb.Eye3DKind.Orbital,
        position=centre + np.array([0.0, -0.55 * span, 0.75 * span]),
        look_target=centre,
        eye_up=[0.0, 0.0, 1.0],
    )


def map_zoom(data: RunData, view_px: float = 400.0) -> float:
    """Web-map zoom level that fits the GPS track / path into about ``view_px`` pixels."""
    pts = gps_enu_m(data)
    if pts is None and data.trajectory is not None and len(data.trajectory):
        pts = data.trajectory.positions_enu_m
    if pts is None or len(pts) < 2 or data.reference is None:
        return 18.0
    extent = max(5.0, float(np.max(np.ptp(pts[:, :2], axis=0))))
    m_per_px_z0 = 156543.03 * math.cos(math.radians(data.reference.lat_deg))
    return float(np.clip(math.log2(m_per_px_z0 * view_px / extent), 3.0, 19.0))


def layout_for(data: RunData) -> rrb.Blueprint:
    """The default blueprint fitted to a run (3D eye over the cloud, map zoom over the track)."""
    return blueprint(data.defects, overview_eye(data), map_zoom(data))


def blueprint(
    defects: list[DefectView] | None = None,
    eye: rrb.EyeControls3D | None = None,
    zoom: float = 18.0,
) -> rrb.Blueprint:
    """Default layout: 3D map left; map / mosaic tabs, current frame and plots right."""
    profile_tabs = [
        rrb.BarChartView(name=f"Profile #{d.id} (mm)", origin=f"profiles/{_safe(d.id)}")
        for d in (defects or [])[:MAX_PROFILE_TABS]
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(
                    name="3D map (ENU m, residual colours)",
                    origin="world",
                    contents=["+ world/**", "- world/cloud_rgb"],
                    eye_controls=eye,
                    background=[28, 30, 36],  # dark: the white flat road and red/blue stand out
                ),
                rrb.Horizontal(
                    rrb.Spatial2DView(name="Residual legend", origin="legend"),
                    rrb.TextDocumentView(name="Summary", origin="summary"),
                    column_shares=[1, 2],
                ),
                row_shares=[4, 1],
            ),
            rrb.Vertical(
                rrb.Tabs(
                    rrb.MapView(name="Map", origin="map", zoom=zoom),
                    rrb.Spatial2DView(name="Mosaic", origin="mosaic"),
                    rrb.Spatial2DView(name="Surface residual", origin="surface"),
                    active_tab=0,
                ),
                rrb.Spatial2DView(name="Current frame", origin="world/camera"),
                rrb.Tabs(
                    rrb.TimeSeriesView(name="Per-frame", origin="frames"),
                    rrb.TextDocumentView(name="Frame", origin="frames/info"),
                    rrb.TextLogView(name="Warnings", origin="log"),
                    *profile_tabs,
                ),
                row_shares=[3, 3, 2],
            ),
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline="frame", state="collapsed"),
    )
