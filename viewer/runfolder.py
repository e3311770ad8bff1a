"""Read a run folder (the output contract of ``roadsurf run``) for the viewer and the report.

Everything is optional: a run killed half-way, a drive without GPS or a run without defects
still loads, and the missing pieces are listed in ``RunData.missing``. Coordinates are converted
to the local ENU frame (metres, float64) around the run's saved reference, so nothing is drawn
in UTM (float32 would lose millimetres there).

Files read (see docs/viewer.md; names from ``roadsurf.io.runfolder``): report.json,
reference.json + poses.npz, map_points.npz or cloud.ply, defects.geojson, frames.csv,
pairs/*.npz, mosaic.tif, surface.tif, masks/*.png and the drive folder named in report.json
(camera.yaml, frames, GPS) when it still exists.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from roadsurf.core.atomic import read_json
from roadsurf.core.errors import InputError, RoadsurfError
from roadsurf.core.geometry import EnuReference, enu_from_lla, lla_from_utm
from roadsurf.detection.types import Defect
from roadsurf.io import drivefolder as df
from roadsurf.io.formats import GridSpec, read_csv, read_ply, validate_geojson
from roadsurf.io.runfolder import (
    CLOUD_PLY,
    DEFECTS_GEOJSON,
    FRAME_LABELS_CSV,
    MOSAIC_TIF,
    PAIRS_DIR,
    POSES_NPZ,
    REFERENCE_JSON,
    RunFolder,
)
from roadsurf.viewer.rundata import DefectView, Raster, RunData, sort_defects

if TYPE_CHECKING:
    from roadsurf.io.drive import Drive
    from roadsurf.mapping.types import Trajectory
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)


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
    run = RunFolder(run_dir)
    if not run.root.is_dir():
        raise RoadsurfError(
            f"{run.root}: run folder not found. Pass the --out folder of "
            "`roadsurf run DRIVE --out OUT`."
        )
    missing: list[str] = []
    report = _read_optional_json(run.report, missing) or {}
    traj = _load_trajectory(run, missing)
    reference = _reference(report, traj)
    crs = report.get("crs") or _reference_crs(run)
    cloud, rgb, resid = _load_cloud(run, crs, reference, missing)
    defects = _load_defects(run, reference, missing)
    labels = _load_frame_labels(run, missing)
    pairs = _load_pairs(run, missing) if with_pairs else []
    mosaic = _load_raster(run.path(MOSAIC_TIF), max_raster_side_px, missing)
    surface = _load_raster(run.surface_tif, max_raster_side_px, missing)
    masks = _find_masks(run)
    drive = _load_drive(drive_dir if drive_dir is not None else report.get("drive"), missing)
    return RunData(
        run_dir=run.root,
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
    return _read_run_json(path)


def _read_run_json(path: Path) -> dict[str, Any]:
    """A JSON object the run wrote; a truncated or edited file is an ``InputError`` (one line)
    that says how to rewrite it."""
    try:
        obj = read_json(path)
    except (ValueError, UnicodeDecodeError) as e:  # JSONDecodeError is a ValueError
        why = f"not valid JSON ({e})"
    except OSError as e:
        why = f"unreadable ({e.strerror or e})"
    else:
        if isinstance(obj, dict):
            return obj
        why = f"holds a JSON {type(obj).__name__}, not an object"
    raise InputError(
        f"{path}: {why}; it was cut short or edited. Run `roadsurf run DRIVE --out "
        f"{path.parent}` again (it resumes and rewrites it)."
    )


def _load_trajectory(run: RunFolder, missing: list[str]) -> Trajectory | None:
    from roadsurf.mapping.types import load_trajectory

    if not run.poses_npz.exists() or not run.path(REFERENCE_JSON).exists():
        missing.append(POSES_NPZ)
        return None
    return load_trajectory(run.root)


def _reference(report: dict[str, Any], traj: Trajectory | None) -> EnuReference | None:
    """The trajectory's ENU reference, else the one report.json names, else None."""
    if traj is not None and traj.reference is not None:
        return traj.reference
    ref = report.get("reference")
    if isinstance(ref, dict) and "lat_deg" in ref:
        return EnuReference.from_dict(ref)
    return None


def _reference_crs(run: RunFolder) -> str | None:
    p = run.path(REFERENCE_JSON)
    if not p.exists():
        return None
    ref = _read_run_json(p).get("reference") or {}
    return ref.get("crs")


