"""Ground truth written beside a simulated drive (DRIVE/truth/), see docs/simulator.md.

- scenario.json, height.tif, residual.tif (float32, scenario UTM CRS, nodata NaN outside the
  corridor the camera saw), defects.geojson, distractors.geojson (RFC 7946, WGS84),
  poses.csv, frame_labels.csv.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon, box
from shapely.prepared import prep

from roadsurf.core.geometry import forward_in_cam, lla_from_utm
from roadsurf.io import drivefolder as df
from roadsurf.io.formats import (
    GridSpec,
    feature,
    polygon_geometry,
    write_csv,
    write_geojson,
    write_geotiff_blocks,
)
from roadsurf.simulation.defects import Pothole, Trough
from roadsurf.simulation.route import Pose
from roadsurf.simulation.world import World

BLOCK = 256
# frame label: footprint area deeper than render.LABEL_DEPTH_M of at least this makes a defect
# frame (20 cm^2)
DEFECT_AREA_M2 = 0.0020

POSE_HEADER = [
    "filename", "timestamp_s", "easting_m", "northing_m", "up_m", "lat_deg", "lon_deg", "alt_m",
    "heading_deg", "roll_deg", "pitch_deg", "qw", "qx", "qy", "qz",
]  # fmt: skip


def quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion (w, x, y, z) with w >= 0."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return -q if q[0] < 0 else q


def true_heading_deg(world: World, C: np.ndarray, R: np.ndarray) -> float:
    """Compass heading of the vehicle's forward direction relative to TRUE north (grid heading
    + meridian convergence); R is world_from_cam, the mount included."""
    cfg = world.cfg
    fwd = R @ forward_in_cam(cfg.vehicle_from_cam()) if cfg.mounted else -R[:, 1]
    fwd = fwd[:2] / max(1e-12, float(np.hypot(fwd[0], fwd[1])))
    pts = np.array([C[:2], C[:2] + fwd])
    ll = lla_from_utm(pts[:, 0] + world.origin_e_m, pts[:, 1] + world.origin_n_m, world.epsg)
    from pyproj import Geod

    az, _, _ = Geod(ellps="WGS84").inv(ll[0, 1], ll[0, 0], ll[1, 1], ll[1, 0])
    return float(az % 360.0)


def corridor_polygon(footprints: list[np.ndarray], pad_m: float = 0.05) -> Polygon | MultiPolygon:
    """Union of the frames' ground footprints (local metres), padded."""
    polys = [Polygon(fp) for fp in footprints]
    return shapely.union_all(polys).buffer(pad_m).simplify(0.005)


def _fill(mask: np.ndarray, geom, x0: float, y_top: float, gsd: float) -> None:
    geoms = [geom] if isinstance(geom, Polygon) else list(getattr(geom, "geoms", []))
    for g in geoms:
        if g.is_empty or not isinstance(g, Polygon):
            continue
        rings = [np.asarray(g.exterior.coords)] + [np.asarray(i.coords) for i in g.interiors]
        pts = []
        for ring in rings:
            px = np.column_stack([(ring[:, 0] - x0) / gsd - 0.5, (y_top - ring[:, 1]) / gsd - 0.5])
            pts.append(np.round(px * 16).astype(np.int32))
        cv2.fillPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=4)


