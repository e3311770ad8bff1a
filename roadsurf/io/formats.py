"""Readers and writers for the standard exchange formats, kept together so they round-trip.

- PLY (binary little-endian, via plyfile): double x,y,z; uchar red,green,blue; float residual_m
  (+ any extra float/int per-vertex properties).
- GeoTIFF (via rasterio): single-band float32 with nodata, or 3-band uint8 RGB; tiled, deflate
  compressed, and sparse (tiles that hold only nodata are not stored, so a long curved corridor
  does not cost its bounding box on disk).
- GeoJSON (RFC 7946): WGS84 lon/lat, closed polygon rings, validated on write.
All writers are atomic (temporary file, then rename).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core.atomic import atomic_path, json_safe, write_text_atomic

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- PLY


def write_ply(
    path: str | Path,
    xyz: np.ndarray,
    rgb: np.ndarray | None = None,
    extra: dict[str, np.ndarray] | None = None,
    vertical_datum: str | None = None,
    comments: Sequence[str] = (),
) -> Path:
    """Write a binary PLY point cloud.

    xyz: (N, 3) float64 coordinates (written as double); rgb: (N, 3) uint8 or None;
    extra: name -> (N,) arrays (float -> float32 'float', ints -> int32), e.g. residual_m;
    vertical_datum: the datum of z, written as a header comment ``vertical_datum: ...``
    (with ``comments``, one header comment line each).
    """
    from plyfile import PlyData, PlyElement

    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz: expected shape (N, 3), got {xyz.shape}")
    n = xyz.shape[0]
    dtype: list[tuple[str, str]] = [("x", "f8"), ("y", "f8"), ("z", "f8")]
    cols: dict[str, np.ndarray] = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    if rgb is not None:
        rgb = np.asarray(rgb)
        if rgb.shape != (n, 3):
            raise ValueError(f"rgb: expected shape ({n}, 3), got {rgb.shape}")
        rgb = np.clip(rgb, 0, 255).astype(np.uint8)
        for i, c in enumerate(("red", "green", "blue")):
            dtype.append((c, "u1"))
            cols[c] = rgb[:, i]
    for name, arr in (extra or {}).items():
        arr = np.asarray(arr)
        if arr.shape != (n,):
            raise ValueError(f"{name}: expected shape ({n},), got {arr.shape}")
        kind = "f4" if arr.dtype.kind == "f" else "i4"
        dtype.append((name, kind))
        cols[name] = arr.astype(kind)
    data = np.empty(n, dtype=dtype)
    for k, v in cols.items():
        data[k] = v
    with atomic_path(path) as tmp:
        lines = list(comments) + ([f"vertical_datum: {vertical_datum}"] if vertical_datum else [])
        ply = PlyData(
            [PlyElement.describe(data, "vertex")], text=False, byte_order="<", comments=lines
        )
        ply.write(str(tmp))
    return Path(path)


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Read a PLY's vertex element: returns {'xyz': (N,3) float64, 'rgb': (N,3) uint8 if present,
    plus every other vertex property by name}."""
    from plyfile import PlyData

    v = PlyData.read(str(path))["vertex"].data
    names = v.dtype.names or ()
    out: dict[str, np.ndarray] = {
        "xyz": np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    }
    if all(c in names for c in ("red", "green", "blue")):
        out["rgb"] = np.column_stack([v["red"], v["green"], v["blue"]]).astype(np.uint8)
    for n in names:
        if n not in ("x", "y", "z", "red", "green", "blue"):
            out[n] = np.asarray(v[n])
    return out


# --------------------------------------------------------------------------- GeoTIFF


