"""Read a run folder (the output contract of ``roadsurf run``) for the viewer and the report.

Everything is optional: a run killed half-way, a drive without GPS or a run without defects
still loads, and the missing pieces are listed in ``RunData.missing``. Coordinates are converted
to the local ENU frame (metres, float64) around the run's saved reference, so nothing is drawn
in UTM (float32 would lose millimetres there).

Files read (see docs/viewer.md): report.json, reference.json + poses.npz, map_points.npz or
cloud.ply, defects.geojson, frames.csv, pairs/*.npz, mosaic.tif, surface.tif, masks/*.png and
the drive folder named in report.json (camera.yaml, frames, GPS) when it still exists.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core.atomic import read_json
from roadsurf.core.errors import RoadsurfError
from roadsurf.core.geometry import (
    EnuReference,
    ExportFrame,
    enu_from_lla,
    lla_from_enu,
    lla_from_utm,
)
from roadsurf.io.formats import GridSpec, read_csv, read_ply, validate_geojson

log = logging.getLogger(__name__)

SEVERITY_RANK = {"high": 3, "medium": 2, "low": 1}
SEVERITY_RGB = {
    "high": (220, 30, 30),
    "medium": (255, 140, 0),
    "low": (240, 210, 40),
}
UNKNOWN_RGB = (150, 150, 150)


def severity_rank(sev: Any) -> int:
    """Sort key of a severity label (high > medium > low > anything else)."""
    s = str(sev).strip().lower()
    s = {"h": "high", "m": "medium", "l": "low"}.get(s, s)
    if s in SEVERITY_RANK:
        return SEVERITY_RANK[s]
    try:  # numeric severities (1..3) sort by value
        return int(float(s))
    except ValueError:
        return 0


def severity_rgb(sev: Any) -> tuple[int, int, int]:
    s = str(sev).strip().lower()
    s = {"h": "high", "m": "medium", "l": "low"}.get(s, s)
    return SEVERITY_RGB.get(s, UNKNOWN_RGB)


@dataclass
class DefectView:
    """One defect as the viewer needs it (ENU metres, lon/lat when georeferenced)."""

    id: str
    type: str
    severity: str
    max_depth_m: float
    mean_depth_m: float
    area_m2: float
    volume_m3: float
    length_m: float
    width_m: float
    confidence: float
    ring_enu_m: np.ndarray  # (K, 2) closed outline, east/north (m)
    ring_lonlat: np.ndarray | None  # (K, 2) lon/lat degrees, None without GPS
    frames: list[str] = field(default_factory=list)

    @property
    def centroid_enu_m(self) -> np.ndarray:
        return self.ring_enu_m[:-1].mean(axis=0) if len(self.ring_enu_m) > 1 else self.ring_enu_m[0]

    @property
    def label(self) -> str:
        return (
            f"#{self.id} {self.type} {1000 * self.max_depth_m:.0f} mm "
            f"{self.area_m2:.3f} m² {self.severity}"
        )


@dataclass
class Raster:
    """A (possibly decimated) GeoTIFF: data is (H, W) float32 with NaN nodata or (H, W, 3) uint8."""

    data: np.ndarray
    grid: GridSpec  # grid of ``data`` (gsd already scaled by the decimation)
    path: Path


@dataclass
class RunData:
    """Everything the viewer found in a run folder. ``None`` means the file is absent."""

    run_dir: Path
    report: dict[str, Any]
    reference: EnuReference | None
    crs: str | None
    trajectory: Any | None  # mapping.types.Trajectory
    cloud_enu_m: np.ndarray | None  # (N, 3) float64
    cloud_rgb: np.ndarray | None  # (N, 3) uint8
    cloud_residual_m: np.ndarray | None  # (N,) float
    defects: list[DefectView]
    frame_labels: dict[str, dict[str, str]]  # filename -> row of frames.csv
    pairs: list[Any]  # reconstruction.types.PairResult, sorted by index_a
    mosaic: Raster | None
    surface: Raster | None
    masks: dict[str, Path]  # frame filename (stem) -> refined 2D defect mask image
    drive: Any | None  # roadsurf.io.drive.Drive
    missing: list[str] = field(default_factory=list)

    @functools.cached_property
    def cloud_tree_xy(self) -> Any:
        """KD-tree (scipy cKDTree) of the cloud's east/north coordinates."""
        from scipy.spatial import cKDTree

        xy = self.cloud_enu_m[:, :2] if self.cloud_enu_m is not None else np.zeros((0, 2))
        return cKDTree(xy)

    @property
    def export_frame(self) -> ExportFrame | None:
        return None if self.reference is None else ExportFrame.for_reference(self.reference)

    def lonlat_from_enu(self, enu_m: np.ndarray) -> np.ndarray | None:
        """(N, 2|3) ENU -> (N, 2) lon/lat, or None without a reference."""
        ef = self.export_frame
        return None if ef is None else ef.lonlat_from_enu(enu_m)


