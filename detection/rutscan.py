"""Seeds for ruts too shallow to cross the map's seed threshold T_d anywhere: scan lines of
transverse profiles across the drive (see ``scan_seeds``)."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from roadsurf.detection.config import MapSegmentConfig, RutConfig
from roadsurf.detection.mapseg import Region
from roadsurf.detection.rutprofile import (
    ProfileReader,
    measure_station,
    observed_enough,
    station_axes,
)
from roadsurf.detection.windows import WindowSource

if TYPE_CHECKING:
    from shapely.geometry.base import BaseGeometry

log = logging.getLogger(__name__)


_BOX = ((-1, -1), (1, -1), (1, 1), (-1, 1))  # a rectangle's corners (across, along) in order


def scan_seeds(
    source: WindowSource,
    path_xy_m: np.ndarray,
    cfg: RutConfig,
    mc: MapSegmentConfig,
    observed: BaseGeometry | None = None,
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
    reader = ProfileReader(source, half_m=cfg.scan_half_width_m + cfg.straightedge_m + 1.0)
    n_off = int(round(cfg.scan_half_width_m / cfg.follow_m))
    offsets = np.arange(-n_off, n_off + 1) * cfg.follow_m
    # Coarse samples (1 cm): the scan only finds seeds, the trace measures.
    u, v = station_axes(source.grid.gsd_m, cfg, 0.01)
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
        enough = observed_enough(z_line)
        for k, o in enumerate(offsets):
            if not enough[k]:
                continue
            st = measure_station(
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
