"""Coarse-grid fallback of the dense matching: pixels that fail on the work grid take the height
matched on a grid coarser by 2^k (``DenseHeightConfig.fallback_levels``).

Why: a matching window of a fixed number of pixels spans a fixed share of the road's grain. On
real photographs of potholes (spd2, 0.3 Mpx work grid, ~1 mm per pixel) the floors' fine
texture does not correlate between the two shots (a view-dependent look of loose or wet
material is the likely cause, not measured) while their coarser texture does. Of the labelled
pothole pixels of a pair (median of 26 pairs) 33 % fail the ZNCC test, 13 % do not converge
and 5 % fail the left-right check, while only 2.5 % are textureless and none dark or saturated;
30 % keep a height. Matched on a 0.1 Mpx grid instead, 64 % do; with one fallback level (the
work grid, then a grid of a quarter of its pixels where it failed) 62 %. Where both grids pass,
the coarse height is the fine one's +0.04 mm (MAD 0.4 mm; +0.2-0.3 mm on the labelled pixels,
whose walls a wider window averages), its own σ about 2x the fine one's (median 0.60 against
0.29 mm): the coarser window sees the floor's coarser, view-stable texture at 2x the footprint.

Each coarse pixel is matched with the full set of checks (ZNCC, texture, convergence,
left-right, range) on its own grid, so what it gives passed the same tests; a work pixel is
filled only when its four bilinear neighbours on the coarse grid are all valid (no fill across
the edge of a coarse hole, e.g. the occluded band of a pothole wall), and its variance is the
interpolated coarse variance plus (half the relief of the coarse heights within their windows)²:
a window that spans a wall reads a mix of its surfaces (the wider the window, the wider the band
it "fattens"), so its height is only known to lie within that relief. The fine grid failed there
for a reason, often the wall itself: on a rendered 45°-pitch pair the filled pixels at the far
rim read the rim (+15 mm), with the plain coarse variance their median |error| / σ was 1.95,
with this bound 0.72; on flat floors the bound is conservative (median |error| / σ 0.15-0.2, the
fills weigh less than any work-grid height of another pair).

Only pixels the work grid refused for their correlation, convergence or texture are filled: one
the left-right check refused lies in the band a step hides from one view, one the step test
refused (``DenseHeightConfig.step_plane_px``) on the step itself, and a window twice as wide
straddles it more. On the seed-7 45° stereo pair (``benchmarks.dense_pair_truth``) the fills of
left-right refusals read the pothole 9-14 mm RMS off (3.6-9 mm shallow), those of ZNCC or
convergence refusals alone 5-6 mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from roadsurf.reconstruction.dense.checks import REJECT_GEOMETRY, REJECT_LR, REJECT_UNMATCHED
from roadsurf.reconstruction.dense.geometry import PlaneParallax


@dataclass
class LevelMatch:
    """Unsmoothed match of one grid (image a resized by its scale): NaN / False where invalid."""

    height_m: np.ndarray  # (h, w) float32 height above the pair's road plane (m)
    var_m2: np.ndarray  # (h, w) float32 its variance (m²)
    valid: np.ndarray  # (h, w) bool
    shift_px: np.ndarray  # (h, w) float32 parallax along the epipolar direction (px, this grid)
    ncc: np.ndarray  # (h, w) float32 ZNCC of the matched windows (−)
    # (h, w) uint8 the checks that refused each pixel (``checks.REJECT_*`` bits; 0 = valid on
    # this grid; a pixel filled from a coarser grid keeps its own)
    reject: np.ndarray
    scale: float = 1.0  # this grid = image a x scale
    # (h, w) float32 the sweep's heights that started the match a -> b and b -> a (m; NaN
    # outside the matched crop; None: no sweep, e.g. the DIS init or no left-right check)
    init_eta_fwd: np.ndarray | None = None
    init_eta_rev: np.ndarray | None = None

    @classmethod
    def empty(cls, h: int, w: int, scale: float = 1.0) -> LevelMatch:
        nan = np.full((h, w), np.nan, np.float32)
        rej = np.full((h, w), REJECT_UNMATCHED, np.uint8)
        return cls(
            nan.copy(), nan.copy(), np.zeros((h, w), bool), nan.copy(), nan.copy(), rej, scale
        )


def coarse_from_work_px(u: np.ndarray, ratio: float) -> np.ndarray:
    """Coarse-grid coordinate (px) of work-grid coordinate u (px, any shape) when the coarse grid
    is the work grid resized by ``ratio`` (< 1), pixel centres kept: u_c = ratio (u + 0.5) - 0.5."""
    return ratio * (np.asarray(u, float) + 0.5) - 0.5


def prior_on_grid(
    eta_fine: np.ndarray, ratio: float, r0: int, c0: int, h: int, w: int
) -> np.ndarray:
    """(h, w) float32 heights (m) of the finer grid's field ``eta_fine`` (full finer grid) at the
    pixels of the coarser grid's crop whose pixel (0, 0) is its (c0, r0), the coarser grid being
    the finer one resized by ``ratio``: bilinear, NaN read as 0 m (the road)."""
    vc, uc = np.mgrid[0:h, 0:w].astype(np.float32)
    uf = (uc + c0 + 0.5) / ratio - 0.5
    vf = (vc + r0 + 0.5) / ratio - 0.5
    src = np.nan_to_num(eta_fine, nan=0.0).astype(np.float32)
    return cv2.remap(src, uf, vf, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def relief(level: LevelMatch, win: int) -> np.ndarray:
    """(h, w) float32 range (max - min, m) of ``level``'s valid heights in the win x win window
    around each pixel (NaN where the pixel is invalid)."""
    k = np.ones((win, win), np.uint8)
    v = level.valid
    h = np.where(v, level.height_m, 0.0).astype(np.float32)
    big = np.float32(1e3)  # m: out of any road's reach, finite (no overflow in hi - lo)
    hi = cv2.dilate(np.where(v, h, -big), k)
    lo = -cv2.dilate(np.where(v, -h, -big), k)
    return np.where(v, hi - lo, np.nan).astype(np.float32)


def fill_from_coarse(
    fine: LevelMatch, coarse: LevelMatch, pp_fine: PlaneParallax, ratio: float, win: int = 1
) -> np.ndarray:
    """Fill ``fine``'s invalid pixels (in place) from ``coarse`` (the same pair matched on the
    work grid resized by ``ratio`` with win x win windows): bilinear heights where all four
    coarse neighbours are valid, variance as in the module docstring, the parallax recomputed
    on the work grid from the height (``pp_fine``, the work grid's model). Returns the (h, w)
    bool mask filled."""
    h, w = fine.valid.shape
    hc, wc = coarse.valid.shape
    # an occlusion (left-right) or a step (the plane test) refused it: a wider window straddles
    # it more, only a window that failed to correlate or converge is tried again
    todo = ~fine.valid & ((fine.reject & (REJECT_LR | REJECT_GEOMETRY)) == 0)
    if not todo.any() or not coarse.valid.any():
        return np.zeros((h, w), bool)
    vv, uu = np.nonzero(todo)
    xc = np.clip(coarse_from_work_px(uu, ratio), 0.0, wc - 1.0)
    yc = np.clip(coarse_from_work_px(vv, ratio), 0.0, hc - 1.0)
    x0 = np.minimum(np.floor(xc).astype(int), wc - 2) if wc > 1 else np.zeros_like(uu)
    y0 = np.minimum(np.floor(yc).astype(int), hc - 2) if hc > 1 else np.zeros_like(vv)
    x1, y1 = np.minimum(x0 + 1, wc - 1), np.minimum(y0 + 1, hc - 1)
    fx, fy = xc - x0, yc - y0
    wts = ((1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy)
    idx = ((y0, x0), (y0, x1), (y1, x0), (y1, x1))
    ok = np.ones(len(vv), bool)
    for r, c in idx:
        ok &= coarse.valid[r, c]
    if not ok.any():
        return np.zeros((h, w), bool)
    vv, uu = vv[ok], uu[ok]
    wk = [x[ok] for x in wts]
    rc = [(r[ok], c[ok]) for r, c in idx]
    hts = np.stack([coarse.height_m[r, c].astype(float) for r, c in rc])
    eta = sum(wt * x for wt, x in zip(wk, hts, strict=True))
    var = sum(wt * coarse.var_m2[r, c] for wt, (r, c) in zip(wk, rc, strict=True))
    rel = relief(coarse, max(int(win), 1))
    span = np.max(np.stack([rel[r, c] for r, c in rc]), axis=0)
    var = var + (0.5 * np.maximum(span, hts.max(0) - hts.min(0))) ** 2
    ncc = sum(wt * coarse.ncc[r, c] for wt, (r, c) in zip(wk, rc, strict=True))
    shift = pp_fine.shift_from_height(eta, uu.astype(float), vv.astype(float))
    good = np.isfinite(eta) & np.isfinite(var) & np.isfinite(shift)
    vv, uu = vv[good], uu[good]
    fine.height_m[vv, uu] = eta[good]
    fine.var_m2[vv, uu] = var[good]
    fine.shift_px[vv, uu] = shift[good]
    fine.ncc[vv, uu] = ncc[good]
    fine.valid[vv, uu] = True
    filled = np.zeros((h, w), bool)
    filled[vv, uu] = True
    return filled
