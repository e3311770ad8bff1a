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

Modules: ``rutprofile`` (one station, steps 2-3), ``ruttrace`` (the march, step 4), ``rutscan``
(seeds for ruts too shallow to segment), ``rutrecord`` (``RutTrace``); this one (step 5) turns
the traces into the map's regions.
"""

from __future__ import annotations

import logging

import numpy as np

from roadsurf.detection.config import MapSegmentConfig, RutConfig
from roadsurf.detection.mapseg import Region
from roadsurf.detection.rutprofile import ProfileReader
from roadsurf.detection.rutrecord import RutTrace, longest_trough_m, union_traces
from roadsurf.detection.ruttrace import trace_rut
from roadsurf.detection.windows import WindowSource

log = logging.getLogger(__name__)


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
    they are. ``scan_seeds`` (from ``rutscan.scan_seeds``) are tried after the regions and returned
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
    reader = ProfileReader(source, half_m=max(1.5, cfg.straightedge_m))  # one cache for all traces
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
                merged[j] = (union_traces(mt, tr, width), mk | tk)
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