# --------------------------------------------------------------------------- loading


def load_run(
    run_dir: str | Path,
    drive_dir: str | Path | None = None,
    *,
    with_pairs: bool = True,
    max_raster_side_px: int = 2048,
) -> RunData:
    """Read a run folder. ``drive_dir`` overrides the drive path recorded in report.json.

    Raises ``RoadsurfError`` when ``run_dir`` is not a folder; every single file is optional.
    """
    run = Path(run_dir)
    if not run.is_dir():
        raise RoadsurfError(
            f"{run}: run folder not found. Pass the --out folder of `roadsurf run DRIVE --out OUT`."
        )
    missing: list[str] = []
    report = _read_optional_json(run / "report.json", missing) or {}
    traj = _load_trajectory(run, missing)
    reference = _reference(run, report, traj)
    crs = report.get("crs") or _reference_crs(run)
    cloud, rgb, resid = _load_cloud(run, crs, reference, missing)
    defects = _load_defects(run, reference, missing)
    labels = _load_frame_labels(run, missing)
    pairs = _load_pairs(run, missing) if with_pairs else []
    mosaic = _load_raster(run / "mosaic.tif", max_raster_side_px, missing)
    surface = _load_raster(run / "surface.tif", max_raster_side_px, missing)
    masks = _find_masks(run)
    drive = _load_drive(drive_dir if drive_dir is not None else report.get("drive"), missing)
    return RunData(
        run_dir=run,
        report=report,
        reference=reference,
        crs=crs,
        trajectory=traj,
        cloud_enu_m=cloud,
        cloud_rgb=rgb,
        cloud_residual_m=resid,
        defects=defects,
        frame_labels=labels,
        pairs=pairs,
        mosaic=mosaic,
        surface=surface,
        masks=masks,
        drive=drive,
        missing=missing,
    )


def _read_optional_json(path: Path, missing: list[str]) -> Any | None:
    if not path.exists():
        missing.append(path.name)
        return None
    return read_json(path)


def _load_trajectory(run: Path, missing: list[str]) -> Any | None:
    from roadsurf.mapping.types import load_trajectory

    if not (run / "poses.npz").exists() or not (run / "reference.json").exists():
        missing.append("poses.npz")
        return None
    return load_trajectory(run)


def _reference(run: Path, report: dict[str, Any], traj: Any | None) -> EnuReference | None:
    if traj is not None and traj.reference is not None:
        return traj.reference
    ref = report.get("reference")
    if isinstance(ref, dict) and "lat_deg" in ref:
        return EnuReference.from_dict(ref)
    return None


def _reference_crs(run: Path) -> str | None:
    p = run / "reference.json"
    if not p.exists():
        return None
    ref = read_json(p).get("reference") or {}
    return ref.get("crs")


