"""A two-frame photo pair's surface against its truth (issue 29's real-pair targets).

The run has no GPS, so its map is in a local metric frame: camera a's pose in the run and in
the truth (``truth/stereo_pair.json``, written by ``simulation.stereo``) tie the two frames,
and a search over whole-millimetre horizontal shifts (±``SHIFT_M``) plus a median height
offset absorbs what the tie leaves (the road level under camera a). Then, over the cells the
run measured (``surface_nobs`` > 0):

- ``pothole_rms_m`` / ``pothole_mae_m``: cells whose true residual is deeper than
  ``POTHOLE_M``, height differences (vertical);
- ``pothole_surface_rms_m``: the same cells' distance to the true surface (issue 29: "RMS
  distance to the true surface ≤ 2.2 mm", Fan et al.'s figure, a cloud-to-surface distance):
  from each cell's point (its centre at the truth's height plus its difference) to the nearest
  point of the bilinear truth surface, searched on a 0.5 mm lattice within the vertical
  difference (the point straight below or above is that far; at most ``SURFACE_SEARCH_M``). On
  a wall of slope m a point off by e along the camera's ray is off vertically by about
  e (1 + m cot θ): the vertical figure triples there;
- ``flat_mae_m``: the other cells;
- ``depth_error_m``: the deepest reported pothole's ``max_depth_m`` minus the truth's deepest
  point among the measured cells (target within 3 mm); ``depth_error_median3_m`` against the
  truth's 3 x 3 median (a support like the run's supported maximum);
- ``found``: a pothole was reported;
- ``pothole_measured_share``: the share of the truth's pothole cells (4 mm) inside the hull of
  the measured cells that hold a measurement (a tilted camera cannot see a steep near wall).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from roadsurf.evaluation.corridor import heights_from_xy
from roadsurf.io import drivefolder as df
from roadsurf.io import runfolder as rf
from roadsurf.io.drive.camera_yaml import load_camera
from roadsurf.io.formats import GridSpec, read_geotiff

POTHOLE_M = 0.005  # truth residual below -5 mm counts as inside the pothole (m)
SHIFT_M = 0.03  # horizontal registration search half-width (m): the tie's lever arm
SHIFT_STEP_M = 0.002  # search step (m); refined to 0.5 mm around the best
SURFACE_SEARCH_M = 0.015  # nearest-surface search radius (m): beyond, the vertical difference
SURFACE_STEP_M = 0.0005  # nearest-surface search lattice (m)


def _read_truth(truth_tif: Path) -> tuple[np.ndarray, GridSpec]:
    """(H, W) float truth raster (NaN where nodata) and its grid."""
    data, grid, nodata = read_geotiff(truth_tif)
    t = np.asarray(data, float)
    if nodata is not None and np.isfinite(nodata):
        t[t == nodata] = np.nan
    return t, grid


def _measured_share(t: np.ndarray, grid: GridSpec, e: np.ndarray, n: np.ndarray) -> float:
    """Share of the truth's pothole cells (deeper than POTHOLE_M) inside the hull of the run's
    measured cells (at e, n) that hold one of them: hidden walls and holes count against it."""
    import cv2

    rc = np.round(grid.rowcol_from_xy(np.column_stack([e, n]))).astype(np.int64)
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < t.shape[0]) & (rc[:, 1] >= 0) & (rc[:, 1] < t.shape[1])
    rc = rc[inside]
    hull = np.zeros(t.shape, np.uint8)
    if len(rc) >= 3:
        cv2.fillConvexPoly(hull, cv2.convexHull(rc[:, ::-1].astype(np.int32)), 1)
    pit = (hull > 0) & (np.nan_to_num(t, nan=0.0) < -POTHOLE_M)
    seen = np.zeros(t.shape, bool)
    seen[rc[:, 0], rc[:, 1]] = True
    return float((seen & pit).sum() / pit.sum()) if pit.any() else float("nan")


def _sampler(t: np.ndarray, grid: GridSpec):
    """(e, n) -> the raster ``t`` bilinear at those points (``surface.heights_from_xy``)."""

    def sample(e: np.ndarray, n: np.ndarray) -> np.ndarray:
        return heights_from_xy(np.column_stack([e, n]), t, grid.transform)

    return sample


def _surface_distance(e: np.ndarray, n: np.ndarray, z: np.ndarray, sample) -> np.ndarray:
    """(N,) distance (m) from points (e, n, z) to the surface ``sample(e, n)`` (bilinear): the
    vertical difference, or less where a surface point within it horizontally (a 0.5 mm
    lattice up to ``SURFACE_SEARCH_M``) is nearer. NaN where the surface is not under the
    point."""
    best = np.abs(z - sample(e, n))
    under = np.isfinite(best)
    r = min(float(best[under].max()), SURFACE_SEARCH_M) if under.any() else 0.0
    k = int(np.ceil(r / SURFACE_STEP_M))
    offsets = [(i, j) for i in range(-k, k + 1) for j in range(-k, k + 1) if 0 < i * i + j * j]
    for i, j in sorted(offsets, key=lambda o: o[0] ** 2 + o[1] ** 2):
        h2 = (i * i + j * j) * SURFACE_STEP_M**2
        sel = np.flatnonzero(best * best > h2)  # only a point further than h can come nearer
        if not len(sel):
            break
        de, dn = i * SURFACE_STEP_M, j * SURFACE_STEP_M
        cand = np.sqrt(h2 + (z[sel] - sample(e[sel] + de, n[sel] + dn)) ** 2)
        best[sel] = np.fmin(best[sel], cand)
    best[~under] = np.nan
    return best


def _deepest_pothole_m(run_dir: Path) -> float | None:
    path = run_dir / rf.DEFECTS_CSV
    if not path.is_file():
        return None
    with path.open(newline="") as f:
        depths = [float(r["max_depth_m"]) for r in csv.DictReader(f) if r["type"] == "pothole"]
    return max(depths) if depths else None


def score_pair(run_dir: str | Path, drive_dir: str | Path) -> dict[str, Any]:
    """Figures of one pair run against its drive's truth (module docstring)."""
    run_dir, drive_dir = Path(run_dir), Path(drive_dir)
    meta = json.loads((drive_dir / df.TRUTH_DIR / df.TRUTH_STEREO_PAIR_JSON).read_text())
    T_true = np.asarray(meta["world_from_cam"][0], float)
    T_run = np.load(run_dir / rf.POSES_NPZ)["world_from_cam"][0]
    R_wl = T_true[:3, :3] @ T_run[:3, :3].T  # truth local from run local
    t_wl = T_true[:3, 3] - R_wl @ T_run[:3, 3]
    height = load_camera(drive_dir / df.CAMERA_YAML).height_m

    s, grid, nodata = read_geotiff(run_dir / rf.SURFACE_TIF)
    s = np.asarray(s, float)
    if nodata is not None and np.isfinite(nodata):
        s[s == nodata] = np.nan
    nobs, _, _ = read_geotiff(run_dir / f"{rf.SURFACE_NOBS}.tif")
    s[np.asarray(nobs) == 0] = np.nan  # the road model's cells are not measurements
    rows, cols = np.nonzero(np.isfinite(s))
    if len(rows) == 0:
        return {"found": False, "cells": 0}
    xy = grid.xy_from_rowcol(rows, cols)
    z = np.full(len(xy), T_run[2, 3] - height)  # the road under camera a, in the run's frame
    p = np.column_stack([xy, z]) @ R_wl.T + t_wl
    e0, n0 = p[:, 0] + meta["origin_e_m"], p[:, 1] + meta["origin_n_m"]
    ours = s[rows, cols]
    truth, tgrid = _read_truth(drive_dir / df.TRUTH_DIR / df.TRUTH_RESIDUAL_TIF)
    sample = _sampler(truth, tgrid)

    def misfit(dx: float, dy: float, sub: slice) -> float:
        t = sample(e0[sub] + dx, n0[sub] + dy)
        d = ours[sub] - t
        d = d[np.isfinite(d)]
        return float(np.sqrt(np.mean((d - np.median(d)) ** 2))) if len(d) > 100 else np.inf

    sub = slice(None, None, max(1, len(ours) // 20000))
    grid_c = np.arange(-SHIFT_M, SHIFT_M + 1e-9, SHIFT_STEP_M)
    _, dx, dy = min((misfit(a, b, sub), a, b) for a in grid_c for b in grid_c)
    fine = np.arange(-SHIFT_STEP_M, SHIFT_STEP_M + 1e-9, 0.0005)
    _, dx, dy = min((misfit(dx + a, dy + b, sub), dx + a, dy + b) for a in fine for b in fine)

    t = sample(e0 + dx, n0 + dy)
    ok = np.isfinite(t)
    d = ours[ok] - t[ok]
    d -= np.median(d)
    pit = t[ok] < -POTHOLE_M
    ours_depth = _deepest_pothole_m(run_dir)
    true_depth = float(-np.min(t[ok])) if ok.any() else float("nan")
    # the truth's deepest point with a support like ours (a 3 x 3 median of the truth grid):
    # the raw one holds the floor's roughness spikes, which no 4-9 mm matching window keeps
    t3 = _sampler(ndimage.median_filter(truth, size=3), tgrid)(e0 + dx, n0 + dy)
    true_depth_3 = float(-np.nanmin(t3[ok])) if ok.any() else float("nan")
    share = _measured_share(truth, tgrid, e0 + dx, n0 + dy)
    ep, np_ = (e0 + dx)[ok][pit], (n0 + dy)[ok][pit]
    dn = _surface_distance(ep, np_, t[ok][pit] + d[pit], sample)
    return {
        "found": ours_depth is not None,
        "pothole_measured_share": share,
        "cells": int(ok.sum()),
        "shift_m": [round(dx, 4), round(dy, 4)],
        "pothole_cells": int(pit.sum()),
        "pothole_rms_m": float(np.sqrt(np.mean(d[pit] ** 2))) if pit.any() else None,
        "pothole_mae_m": float(np.mean(np.abs(d[pit]))) if pit.any() else None,
        "pothole_surface_rms_m": (
            float(np.sqrt(np.nanmean(dn**2))) if np.isfinite(dn).any() else None
        ),
        "flat_mae_m": float(np.mean(np.abs(d[~pit]))) if (~pit).any() else None,
        "true_max_depth_m": true_depth,
        "true_max_depth_median3_m": true_depth_3,
        "max_depth_m": ours_depth,
        "depth_error_m": None if ours_depth is None else ours_depth - true_depth,
        "depth_error_median3_m": None if ours_depth is None else ours_depth - true_depth_3,
    }
