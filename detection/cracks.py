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


@functools.lru_cache(maxsize=8)
def _line_kernels(length_px: float) -> tuple[np.ndarray, ...]:
    """Anti-aliased 1 px line kernels of ``length_px`` (sum 1), one per direction in [0, π).

    Direction step: a segment off the line by half a step deviates at its ends by
    (L / 2)·(π / n) / 2 px; n = ⌈π L / 4⌉ keeps that within 1 px (one crack width), 8..24.
    """
    n = int(np.clip(math.ceil(math.pi * length_px / 4.0), 8, 24))
    size = int(math.ceil(length_px)) | 1
    c, up = size / 2.0, 8  # draw 8x larger, area-average down: anti-aliased, sub-pixel exact
    out = []
    for i in range(n):
        th = math.pi * i / n
        dx, dy = 0.5 * (length_px - 1) * math.cos(th), 0.5 * (length_px - 1) * math.sin(th)
        big = np.zeros((size * up, size * up), np.float32)
        p0 = (round((c - dx) * up * 16), round((c - dy) * up * 16))
        p1 = (round((c + dx) * up * 16), round((c + dy) * up * 16))
        cv2.line(big, p0, p1, 1.0, up, cv2.LINE_AA, 4)
        k = cv2.resize(big, (size, size), interpolation=cv2.INTER_AREA)
        out.append(k / k.sum())
    return tuple(out)