def enu_from_crs(xyz: np.ndarray, crs: str | None, reference: EnuReference | None) -> np.ndarray:
    """(N, 3) points in the export CRS (UTM easting, northing, height) -> local ENU (metres).

    Without a CRS or reference the points are already local ENU (a run without GPS)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if crs is None or reference is None or len(xyz) == 0:
        return xyz
    epsg = int(str(crs).split(":")[-1])
    latlon = lla_from_utm(xyz[:, 0], xyz[:, 1], epsg)
    # exports write ellipsoidal heights (ExportFrame.utm_from_enu, through ECEF): the exact
    # inverse (the tangent plane leaves the ellipsoid by d² / 2R: 7.8 cm at 1 km)
    return enu_from_lla(latlon[:, 0], latlon[:, 1], xyz[:, 2], reference)


def _load_cloud(
    run: RunFolder, crs: str | None, reference: EnuReference | None, missing: list[str]
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    npz = run.map_points
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
    ply = run.cloud_ply
    if ply.exists():
        d = read_ply(ply)
        res = d.get("residual_m")
        return (
            enu_from_crs(d["xyz"], crs, reference),
            d.get("rgb"),
            None if res is None else np.asarray(res, float),
        )
    missing.append(CLOUD_PLY)
    return None, None, None


def _ring_enu(coords: np.ndarray, georef: bool, reference: EnuReference | None) -> np.ndarray:
    c = np.asarray(coords, float)[:, :2]
    if not georef:
        return c
    if reference is None:
        # lon/lat but no saved reference: use the ring's own first vertex (local view only)
        reference = EnuReference(float(c[0, 1]), float(c[0, 0]), 0.0)
    # at the road's height, not the ellipsoid's: the local vertical tilts by d / R, a ring
    # placed at height 0 moved sideways by h d / R (0.57 m at 1 km, 3,640 m up)
    return enu_from_lla(c[:, 1], c[:, 0], reference.alt_m, reference)[:, :2]


def _joined_enu(rings: list, georef: bool, reference: EnuReference | None) -> np.ndarray:
    """(N, 2) ENU exterior of the union of polygon parts (a defect RFC 7946 cut at ±180°: the
    parts meet again in ENU metres)."""
    import shapely

    polys = [shapely.Polygon(_ring_enu(np.asarray(r, float), georef, reference)) for r in rings]
    joined = shapely.union_all([p.buffer(1e-6) for p in polys])
    if joined.geom_type != "Polygon":
        joined = max(getattr(joined, "geoms", [joined]), key=lambda p: p.area)
    return np.asarray(joined.exterior.coords, float)


def _load_defects(
    run: RunFolder, reference: EnuReference | None, missing: list[str]
) -> list[DefectView]:
    path = run.defects_geojson
    if not path.exists():
        missing.append(DEFECTS_GEOJSON)
        return []
    fc = _read_run_json(path)
    georef = bool((fc.get("properties") or {}).get("georeferenced", True))
    if georef:
        validate_geojson(fc)  # lon/lat; without GPS detection writes local ENU metres instead
    out: list[DefectView] = []
    for i, f in enumerate(fc["features"]):
        g = f.get("geometry") or {}
        p = f.get("properties") or {}
        if g.get("type") == "Polygon":
            ring = np.asarray(g["coordinates"][0], float)
        elif g.get("type") == "MultiPolygon":  # one defect cut at the antimeridian
            ring = max((np.asarray(p[0], float) for p in g["coordinates"]), key=len)
        elif g.get("type") == "Point":
            ring = np.asarray([g["coordinates"]], float)
        else:
            log.warning("%s: feature %d has geometry %s; skipped", path, i, g.get("type"))
            continue
        enu = _ring_enu(ring, georef, reference)
        if g.get("type") == "MultiPolygon" and len(g["coordinates"]) > 1:
            enu = _joined_enu([p[0] for p in g["coordinates"]], georef, reference)
        out.append(
            DefectView(
                **Defect.fields_from_properties(p, default_id=i + 1),
                outline_xy_m=enu[:-1] if len(enu) > 1 else enu,
                centroid_xy_m=_centroid_enu(p, ring, enu, georef, reference),
                ring_enu_m=enu,
                ring_lonlat=ring[:, :2] if georef else None,
            )
        )
    return sort_defects(out)


def _centroid_enu(
    props: dict[str, Any],
    ring: np.ndarray,
    enu: np.ndarray,
    georef: bool,
    reference: EnuReference | None,
) -> np.ndarray:
    """(2,) the defect's stored centroid in the viewer's ENU (what defects.csv and the GeoJSON
    say; a crack's outline vertices average elsewhere), else the outline vertices' mean."""
    keys = ("centroid_lon", "centroid_lat") if georef else ("centroid_e_m", "centroid_n_m")
    try:
        c = np.array([float(props[keys[0]]), float(props[keys[1]])])
    except (KeyError, TypeError, ValueError):
        c = np.array([np.nan, np.nan])
    if not np.isfinite(c).all():
        return enu[:-1].mean(axis=0) if len(enu) > 1 else enu[0]
    if not georef:
        return c
    # with the ring's first vertex ahead of it, a missing reference falls back to the same one
    return _ring_enu(np.vstack([ring[:1, :2], c[None]]), True, reference)[1]


def _load_frame_labels(run: RunFolder, missing: list[str]) -> dict[str, dict[str, str]]:
    path = run.frame_labels
    if not path.exists():
        missing.append(FRAME_LABELS_CSV)
        return {}
    return {row["filename"]: row for row in read_csv(path) if row.get("filename")}


def _load_pairs(run: RunFolder, missing: list[str]) -> list[PairResult]:
    from roadsurf.reconstruction.types import load_pair

    folder = run.pairs_dir
    files = sorted(folder.glob("*.npz")) if folder.is_dir() else []
    if not files:
        missing.append(f"{PAIRS_DIR}/")
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
    box = r.grid.crop_to(valid, margin_px)
    if box is None:
        return r
    rs, cs, grid = box
    return Raster(r.data[rs, cs], grid, r.path)


def _find_masks(run: RunFolder) -> dict[str, Path]:
    """Refined 2D defect masks saved by detection (RUN/masks/<frame stem>.png), if any."""
    folder = run.masks_dir
    if not folder.is_dir():
        return {}
    return {p.stem: p for p in sorted(folder.iterdir()) if p.suffix.lower() in (".png", ".tif")}


def _load_drive(drive_dir: object, missing: list[str]) -> Drive | None:
    if not drive_dir:
        missing.append("drive (report.json names none; pass --drive)")
        return None
    root = Path(str(drive_dir))
    if not (root / df.CAMERA_YAML).exists():
        missing.append(f"drive {root} (not found; pass --drive)")
        return None
    from roadsurf.io.drive import load_drive

    try:
        return load_drive(root, check_images=False)
    except RoadsurfError as e:
        log.warning("drive %s could not be loaded (%s); images and GPS are left out", root, e)
        missing.append(f"drive {root} ({e})")
        return None
