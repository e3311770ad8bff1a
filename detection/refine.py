"""2D + 3D refinement of candidate defect points (dissertation Fig. 4.3, CORRECT_DEFECTS).

The image is binarised (dark = 1) at T_b, opened (erode then dilate, W x W) and the 3D candidates
are kept where they fall in the dark region; the region is grown around them and points below
the road inside it join, until the set is stable. Beyond the dissertation, T_b can be chosen per
pixel relative to the local road brightness (``binarise="adaptive"``) so that shadows and
exposure changes do not turn whole image areas "dark".
"""

from __future__ import annotations

import cv2
import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.core.geometry import check_shape
from roadsurf.detection.config import RefineConfig


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) RGB uint8 -> (H, W) uint8 greyscale."""
    img = np.asarray(image)
    if img.ndim == 2:
        return img.astype(np.uint8, copy=False)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        return cv2.cvtColor(np.ascontiguousarray(img[:, :, :3]), cv2.COLOR_RGB2GRAY)
    raise ValueError(f"image: expected (H, W) or (H, W, 3), got {img.shape}")


def local_road_brightness(gray: np.ndarray, window_frac: float) -> tuple[np.ndarray, np.ndarray]:
    """Local median and local MAD of the grey level over a window of ``window_frac`` x width.

    Computed on a reduced image (median filters on uint8 are O(1) per pixel in OpenCV but need
    an odd window <= 255) and resized back. Returns two (H, W) float32 arrays.
    """
    h, w = gray.shape
    win = max(3, int(round(window_frac * w)))
    # Reduce so that the window is about 31 px on the small image.
    f = min(1.0, 31.0 / win)
    small = cv2.resize(gray, (max(1, int(w * f)), max(1, int(h * f))), interpolation=cv2.INTER_AREA)
    k = max(3, int(round(win * f)) | 1)
    k = min(k, 255)
    med = cv2.medianBlur(small, k)
    dev = cv2.absdiff(small, med)
    mad = cv2.medianBlur(dev, k)
    med_f = cv2.resize(med, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float32)
    mad_f = cv2.resize(mad, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float32)
    return med_f, mad_f


def road_brightness_from_points(
    gray: np.ndarray, road_px: np.ndarray, k: int = 12, blur_px: int = 5
) -> tuple[np.ndarray, np.ndarray]:
    """Local road brightness from the pixels of 3D road points (X^rn).

    For a coarse grid of image positions, the median (and MAD) grey level of the ``k`` nearest
    road points, resized to full resolution. Road points are flat road by 3D evidence, so a
    pothole never raises its own reference level, and a shadow on flat road lowers it.
    Returns two (H, W) float32 arrays.
    """
    from scipy.spatial import cKDTree

    h, w = gray.shape
    blur = cv2.blur(gray, (blur_px, blur_px))
    u = np.clip(np.round(road_px[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.round(road_px[:, 1]).astype(int), 0, h - 1)
    vals = blur[v, u].astype(np.float32)
    step = max(1, w // 96)
    gv, gu = np.mgrid[0:h:step, 0:w:step]
    kk = min(k, len(vals))
    _, idx = cKDTree(np.column_stack([u, v])).query(np.column_stack([gu.ravel(), gv.ravel()]), k=kk)
    idx = idx.reshape(len(idx), -1)
    near = vals[idx]
    med = np.median(near, axis=1)
    mad = np.median(np.abs(near - med[:, None]), axis=1)
    shape = gv.shape
    med_f = cv2.resize(
        med.reshape(shape).astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR
    )
    mad_f = cv2.resize(
        mad.reshape(shape).astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR
    )
    return med_f, mad_f


def binarise(gray: np.ndarray, cfg: RefineConfig, road_px: np.ndarray | None = None) -> np.ndarray:
    """Dark mask (H, W) bool at T_b, then opened (erode, dilate) with a W x W window.

    ``fixed``: dark = grey < T_b. ``adaptive``: dark = grey below the local road brightness by
    more than max(k · 1.4826 · MAD, min_drop · level); the level comes from the 3D road points'
    pixels when ``road_px`` (N, 2) is given (>= 20 points), else from a large median window.
    """
    g = to_gray(gray)
    if cfg.binarise == "fixed":
        dark = g < cfg.fixed_threshold
    else:
        # Compare texture-averaged brightness: the road texture's spread would otherwise hide a
        # pothole that is 20-40 % darker.
        b = max(1, int(round(cfg.adaptive_blur_frac * g.shape[1]))) | 1
        gs = cv2.blur(g, (b, b)) if b > 1 else g
        if road_px is not None and len(road_px) >= 20:
            med, mad = road_brightness_from_points(g, np.asarray(road_px, float), blur_px=b)
        else:
            med, mad = local_road_brightness(gs, cfg.adaptive_window_frac)
        drop = np.maximum(cfg.adaptive_dark_k * MAD_TO_SIGMA * mad, cfg.adaptive_min_drop * med)
        dark = gs.astype(np.float32) < med - drop
    W = max(1, int(cfg.window_px))
    kernel = np.ones((W, W), np.uint8)
    opened = cv2.dilate(cv2.erode(dark.astype(np.uint8), kernel), kernel)
    return opened.astype(bool)


def correct_defects(
    dist_m: np.ndarray,
    px: np.ndarray,
    candidate: np.ndarray,
    dark: np.ndarray,
    threshold_m: float,
    cfg: RefineConfig,
) -> np.ndarray:
    """CORRECT_DEFECTS: refined defect mask (N,) bool for one pair.

    dist_m: (N,) signed plane distances (m, negative below); px: (N, 2) pixels (u, v) in the
    image the dark mask comes from; candidate: (N,) bool X^rd; dark: (H, W) bool opened mask;
    threshold_m: T_d used for the candidates.
    Candidates deeper than ``strong_factor`` · T_d are kept without 2D support (clear 3D
    evidence is not overruled by an image that is not darker inside the defect).
    """
    n = check_shape("dist_m", np.asarray(dist_m, float), (None,)).shape[0]
    px = check_shape("px", np.asarray(px, float), (n, 2))
    cand = check_shape("candidate", np.asarray(candidate, bool), (n,))
    h, w = dark.shape
    u = np.clip(np.round(px[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.round(px[:, 1]).astype(int), 0, h - 1)
    inside = (px[:, 0] >= -0.5) & (px[:, 0] < w - 0.5) & (px[:, 1] >= -0.5) & (px[:, 1] < h - 0.5)
    dark_at = dark[v, u] & inside
    strong = cand & (np.abs(dist_m) >= cfg.strong_factor * threshold_m)
    kept = (cand & dark_at) | strong
    if not kept.any():
        return kept
    n_lab, labels = cv2.connectedComponents(dark.astype(np.uint8), connectivity=8)
    below = np.asarray(dist_m) <= -cfg.grow_depth_frac * threshold_m
    lab_at = np.where(inside, labels[v, u], 0)
    for _ in range(cfg.max_iterations):
        comps = np.unique(lab_at[kept & dark_at])
        comps = comps[comps > 0]
        grown = kept | (np.isin(lab_at, comps) & below & dark_at)
        if np.array_equal(grown, kept):
            break
        kept = grown
    return kept


def refined_mask(
    dark: np.ndarray, px: np.ndarray, refined: np.ndarray, radius_px: int = 3
) -> np.ndarray:
    """The refined 2D defect mask (H, W) bool of one image: the dark components (opened mask)
    that hold refined points, plus a disc of ``radius_px`` around refined points outside any
    dark component (kept on 3D evidence alone)."""
    h, w = dark.shape
    px = np.asarray(px, float)
    ref = np.asarray(refined, bool)
    mask = np.zeros((h, w), bool)
    if not ref.any():
        return mask
    p = px[ref]
    inside = (p[:, 0] >= -0.5) & (p[:, 0] < w - 0.5) & (p[:, 1] >= -0.5) & (p[:, 1] < h - 0.5)
    u = np.clip(np.round(p[inside, 0]).astype(int), 0, w - 1)
    v = np.clip(np.round(p[inside, 1]).astype(int), 0, h - 1)
    _, labels = cv2.connectedComponents(dark.astype(np.uint8), connectivity=8)
    lab = labels[v, u]
    comps = np.unique(lab[lab > 0])
    if len(comps):
        mask |= np.isin(labels, comps)
    alone = lab == 0
    if alone.any():
        dots = np.zeros((h, w), np.uint8)
        for x, y in zip(u[alone].tolist(), v[alone].tolist(), strict=True):
            cv2.circle(dots, (x, y), int(radius_px), 1, -1)
        mask |= dots.astype(bool)
    return mask
