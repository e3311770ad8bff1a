"""The static part of a recording: the cloud, the defects (3D, map and profiles), the path with
its GPS fixes and camera frusta, and the mosaic/surface images. Entity paths in ``recording``'s
docstring; 3D in local ENU metres (x east, y north, z up)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np
import rerun as rr

from roadsurf.io.formats import GridSpec
from roadsurf.viewer.colors import legend_png, residual_half_range_m, residual_rgb
from roadsurf.viewer.config import ViewerConfig
from roadsurf.viewer.derived import gps_enu_m, road_height_near, rowcol_from_enu
from roadsurf.viewer.profile import depth_profile
from roadsurf.viewer.rundata import RunData, severity_rgb

if TYPE_CHECKING:
    from roadsurf.core.camera import Camera


def latlon(lonlat: np.ndarray) -> np.ndarray:
    return np.asarray(lonlat, float)[:, ::-1]


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
                lat_lon=latlon(cent),
                colors=[severity_rgb(d.severity) for d in geo],
                radii=rr.Radius.ui_points(7.0),
            ),
            static=True,
        )
        rec.log(
            "map/defect_outlines",
            rr.GeoLineStrings(
                lat_lon=[latlon(d.ring_lonlat) for d in geo],
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
            f"profiles/{entity_part(d.id)}",
            rr.BarChart(
                np.nan_to_num(1000.0 * res_m),
                abscissa=100.0 * dist_m,
                color=severity_rgb(d.severity),
            ),
            static=True,
        )
    return len(defects)


def entity_part(s: str) -> str:
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
                lat_lon=[latlon(ll)], colors=[40, 220, 60], radii=rr.Radius.ui_points(2.5)
            ),
            static=True,
        )
    cam = data.drive.camera if data.drive is not None else None
    if cam is not None:
        for k in range(0, len(t), max(1, cfg.frustum_stride)):
            path = f"world/frusta/f{int(t.frame_indices[k]):06d}"
            log_pose(rec, path, t.world_from_cam[k], static=True)
            rec.log(path, pinhole(cam, cfg.frustum_size_m, (160, 160, 160)), static=True)
    return len(t)


def pinhole(cam: Camera, plane_m: float, color: Iterable[int] | None = None) -> rr.Pinhole:
    return rr.Pinhole(
        image_from_camera=cam.K,
        resolution=[cam.width, cam.height],
        camera_xyz=rr.ViewCoordinates.RDF,  # x right, y down the image (backward), z optical axis
        image_plane_distance=plane_m,
        color=color,
    )


def log_pose(rec: rr.RecordingStream, path: str, T: np.ndarray, static: bool = False) -> None:
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


def _log_raster_outlines(rec: rr.RecordingStream, path: str, data: RunData, grid: GridSpec) -> None:
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
