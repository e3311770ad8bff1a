"""A crack's width and depth read on the surface raster (RUN/surface.tif), across its centre line.

The crack's map samples (``crackmap``: the 2D pieces of every pair, mapped onto the road and
placed with the trajectory, so they lie in the raster's own frame) are thinned to stations every
``raster_step_m`` along the crack; at each station the raster is sampled on a profile across the
crack (its direction from the samples around the station). The road level of a profile is a
straight line fitted to its two outer parts (beyond half the crack's width plus the raster's
smoothing footprint on both sides), so a cross-fall or a slope does not read as depth.

What the raster can tell depends on whether it resolves the crack. The dense surface is a field
of *window means* (``reconstruction.dense``: a ``window_px`` matching window, fused on cells of
``dense_gsd_px`` pixels, so about 2.5 cells: ``raster_footprint_cells``). A crack whose dip is
at least ``raster_resolved_k`` footprints wide at half its depth is **resolved**: width = √2 x
the full width at half depth (the parabolic groove's, depth D (1 − q²)) and depth = the median
over the profiles of each profile's deepest point below its road line (source ``raster``). A
narrower crack is not: the window averages its groove with the road beside it. Linear
smoothing would keep the profile's cross-section ∫ depth ds (= ⅔ D w for the parabola, so
D = 1.5 A / w with the image's w), but the matcher is not linear there: on the simulated drives
the raster keeps 64-87 % of a 4-5 mm crack's cross-section at nadir, 26-61 % in a tilted
camera's near field and nothing in its far field (docs/detection.md), so a depth from it would
read 1.2-4 x shallow, or nothing at all. Such cracks, cracks the raster does not see beyond its
noise, and cracks with too few profiles keep the pairs' figures (source ``points``); the
profiles are still counted and the cross-section logged.

**Confirmation** (``raster_crack_evidence``, for the candidates the pairs' pooled 3D test leaves
unconfirmed): the mean cross-section over the profiles against its standard error. Neighbouring
profiles share window means, the surface's smoothing and the road's own relief, so the error is
taken from blocks of ``raster_block_footprints`` footprints along the crack (batch means) and the
threshold is Student's t with blocks − 1 degrees of freedom at the one-sided level of
``raster_z_k`` σ. A 4-5 mm crack the raster keeps ~30 % of (tilted 25°, D008: 3.7 mm² of
12 mm², z 1.9 over 1.1 m) would need ~3 m of crack at the simulated drives' raster noise.

The raster's noise σ is the robust spread (1.4826 MAD) of the profiles' outer parts around their
road lines; the cross-section's standard error is the spread of the profiles' A over the square
root of the number of *independent* profiles (neighbouring profiles closer than the footprint
share their window means).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA, robust_sigma
from roadsurf.detection.config import CrackConfig
from roadsurf.detection.rutprofile import run_extent
from roadsurf.detection.windows import WindowSource

log = logging.getLogger(__name__)

MAX_WINDOW_CELLS = 4_000_000  # a crack's bounding window larger than this is not read (cells)


@dataclass(frozen=True)
class RasterCrack:
    """A crack measured across its centre line on the raster (lengths in metres)."""

    source: str  # "raster" | "points" (not resolved on the raster: the pairs' figures)
    width_m: float  # NaN when the raster gave none (source "points")
    max_depth_m: float  # NaN when the raster gave none
    profiles: int  # profiles with road on both sides
    cross_section_m2: float  # median ∫ depth ds over the profiles (m²; NaN: none)
    cross_section_se_m2: float  # its standard error (m²)
    noise_m: float  # σ of the profiles' outer road around their lines (m)
    fwhm_m: float  # median full width at half depth of the raster's dip (m)


def not_measured(profiles: int = 0, noise_m: float = math.nan) -> RasterCrack:
    nan = math.nan
    return RasterCrack("points", nan, nan, profiles, nan, nan, noise_m, nan)


def stations_from_samples(xy_m: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Stations every ~``step_m`` along a crack's samples and the unit normal at each.

    xy_m: (N, 2) samples (grid frame, m), unordered. Returns ((S, 2) stations, (S, 2) normals):
    the samples snapped to a ``step_m`` lattice (one station per occupied cell, at the mean of
    its samples); the direction at a station is the principal axis of the samples within
    max(2 cm, 3 step) of it, the normal perpendicular to it.
    """
    from scipy.spatial import cKDTree

    xy = np.asarray(xy_m, float).reshape(-1, 2)
    if len(xy) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    key = np.floor(xy / step_m).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    n = np.bincount(inv)
    st = np.c_[np.bincount(inv, xy[:, 0]), np.bincount(inv, xy[:, 1])] / n[:, None]
    tree = cKDTree(xy)
    r = max(0.02, 3.0 * step_m)
    normals = np.zeros_like(st)
    keep = np.zeros(len(st), bool)
    for i, nb in enumerate(tree.query_ball_point(st, r)):
        if len(nb) < 3:
            continue
        q = xy[nb] - xy[nb].mean(axis=0)
        _, _, vt = np.linalg.svd(q, full_matrices=False)
        normals[i] = (-vt[0, 1], vt[0, 0])
        keep[i] = True
    return st[keep], normals[keep]


