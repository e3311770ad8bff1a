"""Windowed segmentation of the global map: memory grows with the defects and the corridor, not
with the bounding box of the drive.

A long curved drive has a residual raster whose bounding grid is mostly empty (600 frames:
48128 x 4096 px = 197 Mpx for 2.4 Mpx of surface). Instead of reading it whole, the stage reads
fixed-size windows around *candidate* places only: blocks of a lattice (``window_core_m``) that
hold 3D defect evidence (the pairs' refined / candidate points, or deep map points), each read
with a margin (``window_margin_m``) of surrounding road for the re-levelling and noise. Each
window is segmented on its own (``mapseg.segment``: thresholds relative to the window's measured
noise); regions from different windows that share or touch cells are merged (a defect crossing a
block border, or seen in two overlapping windows, comes out whole), with their 3D evidence
counted once.

Sources: ``RasterSource`` (RUN/surface.tif or surface.vrt, read by rasterio windows) and
``PointsSource`` (scattered points rasterised per window when mapping wrote no raster).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from roadsurf.detection.config import MapSegmentConfig
from roadsurf.detection.mapseg import Region, Segmentation, Surface, segment
from roadsurf.io.formats import GridSpec
from roadsurf.mapping.dense_fuse import NOBS as NOBS_NAME
from roadsurf.mapping.dense_fuse import SIGMA as SIGMA_NAME

log = logging.getLogger(__name__)


class WindowSource(Protocol):
    """A residual raster read window by window. ``grid`` is the full grid (metadata only)."""

    grid: GridSpec
    source: str
    footprint_m: float  # ground footprint of what one raster value measures (m); NaN: unknown
    search_depth_m: float  # deepest depth the surface could read (m); NaN: unknown

    def read(self, r0: int, c0: int, h: int, w: int) -> np.ndarray:
        """(h, w) float32 residual (m, negative below), NaN where unobserved."""
        ...

    def read_count(self, r0: int, c0: int, h: int, w: int) -> np.ndarray | None:
        """(h, w) pairs' samples fused into each cell (the dense surface's surface_nobs), or
        None when the source has no such count."""
        ...

    def read_sigma(self, r0: int, c0: int, h: int, w: int) -> np.ndarray | None:
        """(h, w) σ of each cell's height (m; the dense surface's surface_sigma, NaN where
        unknown), or None when the source has none."""
        ...


class RasterSource:
    """A single-band residual GeoTIFF / VRT read by rasterio windows (only the window's blocks
    or tile files are touched)."""

    def __init__(self, path: Path) -> None:
        import rasterio
        from rasterio.enums import MaskFlags

        self.path = Path(path)
        self.source = self.path.name
        with rasterio.open(self.path) as src:
            if src.count != 1:
                raise ValueError(
                    f"{self.path}: expected a single-band residual raster, got {src.count} "
                    "bands; re-run mapping with overwrite"
                )
            t = src.transform
            self.nodata = src.nodata
            # NaN nodata and no other mask (mapping's rasters): a plain read already holds NaN
            # wherever the mask would be, and costs a quarter of a masked read (GDAL's nodata
            # mask band reads and tests the blocks a second time)
            self._plain = (
                self.nodata is not None
                and math.isnan(self.nodata)
                and src.dtypes[0] in ("float32", "float64")
                and list(src.mask_flag_enums[0]) == [MaskFlags.nodata]
            )
            self.grid = GridSpec(str(src.crs), t.c, t.f, t.a, src.width, src.height)
            # written by mapping for the dense surface (the matching window on the ground)
            try:
                self.footprint_m = float(src.tags().get("DENSE_FOOTPRINT_M", "nan"))
            except ValueError:
                self.footprint_m = float("nan")
            # ... and the deepest height its matching searched (m, positive down; NaN: not
            # written): a cell that deep may be deeper
            try:
                self.search_depth_m = float(src.tags().get("DENSE_SEARCH_DEPTH_M", "nan"))
            except ValueError:
                self.search_depth_m = float("nan")
        self._src = None
        # the dense surface's per-cell count and σ, written next to it on the same grid
        self.count_path = self._beside(NOBS_NAME, (src.width, src.height))
        self._cnt = None
        self._last_count: tuple[tuple[int, int, int, int] | None, np.ndarray | None] = (None, None)
        self.sigma_path = self._beside(SIGMA_NAME, (src.width, src.height))
        self._sig = None

    def _beside(self, name: str, size: tuple[int, int]) -> Path | None:
        """The raster ``name`` next to the residual (same suffix) when it has its size."""
        import rasterio

        path = self.path.with_name(name + self.path.suffix)
        if not path.is_file():
            return None
        with rasterio.open(path) as c:
            return path if (c.width, c.height) == size else None

    def read(self, r0: int, c0: int, h: int, w: int) -> np.ndarray:
        import rasterio
        from rasterio.windows import Window

        if self._src is None:
            self._src = rasterio.open(self.path)
        if self._plain:
            res = self._src.read(1, window=Window(c0, r0, w, h)).astype(np.float32, copy=False)
        else:
            data = self._src.read(1, window=Window(c0, r0, w, h), masked=True)
            res = np.ma.filled(data.astype(np.float32), np.nan)
        if self.nodata is not None and np.isfinite(self.nodata):
            res[res == self.nodata] = np.nan
        cnt = self.read_count(r0, c0, h, w)
        if cnt is not None:
            # cells one frame only saw hold the road model (exactly 0 at count 0, mapping's
            # dense_single_view): unknown to detection, whose noise and road level come from
            # what was measured (real photographs: a noise of 1.8 mm had read 0.07 mm)
            res[(cnt == 0) & (res == 0.0)] = np.nan
        return res

    def read_count(self, r0: int, c0: int, h: int, w: int) -> np.ndarray | None:
        import rasterio
        from rasterio.windows import Window

        if self.count_path is None:
            return None
        key = (r0, c0, h, w)
        if self._last_count[0] != key:  # read() and the segmentation ask for the same window
            if self._cnt is None:
                self._cnt = rasterio.open(self.count_path)
            self._last_count = (key, np.asarray(self._cnt.read(1, window=Window(c0, r0, w, h))))
        return self._last_count[1]

    def read_sigma(self, r0: int, c0: int, h: int, w: int) -> np.ndarray | None:
        import rasterio
        from rasterio.windows import Window

        if self.sigma_path is None:
            return None
        if self._sig is None:
            self._sig = rasterio.open(self.sigma_path)
        # NaN nodata (mapping's rasters): a plain read holds NaN where the mask would be
        return self._sig.read(1, window=Window(c0, r0, w, h)).astype(np.float32, copy=False)

    def close(self) -> None:
        for name in ("_src", "_cnt", "_sig"):
            f = getattr(self, name)
            if f is not None:
                f.close()
                setattr(self, name, None)


class PointsSource:
    """Scattered residual points gridded per window (mean per cell): the fallback when mapping
    wrote no raster. The full grid is a lattice over the points' bounds, never allocated."""

    def __init__(
        self, xy_m: np.ndarray, residual_m: np.ndarray, gsd_m: float, crs: str, source: str
    ) -> None:
        xy = np.asarray(xy_m, float)
        self.xy = xy
        self.residual = np.asarray(residual_m, float)
        self.source = source
        self.footprint_m = float("nan")  # one cell per value
        self.search_depth_m = float("nan")
        lo = np.floor(xy.min(axis=0) / gsd_m) * gsd_m - 2 * gsd_m
        hi = np.ceil(xy.max(axis=0) / gsd_m) * gsd_m + 2 * gsd_m
        width = int(round((hi[0] - lo[0]) / gsd_m))
        height = int(round((hi[1] - lo[1]) / gsd_m))
        self.grid = GridSpec(crs, float(lo[0]), float(hi[1]), gsd_m, width, height)
        self._rc = np.floor(self.grid.rowcol_from_xy(xy) + 0.5).astype(np.int64)

    def read_count(self, r0: int, c0: int, h: int, w: int) -> np.ndarray | None:
        return None

    def read_sigma(self, r0: int, c0: int, h: int, w: int) -> np.ndarray | None:
        return None

    def read(self, r0: int, c0: int, h: int, w: int) -> np.ndarray:
        rc = self._rc
        ok = (rc[:, 0] >= r0) & (rc[:, 0] < r0 + h) & (rc[:, 1] >= c0) & (rc[:, 1] < c0 + w)
        flat = (rc[ok, 0] - r0) * w + (rc[ok, 1] - c0)
        s = np.bincount(flat, weights=self.residual[ok], minlength=h * w)
        c = np.bincount(flat, minlength=h * w)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = (s / c).reshape(h, w).astype(np.float32)
        r[c.reshape(h, w) == 0] = np.nan
        return r

    def close(self) -> None:
        return None


