"""Ruts on the global map, measured on transverse profiles (a straightedge across the wheel path).

A rut is a long, shallow trough, as wide as a wheel path (0.3-0.8 m) and often only 6-15 mm
deep: ASTM D6433 rates rutting low from 6 mm. The map segmentation (``mapseg``) finds potholes
well, but a rut near its seed threshold T_d comes out in pieces where noise lifts the
surface over T_d; its 0.6 m re-levelling window is about as wide as the rut; and the deepest
cell of a long noisy outline reads millimetres too deep (the maximum of many noisy cells).

Pavement surveys measure rut depth on transverse profiles under a straightedge (FHWA LTPP
reports a 1.2 m straightedge rut depth). This module does the same on the residual raster:

1. A candidate is a segmented region that is elongated (PCA of its cells).
2. From its centre, stations every ``step_m`` march along the trough in both directions. At each
   station the raster is sampled on a transverse profile ``straightedge_m`` long, averaged over
   ``strip_m`` along the trough (the averaging is what makes a few-mm trough measurable).
3. The road level under the straightedge is a robust line through the profile (points below it
   by more than 2.5 σ left out, refitted), so the rut cannot lower its own reference; the
   station's depth is the deepest point of the levelled, lightly smoothed profile near the
   trough centre, and its width the extent deeper than the rim threshold, extrapolated to depth
   0 like the dense area (w(0) ≈ 2 w(t) − w(2t)).
4. A station is in the rut when its depth is at least max(``trace_min_m``, ``trace_noise_k`` ×
   the profile's σ) and its width lies within [``min_width_m``, ``max_width_m``]; the centre
   line follows the trough's centroid (ruts curve with the road); tracing stops after
   ``max_gap_m`` of stations out of the rut.
5. A trace at least ``MapSegmentConfig.rut_min_length_m`` long becomes a rut: its cells are the
   stations' trough extents, its depth the largest running median (over ``depth_window_m``) of
   the stations' depths, so neither one noisy station nor one noisy cell sets it. Pieces of the
   same rut merge; segmented regions lying mostly inside a rut are pieces of it and go.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from roadsurf.detection.config import MapSegmentConfig, RutConfig
from roadsurf.detection.mapseg import Region
from roadsurf.detection.planefit import robust_sigma
from roadsurf.detection.windows import WindowSource
from roadsurf.io.formats import GridSpec

log = logging.getLogger(__name__)


@dataclass
class RutTrace:
    """A traced rut: stations along its centre line and its cells on the full grid."""

    centres_xy_m: np.ndarray  # (S, 2) station centres (grid easting, northing, m)
    depth_m: np.ndarray  # (S,) station depth below the straightedge line (m)
    width_m: np.ndarray  # (S,) trough width at depth 0, extrapolated (m)
    noise_m: np.ndarray  # (S,) σ of the station's levelled profile on the road (m)
    in_rut: np.ndarray  # (S,) bool
    length_m: float  # along the centre line, first to last station in the rut, plus ends (m)
    max_depth_m: float  # largest running median of the stations' depths (m)
    # length added beyond the first and the last station in the rut: the rut's depth ramp
    # extrapolated to depth 0, like its width (m)
    end_extension_m: tuple[float, float] = (0.0, 0.0)
    rows: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (K,) cells
    cols: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    cell_profile_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (K,) depth (m)

    @property
    def measured_length_m(self) -> float:
        """Length of the stations in the rut, without the extrapolated ends (m)."""
        return self.length_m - sum(self.end_extension_m)

    @property
    def body_width_m(self) -> float:
        """Median trough width of the stations at least half as deep as the rut (m): the
        tapered ends read narrow, because the rim threshold cuts a shallow trough higher up."""
        sel = self.in_rut & (self.depth_m >= 0.5 * self.max_depth_m)
        if not sel.any():
            sel = self.in_rut
        return float(np.median(self.width_m[sel])) if sel.any() else float("nan")


class _Reader:
    """Samples a ``WindowSource`` at grid points through a cached window (re-read on demand)."""

    def __init__(self, source: WindowSource, half_m: float) -> None:
        self.source = source
        self.grid: GridSpec = source.grid
        self.half_px = int(math.ceil(half_m / self.grid.gsd_m))
        self.r0 = self.c0 = 0
        self.data = np.zeros((0, 0), np.float32)
        self.reads = 0

    def _load(self, rc: np.ndarray) -> None:
        g = self.grid
        lo = np.floor(rc.min(axis=0)).astype(int) - 2
        hi = np.ceil(rc.max(axis=0)).astype(int) + 3
        mid = (lo + hi) // 2
        half = np.maximum(self.half_px, (hi - lo) // 2 + 1)
        r0, c0 = max(0, int(mid[0] - half[0])), max(0, int(mid[1] - half[1]))
        r1, c1 = min(g.height, int(mid[0] + half[0])), min(g.width, int(mid[1] + half[1]))
        self.r0, self.c0 = r0, c0
        self.data = (
            self.source.read(r0, c0, r1 - r0, c1 - c0)
            if r1 > r0 and c1 > c0
            else np.zeros((0, 0), np.float32)
        )
        self.reads += 1

    def sample(self, xy_m: np.ndarray) -> np.ndarray:
        """(..., 2) grid points -> (...) residual (m), NaN where unobserved or off the grid."""
        shape = xy_m.shape[:-1]
        rc = np.floor(self.grid.rowcol_from_xy(xy_m.reshape(-1, 2)) + 0.5).astype(np.int64)
        on = (
            (rc[:, 0] >= 0)
            & (rc[:, 0] < self.grid.height)
            & (rc[:, 1] >= 0)
            & (rc[:, 1] < self.grid.width)
        )
        out = np.full(len(rc), np.nan, np.float32)
        if not on.any():
            return out.reshape(shape)
        h, w = self.data.shape
        loc = rc[on] - (self.r0, self.c0)
        if (loc < 0).any() or (loc[:, 0] >= h).any() or (loc[:, 1] >= w).any():
            self._load(rc[on])
            loc = rc[on] - (self.r0, self.c0)
        out[on] = self.data[loc[:, 0], loc[:, 1]]
        return out.reshape(shape)


@dataclass
class _Station:
    centre: np.ndarray  # (2,)
    depth_m: float
    width_m: float
    noise_m: float
    centroid_u_m: float  # trough centroid relative to the centre (m)
    extent_u_m: tuple[float, float]  # trough extent at depth 0 (extrapolated) (m)
    u_m: np.ndarray  # (U,) profile abscissae
    profile_depth_m: np.ndarray  # (U,) levelled, smoothed depth (positive down), NaN unobserved
    ok: bool  # in the rut


def _smooth1d(y: np.ndarray, sigma_px: float) -> np.ndarray:
    valid = np.isfinite(y)
    num = ndimage.gaussian_filter1d(np.where(valid, y, 0.0), sigma_px, mode="constant")
    den = ndimage.gaussian_filter1d(valid.astype(float), sigma_px, mode="constant")
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den
    out[~valid] = np.nan
    return out


def _extent(depth: np.ndarray, i: int, t: float) -> tuple[int, int]:
    """Contiguous run of samples around i with depth >= t: (first, last) indices."""
    lo = i
    while lo > 0 and depth[lo - 1] >= t:
        lo -= 1
    hi = i
    while hi < len(depth) - 1 and depth[hi + 1] >= t:
        hi += 1
    return lo, hi


def _station_axes(
    gsd_m: float, cfg: RutConfig, sample_m: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """A station's sample offsets (m): across (U,) every max(cell, ``sample_m``) over the
    straightedge, along (V,) twice that over the strip (every cell when ``sample_m`` is 0)."""
    gsd = max(gsd_m, sample_m)
    half = 0.5 * cfg.straightedge_m
    u = np.arange(-half, half + 1e-9, gsd)
    v = np.arange(-0.5 * cfg.strip_m, 0.5 * cfg.strip_m + 1e-9, gsd if sample_m <= 0 else 2 * gsd)
    return u, v


def _observed_enough(z: np.ndarray) -> np.ndarray:
    """(..., V, U) samples -> (...) bool: enough of the profile observed for a station (a
    profile sample is observed with 30 % of its strip, and half the samples must be)."""
    n_obs = np.isfinite(z).sum(axis=-2)
    v, u = z.shape[-2:]
    return (n_obs >= max(1, 0.3 * v)).sum(axis=-1) >= 0.5 * u


def _station(
    reader: _Reader,
    centre: np.ndarray,
    along: np.ndarray,
    cfg: RutConfig,
    mc: MapSegmentConfig,
    search_m: float,
    sample_m: float = 0.0,
    z: np.ndarray | None = None,
) -> _Station | None:
    """Transverse profile at ``centre`` across unit direction ``along`` (both (2,) grid m),
    sampled every max(cell, ``sample_m``) across and twice that along (``_station_axes``).
    ``z`` (V, U): those samples when the caller has read them already."""
    gsd = max(reader.grid.gsd_m, sample_m)
    normal = np.array([-along[1], along[0]])
    u, v = _station_axes(reader.grid.gsd_m, cfg, sample_m)
    if z is None:
        pts = centre + u[None, :, None] * normal + v[:, None, None] * along
        z = reader.sample(pts)  # (V, U)
    if not _observed_enough(z):
        return None
    n_obs = np.isfinite(z).sum(axis=0)
    with np.errstate(invalid="ignore"):
        prof = np.nanmean(np.where(n_obs[None, :] > 0, z, 0.0), axis=0)
    prof[n_obs < max(1, 0.3 * len(v))] = np.nan
    valid = np.isfinite(prof)
    # Robust straightedge line: points well below it (the trough) or above it are left out.
    # It starts on the upper half of the profile, like a straightedge resting on the road:
    # a trough filling half the edge would otherwise pull the first fit into itself.
    inl = valid & (prof >= np.nanmedian(prof))
    a = b = 0.0
    for _ in range(8):
        if inl.sum() < 10:
            return None
        b, a = np.polyfit(u[inl], prof[inl], 1)
        r = prof - (a + b * u)
        s = max(robust_sigma(r[inl]), 1e-5)
        new = valid & (r > -max(2.5 * s, 0.5 * mc.rim_threshold_m)) & (r < 3.0 * s)
        if np.array_equal(new, inl):
            break
        inl = new
    noise = max(robust_sigma((prof - (a + b * u))[inl]), 1e-5)
    depth = _smooth1d((a + b * u) - prof, cfg.profile_smooth_m / gsd)
    near = valid & (np.abs(u) <= search_m)
    if not near.any():
        return None
    i = int(np.nanargmax(np.where(near, depth, -np.inf)))
    d_max = float(depth[i])
    rim = max(mc.rim_threshold_m, mc.rim_noise_k * noise)
    ok = d_max >= max(cfg.trace_min_m, cfg.trace_noise_k * noise)
    lo, hi = _extent(np.nan_to_num(depth, nan=-1.0), i, rim)
    w_t = (hi - lo + 1) * gsd
    lo2, hi2 = _extent(np.nan_to_num(depth, nan=-1.0), i, 2 * rim) if d_max >= 2 * rim else (i, i)
    w_2t = (hi2 - lo2 + 1) * gsd if d_max >= 2 * rim else 0.0
    w0 = min(max(w_t, 2 * w_t - w_2t), 2 * w_t) if w_2t > 0 else w_t
    grow = 0.5 * (w0 - w_t)
    ext = (float(u[lo] - 0.5 * gsd - grow), float(u[hi] + 0.5 * gsd + grow))
    # The trough must be bounded by observed road on both sides (a straightedge rests on both).
    left_road = (inl & (u < ext[0])).sum() * gsd
    right_road = (inl & (u > ext[1])).sum() * gsd
    ok = ok and min(left_road, right_road) >= cfg.min_road_side_m
    ok = ok and cfg.min_width_m <= w0 <= cfg.max_width_m
    sel = slice(lo, hi + 1)
    wts = np.clip(depth[sel], 0.0, None)
    cu = float((u[sel] * wts).sum() / wts.sum()) if wts.sum() > 0 else float(u[i])
    return _Station(
        centre=centre,
        depth_m=d_max,
        width_m=float(ext[1] - ext[0]),
        noise_m=noise,
        centroid_u_m=cu,
        extent_u_m=ext,
        u_m=u,
        profile_depth_m=depth,
        ok=bool(ok),
    )


def _march(
    reader: _Reader,
    start: np.ndarray,
    along: np.ndarray,
    cfg: RutConfig,
    mc: MapSegmentConfig,
) -> list[_Station]:
    """Stations from ``start`` in direction ``along`` until the trough ends."""
    out: list[_Station] = []
    centre, d = start.astype(float), along / np.linalg.norm(along)
    gap, unseen, path = 0.0, 0.0, [centre.copy()]
    max_steps = int(cfg.max_length_m / cfg.step_m)
    for _ in range(max_steps):
        centre = centre + cfg.step_m * d
        st = _station(reader, centre, d, cfg, mc, search_m=cfg.follow_m)
        if st is None:
            # Unobserved road (a hole in the map, e.g. between the pairs of a drive whose
            # frames overlap by less than half): no evidence either way, so the trace goes on
            # straight and stops only when the road is seen and the trough is gone, or after
            # max_unobserved_m.
            unseen += cfg.step_m
            if unseen > cfg.max_unobserved_m:
                break
            continue
        unseen = 0.0
        if not st.ok:
            gap += cfg.step_m
            out.append(st)
            if gap > cfg.max_gap_m:
                break
            continue
        gap = 0.0
        # Follow the trough's centroid (damped): ruts curve with the road.
        normal = np.array([-d[1], d[0]])
        centre = centre + 0.5 * st.centroid_u_m * normal
        st.centre = centre.copy()
        out.append(st)
        path.append(centre.copy())
        if len(path) > cfg.direction_stations:
            step = path[-1] - path[-1 - cfg.direction_stations]
            if np.linalg.norm(step) > 0:
                d_new = step / np.linalg.norm(step)
                if float(d_new @ d) > 0.9:  # at most ~25° per baseline: no U-turns on noise
                    d = d_new
    # Trim the stations after the last one in the rut.
    last = max((k for k, s in enumerate(out) if s.ok), default=-1)
    return out[: last + 1]


def _cells(stations: list[_Station], grid: GridSpec, step_m: float) -> tuple[np.ndarray, ...]:
    """Cells of the stations' trough extents: rows, cols, profile depth (m)."""
    rows, cols, prof_d = [], [], []
    gsd = grid.gsd_m
    for k, st in enumerate(stations):
        if not st.ok:
            continue
        if 0 < k < len(stations) - 1:
            d = stations[k + 1].centre - stations[k - 1].centre
        elif len(stations) > 1:
            d = stations[-1].centre - stations[0].centre
        else:
            continue
        d = d / max(np.linalg.norm(d), 1e-9)
        n = np.array([-d[1], d[0]])
        lo, hi = st.extent_u_m
        corners = np.array(
            [st.centre + uu * n + vv * d for uu in (lo, hi) for vv in (-step_m, step_m)]
        )
        rc = grid.rowcol_from_xy(corners)
        r0, c0 = np.floor(rc.min(axis=0)).astype(int)
        r1, c1 = np.ceil(rc.max(axis=0)).astype(int) + 1
        rr, cc = np.mgrid[r0:r1, c0:c1]
        rr, cc = rr.ravel(), cc.ravel()
        xy = grid.xy_from_rowcol(rr, cc) - st.centre
        u, v = xy @ n, xy @ d
        keep = (np.abs(v) <= 0.5 * step_m + 0.5 * gsd) & (u >= lo) & (u <= hi)
        rr, cc, u = rr[keep], cc[keep], u[keep]
        rows.append(rr)
        cols.append(cc)
        prof_d.append(np.interp(u, st.u_m, np.nan_to_num(st.profile_depth_m, nan=0.0)))
    if not rows:
        e = np.zeros(0, np.int64)
        return e, e, np.zeros(0)
    return _dedupe_cells(
        np.concatenate(rows), np.concatenate(cols), np.concatenate(prof_d), grid.width
    )