def _sample(
    win: np.ndarray, rc0: np.ndarray, gsd: float, x0: float, y0: float, pts: np.ndarray
) -> np.ndarray:
    """Bilinear samples of the window ``win`` (NaN where a neighbour is unobserved) at grid-frame
    points ``pts`` (..., 2); ``rc0`` the window's top-left (row, col) in the full grid."""
    from scipy.ndimage import map_coordinates

    col = (pts[..., 0] - x0) / gsd - 0.5 - rc0[1]
    row = (y0 - pts[..., 1]) / gsd - 0.5 - rc0[0]
    ok = np.isfinite(win)
    z = map_coordinates(np.where(ok, win, 0.0), [row, col], order=1, mode="constant", cval=0.0)
    w = map_coordinates(ok.astype(float), [row, col], order=1, mode="constant", cval=0.0)
    return np.where(w > 0.999, z, np.nan)


@dataclass(frozen=True)
class _Profiles:
    """Profiles across a crack, read on the raster (``_profiles``)."""

    stations: np.ndarray  # (n, 2) station of each kept profile (grid frame, m)
    s: np.ndarray  # (P,) offsets across the crack (m)
    depth: np.ndarray  # (n, P) depth below each profile's road line (m, +down)
    outer: np.ndarray  # (P,) bool: the road parts of a profile
    ds: float  # step of the offsets (m)
    foot: float  # the raster's smoothing footprint (m)


def _profiles(
    src: WindowSource, xy_m: np.ndarray, width_m: float, cfg: CrackConfig
) -> tuple[_Profiles | None, int]:
    """The profiles across the crack with road on both sides, and how many there are (None when
    fewer than ``raster_min_profiles``, or no raster there)."""
    g = src.grid
    gsd = float(g.gsd_m)
    # the raster's smoothing footprint (m): the dense matching window on the ground, as mapping
    # wrote it in surface.tif, else the configured number of cells
    foot = float(getattr(src, "footprint_m", math.nan))
    if not (math.isfinite(foot) and foot > 0):
        foot = cfg.raster_footprint_cells * gsd
    # the crack's dip lies within this of the centre line (the image width reads up to ~25 %
    # narrow: docs/detection.md)
    inner = 0.75 * width_m + foot
    half = inner + max(cfg.raster_road_m, 2.0 * foot)  # road beyond ``inner`` on each side
    st, nrm = stations_from_samples(xy_m, cfg.raster_step_m)
    if len(st) == 0:
        return None, 0
    lo = st.min(axis=0) - half - 2 * gsd
    hi = st.max(axis=0) + half + 2 * gsd
    r0 = max(0, int(math.floor((g.y0_m - hi[1]) / gsd)))
    c0 = max(0, int(math.floor((lo[0] - g.x0_m) / gsd)))
    r1 = min(g.height, int(math.ceil((g.y0_m - lo[1]) / gsd)) + 1)
    c1 = min(g.width, int(math.ceil((hi[0] - g.x0_m) / gsd)) + 1)
    if r1 <= r0 or c1 <= c0 or (r1 - r0) * (c1 - c0) > MAX_WINDOW_CELLS:
        return None, 0
    win = src.read(r0, c0, r1 - r0, c1 - c0).astype(float)
    ds = 0.5 * gsd
    s = np.arange(-half, half + 1e-12, ds)  # offsets across the crack (m)
    pts = st[:, None, :] + s[None, :, None] * nrm[:, None, :]
    z = _sample(win, np.array([r0, c0]), gsd, g.x0_m, g.y0_m, pts)  # (S, P) residual, m
    outer = np.abs(s) >= inner
    left, right = outer & (s < 0), outer & (s > 0)
    need = max(3, int(0.5 * (half - inner) / ds))  # half of each side observed
    ok = (np.isfinite(z[:, left]).sum(axis=1) >= need) & (
        np.isfinite(z[:, right]).sum(axis=1) >= need
    )
    ok &= np.isfinite(z[:, ~outer]).all(axis=1)
    n = int(ok.sum())
    if n < cfg.raster_min_profiles:
        return None, n
    z = z[ok]
    # road line of each profile, fitted to its outer parts (least squares, per row)
    A = np.c_[np.ones(outer.sum()), s[outer]]
    zo = z[:, outer]
    fin = np.isfinite(zo)
    coef = np.zeros((n, 2))
    for i in range(n):
        coef[i] = np.linalg.lstsq(A[fin[i]], zo[i, fin[i]], rcond=None)[0]
    d = -(z - coef[:, :1] - coef[:, 1:] * s[None, :])  # depth below the road line (m, +down)
    return _Profiles(st[ok], s, d, outer, ds, foot), n


