"""The 2D thin-structure detector of cracks: an oriented line filter on the greyscale image.

Black top-hat (closing minus image, disc ``tophat_m``) over the closing, averaged along segments
of ``line_m`` in all directions (``line_response``), thresholded relative to the image's own
response; long, thin, elongated components are kept (``thin_dark_components``) and their width
measured on the top-hat profile across the centre line (``equivalent_width_px``). See ``cracks``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import cv2
import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.detection.config import CrackConfig
from roadsurf.detection.crackbank import bank_max


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
    dark: tuple[np.ndarray, int] | None = None,
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
    thin crack's integrated darkness) so the kernels stay small (fast). ``dark``: d from
    ``darkness`` of the same image, reused when its factor matches (two segment lengths at
    one pixel size share it).
    """
    f = _factor(m_per_px, cfg, gsd_m)
    if dark is None or dark[1] != f:
        dark = darkness(gray, m_per_px, cfg, gsd_m)
    d = dark[0]
    h, w = np.asarray(gray).shape[:2]
    length = max(5.0, (cfg.line_m if line_m is None else line_m) / (m_per_px * f))
    # max over directions of cv2.filter2D, bit for bit (the bank's image DFT shared)
    c = bank_max(d, _line_kernels(round(length, 1)), cv2.BORDER_REFLECT)
    s = int(math.ceil(length)) | 1
    c -= cv2.blur(d, (s, s), borderType=cv2.BORDER_REFLECT)
    s2 = 2 * s + 1
    m1 = cv2.blur(d, (s2, s2), borderType=cv2.BORDER_REFLECT)
    sd = np.sqrt(np.maximum(cv2.blur(d * d, (s2, s2), borderType=cv2.BORDER_REFLECT) - m1 * m1, 0))
    # Floor on the spread: 5 % of its median (and 1e-4): a flat patch (saturated, no texture)
    # must not turn quantisation into a strong line.
    z = c / (sd + 0.05 * exact_median(sd) + 1e-4)
    if f > 1:
        z = cv2.resize(z, (w, h), interpolation=cv2.INTER_LINEAR)
        c = cv2.resize(c, (w, h), interpolation=cv2.INTER_LINEAR)
    return z, c


def _factor(m_per_px: float, cfg: CrackConfig, gsd_m: float | None = None) -> int:
    """Whole-pixel downsampling factor to about ``gsd_m`` (``line_gsd_m``) per pixel."""
    return max(1, int((cfg.line_gsd_m if gsd_m is None else gsd_m) / m_per_px))


