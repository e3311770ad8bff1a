"""Corridor rasters: a global tile lattice, per-tile ENU<->grid mapping, point gridding, windowed
sparse GeoTIFF writing and a GDAL VRT index. Reusable outside the mapping stage (e.g. the SfM
baseline): see ``corridor_tiles``, ``interpolate_to_grid``, ``grid_mean`` and ``TiledWriter``.

The grid lives in the export CRS (the drive's UTM zone) or, without GPS, in the local ENU frame.
Only tiles the corridor passes through exist; memory is bounded by one tile at a time.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from roadsurf.core.atomic import atomic_path, library_write_error, write_text_atomic
from roadsurf.core.geometry import EnuReference, enu_from_lla, lla_from_utm
from roadsurf.io import runfolder as rf
from roadsurf.io.formats import LOCAL_CRS, GridSpec, geotiff_profile


@dataclass(frozen=True)
class TileLattice:
    """Fixed-size tiles on a global lattice: tile (r, c) has its top-left corner at
    (x0 + c * tile_m, y0 - r * tile_m) in the grid CRS."""

    crs: str
    x0_m: float
    y0_m: float
    gsd_m: float
    tile_px: int
    n_rows: int  # tiles
    n_cols: int

    @property
    def tile_m(self) -> float:
        return self.tile_px * self.gsd_m

    @property
    def full_grid(self) -> GridSpec:
        """The bounding grid of all tiles (only used as a sparse file layout, never allocated)."""
        return GridSpec(
            self.crs,
            self.x0_m,
            self.y0_m,
            self.gsd_m,
            self.n_cols * self.tile_px,
            self.n_rows * self.tile_px,
        )

    def tile_grid(self, r: int, c: int) -> GridSpec:
        return GridSpec(
            self.crs,
            self.x0_m + c * self.tile_m,
            self.y0_m - r * self.tile_m,
            self.gsd_m,
            self.tile_px,
            self.tile_px,
        )

    def tiles_of_xy(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) grid-CRS points -> (N, 2) int tile (row, col)."""
        xy = np.atleast_2d(xy)
        col = np.floor((xy[:, 0] - self.x0_m) / self.tile_m).astype(int)
        row = np.floor((self.y0_m - xy[:, 1]) / self.tile_m).astype(int)
        return np.column_stack([row, col])


def corridor_tiles(
    xy_grid_m: np.ndarray, crs: str, gsd_m: float, tile_px: int
) -> tuple[TileLattice, list[tuple[int, int]]]:
    """Lattice aligned to multiples of the tile size, and the sorted tiles holding any of the
    (N, 2) sample points (footprint samples, map points)."""
    xy = np.asarray(xy_grid_m, float).reshape(-1, 2)
    tile_m = tile_px * gsd_m
    x0 = math.floor(xy[:, 0].min() / tile_m) * tile_m
    y0 = math.ceil(xy[:, 1].max() / tile_m) * tile_m
    n_cols = int(math.floor((xy[:, 0].max() - x0) / tile_m)) + 1
    n_rows = int(math.floor((y0 - xy[:, 1].min()) / tile_m)) + 1
    lat = TileLattice(crs, x0, y0, gsd_m, tile_px, n_rows, n_cols)
    rc = lat.tiles_of_xy(xy)
    tiles = sorted({(int(r), int(c)) for r, c in rc})
    return lat, tiles


