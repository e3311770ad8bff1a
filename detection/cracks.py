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

from roadsurf.detection.config import CrackConfig
from roadsurf.io.drive import Camera
from roadsurf.reconstruction.types import PairResult

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

    def __post_init__(self) -> None:
        c = len(self.width_m)
        for f in ("dense_sum_m", "dense_n", "dense_below", "dense_var_m2"):
            if getattr(self, f) is None:
                setattr(self, f, np.zeros(c))


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
    gray: np.ndarray,
    m_per_px: float,
    cfg: CrackConfig,
    line_m: float | None = None,
    gsd_m: float | None = None,
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
    f = max(1, int((cfg.line_gsd_m if gsd_m is None else gsd_m) / m_per_px))
    if f > 1:
        d = cv2.resize(d, (max(1, w // f), max(1, h // f)), interpolation=cv2.INTER_AREA)
    length = max(5.0, (cfg.line_m if line_m is None else line_m) / (m_per_px * f))
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
    (area / length ≤ ``max_width_m``) and elongated (≥ ``min_elongation``) are kept. A second,
    longer segment (``line_long_m``, threshold ``long_contrast_k``) adds its long lines,
    thinned, where the short one also sees them darker. The width is the crack's equivalent width measured on the top-hat
    (``equivalent_width_px``).
    """
    z, contrast = line_response(gray, m_per_px, cfg)
    mask = _above(z, cfg.contrast_k) & (contrast >= cfg.min_contrast)
    lab, keep, mask_w = _thin_pieces(mask, m_per_px, cfg)
    if cfg.line_long_m > cfg.line_m:
        # Busy textures: the long segment finds the crack where the short one drowns in
        # texture. Only its lines at least twice its length join (it smears each texture
        # streak to its own length), thinned to their centre line and 1 px each side (it also
        # answers beside a line), where the short segment too sees them darker than their
        # surroundings (the long one overshoots a line's ends by half its length).
        from skimage.morphology import skeletonize

        z_long, c_long = line_response(gray, m_per_px, cfg, cfg.line_long_m, cfg.line_long_gsd_m)
        extra = _above(z_long, cfg.long_contrast_k) & (c_long >= cfg.min_contrast)
        extra = _long_components(extra, 2.0 * cfg.line_long_m / m_per_px)
        if extra.any():
            extra = cv2.dilate(skeletonize(extra).astype(np.uint8), np.ones((3, 3), np.uint8))
            extra = extra.astype(bool) & (contrast >= cfg.min_contrast)
        if extra.any():
            lab, keep, mask_w = _thin_pieces(mask | extra, m_per_px, cfg)
    if not keep:
        return lab, keep, np.zeros(0)
    g = cv2.GaussianBlur(np.asarray(gray, np.uint8), (3, 3), 0)
    widths = [equivalent_width_px(g, lab == i, m_per_px, cfg) for i in keep]
    # No measurable profile (e.g. at the image border): the component's own width.
    widths = [w if np.isfinite(w) else mw for w, mw in zip(widths, mask_w, strict=True)]
    return lab, keep, np.asarray(widths, float)


def _above(z: np.ndarray, k: float) -> np.ndarray:
    """z above the image's own median + k · 1.4826 MAD."""
    med = float(np.median(z))
    mad = 1.4826 * float(np.median(np.abs(z - med)))
    return z > med + k * max(mad, 1e-6)


def _thin_pieces(
    mask: np.ndarray, m_per_px: float, cfg: CrackConfig
) -> tuple[np.ndarray, list[int], list[float]]:
    """Label image of ``mask`` and the ids and mask widths (px) of its long thin components."""
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
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
    return lab, keep, mask_w


def _long_components(mask: np.ndarray, min_len_px: float) -> np.ndarray:
    """Components of ``mask`` (8-connected) at least ``min_len_px`` long (bounding box)."""
    _, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    size = np.maximum(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT])
    ok = size >= min_len_px
    ok[0] = False
    return ok[lab]


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


@dataclass(frozen=True)
class PairView:
    """What the dense crack-depth measurement needs of a pair besides image a: image b (raw
    pixels, like image a) and the pair's metric geometry. ``H`` (a -> b, ideal pixels) is
    only the tracking's initial guess; depths come from R, t, K and the local road plane."""

    gray_b: np.ndarray  # (H, W) image b, same camera as image a
    camera: Camera  # intrinsics and distortion of both images
    R_b_from_a: np.ndarray  # (3, 3) X_b = R X_a + t
    t_b_from_a_m: np.ndarray  # (3,) metric translation (m)

    @staticmethod
    def of(pair: PairResult, gray_b: np.ndarray, camera: Camera) -> PairView | None:
        """The view of an ok pair; None without a metric baseline (t = 0 or not finite)."""
        R = np.asarray(pair.R_b_from_a, float)
        t = np.asarray(pair.t_b_from_a_m, float)
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))) or np.linalg.norm(t) <= 0:
            return None
        return PairView(gray_b, camera, R, t)