@dataclass
class Window:
    r0: int
    c0: int
    h: int
    w: int


def candidate_windows(
    seed_xy_m: np.ndarray, grid: GridSpec, core_m: float, margin_m: float, min_points: int = 1
) -> list[Window]:
    """Windows (core block + margin, clipped to the grid) around the lattice blocks that hold
    seed points. A block is used when it holds a seed and its 3x3 block neighbourhood holds at
    least ``min_points`` (isolated single mismatches cannot pass the 3D veto anyway)."""
    xy = np.asarray(seed_xy_m, float).reshape(-1, 2)
    if len(xy) == 0:
        return []
    core = max(1, int(round(core_m / grid.gsd_m)))
    marg = max(0, int(round(margin_m / grid.gsd_m)))
    rc = np.floor(grid.rowcol_from_xy(xy) + 0.5).astype(np.int64)
    ok = (rc[:, 0] >= 0) & (rc[:, 0] < grid.height) & (rc[:, 1] >= 0) & (rc[:, 1] < grid.width)
    blocks = rc[ok] // core
    if len(blocks) == 0:
        return []
    uniq, counts = np.unique(blocks, axis=0, return_counts=True)
    count_of = {(int(a), int(b)): int(n) for (a, b), n in zip(uniq, counts, strict=True)}
    out: list[Window] = []
    for br, bc in count_of:
        near = sum(count_of.get((br + dr, bc + dc), 0) for dr in (-1, 0, 1) for dc in (-1, 0, 1))
        if near < min_points:
            continue
        r0 = max(0, br * core - marg)
        c0 = max(0, bc * core - marg)
        r1 = min(grid.height, (br + 1) * core + marg)
        c1 = min(grid.width, (bc + 1) * core + marg)
        out.append(Window(r0, c0, r1 - r0, c1 - c0))
    out.sort(key=lambda w: (w.r0, w.c0))
    return out