class GridToEnu:
    """Grid-CRS <-> ENU for one small area, as an affine fit to the exact pyproj transform
    (sub-millimetre over a tile; the ENU frame is tangent, UTM is conformal)."""

    def __init__(self, ref: EnuReference | None, epsg: int | None) -> None:
        self.ref, self.epsg = ref, epsg

    def _samples(self, grid: GridSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """3 x 3 grid points X, Y (3, 3) over the tile and their exact ENU (9, 3) on the road.
        At the road's height (the reference's): the local vertical tilts by d / R, so a cell
        placed at the ellipsoid would move sideways by h d / R (0.57 m at 1 km, 3,640 m up)."""
        if self.ref is None or self.epsg is None:
            raise ValueError("GridToEnu: no reference or CRS")
        xs = grid.x0_m + np.linspace(0, grid.width * grid.gsd_m, 3)
        ys = grid.y0_m - np.linspace(0, grid.height * grid.gsd_m, 3)
        X, Y = np.meshgrid(xs, ys)
        lla = lla_from_utm(X.ravel(), Y.ravel(), self.epsg)
        return X, Y, enu_from_lla(lla[:, 0], lla[:, 1], self.ref.alt_m, self.ref)

    def affine_for(self, grid: GridSpec) -> np.ndarray:
        """(2, 3) A with [e, n] = A @ [x, y, 1] over the tile's extent."""
        if self.ref is None or self.epsg is None:
            return np.array([[1.0, 0, 0], [0, 1.0, 0]])
        X, Y, enu = self._samples(grid)
        M = np.column_stack([X.ravel(), Y.ravel(), np.ones(X.size)])
        A, *_ = np.linalg.lstsq(M - [grid.x0_m, grid.y0_m, 0], enu[:, :2], rcond=None)
        # express relative to the tile corner for numerical safety
        out = A.T.copy()
        out[:, 2] -= out[:, 0] * grid.x0_m + out[:, 1] * grid.y0_m
        return out

    def height_lift(self, grid: GridSpec, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(N,) ellipsoidal height minus (ENU up + the reference's altitude) (m) at grid points
        (N,) x, y of the tile ``grid`` on the road: the tangent plane's rise above the
        ellipsoid, d² / 2R at d from the origin (7.8 cm at 1 km). A quadratic in x, y fitted to
        3 x 3 exact samples over the tile (sub-0.1 mm over a tile of a few metres); zeros
        without a reference."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        if self.ref is None or self.epsg is None:
            return np.zeros(np.broadcast(x, y).shape)
        X, Y, enu = self._samples(grid)
        lift = -enu[:, 2]  # a point at the reference's altitude sits at ENU up -d²/2R

        def basis(u: np.ndarray, v: np.ndarray) -> np.ndarray:
            u, v = u - grid.x0_m, v - grid.y0_m
            return np.column_stack([np.ones(u.size), u, v, u * u, u * v, v * v])

        c, *_ = np.linalg.lstsq(basis(X.ravel(), Y.ravel()), lift, rcond=None)
        return (basis(x.ravel(), y.ravel()) @ c).reshape(x.shape)

    def pixel_enu(self, grid: GridSpec, rows: slice, cols: slice) -> tuple[np.ndarray, np.ndarray]:
        """ENU east, north (H, W) of the pixel centres of a window of ``grid``."""
        A = self.affine_for(grid)
        r = np.arange(rows.start, rows.stop)
        c = np.arange(cols.start, cols.stop)
        x = grid.x0_m + (c + 0.5) * grid.gsd_m
        y = grid.y0_m - (r + 0.5) * grid.gsd_m
        X, Y = np.meshgrid(x, y)
        e = A[0, 0] * X + A[0, 1] * Y + A[0, 2]
        n = A[1, 0] * X + A[1, 1] * Y + A[1, 2]
        return e, n


# --------------------------------------------------------------------------- gridding


def grid_mean(xy_grid_m: np.ndarray, values: np.ndarray, grid: GridSpec) -> np.ndarray:
    """Mean of ``values`` per pixel of ``grid`` ((H, W) float32, NaN where empty). values may be
    (N,) or (N, C) (then (H, W, C))."""
    xy = np.atleast_2d(np.asarray(xy_grid_m, float))
    v = np.asarray(values, float)
    rc = np.floor(grid.rowcol_from_xy(xy) + 0.5).astype(np.int64)
    ok = (rc[:, 0] >= 0) & (rc[:, 0] < grid.height) & (rc[:, 1] >= 0) & (rc[:, 1] < grid.width)
    flat = rc[ok, 0] * grid.width + rc[ok, 1]
    cnt = np.bincount(flat, minlength=grid.width * grid.height).astype(float)
    v2 = v[ok].reshape(int(ok.sum()), -1)
    out = np.full((grid.height * grid.width, v2.shape[1]), np.nan, np.float32)
    has = cnt > 0
    for ch in range(v2.shape[1]):
        s = np.bincount(flat, weights=v2[:, ch], minlength=grid.width * grid.height)
        out[has, ch] = s[has] / cnt[has]
    out = out.reshape(grid.height, grid.width, v2.shape[1])
    return out[..., 0] if v.ndim == 1 else out


def interpolate_to_grid(
    xy_grid_m: np.ndarray,
    values: np.ndarray,
    grid: GridSpec,
    max_edge_m: float,
    edge_factor: float = 4.0,
    min_edge_m: float = 0.02,
) -> np.ndarray:
    """Piecewise-linear (Delaunay) interpolation of scattered (N,) values onto ``grid`` pixel
    centres; triangles with an edge longer than min(max_edge_m, max(min_edge_m, edge_factor ×
    median edge)) are holes. Returns (H, W) float32 with NaN where not interpolated."""
    xy = np.atleast_2d(np.asarray(xy_grid_m, float))
    v = np.asarray(values, float)
    out = np.full((grid.height, grid.width), np.nan, np.float32)
    if len(xy) < 3:
        return out
    # pixel coordinates (col, row) keep the triangulation well conditioned
    rc = grid.rowcol_from_xy(xy)
    pts = np.column_stack([rc[:, 1], rc[:, 0]])
    pts, uniq = np.unique(np.round(pts, 3), axis=0, return_index=True)
    v = v[uniq]
    if len(pts) < 3 or np.ptp(pts[:, 0]) < 1 or np.ptp(pts[:, 1]) < 1:
        return out
    import matplotlib.tri as mtri

    try:
        tri = mtri.Triangulation(pts[:, 0], pts[:, 1])
    except (ValueError, RuntimeError):  # degenerate (collinear) input: nothing to interpolate
        return out
    s = tri.triangles
    e = np.stack(
        [
            np.linalg.norm(pts[s[:, 0]] - pts[s[:, 1]], axis=1),
            np.linalg.norm(pts[s[:, 1]] - pts[s[:, 2]], axis=1),
            np.linalg.norm(pts[s[:, 2]] - pts[s[:, 0]], axis=1),
        ],
        axis=1,
    ).max(1)
    thr_m = min(max_edge_m, max(min_edge_m, edge_factor * float(np.median(e)) * grid.gsd_m))
    tri.set_mask(e * grid.gsd_m > thr_m)
    # only pixels inside the triangulation's bounding box
    c0, r0 = np.floor(pts.min(0)).astype(int)
    c1, r1 = np.ceil(pts.max(0)).astype(int)
    c0, r0 = max(c0, 0), max(r0, 0)
    c1, r1 = min(c1, grid.width - 1), min(r1, grid.height - 1)
    if c1 < c0 or r1 < r0:
        return out
    C, R = np.meshgrid(np.arange(c0, c1 + 1, dtype=float), np.arange(r0, r1 + 1, dtype=float))
    z = mtri.LinearTriInterpolator(tri, v)(C, R)
    out[r0 : r1 + 1, c0 : c1 + 1] = np.ma.filled(z.astype(np.float32), np.nan)
    return out


def fill_nodata_capped(
    values: np.ndarray, allowed: np.ndarray, max_px: float, max_abs: float | None = None
) -> np.ndarray:
    """Fill NaN pixels of (H, W) ``values`` that are inside the (H, W) bool ``allowed`` mask and
    at most ``max_px`` pixels from a valid pixel, like GDAL fillnodata with a max distance.

    Each filled pixel gets a Gaussian-weighted mean (σ = max_px / 2) of the valid pixels around
    it (normalised convolution), so the fill stays within the range of the nearby measured
    values: it continues the surface, never creates a new extremum (no invented depression).
    Pixels further than ``max_px`` from any valid pixel, or outside ``allowed``, stay NaN; so do
    pixels whose fill value would exceed ``max_abs`` in magnitude (for residual heights: only
    road continues, relief such as a pothole running off the measured part is not extrapolated).
    Returns a new float32 array."""
    v = np.asarray(values, np.float32)
    allowed = np.asarray(allowed, bool)
    if v.shape != allowed.shape:
        raise ValueError(f"values {v.shape} and allowed {allowed.shape} must have the same shape")
    out = v.copy()
    valid = np.isfinite(v)
    if max_px <= 0 or valid.all() or not valid.any():
        return out
    import cv2

    # distance (px) of each invalid pixel to the nearest valid one
    dist = cv2.distanceTransform((~valid).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    target = ~valid & allowed & (dist <= max_px)
    if not target.any():
        return out
    sig = max(0.5 * float(max_px), 0.5)
    num = cv2.GaussianBlur(np.where(valid, v, 0).astype(np.float32), (0, 0), sig)
    den = cv2.GaussianBlur(valid.astype(np.float32), (0, 0), sig)
    with np.errstate(invalid="ignore", divide="ignore"):
        fill = num / den
    ok = target & (den > 1e-4)
    if max_abs is not None:
        ok &= np.abs(fill) <= max_abs
    out[ok] = fill[ok]
    return out


# --------------------------------------------------------------------------- writing


class TiledWriter:
    """Writes one raster product (e.g. surface) tile by tile: per-tile GeoTIFFs under
    ``tiles/`` plus, when the bounding grid is small enough, one sparse ``<name>.tif`` written
    window by window (empty tiles are never stored). ``close`` writes ``<name>.vrt``."""

    def __init__(
        self,
        run_dir: Path,
        name: str,
        lattice: TileLattice,
        count: int,
        dtype: str,
        nodata: float | None,
        write_tiles: bool,
        write_full: bool,
        tags: dict[str, str] | None = None,
    ) -> None:
        import rasterio

        self.run_dir, self.name, self.lat = run_dir, name, lattice
        self.count, self.dtype, self.nodata = count, dtype, nodata
        self.write_tiles, self.tags = write_tiles, tags or {}
        self.tile_files: list[tuple[int, int, str]] = []
        self._stack = contextlib.ExitStack()
        self._full = None
        if write_full:
            tmp = self._stack.enter_context(atomic_path(run_dir / f"{name}.tif"))
            self._full = self._stack.enter_context(
                rasterio.open(tmp, "w", **geotiff_profile(lattice.full_grid, count, dtype, nodata))
            )
            if self.tags:
                self._full.update_tags(**self.tags)

    def write(self, r: int, c: int, data: np.ndarray) -> None:
        """data: (H, W) or (H, W, C) for tile (r, c). A failed write (disk full) is a one-line
        OutputError."""
        from rasterio.errors import RasterioError

        try:
            self._write(r, c, data)
        except RasterioError as e:
            raise library_write_error(e, self.run_dir / f"{self.name}.tif") from e

    def _write(self, r: int, c: int, data: np.ndarray) -> None:
        import rasterio
        from rasterio.windows import Window

        bands = data[None] if data.ndim == 2 else np.moveaxis(data, 2, 0)
        if self._full is not None:
            tp = self.lat.tile_px
            self._full.write(bands, window=Window(c * tp, r * tp, tp, tp))
        if self.write_tiles:
            rel = f"{rf.TILES_DIR}/{rf.tile_filename(self.name, r, c)}"
            grid = self.lat.tile_grid(r, c)
            with atomic_path(self.run_dir / rel) as tmp:
                with rasterio.open(
                    tmp, "w", **geotiff_profile(grid, self.count, self.dtype, self.nodata)
                ) as d:
                    d.write(bands)
                    if self.tags:
                        d.update_tags(**self.tags)
            self.tile_files.append((r, c, rel))

    def close(self) -> None:
        from rasterio.errors import RasterioError

        try:
            self._stack.close()
        except RasterioError as e:
            raise library_write_error(e, self.run_dir / f"{self.name}.tif") from e
        if self.write_tiles:
            write_vrt(
                self.run_dir / f"{self.name}.vrt",
                self.lat,
                self.tile_files,
                self.count,
                self.dtype,
                self.nodata,
                self.tags,
            )

    def abort(self) -> None:
        with contextlib.suppress(Exception):
            self._stack.__exit__(RuntimeError, RuntimeError("aborted"), None)


_GDAL_TYPES = {"float32": "Float32", "uint8": "Byte", "float64": "Float64", "int16": "Int16"}


def write_vrt(
    path: Path,
    lat: TileLattice,
    tiles: list[tuple[int, int, str]],
    count: int,
    dtype: str,
    nodata: float | None,
    tags: dict[str, str] | None = None,
) -> Path:
    """A GDAL VRT mosaic of the tile files (paths relative to the VRT), with the tiles'
    dataset tags (units, datums) as its own metadata."""
    from rasterio.crs import CRS

    g = lat.full_grid
    srs = "" if g.crs == LOCAL_CRS else f"  <SRS>{escape(CRS.from_string(g.crs).to_wkt())}</SRS>\n"
    lines = [
        f'<VRTDataset rasterXSize="{g.width}" rasterYSize="{g.height}">',
        srs.rstrip("\n") if srs else "",
        f"  <GeoTransform>{g.x0_m!r}, {g.gsd_m!r}, 0.0, {g.y0_m!r}, 0.0, {-g.gsd_m!r}</GeoTransform>",
    ]
    if tags:
        lines.append("  <Metadata>")
        lines += [
            f'    <MDI key="{escape(k, {chr(34): "&quot;"})}">{escape(str(v))}</MDI>'
            for k, v in tags.items()
        ]
        lines.append("  </Metadata>")
    colour = ["Red", "Green", "Blue", "Alpha"]
    for b in range(1, count + 1):
        lines.append(f'  <VRTRasterBand dataType="{_GDAL_TYPES[dtype]}" band="{b}">')
        if nodata is not None:
            nd = "nan" if isinstance(nodata, float) and math.isnan(nodata) else repr(nodata)
            lines.append(f"    <NoDataValue>{nd}</NoDataValue>")
        if count >= 3:
            lines.append(f"    <ColorInterp>{colour[b - 1]}</ColorInterp>")
        for r, c, rel in tiles:
            tp = lat.tile_px
            lines += [
                "    <SimpleSource>",
                f'      <SourceFilename relativeToVRT="1">{escape(rel)}</SourceFilename>',
                f"      <SourceBand>{b}</SourceBand>",
                f'      <SrcRect xOff="0" yOff="0" xSize="{tp}" ySize="{tp}"/>',
                f'      <DstRect xOff="{c * tp}" yOff="{r * tp}" xSize="{tp}" ySize="{tp}"/>',
                "    </SimpleSource>",
            ]
        lines.append("  </VRTRasterBand>")
    lines.append("</VRTDataset>")
    return write_text_atomic(path, "\n".join(x for x in lines if x) + "\n")


def iter_tiles(
    run_dir: str | Path, name: str = rf.SURFACE
) -> Iterator[tuple[GridSpec, np.ndarray]]:
    """Yield (GridSpec, data) for each non-empty tile of RUN's ``name`` raster ("surface" or
    "mosaic"), one at a time, from the tile list in RUN/map_report.json (the per-tile files, or
    windows of the monolithic GeoTIFF). Memory stays bounded by one tile; use it instead of
    reading the whole bounding grid of a long drive."""
    import rasterio
    from rasterio.windows import Window

    from roadsurf.core.atomic import read_json

    run_dir = Path(run_dir)
    rep = read_json(run_dir / rf.MAP_REPORT)
    g = rep["grid"]
    tp = int(g["tile_px"])
    full = run_dir / f"{name}.tif"
    for t in rep.get("tiles", []):
        x0, y1 = t["bounds"][0], t["bounds"][3]
        grid = GridSpec(g["crs"], x0, y1, g["gsd_m"], tp, tp)
        if name in t and (run_dir / t[name]).is_file():
            with rasterio.open(run_dir / t[name]) as src:
                arr = src.read()
        else:
            with rasterio.open(full) as src:
                arr = src.read(window=Window(t["col"] * tp, t["row"] * tp, tp, tp))
        yield grid, (arr[0] if arr.shape[0] == 1 else np.moveaxis(arr, 0, 2))


# GDAL's block cache defaults to 5 % of the machine's RAM and keeps every block written to an
# open raster (dirty until close) or read from it: with surface.tif/mosaic.tif open for the
# whole drive it grew with the drive's length (issue 31 #10). A fixed cap keeps memory flat;
# blocks are flushed earlier, the files are the same bytes.
GDAL_CACHE_BYTES = 64 * 2**20


def bounded_block_cache() -> contextlib.AbstractContextManager[object]:
    """``with bounded_block_cache(): ...``: GDAL's block cache capped at ``GDAL_CACHE_BYTES``
    inside (the previous setting comes back after)."""
    import rasterio

    return rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_BYTES)