def measure_crack_on_raster(
    src: WindowSource, xy_m: np.ndarray, width_m: float, cfg: CrackConfig
) -> RasterCrack:
    """Width and depth of one crack across its centre line on the raster ``src``.

    xy_m: (N, 2) the crack's map samples (grid frame, m); width_m: its image width (m), which
    sets the inner part of each profile and converts a cross-section into a depth. See the
    module docstring for the sources.
    """
    pr, n = _profiles(src, xy_m, width_m, cfg)
    if pr is None:
        return not_measured(n)
    d, outer, ds, foot = pr.depth, pr.outer, pr.ds, pr.foot
    ro = d[:, outer][np.isfinite(d[:, outer])]
    sigma = robust_sigma(ro)
    din = d[:, ~outer]
    area = din.sum(axis=1) * ds  # cross-section of each profile (m²)
    a_med = float(np.median(area))
    n_ind = max(1.0, n * cfg.raster_step_m / max(foot, cfg.raster_step_m))
    a_se = float(MAD_TO_SIGMA * np.median(np.abs(area - a_med)) / math.sqrt(n_ind))
    dmax = din.max(axis=1)
    # full width at half depth of each profile's dip (cells around its deepest point)
    fwhm = np.array([_width_at(din[i], 0.5 * dmax[i], ds) for i in range(n)])
    fw = float(np.median(fwhm))
    base = RasterCrack("points", math.nan, math.nan, n, a_med, a_se, sigma, fw)
    if not (a_se > 0 and a_med >= cfg.raster_z_k * a_se):
        return base  # the raster does not see the crack beyond its noise
    depth = float(np.median(dmax))
    if fw >= cfg.raster_resolved_k * foot and depth >= cfg.raster_z_k * sigma:
        return RasterCrack("raster", math.sqrt(2.0) * fw, depth, n, a_med, a_se, sigma, fw)
    return base


@dataclass(frozen=True)
class RasterEvidence:
    """The raster's test of a crack candidate: is its cross-section below the road?"""

    confirmed: bool
    z: float  # mean cross-section over its standard error (NaN: not tested)
    cross_section_m2: float  # mean ∫ depth ds over the profiles (m²)
    se_m2: float  # its standard error from the blocks' means (m²)
    blocks: int  # independent blocks along the crack (count)
    threshold: float  # the z the blocks' count asks for (Student's t at the level of raster_z_k)


def raster_crack_evidence(
    src: WindowSource, xy_m: np.ndarray, width_m: float, cfg: CrackConfig
) -> RasterEvidence:
    """Test a crack candidate's cross-section on the raster: the mean over the profiles of
    ∫ depth ds against its standard error (module docstring, *confirmation*).

    Neighbouring profiles share the raster's window means and its smoothing, so they are not
    independent: the profiles are pooled into blocks of ``raster_block_footprints`` footprints
    along the crack (stations snapped to a lattice of that size) and the standard error is the
    spread of the block means (batch means, weighted by the profiles per block). Confirmed when
    z reaches Student's t with (blocks − 1) degrees of freedom at the one-sided level of
    ``raster_z_k`` normal σ, with at least ``raster_min_blocks`` blocks, and the dip's median
    depth within ``dense_max_depth_m`` (a deeper reading is a failed surface).
    """
    from scipy.stats import norm, t

    nan = math.nan
    pr, _ = _profiles(src, xy_m, width_m, cfg)
    if pr is None:
        return RasterEvidence(False, nan, nan, nan, 0, nan)
    din = pr.depth[:, ~pr.outer]
    area = din.sum(axis=1) * pr.ds
    block = cfg.raster_block_footprints * pr.foot
    _, inv = np.unique(np.floor(pr.stations / block).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.ravel()
    nb = int(inv.max()) + 1
    cnt = np.bincount(inv, minlength=nb).astype(float)
    mean_b = np.bincount(inv, area, nb) / cnt
    mean = float(np.sum(cnt * mean_b) / cnt.sum())
    if nb < max(2, cfg.raster_min_blocks):
        return RasterEvidence(False, nan, mean, nan, nb, nan)
    # batch means with unequal blocks: Var(Σ n_b ā_b / N) from the blocks' scatter
    var = nb / (nb - 1.0) * float(np.sum(cnt**2 * (mean_b - mean) ** 2)) / cnt.sum() ** 2
    se = math.sqrt(var)
    thr = float(t.isf(norm.sf(cfg.raster_z_k), nb - 1))
    z = mean / se if se > 0 else nan
    depth = float(np.median(din.max(axis=1)))
    ok = bool(se > 0 and z >= thr and depth <= cfg.dense_max_depth_m)
    return RasterEvidence(ok, z, mean, se, nb, thr)


def _width_at(prof: np.ndarray, level: float, ds: float) -> float:
    """Width (m) of the run of ``prof`` (depths, m, step ``ds``) at or above ``level`` that holds
    its deepest point; the run's ends are interpolated linearly between samples."""
    if not np.isfinite(level) or level <= 0:
        return 0.0
    a, b = run_extent(prof, int(np.argmax(prof)), level)
    w = (b - a) * ds
    if a > 0 and prof[a] > prof[a - 1]:
        w += ds * (prof[a] - level) / (prof[a] - prof[a - 1])
    if b < len(prof) - 1 and prof[b] > prof[b + 1]:
        w += ds * (prof[b] - level) / (prof[b] - prof[b + 1])
    return float(w)