def enu_from_crs(xyz: np.ndarray, crs: str | None, reference: EnuReference | None) -> np.ndarray:
    """(N, 3) points in the export CRS (UTM easting, northing, height) -> local ENU (metres).

    Without a CRS or reference the points are already local ENU (a run without GPS)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if crs is None or reference is None or len(xyz) == 0:
        return xyz
    epsg = int(str(crs).split(":")[-1])
    latlon = lla_from_utm(xyz[:, 0], xyz[:, 1], epsg)
    enu = enu_from_lla(latlon[:, 0], latlon[:, 1], xyz[:, 2], reference)
    # exports write height = ENU up + reference altitude (ExportFrame.utm_from_enu), not the
    # ellipsoidal height, so undo exactly that instead of Earth curvature (mm over 100 m)
    enu[:, 2] = xyz[:, 2] - reference.alt_m
    return enu


def _load_cloud(
    run: Path, crs: str | None, reference: EnuReference | None, missing: list[str]
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    npz = run / "map_points.npz"
    if npz.exists():
        with np.load(npz, allow_pickle=False) as z:
            keys = set(z.files)
            key = next(
                (k for k in ("xyz_enu_m", "xyz", "enu_m", "points_enu_m") if k in keys), None
            )
            if key is not None:
                xyz = np.asarray(z[key], dtype=np.float64)
                rgb = np.asarray(z["rgb"], dtype=np.uint8) if "rgb" in keys else None
                res = np.asarray(z["residual_m"], dtype=float) if "residual_m" in keys else None
                return xyz, rgb, res
            log.warning("%s has no ENU point array (keys %s); trying cloud.ply", npz, sorted(keys))
    ply = run / "cloud.ply"
    if ply.exists():
        d = read_ply(ply)
        res = d.get("residual_m")
        return (
            enu_from_crs(d["xyz"], crs, reference),
            d.get("rgb"),
            None if res is None else np.asarray(res, float),
        )
    missing.append("cloud.ply")
    return None, None, None


def _ring_enu(coords: np.ndarray, georef: bool, reference: EnuReference | None) -> np.ndarray:
    c = np.asarray(coords, float)[:, :2]
    if not georef:
        return c
    if reference is None:
        # lon/lat but no saved reference: use the ring's own first vertex (local view only)
        reference = EnuReference(float(c[0, 1]), float(c[0, 0]), 0.0)
    return enu_from_lla(c[:, 1], c[:, 0], 0.0, reference)[:, :2]


def _fnum(props: dict[str, Any], key: str) -> float:
    v = props.get(key)
    try:
        return float(v) if v is not None else math.nan
    except (TypeError, ValueError):
        return math.nan


def _load_defects(
    run: Path, reference: EnuReference | None, missing: list[str]
) -> list[DefectView]:
    path = run / "defects.geojson"
    if not path.exists():
        missing.append("defects.geojson")
        return []
    fc = read_json(path)
    georef = bool((fc.get("properties") or {}).get("georeferenced", True))
    if georef:
        validate_geojson(fc)  # lon/lat; without GPS detection writes local ENU metres instead
    out: list[DefectView] = []
    for i, f in enumerate(fc["features"]):
        g = f.get("geometry") or {}
        p = f.get("properties") or {}
        if g.get("type") == "Polygon":
            ring = np.asarray(g["coordinates"][0], float)
        elif g.get("type") == "MultiPolygon":
            ring = np.asarray(g["coordinates"][0][0], float)
        elif g.get("type") == "Point":
            ring = np.asarray([g["coordinates"]], float)
        else:
            log.warning("%s: feature %d has geometry %s; skipped", path, i, g.get("type"))
            continue
        enu = _ring_enu(ring, georef, reference)
        out.append(
            DefectView(
                id=str(p.get("id", i + 1)),
                type=str(p.get("type", "defect")),
                severity=str(p.get("severity", "unknown")),
                max_depth_m=_fnum(p, "max_depth_m"),
                mean_depth_m=_fnum(p, "mean_depth_m"),
                area_m2=_fnum(p, "area_m2"),
                volume_m3=_fnum(p, "volume_m3"),
                length_m=_fnum(p, "length_m"),
                width_m=_fnum(p, "width_m"),
                confidence=_fnum(p, "confidence"),
                ring_enu_m=enu,
                ring_lonlat=ring[:, :2] if georef else None,
                frames=[str(x) for x in (p.get("frames") or [])],
            )
        )
    return sort_defects(out)


def sort_defects(defects: list[DefectView]) -> list[DefectView]:
    """Most severe first, then deepest first."""
    return sorted(
        defects,
        key=lambda d: (
            -severity_rank(d.severity),
            -(d.max_depth_m if math.isfinite(d.max_depth_m) else -1.0),
        ),
    )


def _load_frame_labels(run: Path, missing: list[str]) -> dict[str, dict[str, str]]:
    path = run / "frames.csv"
    if not path.exists():
        missing.append("frames.csv")
        return {}
    return {row["filename"]: row for row in read_csv(path) if row.get("filename")}


def _load_pairs(run: Path, missing: list[str]) -> list[Any]:
    from roadsurf.reconstruction.types import load_pair

    folder = run / "pairs"
    files = sorted(folder.glob("*.npz")) if folder.is_dir() else []
    if not files:
        missing.append("pairs/")
        return []
    pairs = []
    for f in files:
        try:
            pairs.append(load_pair(f))
        except (OSError, KeyError, ValueError) as e:  # a foreign or half-written file
            log.warning("%s: not a pair result (%s); skipped", f, e)
    return sorted(pairs, key=lambda p: (int(p.index_a), int(p.index_b)))


def _load_raster(path: Path, max_side: int, missing: list[str]) -> Raster | None:
    """Read a GeoTIFF decimated so its longest side is <= max_side (nearest neighbour)."""
    if not path.exists():
        missing.append(path.name)
        return None
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(path) as src:
        f = max(1, math.ceil(max(src.width, src.height) / max(1, max_side)))
        w, h = max(1, src.width // f), max(1, src.height // f)
        win = Window(0, 0, min(src.width, w * f), min(src.height, h * f))
        arr = src.read(window=win, out_shape=(src.count, h, w))
        t = src.transform
        nodata = src.nodata
        grid = GridSpec(str(src.crs) if src.crs else "", t.c, t.f, t.a * f, w, h)
    if arr.shape[0] == 1:
        data = arr[0].astype(np.float32)
        if nodata is not None and not np.isnan(nodata):
            data[data == nodata] = np.nan
    else:
        data = np.moveaxis(arr[:3], 0, 2).astype(np.uint8)
    return crop_to_data(Raster(data=data, grid=grid, path=path))


def crop_to_data(r: Raster, margin_px: int = 8) -> Raster:
    """The raster cut to the bounding box of its observed pixels (+ margin); same if empty."""
    valid = np.isfinite(r.data) if r.data.ndim == 2 else np.any(r.data > 0, axis=2)
    rows, cols = np.nonzero(np.any(valid, axis=1))[0], np.nonzero(np.any(valid, axis=0))[0]
    if rows.size == 0:
        return r
    r0, r1 = max(0, rows[0] - margin_px), min(r.data.shape[0], rows[-1] + 1 + margin_px)
    c0, c1 = max(0, cols[0] - margin_px), min(r.data.shape[1], cols[-1] + 1 + margin_px)
    g = r.grid
    grid = GridSpec(g.crs, g.x0_m + c0 * g.gsd_m, g.y0_m - r0 * g.gsd_m, g.gsd_m, c1 - c0, r1 - r0)
    return Raster(r.data[r0:r1, c0:c1], grid, r.path)


def _find_masks(run: Path) -> dict[str, Path]:
    """Refined 2D defect masks saved by detection (RUN/masks/<frame stem>.png), if any."""
    folder = run / "masks"
    if not folder.is_dir():
        return {}
    return {p.stem: p for p in sorted(folder.iterdir()) if p.suffix.lower() in (".png", ".tif")}


def _load_drive(drive_dir: Any, missing: list[str]) -> Any | None:
    if not drive_dir:
        missing.append("drive (report.json names none; pass --drive)")
        return None
    root = Path(str(drive_dir))
    if not (root / "camera.yaml").exists():
        missing.append(f"drive {root} (not found; pass --drive)")
        return None
    from roadsurf.io.drive import load_drive

    try:
        return load_drive(root, check_images=False)
    except RoadsurfError as e:
        log.warning("drive %s could not be loaded (%s); images and GPS are left out", root, e)
        missing.append(f"drive {root} ({e})")
        return None


# --------------------------------------------------------------------------- derived geometry


def gps_enu_m(data: RunData) -> np.ndarray | None:
    """(N, 3) GPS fixes in ENU (alt NaN -> reference altitude), or None."""
    d = data.drive
    if d is None or d.gps is None or len(d.gps) == 0 or data.reference is None:
        return None
    alt = np.where(np.isfinite(d.gps.alt_m), d.gps.alt_m, data.reference.alt_m)
    return enu_from_lla(d.gps.lat_deg, d.gps.lon_deg, alt, data.reference)


def road_height_near(data: RunData, east_north: np.ndarray, radius_m: float = 0.5) -> float:
    """Median cloud height around a point (m, ENU up); falls back to camera height below the
    nearest pose, then 0."""
    c = data.cloud_enu_m
    if c is not None and len(c):
        near = data.cloud_tree_xy.query_ball_point(np.asarray(east_north, float)[:2], radius_m)
        if len(near) >= 3:
            z = c[near, 2]
            if data.cloud_residual_m is not None:
                z = z - data.cloud_residual_m[near]  # the road surface, not the defect floor
            return float(np.median(z))
    t = data.trajectory
    if t is not None and len(t):
        pos = t.positions_enu_m
        k = int(np.argmin(np.sum((pos[:, :2] - east_north[None, :2]) ** 2, axis=1)))
        h = float(data.drive.camera.height_m) if data.drive is not None else 0.0
        return float(pos[k, 2] - h)
    return 0.0


def _profile_axis(defect: DefectView, margin: float) -> tuple[np.ndarray, ...] | None:
    """Centre, long axis, short axis, half length, half width (m) of a defect's outline."""
    if len(defect.ring_enu_m) < 4:
        return None
    ring = defect.ring_enu_m[:-1]
    c0 = ring.mean(axis=0)
    _, _, vt = np.linalg.svd(ring - c0, full_matrices=False)
    along = (ring - c0) @ vt[0]
    half_len = (along.max() - along.min()) / 2 * (1 + margin)
    if half_len <= 0:
        return None
    return c0, vt[0], vt[1], half_len, max(0.02, 0.15 * half_len)