@dataclass
class DenseCrack:
    """Dense depth of one crack piece in one pair, from the parallax across the crack."""

    depth_m: np.ndarray  # (M,) depth below the local road of each valid centre-line track (m)
    noise_m: float  # σ of one track's depth: robust spread of the side band about its fit (m)
    n_eff: float  # independent samples along the line: valid tracks / LK window length
    ref_var_m2: float  # variance of the local road reference (side-band fit) at the line (m²)

    def summary(self) -> tuple[float, float, float, float]:
        """(Σ depth, samples, samples below the road, variance of Σ) for the pooled test."""
        below = self.n_eff * float((self.depth_m > 0).mean())
        return self.sum_m, self.n_eff, below, self.var_m2

    @property
    def sum_m(self) -> float:
        """Σ depth over the independent samples (n_eff · mean), for the pooled test (m)."""
        return float(self.n_eff * self.depth_m.mean())

    @property
    def var_m2(self) -> float:
        """Variance of ``sum_m``: n_eff σ² (samples) + n_eff² σ_ref² (shared reference)."""
        return float(self.n_eff * self.noise_m**2 + self.n_eff**2 * self.ref_var_m2)


def _ray_points(px: np.ndarray, K: np.ndarray, plane: np.ndarray, depth_m: float) -> np.ndarray:
    """(N, 3) camera-a points on the rays of ideal pixels ``px`` at ``depth_m`` below the road
    plane Z = p0 X + p1 Y + p2 (positive: farther from the camera)."""
    v = np.c_[(px[:, 0] - K[0, 2]) / K[0, 0], (px[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(px))]
    a, b, c = plane
    s = (c + depth_m * math.sqrt(a * a + b * b + 1.0)) / (v[:, 2] - a * v[:, 0] - b * v[:, 1])
    return v * s[:, None]


def _project(X: np.ndarray, view: PairView) -> np.ndarray:
    Xb = X @ view.R_b_from_a.T + view.t_b_from_a_m
    q = Xb @ view.camera.K.T
    return q[:, :2] / q[:, 2:3]


def _tangents(xy: np.ndarray, radius_px: float) -> np.ndarray:
    """(N, 2) unit tangent of a centre line at each of its pixels: principal direction of the
    line's pixels within ``radius_px``."""
    from scipy.spatial import cKDTree

    tree = cKDTree(xy)
    out = np.zeros_like(xy, dtype=float)
    for i, nb in enumerate(tree.query_ball_point(xy, radius_px)):
        p = xy[nb] - xy[nb].mean(axis=0)
        w, V = np.linalg.eigh(p.T @ p)
        out[i] = V[:, 1]
    return out


def dense_crack_depth(
    line: np.ndarray,
    width_px: float,
    gray_a: np.ndarray,
    view: PairView,
    plane: np.ndarray,
    cfg: CrackConfig,
) -> DenseCrack | None:
    """Dense depth of one crack piece (centre line ``line``, (H, W) bool, in image a).

    The centre-line pixels and a road band on both sides (from ``width_px`` + half the LK window
    to one window farther, so the side windows hold no crack) are tracked into image b with a
    small-window Lucas-Kanade from their road-plane prediction (forward-backward checked). A
    point ``δ`` below the road plane ``plane`` (camera a, Z = p0 X + p1 Y + p2) moves in b by
    J δ from its road prediction (J from R, t, K); only the residual's component across the
    crack is used (LK cannot see a shift along a line): δ = c·r / c·J, c the crack normal in b.
    Where the parallax runs nearly along the crack (|c·J| < ``dense_min_across`` |J|) there is
    no depth to read and None is returned. The side band's δ, fitted by a plane in the image
    (robust), is the local road; the centre's depth is its δ minus that fit and one track's
    noise is the side band's robust spread about the fit (same pair, same direction, same
    window). None when too few tracks survive.
    """
    from roadsurf.detection.dense import _as_u8, _distort, _undistort
    from roadsurf.detection.planefit import robust_sigma
    from roadsurf.reconstruction.features import track_forward_backward

    cam = view.camera
    K = cam.K
    win = int(cfg.dense_window_px) | 1
    half = win // 2
    r0 = width_px + half + 1.0  # side band: its LK windows stay off the crack's dark band
    r1 = r0 + win
    ys, xs = np.nonzero(line)
    if len(xs) < 2 * win:
        return None
    h, w = line.shape
    m = int(math.ceil(r1)) + 2
    y0, y1 = max(0, ys.min() - m), min(h, ys.max() + m + 1)
    x0, x1 = max(0, xs.min() - m), min(w, xs.max() + m + 1)
    sub = ~line[y0:y1, x0:x1]
    dist, lab = cv2.distanceTransformWithLabels(
        sub.astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    # Label of each centre pixel (zero pixels get labels in scan order) -> its index in xs, ys.
    lab_of = np.zeros(int(lab.max()) + 1, int)
    lab_of[lab[ys - y0, xs - x0]] = np.arange(len(xs))
    sv, su = np.nonzero((dist >= r0) & (dist <= r1))
    keep = (su % 2 == 0) & (sv % 2 == 0)  # every second pixel: windows overlap anyway
    sv, su = sv[keep], su[keep]
    near = lab_of[lab[sv, su]]  # nearest centre pixel of each side pixel
    raw = np.r_[np.c_[xs, ys], np.c_[su + x0, sv + y0]].astype(float)
    n_c = len(xs)
    owner = np.r_[np.arange(n_c), near]
    # Geometry at each pixel: road prediction in b, its parallax per metre of depth, the
    # crack's normal in b.
    pa = _undistort(raw, cam)
    X0 = _ray_points(pa, K, plane, 0.0)
    if not np.all(X0[:, 2] > 0):
        return None
    pb0 = _project(X0, view)
    J = (_project(_ray_points(pa, K, plane, 1e-3), view) - pb0) / 1e-3  # px per m of depth
    tan_a = _tangents(pa[:n_c], float(win))
    ends = [_project(_ray_points(pa[:n_c] + s * tan_a, K, plane, 0.0), view) for s in (-1, 1)]
    tan_b = ends[1] - ends[0]
    tan_b /= np.maximum(np.linalg.norm(tan_b, axis=1, keepdims=True), 1e-12)
    nrm = np.c_[-tan_b[:, 1], tan_b[:, 0]][owner]
    cj = np.sum(nrm * J, axis=1)
    # LK's aperture: along the line the shift is unknown, so only the parallax across the
    # crack carries depth; nearly parallel to the parallax there is none (report, no guess).
    if np.median(np.abs(cj[:n_c])) < cfg.dense_min_across * np.median(np.linalg.norm(J, axis=1)):
        return None
    ga, gb = _as_u8(gray_a), _as_u8(view.gray_b)
    ra = raw.astype(np.float32).reshape(-1, 1, 2)
    rb0 = _distort(pb0, cam).astype(np.float32).reshape(-1, 1, 2)
    rb, ra2, ok = track_forward_backward(ga, gb, ra, rb0, win, max_level=2, iterations=30)
    ok &= (
        (raw[:, 0] >= half) & (raw[:, 0] < w - half) & (raw[:, 1] >= half) & (raw[:, 1] < h - half)
    )
    rbv = rb.reshape(-1, 2)
    hb, wb = gb.shape[:2]
    ok &= (rbv[:, 0] >= half) & (rbv[:, 0] < wb - half) & (rbv[:, 1] >= half)
    ok &= rbv[:, 1] < hb - half
    if ok[:n_c].sum() < win or ok[n_c:].sum() < 2 * win:
        return None
    # Forward-backward error against its own robust spread (as in detection/dense.py).
    fb = np.linalg.norm((ra2 - ra).reshape(-1, 2), axis=1)
    ok &= fb <= np.median(fb[ok]) + 3.0 * max(robust_sigma(fb[ok]), 0.02)
    pb = _undistort(rbv.astype(float), cam)
    d = np.sum(nrm * (pb - pb0), axis=1) / np.where(np.abs(cj) > 1e-9, cj, np.nan)
    # A crack floor deeper than this is a failed track (slid, or a shadow moving with the car).
    ok &= np.isfinite(d) & (np.abs(d) <= cfg.dense_max_depth_m)
    ok &= np.abs(cj) >= cfg.dense_min_across * np.linalg.norm(J, axis=1)
    c_ok, s_ok = ok[:n_c], ok[n_c:]
    if c_ok.sum() < win or s_ok.sum() < 2 * win:
        return None
    # Local road: a plane in the image through the side band's δ (robust: 3 σ trimmed).
    A = np.c_[np.ones(len(raw)), (raw - raw[:n_c].mean(axis=0)) / max(w, h)]
    As, ds = A[n_c:][s_ok], d[n_c:][s_ok]
    use = np.ones(len(ds), bool)
    for _ in range(3):
        coef = np.linalg.lstsq(As[use], ds[use], rcond=None)[0]
        res = ds - As @ coef
        sig = max(robust_sigma(res[use]), 1e-5)
        use = np.abs(res) <= 3.0 * sig
        if use.sum() < 2 * win:
            return None
    # Floor: LK's sub-pixel precision (0.02 px, as the forward-backward floor in dense.py)
    # over the parallax across the crack per metre of depth: a noiseless render is not exact.
    floor = 0.02 / max(float(np.median(np.abs(cj[:n_c][c_ok]))), 1e-9)
    sig = max(robust_sigma(res[use]), floor)
    depth = d[:n_c][c_ok] - A[:n_c][c_ok] @ coef
    # Independent samples: tracks closer than one LK window share their pixels.
    n_eff = max(1.0, c_ok.sum() / win)
    n_side = max(1.0, use.sum() * 4.0 / win**2)  # side pixels every 2nd: 4 px² each
    return DenseCrack(depth, sig, n_eff, sig**2 / n_side)


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
    lab, keep, widths = thin_dark_components(gray, m_per_px, cfg)
    if not keep:
        return empty()
    h, w = lab.shape
    u = np.clip(np.round(px[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.round(px[:, 1]).astype(int), 0, h - 1)
    from roadsurf.reconstruction.features import undistort_px

    cam = camera if camera is not None else (view.camera if view is not None else None)
    if px_ideal is None:
        px_ideal = px if cam is None else undistort_px(px, cam)
    px_ideal = np.asarray(px_ideal, float)
    H, _ = cv2.findHomography(px_ideal[road].astype(np.float32), P[road, :2].astype(np.float32), 0)
    if H is None:
        return empty()
    A = np.c_[P[road, :2], np.ones(int(road.sum()))]
    zcoef = np.linalg.lstsq(A, P[road, 2], rcond=None)[0]
    xyz, labels, wd, sd, nn, nb, vv, mx = [], [], [], [], [], [], [], []
    dense: list[DenseCrack | None] = []
    for i, wpx in zip(keep, widths, strict=True):
        line = centre_line(lab == i)
        if not line.any():
            continue
        dist_px = cv2.distanceTransform((~line).astype(np.uint8), cv2.DIST_L2, 3)
        # Points on the groove: within half its width of the centre line (at least ``near_px``,
        # the points' localisation); points beside it are road and only dilute the mean depth.
        near = dist_px[v, u] <= max(cfg.near_px, 0.5 * wpx)
        n = int(near.sum())
        dn = (
            None
            if view is None or not cfg.dense
            else dense_crack_depth(line, wpx, gray, view, np.asarray(zcoef, float), cfg)
        )
        # A thin crack often has no sparse point on it (features straddle it); its dense
        # reading alone then carries it.
        if n == 0 and dn is None:
            continue
        # No decision here: one pair holds only a few points on a crack; the evidence of all
        # pairs that saw it is pooled on the map (``crack_evidence``).
        d = -np.asarray(dist_m, float)[near]  # depth below the road, positive down
        ys, xs = np.nonzero(line)
        step = max(1, len(xs) // cfg.max_samples)
        q = np.c_[xs[::step], ys[::step]].astype(float)
        q = (q if cam is None else undistort_px(q, cam)).astype(np.float32).reshape(-1, 1, 2)
        xy = cv2.perspectiveTransform(q, H).reshape(-1, 2).astype(float)
        zc = np.c_[xy, np.ones(len(xy))] @ zcoef
        xyz.append(np.c_[xy, zc])
        labels.append(np.full(len(xy), len(wd)))
        wd.append(wpx * m_per_px)
        sd.append(float(d.sum()))
        nn.append(n)
        nb.append(int((d > 0).sum()))
        vv.append(n * noise_m**2)
        # robust max: the second-deepest point; without points, the dense reading's 90th
        # percentile (a lower bound, like every dense depth)
        if n >= 2:
            mx.append(float(np.sort(d)[-2]))
        elif n == 1:
            mx.append(float(d[0]))
        elif dn is not None:
            mx.append(float(np.percentile(dn.depth_m, 90)))
        dense.append(dn)
    if not wd:
        return empty()
    dd = [(0.0, 0.0, 0.0, 0.0) if m is None else m.summary() for m in dense]
    return PairCracks(
        np.vstack(xyz),
        np.concatenate(labels),
        *(np.asarray(a, float) for a in (wd, sd, nn, nb, vv, mx)),
        *(np.asarray(a, float) for a in zip(*dd, strict=True)),
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