def write_rasters(world: World, corridor, out: Path) -> GridSpec:
    """height.tif and residual.tif over the corridor, evaluated and written block by block."""
    g = world.cfg.truth_gsd_m
    xmin, ymin, xmax, ymax = corridor.bounds
    # Align the grid to multiples of the GSD in UTM metres.
    e0 = math.floor((xmin + world.origin_e_m) / g) * g
    n0 = math.ceil((ymax + world.origin_n_m) / g) * g
    width = int(math.ceil((xmax + world.origin_e_m - e0) / g))
    height = int(math.ceil((n0 - (ymin + world.origin_n_m)) / g))
    grid = GridSpec(world.crs, e0, n0, g, width, height)
    lx0, ly0 = e0 - world.origin_e_m, n0 - world.origin_n_m  # grid corner in local metres
    prepared = prep(corridor)
    alt0 = world.cfg.origin_alt_m

    def block_fields(r0: int, c0: int) -> tuple[np.ndarray, np.ndarray] | None:
        h, w = min(BLOCK, height - r0), min(BLOCK, width - c0)
        bx0, by_top = lx0 + c0 * g, ly0 - r0 * g
        if not prepared.intersects(box(bx0, by_top - h * g, bx0 + w * g, by_top)):
            return None
        mask = np.zeros((h, w), np.uint8)
        _fill(
            mask,
            corridor.intersection(
                box(bx0 - g, by_top - (h + 1) * g, bx0 + (w + 1) * g, by_top + g)
            ),
            bx0,
            by_top,
            g,
        )
        if not mask.any():
            return None
        f = world.evaluate(bx0, by_top, g, h, w, appearance=False)
        m = mask.astype(bool)
        hgt = np.where(m, f["height"].astype(np.float64) + alt0, np.nan).astype(np.float32)
        res = np.where(m, f["height"] - f["base"], np.nan).astype(np.float32)
        return hgt, res

    blocks = [(r0, c0) for r0 in range(0, height, BLOCK) for c0 in range(0, width, BLOCK)]
    computed: dict[tuple[int, int], tuple[np.ndarray, np.ndarray] | None] = {}

    def gen(which: int) -> Iterator[tuple[int, int, np.ndarray]]:
        for r0, c0 in blocks:
            if which == 0:
                v = block_fields(r0, c0)
                # Keep only the residual for the second pass (memory ~ corridor, float32).
                computed[(r0, c0)] = None if v is None else (None, v[1])  # type: ignore[assignment]
                if v is not None:
                    yield r0, c0, v[0]
            else:
                v = computed.pop((r0, c0), None)
                if v is not None:
                    yield r0, c0, v[1]

    tags = {"units": "m", "datum": "WGS84 ellipsoidal height", "source": "roadsurf simulator"}
    write_geotiff_blocks(out / df.TRUTH_HEIGHT_TIF, grid, gen(0), nodata=float("nan"), tags=tags)
    tags_r = dict(tags, meaning="height minus the smooth road surface; negative below the road")
    write_geotiff_blocks(
        out / df.TRUTH_RESIDUAL_TIF, grid, gen(1), nodata=float("nan"), tags=tags_r
    )
    return grid


def _measure_grid(
    fn, bbox, gsd: float = 0.001
) -> tuple[float, float, float, float, Polygon | None]:
    """Measure a defect from its depth function on a fine grid: max depth, mean depth over the
    outline (depth > 0), area (m^2), volume (m^3) and the outline polygon (the rim contour)."""
    from skimage.measure import find_contours

    x0, y0, x1, y1 = bbox
    xs = np.arange(x0, x1, gsd) + gsd / 2
    ys = np.arange(y0, y1, gsd) + gsd / 2
    X, Y = np.meshgrid(xs, ys)
    d = fn(X, Y)
    inside = d > 0
    if not inside.any():
        return 0.0, 0.0, 0.0, 0.0, None
    padded = np.pad(inside.astype(np.float32), 1)
    best = max(find_contours(padded, 0.5), key=len)
    ring = np.column_stack([x0 + (best[:, 1] - 1 + 0.5) * gsd, y0 + (best[:, 0] - 1 + 0.5) * gsd])
    poly = Polygon(ring).buffer(0).simplify(0.5 * gsd)
    if isinstance(poly, MultiPolygon):
        poly = max(poly.geoms, key=lambda g: g.area)
    return (
        float(d.max()),
        float(d[inside].mean()),
        float(inside.sum() * gsd * gsd),
        float(d.sum() * gsd * gsd),
        poly,
    )


def _length_width(poly: Polygon) -> tuple[float, float]:
    r = poly.minimum_rotated_rectangle
    xy = np.asarray(r.exterior.coords)[:4]
    a = float(np.hypot(*(xy[1] - xy[0])))
    b = float(np.hypot(*(xy[2] - xy[1])))
    return max(a, b), min(a, b)


def _props(
    world: World,
    idx: str,
    kind: str,
    poly: Polygon,
    mx: float,
    mean: float,
    area: float,
    vol: float,
    length: float | None = None,
    width: float | None = None,
) -> dict[str, Any]:
    c = poly.centroid
    L, W = _length_width(poly)
    lonlat = world.lonlat_from_local(np.array([[c.x, c.y]]))[0]
    return {
        "id": idx,
        "type": kind,
        "max_depth_m": round(mx, 5),
        "mean_depth_m": round(mean, 5),
        "area_m2": round(area, 6),
        "volume_m3": round(vol, 8),
        "length_m": round(length if length is not None else L, 4),
        "width_m": round(width if width is not None else W, 4),
        "centroid_lon": round(float(lonlat[0]), 9),
        "centroid_lat": round(float(lonlat[1]), 9),
        "centroid_e_m": round(c.x + world.origin_e_m, 4),
        "centroid_n_m": round(c.y + world.origin_n_m, 4),
    }


