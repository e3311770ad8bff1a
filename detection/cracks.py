"""Cracks: thin dark linear features in the image, confirmed by 3D points just below the road.

Cracks are a few millimetres wide and deep: below the map's T_d and its 5 mm raster, so the
surface segmentation never sees them. Per pair:

1. **2D thin-structure detector: an oriented line filter.** Black top-hat of the greyscale
   image (closing minus image, disc ``tophat_m``: wider than any crack, narrower than a
   pothole) over the closing: the share by which a pixel is darker than its surroundings. On
   coarse texture its pores answer as strongly as a crack, so it is averaged along segments of
   ``line_m`` in all directions (max over directions; length, not point contrast, separates a
   crack from pores), minus the local mean, over the local spread (``line_response``).
   Threshold relative to the image's own response (median + ``contrast_k`` · 1.4826 MAD) and a
   line darker than its surroundings by ``min_contrast``. Connected components are kept when
   long (≥ ``min_length_m``), thin (area / length ≤ ``max_width_m``) and elongated; their width
   is the equivalent width of the top-hat profile across the centre line.
2. **3D confirmation (the veto), pooled over pairs.** The 3D points on the groove (within half
   the crack's width, at least ``near_px``, of its centre line) are collected; one pair holds
   only a few points on a crack, so the test is done on the map over all pairs whose pieces
   link up: at least ``min_points``, mostly below the
   plane (share ≥ ``min_below_share``), and the mean depth significant against each pair's
   measured point noise σ (z = Σ depth / √(Σ n σ²) ≥ ``z_k``). Lane-marking edges, shadow
   borders and texture are at road level and fail it.

The confirmed components are sampled and mapped onto the road plane of camera a (homography
fitted from the pair's road points, pixel -> camera X, Y; Z from the plane). On the map, samples
from all pairs closer than ``link_m`` form one crack (the same crack seen by several pairs is one
defect).
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.fits import fit_plane_z
from roadsurf.detection.config import CrackConfig
from roadsurf.detection.crackaperture import across_parallax
from roadsurf.detection.crackdepth import DenseCrack, PairView, dense_crack_depth
from roadsurf.detection.crackfilter import centre_line, thin_dark_components
from roadsurf.detection.crackgroove import groove_crack_depth
from roadsurf.detection.gsd import ground_px_m_raw

log = logging.getLogger(__name__)


@dataclass
class PairCracks:
    """Confirmed cracks of one pair, sampled in camera-a coordinates."""

    xyz_cam_m: np.ndarray  # (K, 3) samples along the cracks (camera a, m)
    label: np.ndarray  # (K,) int crack index within the pair
    width_m: np.ndarray  # (C,) mean width of each crack piece (m)
    sum_depth_m: np.ndarray  # (C,) sum of the depths below the road of the 3D points on it (m)
    n_points: np.ndarray  # (C,) 3D points on it
    n_below: np.ndarray  # (C,) ... of which below the road plane
    var_m2: np.ndarray  # (C,) n · σ² (σ: the pair's point noise), for the pooled test
    max_depth_m: np.ndarray  # (C,) second-deepest point on it (m, positive; robust max)
    # Dense depth across the crack (``dense_crack_depth``); zeros where not measured:
    dense_sum_m: np.ndarray | None = None  # (C,) Σ depth over the independent samples (m)
    dense_n: np.ndarray | None = None  # (C,) independent samples (float)
    dense_below: np.ndarray | None = None  # (C,) ... of which below the road
    dense_var_m2: np.ndarray | None = None  # (C,) variance of dense_sum_m (m²)
    # The pair's geometry at each piece (``crackaperture.across_parallax``); NaN without image
    # b: share of the depth parallax across the crack (sine of its angle to the epipolar
    # direction)
    across_share: np.ndarray | None = None  # (C,) (0-1)

    def __post_init__(self) -> None:
        c = len(self.width_m)
        for f in ("dense_sum_m", "dense_n", "dense_below", "dense_var_m2"):
            if getattr(self, f) is None:
                setattr(self, f, np.zeros(c))
        if self.across_share is None:
            self.across_share = np.full(c, np.nan)


def empty() -> PairCracks:
    z = np.zeros(0)
    return PairCracks(np.zeros((0, 3)), np.zeros(0, int), z, z, z, z, z, z)


def detect_pair_cracks(
    gray: np.ndarray,
    px: np.ndarray,
    points_cam_m: np.ndarray,
    dist_m: np.ndarray,
    road: np.ndarray,
    noise_m: float,
    m_per_px: float,
    cfg: CrackConfig,
    view: PairView | None = None,
    camera: Camera | None = None,
    px_ideal: np.ndarray | None = None,
) -> PairCracks:
    """Cracks of one image confirmed by the pair's 3D points (see the module docstring).

    px: (N, 2) raw pixels of the points in ``gray`` (as captured; ``camera`` with lens
    distortion maps them and the crack lines to ideal pixels before any geometry; pass the
    points' ideal pixels as ``px_ideal`` when at hand);
    points_cam_m: (N, 3) camera-a coordinates;
    dist_m: (N,) signed plane distances (negative below); road: (N,) bool road points (for the
    pixel -> road-plane mapping); noise_m: σ of the road points' distances. With ``view``
    (image b and the pair's R, t, camera) each piece's depth is also measured densely across
    the crack (``dense_crack_depth``).
    """
    px = np.asarray(px, float)
    P = np.asarray(points_cam_m, float)
    if len(px) < 20 or road.sum() < 10 or not np.isfinite(noise_m) or noise_m <= 0:
        return empty()
    cam = camera if camera is not None else (view.camera if view is not None else None)
    # Lengths and widths in metres at each crack's own pixels (a tilted camera's pixels cover
    # more road towards the horizon); ``m_per_px`` sets the filters' scales.
    gsd_at = None if cam is None else functools.partial(ground_px_m_raw, cam, fallback_m=m_per_px)
    # off the camera's mask by more than the line filter's half-width (3 px)
    usable = None if cam is None or cam.mask is None else cam.mask.eroded(3.0)
    lab, keep, widths, gsds = thin_dark_components(gray, m_per_px, cfg, gsd_at, usable)
    if not keep:
        return empty()
    h, w = lab.shape
    u = np.clip(np.round(px[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.round(px[:, 1]).astype(int), 0, h - 1)
    if px_ideal is None:
        px_ideal = px if cam is None else cam.undistort_px(px)
    px_ideal = np.asarray(px_ideal, float)
    H, _ = cv2.findHomography(px_ideal[road].astype(np.float32), P[road, :2].astype(np.float32), 0)
    if H is None:
        return empty()
    zcoef = fit_plane_z(P[road])
    xyz, labels, wd, sd, nn, nb, vv, mx = [], [], [], [], [], [], [], []
    dense: list[DenseCrack | None] = []
    across: list[float] = []
    for i, wpx, gsd in zip(keep, widths, gsds, strict=True):
        line = centre_line(lab == i)
        if not line.any():
            continue
        dist_px = cv2.distanceTransform((~line).astype(np.uint8), cv2.DIST_L2, 3)
        # Points on the groove: within half its width of the centre line (at least ``near_px``,
        # the points' localisation); points beside it are road and only dilute the mean depth.
        near = dist_px[v, u] <= max(cfg.near_px, 0.5 * wpx)
        n = int(near.sum())
        dn = None if view is None or not cfg.dense else _dense(line, wpx, gray, view, zcoef, cfg)
        # A thin crack often has no sparse point on it (features straddle it); its dense
        # reading alone then carries it.
        if n == 0 and dn is None:
            continue
        # No decision here: one pair holds only a few points on a crack; the evidence of all
        # pairs that saw it is pooled on the map (``crack_evidence``).
        ys, xs = np.nonzero(line)
        step = max(1, len(xs) // cfg.max_samples)
        q = np.c_[xs[::step], ys[::step]].astype(float)
        q = (q if cam is None else cam.undistort_px(q)).astype(np.float32).reshape(-1, 1, 2)
        xy = cv2.perspectiveTransform(q, H).reshape(-1, 2).astype(float)
        # Road points whose tracking window (the reconstruction's LK window) reached the crack
        # are not its reference: the crack's edge dominates their match.
        off = dist_px[v, u] > max(cfg.local_road_gap_px, wpx)
        d, var = _local_depths(P, dist_m, road & off, near, xy, noise_m, cfg)
        zc = np.c_[xy, np.ones(len(xy))] @ zcoef
        xyz.append(np.c_[xy, zc])
        labels.append(np.full(len(xy), len(wd)))
        wd.append(wpx * gsd)
        sd.append(float(d.sum()))
        nn.append(n)
        nb.append(int((d > 0).sum()))
        vv.append(var)
        # robust max: the second-deepest point (two points must reach it), or the dense
        # reading's 90th percentile (a lower bound, like every dense depth) when deeper: points
        # "on" a narrow groove sit on its rims (a 5 mm deep, 8 mm wide crack confirmed by its
        # cross-section read 0.0 mm from them); a lone point only when there is nothing else
        if n >= 2:
            top = float(np.sort(d)[-2])
            mx.append(top if dn is None else max(top, float(np.percentile(dn.depth_m, 90))))
        elif dn is not None:
            mx.append(float(np.percentile(dn.depth_m, 90)))
        elif n == 1:
            mx.append(float(d[0]))
        dense.append(dn)
        across.append(
            math.nan
            if view is None
            else across_parallax(
                np.c_[xs, ys].astype(float),
                view,
                np.asarray(zcoef, float),
                # the crack's direction over the sparse points' matching window (the
                # reconstruction's 21 px LK window): what their aperture sees; a 7 px tangent
                # follows the centre line's pixel steps
                max(float(cfg.local_road_gap_px), float(cfg.dense_window_px)),
            )[0]  # fmt: skip
        )
    if not wd:
        return empty()
    dd = [(0.0, 0.0, 0.0, 0.0) if m is None else m.summary() for m in dense]
    return PairCracks(
        np.vstack(xyz),
        np.concatenate(labels),
        *(np.asarray(a, float) for a in (wd, sd, nn, nb, vv, mx)),
        *(np.asarray(a, float) for a in zip(*dd, strict=True)),
        np.asarray(across, float),
    )


def _dense(
    line: np.ndarray,
    width_px: float,
    gray: np.ndarray,
    view: PairView,
    zcoef: np.ndarray,
    cfg: CrackConfig,
) -> DenseCrack | None:
    """Dense depth of one piece: the groove model on its cross-section profiles
    (``crackgroove``, with ``groove``), else or where it measures nothing the LK tracks of its
    centre line (``dense_crack_depth``)."""
    plane = np.asarray(zcoef, float)
    if cfg.groove:
        dn = groove_crack_depth(line, width_px, gray, view, plane, cfg)
        if dn is not None:
            return dn
    return dense_crack_depth(line, width_px, gray, view, plane, cfg)


def _local_depths(
    P: np.ndarray,
    dist_m: np.ndarray,
    road: np.ndarray,
    near: np.ndarray,
    line_xy_m: np.ndarray,
    noise_m: float,
    cfg: CrackConfig,
) -> tuple[np.ndarray, float]:
    """Depths of the ``near`` points below the crack's *local* road, and the variance of their
    sum: ((n,) m positive down, m²).

    The pair's plane is fitted to the whole image; under a tilted camera the far field holds a
    small share of its points and sits far from their centroid, so a small tilt error of the
    plane there becomes a millimetre offset — the size of a crack. The reference is instead a
    plane (least squares, 3 σ trimmed) through the signed distances of the road points whose
    ground position (camera X, Y) lies within ``local_road_m`` of the crack's centre line
    (``line_xy_m``, (K, 2); ``road`` already without the points next to the crack); their spread
    about it is the local point noise σ (the far field's points are noisier than the pair's
    average). The points on the crack may scatter more than the road's (a feature on a line
    slides along it: where the crack runs with the parallax that is depth), so each point's σ
    is the larger of σ and their own standard deviation (3 points or more). Var(Σ d) = n σ² +
    the reference's own variance at the crack's points (σ² 1ᵀ A_c (AᵀA)⁻¹ A_cᵀ 1). With fewer
    than ``local_road_min_points`` such road points: the pair's plane and ``noise_m``.
    """
    d_glob = -np.asarray(dist_m, float)[near]
    n = len(d_glob)
    s_own = float(np.std(d_glob, ddof=1)) if n >= 3 and cfg.own_scatter else 0.0
    fallback = d_glob, n * max(noise_m, s_own) ** 2
    if cfg.local_road_m <= 0 or n == 0 or len(line_xy_m) == 0:
        return fallback
    from scipy.spatial import cKDTree

    from roadsurf.core.fits import trimmed_lstsq

    gap = cKDTree(line_xy_m).query(P[:, :2], distance_upper_bound=cfg.local_road_m)[0]
    ring = road & ~near & (gap <= cfg.local_road_m)
    if ring.sum() < cfg.local_road_min_points:
        return fallback
    o = line_xy_m.mean(axis=0)
    A = np.c_[np.ones(int(ring.sum())), P[ring, :2] - o]
    fit = trimmed_lstsq(A, np.asarray(dist_m, float)[ring], cfg.local_road_min_points, 1e-6)
    if fit is None:
        return fallback
    coef, _, sig, use = fit
    Ac = np.c_[np.ones(n), P[near, :2] - o]
    a = Ac.sum(axis=0)
    ref_var = sig**2 * float(a @ np.linalg.pinv(A[use].T @ A[use]) @ a)
    d = -(np.asarray(dist_m, float)[near] - Ac @ coef)
    s_own = float(np.std(d, ddof=1)) if n >= 3 and cfg.own_scatter else 0.0
    return d, n * max(sig, s_own) ** 2 + ref_var