def depth_profile(
    data: RunData, defect: DefectView, n_samples: int = 64, margin: float = 0.3
) -> tuple[np.ndarray, np.ndarray] | None:
    """Residual height (m) along the defect's long axis (``margin`` beyond the rim each side).

    Sampled from surface.tif at full resolution (mean across a 2 cm strip) when the run has it,
    else binned from the cloud points in a strip. Returns (distance_m (S,), residual_m (S,),
    NaN where unobserved) or None without data."""
    ax = _profile_axis(defect, margin)
    if ax is None:
        return None
    prof = _profile_from_surface(data, ax, n_samples)
    return prof if prof is not None else _profile_from_cloud(data, ax, n_samples)


def _profile_from_surface(
    data: RunData, ax: tuple[np.ndarray, ...], n: int
) -> tuple[np.ndarray, np.ndarray] | None:
    path = data.run_dir / "surface.tif"
    if data.surface is None or not path.exists():
        return None
    import rasterio
    from rasterio.windows import Window

    c0, axis, side, half_len, _ = ax
    s = np.linspace(-half_len, half_len, n)
    offsets = np.linspace(-0.01, 0.01, 5)  # a 2 cm strip across the axis
    pts = (c0 + s[:, None, None] * axis + offsets[None, :, None] * side).reshape(-1, 2)
    with rasterio.open(path) as src:
        t = src.transform
        grid = GridSpec(str(src.crs), t.c, t.f, t.a, src.width, src.height)
        rc = np.rint(rowcol_from_enu(data, grid, pts)).astype(int)
        r0, c0_ = rc.min(axis=0)
        r1, c1 = rc.max(axis=0) + 1
        r0, c0_ = max(r0, 0), max(c0_, 0)
        r1, c1 = min(r1, src.height), min(c1, src.width)
        if r1 <= r0 or c1 <= c0_:
            return None
        win = src.read(1, window=Window(c0_, r0, c1 - c0_, r1 - r0)).astype(float)
        nodata = src.nodata
    if nodata is not None and not np.isnan(nodata):
        win[win == nodata] = np.nan
    rr_, cc = rc[:, 0] - r0, rc[:, 1] - c0_
    ok = (rr_ >= 0) & (rr_ < win.shape[0]) & (cc >= 0) & (cc < win.shape[1])
    vals = np.full(len(rc), np.nan)
    vals[ok] = win[rr_[ok], cc[ok]]
    vals = vals.reshape(n, len(offsets))
    if not np.isfinite(vals).any():
        return None
    cnt = np.isfinite(vals).sum(axis=1)
    prof = np.where(cnt > 0, np.nansum(vals, axis=1) / np.maximum(cnt, 1), np.nan)
    return s + half_len, prof