def line_response(
    gray: np.ndarray, m_per_px: float, cfg: CrackConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Oriented dark-line response: (z, contrast), both (H, W) float32.

    Darkness d is the black top-hat (disc ``tophat_m``) over the local background (the
    closing): the share by which a pixel is darker than its surroundings, so independent of
    lighting and albedo. d is averaged along segments of ``line_m`` in all directions (max over
    directions), minus its mean over the segment's square (the texture's level there): the
    line ``contrast``. Pores of a coarse texture answer the top-hat as strongly as a crack, but a
    segment much longer than a pore averages them out; a crack keeps its contrast along its
    length. ``z`` is the contrast over d's standard deviation in a window twice as large (the
    texture's spread there): busy textures (gravel, worn paint on a marking) need a stronger
    line than smooth asphalt. Runs at about ``line_gsd_m`` per pixel (area averaging keeps a
    thin crack's integrated darkness) so the kernels stay small (fast).
    """
    g = cv2.GaussianBlur(np.asarray(gray, np.uint8), (3, 3), 0)
    k = max(3, int(round(cfg.tophat_m / m_per_px)) | 1)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    close = cv2.morphologyEx(g, cv2.MORPH_CLOSE, disc).astype(np.float32)
    d = (close - g) / np.maximum(close, 1.0)
    h, w = d.shape
    f = max(1, int(cfg.line_gsd_m / m_per_px))
    if f > 1:
        d = cv2.resize(d, (max(1, w // f), max(1, h // f)), interpolation=cv2.INTER_AREA)
    length = max(5.0, cfg.line_m / (m_per_px * f))
    c = None
    for kern in _line_kernels(round(length, 1)):
        x = cv2.filter2D(d, -1, kern, borderType=cv2.BORDER_REFLECT)
        c = x if c is None else np.maximum(c, x)
    s = int(math.ceil(length)) | 1
    c -= cv2.blur(d, (s, s), borderType=cv2.BORDER_REFLECT)
    s2 = 2 * s + 1
    m1 = cv2.blur(d, (s2, s2), borderType=cv2.BORDER_REFLECT)
    sd = np.sqrt(np.maximum(cv2.blur(d * d, (s2, s2), borderType=cv2.BORDER_REFLECT) - m1 * m1, 0))
    # Floor on the spread: 5 % of its median (and 1e-4): a flat patch (saturated, no texture)
    # must not turn quantisation into a strong line.
    z = c / (sd + 0.05 * float(np.median(sd)) + 1e-4)
    if f > 1:
        z = cv2.resize(z, (w, h), interpolation=cv2.INTER_LINEAR)
        c = cv2.resize(c, (w, h), interpolation=cv2.INTER_LINEAR)
    return z, c


def thin_dark_components(
    gray: np.ndarray, m_per_px: float, cfg: CrackConfig
) -> tuple[np.ndarray, list[int], np.ndarray]:
    """Label image (H, W) int32, the ids of long thin dark components, and their width (px).

    Pixels whose oriented line response (``line_response``) exceeds the image's own median +
    ``contrast_k`` · 1.4826 MAD form components; those long (≥ ``min_length_m``), thin
    (area / length ≤ ``max_width_m``) and elongated (≥ ``min_elongation``) are kept. The width
    is the crack's equivalent width measured on the top-hat (``equivalent_width_px``).
    """
    z, contrast = line_response(gray, m_per_px, cfg)
    med = float(np.median(z))
    mad = 1.4826 * float(np.median(np.abs(z - med)))
    mask = ((z > med + cfg.contrast_k * max(mad, 1e-6)) & (contrast >= cfg.min_contrast)).astype(
        np.uint8
    )
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    keep: list[int] = []
    mask_w: list[float] = []
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
            mask_w.append(width)
    if not keep:
        return lab, keep, np.zeros(0)
    g = cv2.GaussianBlur(np.asarray(gray, np.uint8), (3, 3), 0)
    widths = [equivalent_width_px(g, lab == i, m_per_px, cfg) for i in keep]
    # No measurable profile (e.g. at the image border): the component's own width.
    widths = [w if np.isfinite(w) else mw for w, mw in zip(widths, mask_w, strict=True)]
    return lab, keep, np.asarray(widths, float)


def centre_line(comp: np.ndarray) -> np.ndarray:
    """(H, W) bool 1 px centre line (skeleton) of a component mask."""
    from skimage.morphology import skeletonize

    ys, xs = np.nonzero(comp)
    if not len(ys):
        return np.zeros_like(comp, bool)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    out = np.zeros(comp.shape, bool)
    out[y0:y1, x0:x1] = skeletonize(np.pad(comp[y0:y1, x0:x1], 1))[1:-1, 1:-1]
    return out


def equivalent_width_px(
    g: np.ndarray, comp: np.ndarray, m_per_px: float, cfg: CrackConfig
) -> float:
    """Equivalent width of a crack (px): its integrated darkness across the line over its peak
    darkness (a rectangular profile gives its width, the simulator's triangular one 0.9 x).

    Darkness is the top-hat (disc ``tophat_m``) above the mean of a ring around the crack (the
    texture's level); integrated over the band within ``max_width_m`` / 2 of the centre line.
    """
    ys, xs = np.nonzero(comp)
    hw = max(2, int(math.ceil(0.5 * cfg.max_width_m / m_per_px)))
    m = hw + 3
    y0, y1 = max(0, ys.min() - m), min(comp.shape[0], ys.max() + m + 1)
    x0, x1 = max(0, xs.min() - m), min(comp.shape[1], xs.max() + m + 1)
    k = max(3, int(round(cfg.tophat_m / m_per_px)) | 1)
    pad = k
    Y0, Y1 = max(0, y0 - pad), min(g.shape[0], y1 + pad)
    X0, X1 = max(0, x0 - pad), min(g.shape[1], x1 + pad)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    b = cv2.morphologyEx(g[Y0:Y1, X0:X1], cv2.MORPH_BLACKHAT, disc).astype(np.float32)
    b = b[y0 - Y0 : y1 - Y0, x0 - X0 : x1 - X0]
    skel = centre_line(comp[y0:y1, x0:x1])
    n = int(skel.sum())
    if n == 0:
        return float("nan")
    d = cv2.distanceTransform((~skel).astype(np.uint8), cv2.DIST_L2, 3)
    band = d <= hw
    ring = (d > hw) & (d <= hw + 3)
    if not ring.any():
        return float("nan")
    base = float(b[ring].mean())
    peak = float(np.median(cv2.dilate(b, np.ones((3, 3), np.uint8))[skel])) - base
    if peak <= 0:
        return float("nan")
    return float(np.clip((b[band] - base).sum() / (n * peak), 1.0, 2 * hw))


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
        line = centre_line(lab == i)
        if not line.any():
            continue
        dist_px = cv2.distanceTransform((~line).astype(np.uint8), cv2.DIST_L2, 3)
        # Points on the groove: within half its width of the centre line (at least ``near_px``,
        # the points' localisation); points beside it are road and only dilute the mean depth.
        near = dist_px[v, u] <= max(cfg.near_px, 0.5 * wpx)
        n = int(near.sum())
        if n == 0:
            continue
        # No decision here: one pair holds only a few points on a crack; the evidence of all
        # pairs that saw it is pooled on the map (``crack_evidence``).
        d = -np.asarray(dist_m, float)[near]  # depth below the road, positive down
        ys, xs = np.nonzero(line)
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