def defect_features(world: World) -> list[dict[str, Any]]:
    feats = []
    items: list[Pothole | Trough] = [*world.potholes, *world.troughs]
    for i, d in enumerate(items):
        if isinstance(d, Pothole):
            mx, mean, area, vol, poly = _measure_grid(d.depth, d.bbox(0.002))
            if poly is None:
                continue
            props = _props(world, f"D{i + 1:03d}", "pothole", poly, mx, mean, area, vol)
        else:
            line = shapely.LineString(d.line.array)
            cap = "round" if d.kind == "crack" else "flat"
            poly = line.buffer(d.line.width / 2, cap_style=cap, quad_segs=4)
            if d.kind == "crack":
                mean = d.depth_m * 2.0 / 3.0  # parabolic cross-section
            else:
                L = d.line.length
                a = np.linspace(0, L, 2001)
                r = np.clip(np.minimum(a, L - a) / d.taper_m, 0, 1)
                mean = d.depth_m * 8.0 / 15.0 * float(np.mean(r * r * (3 - 2 * r)))
            props = _props(
                world,
                f"D{i + 1:03d}",
                d.kind,
                poly,
                d.depth_m,
                mean,
                poly.area,
                mean * poly.area,
                d.line.length,
                d.line.width,
            )
        ring = world.lonlat_from_local(np.asarray(poly.exterior.coords))
        feats.append(feature(polygon_geometry(ring), props))
    return feats


def distractor_features(world: World) -> list[dict[str, Any]]:
    feats = []
    for i, d in enumerate(world.distractors):
        poly = Polygon(d.shape.outline())
        props = _props(world, f"X{i + 1:03d}", d.kind, poly, 0.0, 0.0, poly.area, 0.0)
        ring = world.lonlat_from_local(np.asarray(poly.exterior.coords))
        feats.append(feature(polygon_geometry(ring), props))
    return feats


def write_features(world: World, out: Path) -> None:
    meta = {"crs_of_e_n": world.crs, "scenario_seed": world.seed}
    write_geojson(out / df.TRUTH_DEFECTS_GEOJSON, defect_features(world), meta)
    write_geojson(out / df.TRUTH_DISTRACTORS_GEOJSON, distractor_features(world), meta)


def write_poses(
    world: World, out: Path, rows: list[tuple[str, Pose]], time_offset_s: float = 0.0
) -> None:
    """rows: (filename, Pose) per frame; ``time_offset_s`` is added to the timestamps (the
    drive's clock, see sensors.time_offset_s)."""
    data = []
    for name, p in rows:
        e, n = p.C[0] + world.origin_e_m, p.C[1] + world.origin_n_m
        lat, lon = lla_from_utm(np.array([e]), np.array([n]), world.epsg)[0]
        up = p.C[2] + world.cfg.origin_alt_m
        q = quat_wxyz(p.R)
        data.append([
            name, round(p.t + time_offset_s, 6), round(e, 4), round(n, 4), round(up, 5), round(lat, 9),
            round(lon, 9), round(up, 5), round(true_heading_deg(world, p.C, p.R), 5),
            round(math.degrees(p.roll_rad), 5), round(math.degrees(p.pitch_rad), 5),
            *[round(float(v), 9) for v in q],
        ])  # fmt: skip
    write_csv(out / df.TRUTH_POSES_CSV, POSE_HEADER, data)


def write_frame_labels(out: Path, rows: list[tuple[str, float, float]]) -> None:
    """rows: (filename, defect_area_m2, max_depth_m)."""
    data = [
        [name, int(area >= DEFECT_AREA_M2), round(area * 1e4, 3), round(max(mx, 0.0), 5)]
        for name, area, mx in rows
    ]
    write_csv(
        out / df.TRUTH_FRAME_LABELS_CSV,
        ["filename", "defect", "defect_area_cm2", "max_depth_m"],
        data,
    )