def _profile_from_cloud(
    data: RunData, ax: tuple[np.ndarray, ...], n_samples: int
) -> tuple[np.ndarray, np.ndarray] | None:
    if data.cloud_enu_m is None or data.cloud_residual_m is None:
        return None
    c0, axis, side, half_len, half_w = ax
    cand = np.asarray(data.cloud_tree_xy.query_ball_point(c0, math.hypot(half_len, half_w)), int)
    if len(cand) < 3:
        return None
    rel = data.cloud_enu_m[cand, :2] - c0
    s, t = rel @ axis, rel @ side
    sel = (np.abs(s) <= half_len) & (np.abs(t) <= half_w)
    if np.count_nonzero(sel) < 3:
        return None
    edges = np.linspace(-half_len, half_len, n_samples + 1)
    idx = np.clip(np.digitize(s[sel], edges) - 1, 0, n_samples - 1)
    r = data.cloud_residual_m[cand[sel]]
    sums = np.bincount(idx, weights=r, minlength=n_samples)
    cnt = np.bincount(idx, minlength=n_samples)
    prof = np.full(n_samples, np.nan)
    prof[cnt > 0] = sums[cnt > 0] / cnt[cnt > 0]
    centres = (edges[:-1] + edges[1:]) / 2 + half_len
    return centres, prof


