"""Cracks: thin dark linear features in the image, confirmed by 3D points just below the road.

Cracks are a few millimetres wide and deep: below the map's T_d and its 5 mm raster, so the
surface segmentation never sees them. Per pair:

1. **2D thin-structure detector.** Black top-hat of the greyscale image (closing minus image)
   with a disc of ``tophat_m`` (wider than any crack, narrower than a pothole): only dark
   structures thinner than the disc respond. Threshold relative to the image's own response
   (median + ``contrast_k`` · 1.4826 MAD) and to the local brightness (``min_contrast`` of the
   median grey). Connected components (after a 3 px closing, which bridges texture gaps along
   the crack) are kept when long (≥ ``min_length_m``) and thin (area / length ≤ ``max_width_m``).
2. **3D confirmation (the veto), pooled over pairs.** The 3D points on the component (within
   ``near_px``) are collected; one pair holds only a few points on a crack, so the test is done
   on the map over all pairs whose pieces link up: at least ``min_points``, mostly below the
   plane (share ≥ ``min_below_share``), and the mean depth significant against each pair's
   measured point noise σ (z = Σ depth / √(Σ n σ²) ≥ ``z_k``). Lane-marking edges, shadow
   borders and texture are at road level and fail it.

The confirmed components are sampled and mapped onto the road plane of camera a (homography
fitted from the pair's road points, pixel -> camera X, Y; Z from the plane). On the map, samples
from all pairs closer than ``link_m`` form one crack (the same crack seen by several pairs is one
defect).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from detection.config import CrackConfig

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


def empty() -> PairCracks:
    z = np.zeros(0)
    return PairCracks(np.zeros((0, 3)), np.zeros(0, int), z, z, z, z, z, z)


def thin_dark_components(
    gray: np.ndarray, m_per_px: float, cfg: CrackConfig
) -> tuple[np.ndarray, list[int], np.ndarray]:
    """Label image (H, W) int32, the ids of long thin dark components, and their width (px)."""
    g = cv2.GaussianBlur(np.asarray(gray, np.uint8), (3, 3), 0)
    k = max(3, int(round(cfg.tophat_m / m_per_px)) | 1)
    bth = cv2.morphologyEx(
        g, cv2.MORPH_BLACKHAT, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    )
    b = bth.astype(np.float32)
    med = float(np.median(b))
    mad = 1.4826 * float(np.median(np.abs(b - med)))
    thr = max(med + cfg.contrast_k * mad, cfg.min_contrast * float(np.median(g)))
    mask = (b > thr).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    keep, widths = [], []
    min_len_px = cfg.min_length_m / m_per_px
    max_w_px = max(2.5, cfg.max_width_m / m_per_px)
    for i in range(1, n):
        area = int(stats[i, cv2.CC_STAT_AREA])
        bw, bh = int(stats[i, cv2.CC_STAT_WIDTH]), int(stats[i, cv2.CC_STAT_HEIGHT])
        if max(bw, bh) < min_len_px or area < min_len_px:
            continue
        ys, xs = np.nonzero(
            lab[stats[i, 1] : stats[i, 1] + bh, stats[i, 0] : stats[i, 0] + bw] == i
        )
        pts = np.c_[xs, ys].astype(np.float32)
        (_, _), (a, c), _ = cv2.minAreaRect(pts)
        # Length along a curved crack: the skeleton-free estimate max(rect side, area / width).
        length = max(a, c)
        width = area / max(length, 1.0)
        if length >= min_len_px and width <= max_w_px and length >= cfg.min_elongation * width:
            keep.append(i)
            widths.append(width)
    return lab, keep, np.asarray(widths, float)


def detect_pair_cracks(
    gray: np.ndarray,
    px: np.ndarray,
    points_cam_m: np.ndarray,
    dist_m: np.ndarray,
    road: np.ndarray,
    noise_m: float,
    m_per_px: float,
    cfg: CrackConfig,
) -> PairCracks:
    """Cracks of one image confirmed by the pair's 3D points (see the module docstring).

    px: (N, 2) pixels of the points in ``gray``; points_cam_m: (N, 3) camera-a coordinates;
    dist_m: (N,) signed plane distances (negative below); road: (N,) bool road points (for the
    pixel -> road-plane mapping); noise_m: σ of the road points' distances.
    """
    px = np.asarray(px, float)
    P = np.asarray(points_cam_m, float)
    if len(px) < 20 or road.sum() < 10 or not np.isfinite(noise_m) or noise_m <= 0:
        return empty()
    lab, keep, widths = thin_dark_components(gray, m_per_px, cfg)
    if not keep:
        return empty()
    h, w = lab.shape
    u = np.clip(np.round(px[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.round(px[:, 1]).astype(int), 0, h - 1)
    H, _ = cv2.findHomography(px[road].astype(np.float32), P[road, :2].astype(np.float32), 0)
    if H is None:
        return empty()
    A = np.c_[P[road, :2], np.ones(int(road.sum()))]
    zcoef = np.linalg.lstsq(A, P[road, 2], rcond=None)[0]
    xyz, labels, wd, sd, nn, nb, vv, mx = [], [], [], [], [], [], [], []
    for i, wpx in zip(keep, widths, strict=True):
        comp = (lab == i).astype(np.uint8)
        dist_px = cv2.distanceTransform(1 - comp, cv2.DIST_L2, 3)
        near = dist_px[v, u] <= cfg.near_px
        n = int(near.sum())
        if n == 0:
            continue
        # No decision here: one pair holds only a few points on a crack; the evidence of all
        # pairs that saw it is pooled on the map (``crack_evidence``).
        d = -np.asarray(dist_m, float)[near]  # depth below the road, positive down
        ys, xs = np.nonzero(comp)
        step = max(1, len(xs) // cfg.max_samples)
        q = np.c_[xs[::step], ys[::step]].astype(np.float32).reshape(-1, 1, 2)
        xy = cv2.perspectiveTransform(q, H).reshape(-1, 2).astype(float)
        zc = np.c_[xy, np.ones(len(xy))] @ zcoef
        xyz.append(np.c_[xy, zc])
        labels.append(np.full(len(xy), len(wd)))
        wd.append(wpx * m_per_px)
        sd.append(float(d.sum()))
        nn.append(n)
        nb.append(int((d > 0).sum()))
        vv.append(n * noise_m**2)
        mx.append(float(np.sort(d)[-2]) if n >= 2 else float(d[0]))
    if not wd:
        return empty()
    return PairCracks(
        np.vstack(xyz),
        np.concatenate(labels),
        *(np.asarray(a, float) for a in (wd, sd, nn, nb, vv, mx)),
    )


def crack_evidence(
    sum_depth_m: float, n_points: int, n_below: int, var_m2: float, cfg: CrackConfig
) -> tuple[bool, float]:
    """Pooled 3D test of one crack over all pairs that saw it: (confirmed, z).

    z = Σ depth / √(Σ n σ²) (the mean depth over its standard error); confirmed when
    z ≥ ``z_k``, at least ``min_points`` points and a share ≥ ``min_below_share`` below the road.
    """
    if n_points <= 0 or var_m2 <= 0:
        return False, 0.0
    z = float(sum_depth_m / math.sqrt(var_m2))
    ok = z >= cfg.z_k and n_points >= cfg.min_points and n_below >= cfg.min_below_share * n_points
    return bool(ok), z


def cluster_cracks(xy_m: np.ndarray, link_m: float) -> np.ndarray:
    """(N,) cluster label of crack samples: samples closer than ``link_m`` are linked."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(xy_m)
    if n == 0:
        return np.zeros(0, int)
    pairs = cKDTree(xy_m).query_pairs(link_m, output_type="ndarray")
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)[1]