def _dedupe_cells(
    r: np.ndarray, c: np.ndarray, p: np.ndarray, width: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each cell once (its first occurrence): rows, cols, profile depth."""
    key = r.astype(np.int64) * width + c
    _, first = np.unique(key, return_index=True)
    first = np.sort(first)
    return r[first], c[first], p[first]


def _end_extension(stations: list[_Station], cfg: RutConfig, end: int) -> float:
    """Length (m) to add beyond the end station (``end`` 0: first, -1: last): the depth ramp
    extrapolated to 0 from where it crosses the trace threshold t and 2t, as the width is
    (w(0) ≈ 2 w(t) − w(2t)). A rut's ends taper; the trace stops where the taper crosses t, a
    third of a 10 mm rut, so without this the length reads short (0.3 m per end on a 0.8 m
    smoothstep taper). An abrupt end (already deeper than 2t) gets nothing; a rut never
    2t deep gets nothing. Depths are a running median over 3 stations (one noisy station
    does not move the end)."""
    if not cfg.extrapolate_ends or len(stations) < 3:
        return 0.0
    seq = stations if end == 0 else stations[::-1]
    d = np.array([s.depth_m for s in seq])
    sm = np.array([np.median(d[max(0, k - 1) : k + 2]) for k in range(len(d))])
    t = max(cfg.trace_min_m, cfg.trace_noise_k * seq[0].noise_m)
    deep = np.flatnonzero(sm >= 2.0 * t)
    if not len(deep) or deep[0] == 0:
        return 0.0
    j = int(deep[0])
    centres = np.array([s.centre for s in seq[: j + 1]])
    return float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum())


def _bridge_stations(stations: list[_Station], cfg: RutConfig) -> list[_Station]:
    """Virtual stations (cells only) across the unobserved stretches a trace went through
    (consecutive stations more than 1.5 steps apart), between two stations in the rut: the
    rut's outline is continuous where the map has a hole, its depth and extent interpolated."""
    out = []
    for a, b in zip(stations[:-1], stations[1:], strict=True):
        dist = float(np.linalg.norm(b.centre - a.centre))
        if not (a.ok and b.ok) or dist <= 1.5 * cfg.step_m:
            continue
        n = int(round(dist / cfg.step_m)) - 1
        for k in range(1, n + 1):
            f = k / (n + 1)
            pa = np.nan_to_num(a.profile_depth_m, nan=0.0)
            pb = np.interp(a.u_m, b.u_m, np.nan_to_num(b.profile_depth_m, nan=0.0))
            out.append(
                _Station(
                    centre=(1 - f) * a.centre + f * b.centre,
                    depth_m=(1 - f) * a.depth_m + f * b.depth_m,
                    width_m=(1 - f) * a.width_m + f * b.width_m,
                    noise_m=max(a.noise_m, b.noise_m),
                    centroid_u_m=0.0,
                    extent_u_m=(
                        (1 - f) * a.extent_u_m[0] + f * b.extent_u_m[0],
                        (1 - f) * a.extent_u_m[1] + f * b.extent_u_m[1],
                    ),
                    u_m=a.u_m,
                    profile_depth_m=(1 - f) * pa + f * pb,
                    ok=True,
                )
            )
    return out


def _extension_stations(
    stations: list[_Station], cfg: RutConfig, end: int, length_m: float
) -> list[_Station]:
    """Virtual stations (cells only) continuing the trace ``length_m`` beyond its ``end``
    station, with that station's trough extent and its profile ramped linearly to 0."""
    n = int(round(length_m / cfg.step_m))
    if n <= 0 or len(stations) < 2:
        return []
    seq = stations if end == 0 else stations[::-1]
    e = seq[0]
    back = seq[min(len(seq) - 1, cfg.direction_stations)]
    d = e.centre - back.centre
    d = d / max(float(np.linalg.norm(d)), 1e-9)
    out = []
    for k in range(1, n + 1):
        f = 1.0 - k / (n + 1)
        out.append(
            dataclasses.replace(
                e,
                centre=e.centre + k * cfg.step_m * d,
                depth_m=f * e.depth_m,
                centroid_u_m=0.0,
                profile_depth_m=f * e.profile_depth_m,
                ok=True,
            )
        )
    return out if end == -1 else out[::-1]


def trace_rut(
    source: WindowSource,
    region: Region,
    cfg: RutConfig,
    mc: MapSegmentConfig,
    reader: _Reader | None = None,
) -> RutTrace | None:
    """Trace the trough through a region (rows/cols on ``source.grid``).

    An elongated region seeds along its long axis. A compact one (a piece of a shallow rut
    where noise crossed T_d) seeds along the direction whose transverse profile holds the
    deepest trough, if that trough is much wider than the region (a pothole is its own trough).
    Returns None when no trough is found at the region's centre.
    """
    grid = source.grid
    if len(region.rows) < 4:
        return None
    xy = grid.xy_from_rowcol(region.rows, region.cols)
    c = xy.mean(axis=0)
    evals, evecs = np.linalg.eigh(np.cov((xy - c).T))
    length = max(4.0 * math.sqrt(max(evals[1], 0.0)), grid.gsd_m)  # ±2σ: a strip's full length
    width = max(4.0 * math.sqrt(max(evals[0], 0.0)), grid.gsd_m)
    elongated = length >= cfg.seed_min_length_m and length >= cfg.seed_elongation * width
    if elongated:
        dirs = [evecs[:, 1]]
    else:
        ang = np.arange(cfg.seed_directions) * math.pi / cfg.seed_directions
        dirs = list(np.column_stack([np.cos(ang), np.sin(ang)]))
    if reader is None:
        reader = _Reader(source, half_m=max(1.5, cfg.straightedge_m))
    st0, along = None, dirs[0]
    for d in dirs:
        st = _station(reader, c, d, cfg, mc, search_m=max(cfg.follow_m, 0.5 * width))
        if st is not None and (st0 is None or (st.ok, st.depth_m) > (st0.ok, st0.depth_m)):
            st0, along = st, d
    if elongated and st0 is None:
        # The profile across the long axis is unobserved: the region is a piece of a trough cut
        # short by holes in the map (a map of narrow strips, frames overlapping by less than
        # half), elongated across the trough. Try every direction; whether the trough goes on
        # beyond the holes (a rut) or not (a pothole) is decided by the trace's length.
        ang = np.arange(cfg.seed_directions) * math.pi / cfg.seed_directions
        for d in np.column_stack([np.cos(ang), np.sin(ang)]):
            st = _station(reader, c, d, cfg, mc, search_m=max(cfg.follow_m, 0.5 * length))
            if st is not None and (st0 is None or (st.ok, st.depth_m) > (st0.ok, st0.depth_m)):
                st0, along = st, d
    if st0 is not None and st0.ok and not elongated and st0.width_m < cfg.seed_width_ratio * length:
        st0.ok = False  # the trough is the region itself: a pothole, not a piece of a rut
    if st0 is None or not st0.ok:
        log.debug(
            "ruts: region at %s (%.2f x %.2f m): no trough through it (%s)",
            np.round(c, 2), length, width,
            "unobserved" if st0 is None else
            f"{1000 * st0.depth_m:.1f} mm, σ {1000 * st0.noise_m:.2f} mm, {st0.width_m:.2f} m wide",
        )  # fmt: skip
        return None
    st0.centre = c + st0.centroid_u_m * np.array([-along[1], along[0]])
    fwd = _march(reader, st0.centre, along, cfg, mc)
    bwd = _march(reader, st0.centre, -along, cfg, mc)
    stations = bwd[::-1] + [st0] + fwd
    ok = np.array([s.ok for s in stations])
    idx = np.flatnonzero(ok)
    stations = stations[idx[0] : idx[-1] + 1]
    ok = ok[idx[0] : idx[-1] + 1]
    centres = np.array([s.centre for s in stations])
    seg = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    length_m = float(seg.sum()) + cfg.step_m
    depths = np.array([s.depth_m for s in stations])
    k = max(1, int(round(cfg.depth_window_m / cfg.step_m)) | 1)
    if len(depths) >= k:
        med = np.median(np.lib.stride_tricks.sliding_window_view(depths, k), axis=1)
    else:
        med = np.array([np.median(depths)])
    ext_b, ext_f = (_end_extension(stations, cfg, end) for end in (0, -1))
    virtual = (
        _extension_stations(stations, cfg, 0, ext_b)
        + _extension_stations(stations, cfg, -1, ext_f)
        + _bridge_stations(stations, cfg)
    )
    rows, cols, prof = _cells(stations, grid, cfg.step_m)
    if virtual:
        rv, cv, pv = _cells(virtual, grid, cfg.step_m)
        rows, cols, prof = _dedupe_cells(
            np.concatenate([rows, rv]), np.concatenate([cols, cv]), np.concatenate([prof, pv]),
            grid.width,
        )  # fmt: skip
    trace = RutTrace(
        centres_xy_m=centres,
        depth_m=depths,
        width_m=np.array([s.width_m for s in stations]),
        noise_m=np.array([s.noise_m for s in stations]),
        in_rut=ok,
        length_m=length_m + ext_b + ext_f,
        max_depth_m=float(med.max()),
        end_extension_m=(ext_b, ext_f),
        rows=rows,
        cols=cols,
        cell_profile_m=prof,
    )
    log.debug(
        "ruts: trace at %s: %d stations (%d in rut), %.2f m (+ %.2f, %.2f m ends), depth %.1f mm, "
        "%d window read(s)",
        np.round(c, 2), len(stations), int(ok.sum()), length_m, ext_b, ext_f,
        1000 * trace.max_depth_m, reader.reads,
    )  # fmt: skip
    return trace


def longest_trough_m(trace: RutTrace, cfg: RutConfig) -> float:
    """Length (m) of the trace's longest stretch that no flat gap cuts.

    A station is at road level when it lies shallower than ``flat_gap_frac`` x the trough on
    both sides of it (the deepest station within ``flat_gap_ref_m`` before it, and after it);
    at least ``flat_gap_m`` of such stations in a row are flat road between two troughs. A
    rut shallows and deepens along its length and noise drops single stations out of it, but
    it does not come back to the road level between two deep stretches; two potholes in a
    line do. A stretch runs from its first station in the rut to its last. Without flat gaps
    this is ``measured_length_m``."""
    ok = np.asarray(trace.in_rut, bool)
    if not ok.any():
        return 0.0
    c = np.asarray(trace.centres_xy_m, float)
    depth = np.where(np.isfinite(trace.depth_m), trace.depth_m, 0.0)
    n = depth.size
    w = max(1, int(round(cfg.flat_gap_ref_m / cfg.step_m)))
    pad = np.r_[np.full(w, -np.inf), depth, np.full(w, -np.inf)]
    win = np.lib.stride_tricks.sliding_window_view(pad, w)  # win[j] = pad[j : j + w]
    before = win[:n].max(axis=1)  # depth[k - w : k]
    after = win[w + 1 : w + 1 + n].max(axis=1)  # depth[k + 1 : k + 1 + w]
    flat = depth < cfg.flat_gap_frac * np.minimum(before, after)
    min_run = max(1, int(round(cfg.flat_gap_m / cfg.step_m)))
    # runs of flat stations at least min_run long cut the trace into stretches
    runs, n_runs = ndimage.label(flat)
    long_runs = 1 + np.flatnonzero(np.bincount(runs, minlength=n_runs + 1)[1:] >= min_run)
    stretches, n_stretches = ndimage.label(~np.isin(runs, long_runs))
    seg = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))]
    best = 0.0
    for s in range(1, n_stretches + 1):
        idx = np.flatnonzero((stretches == s) & ok)
        if idx.size:
            best = max(best, float(seg[idx[-1]] - seg[idx[0]]) + cfg.step_m)
    return best


