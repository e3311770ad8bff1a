"""Depth profile of a defect along its long axis, from surface.tif or from the cloud."""

from __future__ import annotations

import math

import numpy as np

from roadsurf.io.formats import GridSpec
from roadsurf.io.runfolder import RunFolder
from roadsurf.viewer.derived import rowcol_from_enu
from roadsurf.viewer.rundata import DefectView, RunData


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
    path = RunFolder(data.run_dir).surface_tif
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