def segment_windows(
    source: WindowSource,
    cfg: MapSegmentConfig,
    seed_xy_m: np.ndarray,
    evidence_xy_m: np.ndarray | None = None,
    evidence_pair: np.ndarray | None = None,
    min_points: int = 1,
) -> Segmentation:
    """Segment the windows around the seed points and merge the regions into one
    ``Segmentation`` on the full grid (rows/cols in the full grid; ``smoothed`` is empty).

    noise_m / seed_m of the result are the medians over the windows; each region keeps its own
    window's values (``Region.noise_m``, ``Region.seed_m``).
    """
    grid = source.grid
    # The margin must hold enough road for the re-levelling window, or a wide defect filling
    # the window would become its own road level.
    margin = max(cfg.window_margin_m, cfg.level_window_m)
    windows = candidate_windows(seed_xy_m, grid, cfg.window_core_m, margin, min_points=min_points)
    ev_xy = np.zeros((0, 2)) if evidence_xy_m is None else np.asarray(evidence_xy_m, float)
    ev_pair = np.zeros(len(ev_xy), int) if evidence_pair is None else np.asarray(evidence_pair)
    ev_rc = np.floor(grid.rowcol_from_xy(ev_xy) + 0.5).astype(np.int64) if len(ev_xy) else None
    pad = int(math.ceil(cfg.point_support_radius_m / grid.gsd_m)) + 1
    regions: list[Region] = []
    noises, seeds = [], []
    for win in windows:
        data = source.read(win.r0, win.c0, win.h, win.w)
        if not np.isfinite(data).any():
            continue
        wgrid = GridSpec(
            grid.crs,
            grid.x0_m + win.c0 * grid.gsd_m,
            grid.y0_m - win.r0 * grid.gsd_m,
            grid.gsd_m,
            win.w,
            win.h,
        )
        sel = np.zeros(0, np.int64)
        if ev_rc is not None:
            sel = np.flatnonzero(
                (ev_rc[:, 0] >= win.r0 - pad)
                & (ev_rc[:, 0] < win.r0 + win.h + pad)
                & (ev_rc[:, 1] >= win.c0 - pad)
                & (ev_rc[:, 1] < win.c0 + win.w + pad)
            )
        sig = source.read_sigma(win.r0, win.c0, win.h, win.w)
        count = source.read_count(win.r0, win.c0, win.h, win.w)
        surf = Surface(data, wgrid, source.source, sig, count)
        seg = segment(surf, cfg, ev_xy[sel], ev_pair[sel])
        del data, surf
        if not np.isfinite(seg.noise_m):
            continue
        noises.append(seg.noise_m)
        seeds.append(seg.seed_m)
        # Regions in full-grid rows/cols (segment crops the window to its data).
        r_off = int(round((grid.y0_m - seg.grid.y0_m) / grid.gsd_m))
        c_off = int(round((seg.grid.x0_m - grid.x0_m) / grid.gsd_m))
        for reg in seg.regions:
            reg.rows = reg.rows + r_off
            reg.cols = reg.cols + c_off
            reg.support_idx = sel[reg.support_idx]
            reg.noise_m, reg.seed_m = seg.noise_m, seg.seed_m
            if count is not None:
                # cells deeper than T_d that two or more pairs measured alike (dense_fuse keeps
                # a pair's sample only within 3 σ of the cell's weighted median), or deeper
                # than 2 T_d that one pair's dense matching measured (count 1, not filled): one
                # pair's cells get no second view to average a systematic error of its match
                # (a mismatched block in a tilted camera's far field read 14-17 mm over
                # 70-210 cm² at 45°), so they must clear twice the threshold. Most of a tilted
                # camera's road is seen by one pair: a 14 cm, 53 mm pothole there (2 feature
                # points) was vetoed on the varied drive when two pairs were asked of it
                d = np.nan_to_num(reg.depth_m, nan=0.0)
                n = count[reg.rows - win.r0, reg.cols - win.c0]
                ok = ((d >= reg.seed_m) & (n >= 2)) | ((d >= 2 * reg.seed_m) & (n >= 1))
                reg.dense_support_m2 = float(ok.sum() * grid.gsd_m**2)
            regions.append(reg)
    merged = merge_regions(regions, grid.width, ev_pair)
    noise = float(np.median(noises)) if noises else float("nan")
    seed = float(np.median(seeds)) if seeds else float("nan")
    rim = float("nan")
    log.info(
        "detection: %d window(s) of <= %d x %d px read around candidates (grid %d x %d px); "
        "%d region(s) -> %d after merging across windows",
        len(windows),
        max((w.h for w in windows), default=0),
        max((w.w for w in windows), default=0),
        grid.height,
        grid.width,
        len(regions),
        len(merged),
    )
    return Segmentation(noise, seed, rim, merged, grid)