def trace_ruts(
    source: WindowSource,
    regions: list[Region],
    cfg: RutConfig,
    mc: MapSegmentConfig,
    ev_xy_m: np.ndarray,
    ev_pair: np.ndarray,
    scan_seeds: list[Region] | None = None,
) -> list[Region]:
    """Replace the pieces of every rut among ``regions`` by the traced rut (``Region.rut`` set).

    ev_xy_m: (N, 2) grid xy of the pairs' defect points, ev_pair: (N,) their pair ids; the
    points inside a rut's cells are its 3D support. Regions that seed no rut are returned as
    they are. ``scan_seeds`` (from ``scan_seeds``) are tried after the regions and returned
    only as traced ruts.
    """
    seeds = list(scan_seeds or [])
    if not cfg.enabled or not (regions or seeds):
        return regions
    grid = source.grid
    width = grid.width
    keyset_of = [set((r.rows.astype(np.int64) * width + r.cols).tolist()) for r in regions]
    ruts: list[tuple[RutTrace, set[int]]] = []
    covered: set[int] = set()
    # Largest regions first (one trace usually swallows the other pieces), then the scan seeds.
    order = sorted(range(len(regions)), key=lambda i: -len(regions[i].rows))
    todo = [(regions[i], keyset_of[i]) for i in order] + [
        (r, set((r.rows.astype(np.int64) * width + r.cols).tolist())) for r in seeds
    ]
    reader = _Reader(source, half_m=max(1.5, cfg.straightedge_m))  # one cache for all traces
    for reg, keys in todo:
        if keys and len(keys & covered) >= 0.5 * len(keys):
            continue  # a piece of a rut traced already
        tr = trace_rut(source, reg, cfg, mc, reader)
        if tr is None or not len(tr.rows):
            continue
        w_med = float(np.median(tr.width_m[tr.in_rut]))
        min_len = max(mc.rut_min_length_m, mc.elongation_min * w_med)
        if tr.measured_length_m < min_len:
            log.debug("ruts: trace of %.2f x %.2f m is too short for a rut", tr.length_m, w_med)
            continue
        longest = longest_trough_m(tr, cfg)
        if longest < min_len:
            log.debug(
                "ruts: trace of %.2f m crosses flat road (longest trough %.2f m): not a rut",
                tr.length_m, longest,
            )  # fmt: skip
            continue
        tkeys = set((tr.rows.astype(np.int64) * width + tr.cols).tolist())
        ruts.append((tr, tkeys))
        covered |= tkeys
    if not ruts:
        return regions
    # Traces that overlap are the same rut: keep the longer one's stations, union the cells.
    merged: list[tuple[RutTrace, set[int]]] = []
    for tr, tk in sorted(ruts, key=lambda t: -t[0].length_m):
        for j, (mt, mk) in enumerate(merged):
            if len(tk & mk) >= 0.2 * min(len(tk), len(mk)):
                merged[j] = (_union(mt, tr, width), mk | tk)
                break
        else:
            merged.append((tr, tk))
    out: list[Region] = []
    rut_keys: set[int] = set().union(*(k for _, k in merged))
    for i, reg in enumerate(regions):
        keys = keyset_of[i]
        if keys and len(keys & rut_keys) >= 0.5 * len(keys):
            log.debug("ruts: region at %s is a piece of a rut", (reg.rows[0], reg.cols[0]))
            continue
        out.append(reg)
    ev_rc = (
        np.floor(grid.rowcol_from_xy(ev_xy_m) + 0.5).astype(np.int64)
        if len(ev_xy_m)
        else np.zeros((0, 2), np.int64)
    )
    ev_key = ev_rc[:, 0] * width + ev_rc[:, 1]
    r_pad = max(0, int(round(mc.point_support_radius_m / grid.gsd_m)))
    dr, dc = np.mgrid[-r_pad : r_pad + 1, -r_pad : r_pad + 1]
    offsets = (dr * width + dc).ravel()
    for tr, tk in merged:
        # Support: defect points on the rut's cells or within the support radius.
        cells = np.fromiter(tk, np.int64)
        box = (
            (ev_rc[:, 0] >= tr.rows.min() - r_pad)
            & (ev_rc[:, 0] <= tr.rows.max() + r_pad)
            & (ev_rc[:, 1] >= tr.cols.min() - r_pad)
            & (ev_rc[:, 1] <= tr.cols.max() + r_pad)
        )
        idx = np.flatnonzero(box)
        idx = idx[np.isin(ev_key[idx, None] + offsets[None, :], cells).any(axis=1)]
        prof = tr.cell_profile_m.astype(float)
        # The profile depth stands for the cell's depth too: measure() reads both, and the
        # station averages are what the rut is measured by (a single cell is noise).
        reg = Region(rows=tr.rows, cols=tr.cols, depth_m=prof, depth_smooth_m=prof)
        reg.support_idx = idx
        reg.support_pairs = set(np.unique(ev_pair[idx]).tolist()) if len(idx) else set()
        reg.n_support_points = len(idx)
        reg.noise_m = float(np.median(tr.noise_m))
        reg.seed_m = float("nan")
        reg.rut = tr
        out.append(reg)
        log.info(
            "ruts: %.2f m rut, depth %.1f mm (straightedge %.1f m), width %.2f m, %d pair(s)",
            tr.length_m, 1000 * tr.max_depth_m, cfg.straightedge_m,
            float(np.median(tr.width_m[tr.in_rut])), len(reg.support_pairs),
        )  # fmt: skip
    return out


