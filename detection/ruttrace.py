"""Tracing a rut from a seed region: stations march along the trough in both directions, and the
stations in the rut become its cells, length and depth (a ``RutTrace``).

Stations every ``step_m`` follow the trough's centroid (ruts curve with the road) and stop after
``max_gap_m`` out of the rut; the ends are extended by the depth ramp extrapolated to 0, and
unobserved stretches between two stations in the rut are bridged by virtual stations.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from roadsurf.detection.config import MapSegmentConfig, RutConfig
from roadsurf.detection.mapseg import Region
from roadsurf.detection.rutprofile import ProfileReader, Station, measure_station
from roadsurf.detection.rutrecord import RutTrace
from roadsurf.detection.windows import WindowSource
from roadsurf.io.formats import GridSpec

log = logging.getLogger(__name__)


def _march(
    reader: ProfileReader,
    start: np.ndarray,
    along: np.ndarray,
    cfg: RutConfig,
    mc: MapSegmentConfig,
) -> list[Station]:
    """Stations from ``start`` in direction ``along`` until the trough ends."""
    out: list[Station] = []
    centre, d = start.astype(float), along / np.linalg.norm(along)
    gap, unseen, path = 0.0, 0.0, [centre.copy()]
    max_steps = int(cfg.max_length_m / cfg.step_m)
    for _ in range(max_steps):
        centre = centre + cfg.step_m * d
        st = measure_station(reader, centre, d, cfg, mc, search_m=cfg.follow_m)
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


def _cells(stations: list[Station], grid: GridSpec, step_m: float) -> tuple[np.ndarray, ...]:
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


def _end_extension(stations: list[Station], cfg: RutConfig, end: int) -> float:
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


def _bridge_stations(stations: list[Station], cfg: RutConfig) -> list[Station]:
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
                Station(
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
    stations: list[Station], cfg: RutConfig, end: int, length_m: float
) -> list[Station]:
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
    reader: ProfileReader | None = None,
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
        reader = ProfileReader(source, half_m=max(1.5, cfg.straightedge_m))
    st0, along = None, dirs[0]
    for d in dirs:
        st = measure_station(reader, c, d, cfg, mc, search_m=max(cfg.follow_m, 0.5 * width))
        if st is not None and (st0 is None or (st.ok, st.depth_m) > (st0.ok, st0.depth_m)):
            st0, along = st, d
    if elongated and st0 is None:
        # The profile across the long axis is unobserved: the region is a piece of a trough cut
        # short by holes in the map (a map of narrow strips, frames overlapping by less than
        # half), elongated across the trough. Try every direction; whether the trough goes on
        # beyond the holes (a rut) or not (a pothole) is decided by the trace's length.
        ang = np.arange(cfg.seed_directions) * math.pi / cfg.seed_directions
        for d in np.column_stack([np.cos(ang), np.sin(ang)]):
            st = measure_station(reader, c, d, cfg, mc, search_m=max(cfg.follow_m, 0.5 * length))
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
