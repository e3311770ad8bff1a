"""One station of a rut: the transverse profile under a straightedge across the trough.

The residual raster is sampled on a profile ``straightedge_m`` long, averaged over ``strip_m``
along the trough; the road level is a robust line through the profile (the trough left out), and
the station's depth, width and trough centroid are read off the levelled, smoothed profile (see
``ruts`` for the method and ``measure_station`` for the rules).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from roadsurf.core.fits import robust_sigma
from roadsurf.detection.config import MapSegmentConfig, RutConfig
from roadsurf.detection.windows import WindowSource
from roadsurf.io.formats import GridSpec


class ProfileReader:
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
class Station:
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


def run_extent(depth: np.ndarray, i: int, t: float) -> tuple[int, int]:
    """Contiguous run of samples around i with depth >= t: (first, last) indices (a rut's
    profile here, a crack's cross profile in ``crackraster``)."""
    lo = i
    while lo > 0 and depth[lo - 1] >= t:
        lo -= 1
    hi = i
    while hi < len(depth) - 1 and depth[hi + 1] >= t:
        hi += 1
    return lo, hi


def station_axes(
    gsd_m: float, cfg: RutConfig, sample_m: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """A station's sample offsets (m): across (U,) every max(cell, ``sample_m``) over the
    straightedge, along (V,) twice that over the strip (every cell when ``sample_m`` is 0)."""
    gsd = max(gsd_m, sample_m)
    half = 0.5 * cfg.straightedge_m
    u = np.arange(-half, half + 1e-9, gsd)
    v = np.arange(-0.5 * cfg.strip_m, 0.5 * cfg.strip_m + 1e-9, gsd if sample_m <= 0 else 2 * gsd)
    return u, v


def observed_enough(z: np.ndarray) -> np.ndarray:
    """(..., V, U) samples -> (...) bool: enough of the profile observed for a station (a
    profile sample is observed with 30 % of its strip, and half the samples must be)."""
    n_obs = np.isfinite(z).sum(axis=-2)
    v, u = z.shape[-2:]
    return (n_obs >= max(1, 0.3 * v)).sum(axis=-1) >= 0.5 * u


def measure_station(
    reader: ProfileReader,
    centre: np.ndarray,
    along: np.ndarray,
    cfg: RutConfig,
    mc: MapSegmentConfig,
    search_m: float,
    sample_m: float = 0.0,
    z: np.ndarray | None = None,
) -> Station | None:
    """Transverse profile at ``centre`` across unit direction ``along`` (both (2,) grid m),
    sampled every max(cell, ``sample_m``) across and twice that along (``station_axes``).
    ``z`` (V, U): those samples when the caller has read them already."""
    gsd = max(reader.grid.gsd_m, sample_m)
    normal = np.array([-along[1], along[0]])
    u, v = station_axes(reader.grid.gsd_m, cfg, sample_m)
    if z is None:
        pts = centre + u[None, :, None] * normal + v[:, None, None] * along
        z = reader.sample(pts)  # (V, U)
    if not observed_enough(z):
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
    lo, hi = run_extent(np.nan_to_num(depth, nan=-1.0), i, rim)
    w_t = (hi - lo + 1) * gsd
    lo2, hi2 = (
        run_extent(np.nan_to_num(depth, nan=-1.0), i, 2 * rim) if d_max >= 2 * rim else (i, i)
    )
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
    return Station(
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