def _union(a: RutTrace, b: RutTrace, width: int) -> RutTrace:
    """Two traces of one rut: the stations of ``a`` (the longer, see ``trace_ruts``), both
    traces' cells."""
    key_a = a.rows.astype(np.int64) * width + a.cols
    key_b = b.rows.astype(np.int64) * width + b.cols
    extra = ~np.isin(key_b, key_a)
    return dataclasses.replace(
        a,
        max_depth_m=max(a.max_depth_m, b.max_depth_m),
        rows=np.concatenate([a.rows, b.rows[extra]]),
        cols=np.concatenate([a.cols, b.cols[extra]]),
        cell_profile_m=np.concatenate([a.cell_profile_m, b.cell_profile_m[extra]]),
    )


_BOX = ((-1, -1), (1, -1), (1, 1), (-1, 1))  # a rectangle's corners (across, along) in order


def scan_seeds(
    source: WindowSource,
    path_xy_m: np.ndarray,
    cfg: RutConfig,
    mc: MapSegmentConfig,
    observed: Any = None,
) -> list[Region]:
    """Seeds for ruts too shallow to cross T_d anywhere: transverse profiles across the drive.

    path_xy_m: (P, 2) grid xy of the footprint centres in drive order. Every ``scan_step_m``
    along it, stations at lateral offsets up to ``scan_half_width_m`` look for a trough (the
    same test as a traced station, along the direction of travel: wheel-path ruts run with
    the lane). Troughs found at two consecutive scan lines within ``follow_m`` of each other
    become a thin seed region between them. Returns [] when scanning is off.
    ``observed``: optional shapely geometry (grid m) outside which the source holds no data
    (a fused run maps only the stretches it reconstructed); scan lines that miss it are not
    read.
    """
    path = np.asarray(path_xy_m, float)
    if path.ndim != 2 or path.shape[1] != 2:
        raise ValueError(f"path_xy_m: expected (P, 2), got {path.shape}")
    if not cfg.enabled or cfg.scan_step_m <= 0 or len(path) < 2:
        return []
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] < cfg.scan_step_m:
        return []
    t0 = time.perf_counter()
    ss = np.arange(0.0, s[-1], cfg.scan_step_m)
    pts = np.column_stack([np.interp(ss, s, path[:, 0]), np.interp(ss, s, path[:, 1])])
    tang = np.gradient(pts, axis=0)
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-9)
    # Windows wide enough for a whole scan line (and ~2 m of drive): few reads.
    reader = _Reader(source, half_m=cfg.scan_half_width_m + cfg.straightedge_m + 1.0)
    n_off = int(round(cfg.scan_half_width_m / cfg.follow_m))
    offsets = np.arange(-n_off, n_off + 1) * cfg.follow_m
    # Coarse samples (1 cm): the scan only finds seeds, the trace measures.
    u, v = _station_axes(source.grid.gsd_m, cfg, 0.01)
    hits: list[list[np.ndarray]] = []
    # a scan line's samples lie within these half-widths of its centre (+2 cm for the cells)
    reach_u = cfg.scan_half_width_m + 0.5 * cfg.straightedge_m + 0.02
    reach_v = 0.5 * cfg.strip_m + 0.02
    mapped = np.ones(len(pts), bool)
    if observed is not None:
        import shapely

        nrms = np.column_stack([-tang[:, 1], tang[:, 0]])
        corners = [pts + a * reach_u * nrms + b * reach_v * tang for a, b in _BOX]
        bands = shapely.polygons(np.stack(corners, axis=1))
        mapped = shapely.intersects(observed, bands)
    for p, d, on_map in zip(pts, tang, mapped, strict=True):
        found: list[np.ndarray] = []
        if not on_map:
            hits.append(found)
            continue
        nrm = np.array([-d[1], d[0]])
        # One read for the whole scan line; stations on unmapped road (most of a fused run's
        # map) are skipped before any profile work.
        centres = p + offsets[:, None] * nrm
        line = centres[:, None, None] + u[None, None, :, None] * nrm + v[None, :, None, None] * d
        z_line = reader.sample(line)  # (offsets, V, U)
        enough = _observed_enough(z_line)
        for k, o in enumerate(offsets):
            if not enough[k]:
                continue
            st = _station(
                reader, p + o * nrm, d, cfg, mc, search_m=cfg.follow_m, sample_m=0.01, z=z_line[k]
            )
            if st is None or not st.ok:
                continue
            c = st.centre + st.centroid_u_m * nrm
            if all(np.linalg.norm(c - f) > cfg.follow_m for f in found):
                found.append(c)
        hits.append(found)
    grid = source.grid
    out: list[Region] = []
    for k in range(len(hits) - 1):
        for a in hits[k]:
            for b in hits[k + 1]:
                if abs(float((b - a) @ np.array([-tang[k][1], tang[k][0]]))) > cfg.follow_m:
                    continue
                t = np.linspace(0.0, 1.0, max(2, int(np.linalg.norm(b - a) / grid.gsd_m) + 1))
                line = a + t[:, None] * (b - a)
                rc = np.unique(np.floor(grid.rowcol_from_xy(line) + 0.5).astype(np.int64), axis=0)
                z = np.zeros(len(rc))
                out.append(Region(rows=rc[:, 0], cols=rc[:, 1], depth_m=z, depth_smooth_m=z))
    log.info(
        "ruts: scanned %.0f m of drive (%d lines x %d stations) in %.2f s: %d seed(s), "
        "%d window read(s)",
        s[-1], len(pts), len(offsets), time.perf_counter() - t0, len(out), reader.reads,
    )  # fmt: skip
    return out