def defect_rings_3d(data: RunData) -> list[tuple[DefectView, np.ndarray]]:
    """(defect, (K, 3) ENU outline at the road surface) for every defect."""
    out = []
    for d in data.defects:
        z = road_height_near(data, d.centroid_enu_m)
        out.append((d, np.column_stack([d.ring_enu_m, np.full(len(d.ring_enu_m), z)])))
    return out


def project_to_image(
    world_from_cam: np.ndarray, cam: Any, pts_enu_m: np.ndarray
) -> np.ndarray | None:
    """(K, 3) ENU points -> (K, 2) pixels (u right, v down) of a pinhole camera (no distortion);
    None when any point is behind the camera or none falls inside the image."""
    from roadsurf.core.geometry import invert_pose, transform_points

    pc = transform_points(invert_pose(world_from_cam), pts_enu_m)
    if np.any(pc[:, 2] <= 1e-3):
        return None
    uv = (pc @ cam.K.T)[:, :2] / pc[:, 2:3]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    return uv if inside.any() else None


def rowcol_from_enu(data: RunData, grid: GridSpec, enu_m: np.ndarray) -> np.ndarray:
    """(N, 2|3) ENU -> (N, 2) float row, col on a raster grid in the run's export CRS."""
    enu = np.atleast_2d(np.asarray(enu_m, float))
    if enu.shape[1] == 2:
        enu = np.column_stack([enu, np.zeros(len(enu))])
    ef = data.export_frame
    xy = enu[:, :2] if ef is None else ef.utm_from_enu(enu)[:, :2]
    return grid.rowcol_from_xy(xy)


def lla_of_enu(data: RunData, enu_m: np.ndarray) -> np.ndarray | None:
    """(N, 3) ENU -> (N, 3) lat, lon, alt, or None without a reference."""
    return None if data.reference is None else lla_from_enu(enu_m, data.reference)