def merge_regions(regions: list[Region], width: int, ev_pair: np.ndarray) -> list[Region]:
    """Union regions that share or 8-touch a cell (across window borders / overlaps). Cells
    seen twice keep their first values; evidence points are counted once."""
    if not regions:
        return []
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n_reg = len(regions)
    keys = np.concatenate([r.rows.astype(np.int64) * width + r.cols for r in regions])
    owner = np.concatenate([np.full(len(r.rows), i, np.int64) for i, r in enumerate(regions)])
    # Each cell's first owner; a region sharing or 8-touching a cell of another is linked to it.
    order = np.argsort(keys, kind="stable")
    uk, first = np.unique(keys[order], return_index=True)
    first_owner = owner[order][first]
    # Links as unique region pairs (a * n_reg + b), not one per touching cell: the components
    # are the same, and memory stays with the regions, not 9x their cells (issue 31 #10).
    links = [_region_links(owner, first_owner[np.searchsorted(uk, keys)], n_reg)]
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr == 0 and dc == 0:
                continue
            nk = keys + dr * width + dc
            pos = np.minimum(np.searchsorted(uk, nk), len(uk) - 1)
            hit = uk[pos] == nk
            links.append(_region_links(owner[hit], first_owner[pos[hit]], n_reg))
    link = np.unique(np.concatenate(links))
    a, b = link // n_reg, link % n_reg
    g = coo_matrix((np.ones(len(a)), (a, b)), shape=(n_reg, n_reg))
    comp = connected_components(g, directed=False)[1]
    groups: dict[int, list[int]] = {}
    for i, c in enumerate(comp.tolist()):  # groups ordered by their first region
        groups.setdefault(c, []).append(i)
    out: list[Region] = []
    for members in groups.values():
        if len(members) == 1:
            out.append(regions[members[0]])
            continue
        parts = [regions[i] for i in members]
        keys = np.concatenate([p.rows.astype(np.int64) * width + p.cols for p in parts])
        _, first = np.unique(keys, return_index=True)
        first = np.sort(first)

        def cat(name: str, parts: list[Region] = parts, first: np.ndarray = first) -> np.ndarray:
            return np.concatenate([getattr(p, name) for p in parts])[first]

        idx = np.unique(np.concatenate([p.support_idx for p in parts]))
        reg = Region(
            rows=cat("rows"),
            cols=cat("cols"),
            depth_m=cat("depth_m"),
            depth_smooth_m=cat("depth_smooth_m"),
        )
        reg.support_idx = idx
        reg.support_pairs = set(np.unique(ev_pair[idx]).tolist()) if len(idx) else set()
        reg.n_support_points = len(idx)
        reg.dense_support_m2 = float(sum(p.dense_support_m2 for p in parts))
        reg.noise_m = float(np.median([p.noise_m for p in parts]))
        reg.seed_m = float(np.median([p.seed_m for p in parts]))
        out.append(reg)
    return out


def _region_links(src: np.ndarray, dst: np.ndarray, n_reg: int) -> np.ndarray:
    """Unique links between different regions, encoded ``src * n_reg + dst`` (int64)."""
    other = src != dst
    return np.unique(src[other].astype(np.int64) * n_reg + dst[other])