@dataclass(frozen=True)
class GridSpec:
    """A north-up raster grid in a projected CRS. Pixel (row, col) centre is at
    (x0 + (col + 0.5) * gsd, y0 - (row + 0.5) * gsd); (x0, y0) is the top-left corner."""

    crs: str  # e.g. "EPSG:32617"
    x0_m: float  # easting of the top-left corner (m)
    y0_m: float  # northing of the top-left corner (m)
    gsd_m: float  # pixel size (m), square pixels
    width: int  # columns
    height: int  # rows

    @property
    def transform(self) -> Any:
        from rasterio.transform import from_origin

        return from_origin(self.x0_m, self.y0_m, self.gsd_m, self.gsd_m)

    def xy_from_rowcol(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Pixel centres -> (N, 2) easting, northing (m)."""
        r, c = np.asarray(rows, float), np.asarray(cols, float)
        return np.column_stack(
            [self.x0_m + (c + 0.5) * self.gsd_m, self.y0_m - (r + 0.5) * self.gsd_m]
        )

    def rowcol_from_xy(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) easting, northing -> (N, 2) float row, col (pixel centres at integers)."""
        xy = np.atleast_2d(np.asarray(xy, float))
        col = (xy[:, 0] - self.x0_m) / self.gsd_m - 0.5
        row = (self.y0_m - xy[:, 1]) / self.gsd_m - 0.5
        return np.column_stack([row, col])

    def crop_to(self, valid: np.ndarray, pad: int = 0) -> tuple[slice, slice, GridSpec] | None:
        """The bounding box of the ``valid`` (height, width) cells plus ``pad`` cells, as
        (row slice, column slice, the cropped grid); None when no cell is valid."""
        rows = np.flatnonzero(valid.any(axis=1))
        cols = np.flatnonzero(valid.any(axis=0))
        if rows.size == 0:
            return None
        r0, r1 = max(0, rows[0] - pad), min(valid.shape[0], rows[-1] + pad + 1)
        c0, c1 = max(0, cols[0] - pad), min(valid.shape[1], cols[-1] + pad + 1)
        g = GridSpec(
            self.crs,
            self.x0_m + c0 * self.gsd_m,
            self.y0_m - r0 * self.gsd_m,
            self.gsd_m,
            int(c1 - c0),
            int(r1 - r0),
        )
        return slice(r0, r1), slice(c0, c1), g


LOCAL_CRS = (
    "LOCAL_ENU"  # GridSpec.crs of a run without GPS: written without a CRS, read back as this
)
# What a run without GPS writes its coordinates in (mapping.pose_init.chain: the first frame's
# vehicle level at heading 0); named in report.json, the PLY comment and the files' tags.
LOCAL_FRAME_TEXT = (
    "local metric frame (no GPS, not georeferenced): metres from the first frame's camera "
    "centre, y along its direction of travel, x to its right, z up; never lon/lat"
)
# The same as an engineering CRS (WKT2), for GeoJSON's legacy "crs" member: GDAL (QGIS,
# pyogrio, ogr2ogr) then reads the file as metres in a local frame instead of taking the
# numbers for WGS84 lon/lat, which RFC 7946 would otherwise imply.
LOCAL_FRAME_WKT = (
    'ENGCRS["roadsurf local metric frame (no GPS)",'
    'EDATUM["the first frame\'s camera centre"],CS[Cartesian,3],'
    'AXIS["x (right of travel)",east,ORDER[1],LENGTHUNIT["metre",1]],'
    'AXIS["y (along travel)",north,ORDER[2],LENGTHUNIT["metre",1]],'
    'AXIS["z (up)",up,ORDER[3],LENGTHUNIT["metre",1]]]'
)


def geotiff_profile(grid: GridSpec, count: int, dtype: str, nodata: float | None) -> dict[str, Any]:
    """The one GeoTIFF layout every raster of the project uses: tiled 256, deflate with a
    predictor, sparse (nodata-only tiles are not stored), BigTIFF when needed."""
    profile: dict[str, Any] = {
        "driver": "GTiff",
        "width": grid.width,
        "height": grid.height,
        "count": count,
        "dtype": dtype,
        "crs": None if grid.crs == LOCAL_CRS else grid.crs,
        "transform": grid.transform,
        "compress": "deflate",
        "predictor": 3 if np.dtype(dtype).kind == "f" else 2,
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
        "SPARSE_OK": "TRUE",
        "BIGTIFF": "IF_SAFER",
    }
    if count >= 3 and np.dtype(dtype) == np.uint8:
        profile["photometric"] = "RGB"
    if nodata is not None:
        profile["nodata"] = nodata
    return profile


def write_geotiff(
    path: str | Path,
    data: np.ndarray,
    grid: GridSpec,
    nodata: float | None = None,
    tags: dict[str, str] | None = None,
    vertical_datum: str | None = None,
) -> Path:
    """Write (H, W) float or (H, W, 3) uint8 data as a tiled, compressed, sparse GeoTIFF;
    ``vertical_datum`` (of the values, when they are heights) goes to the VERTICAL_DATUM tag."""
    tags = with_datum_tag(tags, vertical_datum)
    import rasterio

    arr = np.asarray(data)
    if arr.ndim == 2:
        bands = arr[None]
    elif arr.ndim == 3 and arr.shape[2] in (3, 4):
        bands = np.moveaxis(arr, 2, 0)
    else:
        raise ValueError(f"data: expected (H, W) or (H, W, 3|4), got {arr.shape}")
    if bands.shape[1:] != (grid.height, grid.width):
        raise ValueError(f"data is {bands.shape[1:]} but grid is {(grid.height, grid.width)}")
    profile = geotiff_profile(grid, bands.shape[0], bands.dtype.name, nodata)
    with atomic_path(path) as tmp:
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(bands)
            if tags:
                dst.update_tags(**tags)
    return Path(path)


def write_geotiff_blocks(
    path: str | Path,
    grid: GridSpec,
    blocks: Iterable[tuple[int, int, np.ndarray]],
    dtype: str = "float32",
    nodata: float | None = None,
    tags: dict[str, str] | None = None,
    vertical_datum: str | None = None,
) -> Path:
    """Write a single-band GeoTIFF window by window, for rasters whose full array would not fit
    in memory (e.g. the corridor of a long curved route). ``blocks`` yields (row0, col0, (h, w)
    array); blocks never written stay unstored (sparse) and read back as nodata. Same layout as
    ``write_geotiff`` (tiled 256, deflate, sparse, VERTICAL_DATUM tag), plus a floating-point
    predictor."""
    tags = with_datum_tag(tags, vertical_datum)
    import rasterio
    from rasterio.windows import Window

    profile = geotiff_profile(grid, 1, dtype, nodata)
    with atomic_path(path) as tmp:
        with rasterio.open(tmp, "w", **profile) as dst:
            for r0, c0, arr in blocks:
                a = np.asarray(arr, dtype=dtype)
                dst.write(a[None], window=Window(c0, r0, a.shape[1], a.shape[0]))
            if tags:
                dst.update_tags(**tags)
    return Path(path)


def with_datum_tag(tags: dict[str, str] | None, vertical_datum: str | None) -> dict[str, str]:
    """``tags`` plus ``VERTICAL_DATUM`` (the GeoTIFF tag that names the heights' datum)."""
    return {**(tags or {}), **({"VERTICAL_DATUM": vertical_datum} if vertical_datum else {})}


def read_geotiff(path: str | Path) -> tuple[np.ndarray, GridSpec, float | None]:
    """Read a GeoTIFF written by ``write_geotiff``: (data, grid, nodata). data is (H, W) for one
    band or (H, W, C) otherwise."""
    import rasterio

    with rasterio.open(path) as src:
        arr = src.read()
        t = src.transform
        if abs(t.a + t.e) > 1e-12 * max(1.0, abs(t.a)) or t.b != 0 or t.d != 0:
            raise ValueError(f"{path}: only north-up square-pixel rasters are supported")
        crs = LOCAL_CRS if src.crs is None else str(src.crs)
        grid = GridSpec(crs, t.c, t.f, t.a, src.width, src.height)
        nodata = src.nodata
    data = arr[0] if arr.shape[0] == 1 else np.moveaxis(arr, 0, 2)
    return data, grid, nodata


# --------------------------------------------------------------------------- GeoJSON (RFC 7946)


def _check_lonlat(coords: Any, where: str) -> None:
    a = np.asarray(coords, dtype=float)
    if a.size == 0:
        return
    a = a.reshape(-1, a.shape[-1])
    if a.shape[1] < 2 or not np.all(np.isfinite(a[:, :2])):
        raise ValueError(f"{where}: coordinates must be finite [lon, lat] pairs")
    if np.any(np.abs(a[:, 0]) > 180) or np.any(np.abs(a[:, 1]) > 90):
        raise ValueError(
            f"{where}: coordinates out of lon/lat range (RFC 7946 needs WGS84 lon, lat)"
        )


def polygon_geometry(ring_lonlat: np.ndarray) -> dict[str, Any]:
    """(N, 2) lon/lat ring -> closed, counter-clockwise GeoJSON Polygon (RFC 7946 §3.1.6)."""
    ring = np.asarray(ring_lonlat, float)[:, :2]
    if len(ring) < 3:
        raise ValueError("a polygon ring needs at least 3 distinct points")
    # Exact comparison: lon/lat vertices a few cm apart differ only in the 6th decimal.
    if not np.array_equal(ring[0], ring[-1]):
        ring = np.vstack([ring, ring[:1]])
    if len(ring) < 4:
        raise ValueError("a polygon ring needs at least 3 distinct points")
    x, y = ring[:, 0], ring[:, 1]
    signed_area = 0.5 * np.sum(x[:-1] * y[1:] - x[1:] * y[:-1])
    if signed_area < 0:
        ring = ring[::-1]
    return {"type": "Polygon", "coordinates": [ring.tolist()]}


def feature(geometry: dict[str, Any], properties: dict[str, Any]) -> dict[str, Any]:
    return {"type": "Feature", "geometry": geometry, "properties": json_safe(properties)}


def validate_geojson(fc: dict[str, Any]) -> None:
    """Raise ValueError unless ``fc`` is an RFC 7946 FeatureCollection with lon/lat coordinates
    and closed polygon rings."""
    if fc.get("type") != "FeatureCollection" or not isinstance(fc.get("features"), list):
        raise ValueError("GeoJSON: expected a FeatureCollection with a 'features' list")
    for i, f in enumerate(fc["features"]):
        g = f.get("geometry") or {}
        kind = g.get("type")
        where = f"feature {i} ({kind})"
        coords = g.get("coordinates", [])
        if kind in ("Polygon", "MultiPolygon"):
            for poly in coords if kind == "MultiPolygon" else [coords]:
                for ring in poly:
                    if len(ring) < 4 or list(ring[0]) != list(ring[-1]):
                        raise ValueError(
                            f"{where}: polygon rings must be closed with >= 4 positions"
                        )
                    _check_lonlat(ring, where)
        elif kind == "MultiLineString":
            for line in coords:
                _check_lonlat(line, where)
        else:
            _check_lonlat(coords, where)


def _crosses_antimeridian(geom: dict[str, Any]) -> bool:
    """True when a (Multi)LineString or (Multi)Polygon has a longitude step over 180°."""
    kind = geom.get("type")
    depth = {"LineString": 0, "MultiLineString": 1, "Polygon": 1, "MultiPolygon": 2}.get(str(kind))
    if depth is None:
        return False
    lines = [geom["coordinates"]]
    for _ in range(depth):
        lines = [part for line in lines for part in line]
    return any(
        len(line) > 1 and np.any(np.abs(np.diff(np.asarray(line, float)[:, 0])) > 180)
        for line in lines
    )


def split_at_antimeridian(geom: dict[str, Any]) -> dict[str, Any]:
    """A geometry crossing the antimeridian (a road on Taveuni, Fiji) cut at ±180° as RFC 7946
    §3.1.9 asks (``antimeridian``: LineString -> MultiLineString, Polygon -> MultiPolygon,
    parts counter-clockwise); one that does not cross is returned as it is."""
    if not _crosses_antimeridian(geom):
        return geom
    import copy

    import antimeridian

    flat = copy.deepcopy(geom)
    if _has_height(flat["coordinates"]):  # antimeridian cuts lon/lat only
        log.warning(
            "a %s with heights crosses the antimeridian: written without them", geom["type"]
        )
        flat["coordinates"] = _lonlat_only(flat["coordinates"])
    fixed = antimeridian.fix_geojson(flat, fix_winding=True)
    return json.loads(json.dumps(fixed))  # tuples -> lists, as the rest of the file


def _has_height(coords: Any) -> bool:
    while isinstance(coords, list) and coords and isinstance(coords[0], list):
        coords = coords[0]
    return isinstance(coords, list) and len(coords) > 2


def _lonlat_only(coords: Any) -> Any:
    if coords and isinstance(coords[0], list):
        return [_lonlat_only(c) for c in coords]
    return list(coords[:2])


def write_geojson(
    path: str | Path,
    features: Iterable[dict[str, Any]],
    properties: dict[str, Any] | None = None,
    vertical_datum: str | None = None,
) -> Path:
    """Write an RFC 7946 FeatureCollection (validated) atomically, geometries that cross the
    antimeridian cut there (``split_at_antimeridian``). Extra top-level members
    (``properties``) are allowed by RFC 7946 §6.1 and used for provenance; ``vertical_datum``
    (of any heights in it) joins them."""
    if vertical_datum:
        properties = {**(properties or {}), "vertical_datum": vertical_datum}
    feats = [
        {**f, "geometry": split_at_antimeridian(f["geometry"])} if f.get("geometry") else f
        for f in features
    ]
    fc: dict[str, Any] = {"type": "FeatureCollection", "features": feats}
    if properties:
        fc["properties"] = json_safe(properties)
    validate_geojson(fc)
    return write_text_atomic(path, json.dumps(fc, indent=1, allow_nan=False) + "\n")


def write_local_geojson(
    path: str | Path, features: Iterable[dict[str, Any]], properties: dict[str, Any]
) -> Path:
    """A FeatureCollection in the local metric frame of a run without GPS (not RFC 7946): the
    legacy "crs" member names ``LOCAL_FRAME_WKT`` so GIS readers do not place it as lon/lat,
    and ``properties.coordinates`` says the same in words."""
    fc = {
        "type": "FeatureCollection",
        "crs": {"type": "name", "properties": {"name": LOCAL_FRAME_WKT}},
        "properties": json_safe({**properties, "coordinates": LOCAL_FRAME_TEXT}),
        "features": list(features),
    }
    return write_text_atomic(path, json.dumps(fc, indent=1, allow_nan=False) + "\n")


def read_geojson(path: str | Path) -> dict[str, Any]:
    with open(path, encoding="utf-8") as f:
        fc = json.load(f)
    validate_geojson(fc)
    return fc


# --------------------------------------------------------------------------- CSV


def write_csv(path: str | Path, header: Sequence[str], rows: Iterable[Sequence[Any]]) -> Path:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in rows:
        w.writerow([_fmt(v) for v in r])
    return write_text_atomic(path, buf.getvalue())


def _fmt(v: Any) -> Any:
    if isinstance(v, (float, np.floating)):
        return "" if not math.isfinite(float(v)) else repr(float(v))
    if isinstance(v, np.generic):
        return v.item()
    return v


def read_csv(path: str | Path) -> list[dict[str, str]]:
    with open(path, encoding="utf-8", newline="") as f:
        return list(csv.DictReader(f))