def darkness(
    gray: np.ndarray, m_per_px: float, cfg: CrackConfig, gsd_m: float | None = None
) -> tuple[np.ndarray, int]:
    """The darkness d of ``line_response`` (black top-hat, disc ``tophat_m``, over the closing;
    float32) area-averaged down by the factor f to about ``gsd_m`` per pixel: (d, f)."""
    g = cv2.GaussianBlur(np.asarray(gray, np.uint8), (3, 3), 0)
    k = max(3, int(round(cfg.tophat_m / m_per_px)) | 1)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    close = cv2.morphologyEx(g, cv2.MORPH_CLOSE, disc).astype(np.float32)
    d: np.ndarray = (close - g) / np.maximum(close, 1.0)
    h, w = d.shape
    f = _factor(m_per_px, cfg, gsd_m)
    if f > 1:
        d = cv2.resize(d, (max(1, w // f), max(1, h // f)), interpolation=cv2.INTER_AREA)
    return d, f


def exact_median(x: np.ndarray) -> float:
    """``float(np.median(x))`` bit for bit, for a large float array in a fraction of its time:
    the middle order statistics are selected among the values between two bounds read off a
    strided subsample (their ranks checked by counting; a full ``np.median`` when the bounds
    miss them or x holds NaN)."""
    a = np.asarray(x).ravel()
    n = a.size
    if n < 1 << 14 or a.dtype.kind != "f":
        return float(np.median(a))
    k1, k2 = (n - 1) // 2, n // 2
    s = np.sort(a[:: n >> 10])
    m = len(s)
    lo, hi = s[int(0.46 * m)], s[min(m - 1, int(0.54 * m))]
    below = int(np.count_nonzero(a < lo))
    mid = a[(a >= lo) & (a <= hi)]
    above = int(np.count_nonzero(a > hi))
    if below + mid.size + above != n or below > k1 or below + mid.size <= k2:
        return float(np.median(a))
    part = np.partition(mid, sorted({k1 - below, k2 - below}))
    # as np.median: the mean of the middle one or two values, in the array's dtype
    return float(np.mean(part[k1 - below : k2 - below + 1]))


def thin_dark_components(
    gray: np.ndarray,
    m_per_px: float,
    cfg: CrackConfig,
    gsd_at: Callable[[np.ndarray], np.ndarray] | None = None,
    usable: np.ndarray | None = None,
) -> tuple[np.ndarray, list[int], np.ndarray, np.ndarray]:
    """Label image (H, W) int32, the ids of long thin dark components, their width (px) and the
    ground size of a pixel where each lies (m/px). ``usable``: (H, W) bool pixels off the
    camera's mask (None: all); line pixels elsewhere are dropped (the gaps between a burned-in
    stamp's letters are thin dark lines).

    ``m_per_px`` sets the filters' scales (top-hat disc, line length); each component's length
    and width limits and its measured width use the ground size of a pixel at the component
    (``gsd_at``: (N, 2) raw pixels -> (N,) m/px; None: ``m_per_px`` everywhere), so a tilted
    camera, whose pixels cover more road towards the horizon, measures every crack in metres.

    Pixels whose oriented line response (``line_response``) exceeds the image's own median +
    ``contrast_k`` · 1.4826 MAD form components; those long (≥ ``min_length_m``), thin
    (area / length ≤ ``max_width_m``) and elongated (≥ ``min_elongation``) are kept. A second,
    longer segment (``line_long_m``, threshold ``long_contrast_k``) adds its long lines,
    thinned, where the short one also sees them darker. The width is the crack's equivalent width measured on the top-hat
    (``equivalent_width_px``).
    """
    dark = darkness(gray, m_per_px, cfg)  # the long segment shares it at the same pixel size
    z, contrast = line_response(gray, m_per_px, cfg, dark=dark)
    mask = _above(z, cfg.contrast_k) & (contrast >= cfg.min_contrast)
    if usable is not None:
        mask &= usable
    extra: np.ndarray | None = None
    if cfg.line_long_m > cfg.line_m:
        # Busy textures: the long segment finds the crack where the short one drowns in
        # texture. Only its lines at least twice its length join (it smears each texture
        # streak to its own length), thinned to their centre line and 1 px each side (it also
        # answers beside a line), where the short segment too sees them darker than their
        # surroundings (the long one overshoots a line's ends by half its length).
        from skimage.morphology import skeletonize

        z_long, c_long = line_response(
            gray, m_per_px, cfg, cfg.line_long_m, cfg.line_long_gsd_m, dark=dark
        )
        extra = _above(z_long, cfg.long_contrast_k) & (c_long >= cfg.min_contrast)
        extra = _long_components(extra, 2.0 * cfg.line_long_m / m_per_px)
        if extra.any():
            extra = cv2.dilate(skeletonize(extra).astype(np.uint8), np.ones((3, 3), np.uint8))
            extra = extra.astype(bool) & (contrast >= cfg.min_contrast)
    if extra is not None and usable is not None:
        extra &= usable
    pieces = mask if extra is None or not extra.any() else mask | extra
    lab, keep, mask_w, gsd = _thin_pieces(pieces, m_per_px, cfg, gsd_at)
    if not keep:
        return lab, keep, np.zeros(0), np.zeros(0)
    g = cv2.GaussianBlur(np.asarray(gray, np.uint8), (3, 3), 0)
    widths = [equivalent_width_px(g, lab == i, m, cfg) for i, m in zip(keep, gsd, strict=True)]
    # No measurable profile (e.g. at the image border): the component's own width.
    widths = [w if np.isfinite(w) else mw for w, mw in zip(widths, mask_w, strict=True)]
    return lab, keep, np.asarray(widths, float), np.asarray(gsd, float)


def _above(z: np.ndarray, k: float) -> np.ndarray:
    """z above the image's own median + k · 1.4826 MAD."""
    med = exact_median(z)
    mad = MAD_TO_SIGMA * exact_median(np.abs(z - med))
    return z > med + k * max(mad, 1e-6)


def _thin_pieces(
    mask: np.ndarray,
    m_per_px: float,
    cfg: CrackConfig,
    gsd_at: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, list[int], list[float], list[float]]:
    """Label image of ``mask`` and the ids, mask widths (px) and ground pixel sizes (m/px, at
    each component's centroid; ``m_per_px`` without ``gsd_at``) of its long thin components."""
    n, lab, stats, cent = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep: list[int] = []
    mask_w: list[float] = []
    gsd_kept: list[float] = []
    gsd = np.full(n, float(m_per_px)) if gsd_at is None or n < 2 else gsd_at(cent)
    for i in range(1, n):
        min_len_px = cfg.min_length_m / gsd[i]
        max_w_px = max(2.5, cfg.max_width_m / gsd[i])
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
            gsd_kept.append(float(gsd[i]))
    return lab, keep, mask_w, gsd_kept


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
