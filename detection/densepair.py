"""Dense tracks of one pair on and around one candidate defect (see ``dense``).

A grid of pixels of image a inside the defect's outline and a road ring around it is tracked
into image b with pyramidal Lucas-Kanade; tracks that come back (forward-backward), keep to the
epipolar line and agree with their neighbours (``densecheck``) are triangulated with the pair's
R, t and K and levelled on a robust plane through the ring.

LK's window only translates. Where the pair's road homography H turns, scales or shears the
ground under a window so much that the window's corners land more than half a pixel from where
a translation puts them (``WINDOW_SLACK_PX``; a camera turned by tens of degrees between two
photographs, a 45° view), image b is first warped onto image a by H (``road_aligned_tracks``):
the road then lies where it lies in a and LK only has to find the parallax of what is off the
road. Tracked in b's own pixels those windows do not show the same ground, and the tracks fail
(real photographs turned by 20-80°: dense road σ 10-60 mm against 1-2 mm for the sparse
points). A driving nadir camera moves its windows by a few hundredths of a pixel that way and
is tracked in b's own pixels (no resampling of b).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from roadsurf.core.camera import Camera, normalised_from_px
from roadsurf.core.fits import plane_signed_distance, robust_plane_z, robust_sigma
from roadsurf.core.geometry import skew
from roadsurf.detection.densecheck import cell_area, consistent, no_deep_patch
from roadsurf.reconstruction.features import track_forward_backward
from roadsurf.reconstruction.geometry import triangulate
from roadsurf.reconstruction.types import PairResult

if TYPE_CHECKING:
    from shapely.geometry import Polygon

log = logging.getLogger(__name__)


@dataclass
class PairDense:
    """One pair's dense points on and around one defect (grid frame; depths positive down)."""

    xy_m: np.ndarray  # (M, 2) grid-frame xy of the valid tracks inside the outline (+ edge band)
    depth_m: np.ndarray  # (M,) their depth below the pair's local road plane (m)
    spacing_m: float  # road distance between neighbouring tracked pixels (m)
    noise_m: float  # σ of the dense road points about their plane (m)


def _apply_h(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    q = np.column_stack([xy, np.ones(len(xy))]) @ H.T
    return q[:, :2] / q[:, 2:3]


def grid_to_image_h(
    grid_xy: np.ndarray, px_a: np.ndarray, road: np.ndarray, origin: np.ndarray
) -> np.ndarray | None:
    """Homography (3, 3) from grid-frame xy (minus ``origin``) to image-a pixels, fitted on the
    pair's road points (the road is a plane, so a homography maps it exactly); None when too
    few road points."""
    if road.sum() < 8:
        return None
    H, _ = cv2.findHomography(
        (grid_xy[road] - origin).astype(np.float64), px_a[road].astype(np.float64), 0
    )
    return H


def road_homography(pair: PairResult, road: np.ndarray) -> np.ndarray | None:
    """The pair's road homography a -> b (3, 3): its own H, else (estimators that do not
    store one, e.g. colmap) fitted with RANSAC on its road matches; None without a metric
    baseline (t = 0) or too few road matches."""
    H = np.asarray(pair.H, float)
    if np.all(np.isfinite(H)):
        return H
    t = np.asarray(pair.t_b_from_a_m, float)
    if not np.all(np.isfinite(t)) or np.linalg.norm(t) <= 0 or road.sum() < 8:
        return None
    pa = np.asarray(pair.px_a, float)[road]
    pb = np.asarray(pair.px_b, float)[road]
    H, _ = cv2.findHomography(pa, pb, cv2.RANSAC, 2.0)
    return H


def measure_dense(
    poly: Polygon,
    gray_a: np.ndarray,
    gray_b: np.ndarray,
    pair: PairResult,
    grid_xy: np.ndarray,
    road: np.ndarray,
    camera: Camera,
    *,
    ring_m: float,
    edge_m: float,
    step_px: float,
    window_px: int = 15,
    road_cam_m: np.ndarray | None = None,
    max_depth_m: float = 0.25,
    patch_window_m: float = 0.04,
) -> PairDense | None:
    """Dense depths of the defect inside ``poly`` (shapely Polygon, grid frame) seen by ``pair``.

    The outline grown by ``edge_m`` is tracked (the raster outline may stop short of the rim);
    the road ring from there to ``ring_m`` levels the depths. ``grid_xy`` (N, 2): the pair's
    sparse points in the grid frame (they place the outline in image a); ``road`` (N,): which
    of them are road. Only the part of the defect inside both images is measured. None when
    too few tracks survive or the visible road ring is too small to level against.
    ``patch_window_m``: the window (m on the road) of the island / deep-patch check
    (``no_deep_patch``).
    """
    from shapely import contains_xy

    origin = np.asarray(poly.centroid.coords[0], float)
    Hg = grid_to_image_h(grid_xy, np.asarray(pair.px_a, float), road, origin)
    H = road_homography(pair, road)
    if Hg is None or H is None:
        return _none("no homography")
    core = poly.buffer(edge_m)
    outer = poly.buffer(edge_m + ring_m)
    ox0, oy0, ox1, oy1 = outer.bounds
    box = np.array([[ox0, oy0], [ox1, oy0], [ox1, oy1], [ox0, oy1]]) - origin
    corners = _apply_h(Hg, box)
    h_img, w_img = gray_a.shape[:2]
    margin = window_px // 2 + 1  # LK window half-size
    u0, v0 = np.maximum(np.floor(corners.min(axis=0)), margin)
    u1 = min(np.ceil(corners[:, 0].max()), w_img - 1 - margin)
    v1 = min(np.ceil(corners[:, 1].max()), h_img - 1 - margin)
    if u1 - u0 < 4 * step_px or v1 - v0 < 4 * step_px:
        return _none("outside image a")
    U, V = np.meshgrid(np.arange(u0, u1 + 1, step_px), np.arange(v0, v1 + 1, step_px))
    pa = np.column_stack([U.ravel(), V.ravel()])
    g = _apply_h(np.linalg.inv(Hg), pa) + origin  # grid xy of every tracked pixel
    inside = contains_xy(core, g[:, 0], g[:, 1])
    ring = contains_xy(outer, g[:, 0], g[:, 1]) & ~inside
    pb0 = _apply_h(H, pa)
    in_b = (pb0[:, 0] >= margin) & (pb0[:, 1] >= margin)
    in_b &= (pb0[:, 0] <= gray_b.shape[1] - 1 - margin) & (
        pb0[:, 1] <= gray_b.shape[0] - 1 - margin
    )
    use = (inside | ring) & in_b
    if camera.mask is not None:  # LK windows off the camera's mask, in a and in b
        use &= camera.usable_px(camera.distort_px(pa), margin)
        use &= camera.usable_px(camera.distort_px(pb0), margin)
    if (inside & use).sum() < 10 or (ring & use).sum() < 30:
        return _none("too little of the defect in both images")
    a8, b8 = as_u8(gray_a), as_u8(gray_b)
    ra = camera.distort_px(pa[use]).astype(np.float32).reshape(-1, 1, 2)
    if window_misfit_px(H, pa[use].mean(axis=0), window_px) > WINDOW_SLACK_PX:
        rb, ra2, ok = road_aligned_tracks(a8, b8, ra, H, camera, window_px)
    else:
        rb0 = camera.distort_px(pb0[use]).astype(np.float32).reshape(-1, 1, 2)
        rb, ra2, ok = track_forward_backward(a8, b8, ra, rb0, window_px, max_level=3, iterations=40)
    if ok.sum() < 30:
        return _none("too few tracks")
    # Forward-backward error and epipolar residual, each against its own robust spread: LK is
    # free in 2D, a track that does not come back or leaves the epipolar line is a wrong match.
    fb = np.linalg.norm((ra2 - ra).reshape(-1, 2), axis=1)
    ok &= fb <= np.median(fb[ok]) + 3.0 * max(robust_sigma(fb[ok]), 0.02)
    K = camera.K
    R = np.asarray(pair.R_b_from_a, float)
    t = np.asarray(pair.t_b_from_a_m, float)
    na = normalised_from_px(camera.undistort_px(ra.reshape(-1, 2)), K)
    nb = normalised_from_px(camera.undistort_px(rb.reshape(-1, 2)), K)
    epi = np.abs(_sampson(skew(t) @ R, na, nb)) * camera.fx
    ok &= epi <= np.median(epi[ok]) + 3.0 * max(robust_sigma(epi[ok]), 0.02)
    P = triangulate(na, nb, R, t)
    ok &= P[:, 2] > 0
    gi = g[use]
    ins_u, ring_u = inside[use], ring[use]
    road_ok = ok & ring_u
    if road_ok.sum() < 30 or (ok & ins_u).sum() < 10:
        return _none("too few valid tracks")
    lev = P[road_ok] if road_cam_m is None else np.vstack([P[road_ok], road_cam_m])
    plane = robust_plane_z(lev, iterations=4)
    if plane is None:
        return _none("no road plane")
    d = -plane_signed_distance(P, plane)  # positive below the road
    noise = max(robust_sigma(d[road_ok]), 1e-4)
    # A track that slid along the epipolar line (weak texture along it, e.g. a rut running
    # with the direction of travel) passes both checks above with a wildly wrong depth. Drop
    # depths no road defect has (the plane fit's own mismatch bound) and spikes that disagree
    # with their neighbours on the tracking grid: a real surface is continuous at 2 px.
    ok &= np.abs(d) <= max_depth_m
    ok &= consistent(d, ok, use, U.shape, noise)
    # A small patch of tracks that slid together agrees with itself in the 5 x 5 check; against
    # the road around it (patch_window_m) it stands out as a narrow, far deeper hole.
    spacing = float(np.sqrt(np.median(cell_area(g, U.shape)[use])))
    half = int(np.clip(round(patch_window_m / max(spacing, 1e-6) / 2), 2, 10))
    ok &= no_deep_patch(d, ok, use, U.shape, noise, half)
    road_ok = ok & ring_u
    if road_ok.sum() < 30 or (ok & ins_u).sum() < 10:
        return _none("too few consistent tracks")
    sel = ok & ins_u
    return PairDense(gi[sel], d[sel], spacing, noise)


WINDOW_SLACK_PX = 0.5  # a window's corners may be off a translation by half a pixel (px)


def window_misfit_px(H: np.ndarray, px: np.ndarray, window_px: int) -> float:
    """How far (px) the homography ``H`` moves the corners of a ``window_px`` window at ideal
    pixel ``px`` (2,) from where the translation of its centre puts them: ||J - I||₂ r √2, J
    the Jacobian of H there, r the window's half size. The same in every pyramid level."""
    x = np.array([px[0], px[1], 1.0])
    y = np.asarray(H, float) @ x
    J = (H[:2, :2] * y[2] - np.outer(y[:2], H[2, :2])) / y[2] ** 2
    return float(np.linalg.norm(J - np.eye(2), 2)) * (window_px // 2) * math.sqrt(2.0)


def road_aligned_tracks(
    a8: np.ndarray,
    b8: np.ndarray,
    ra: np.ndarray,
    H: np.ndarray,
    camera: Camera,
    window_px: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Track raw pixels ``ra`` (N, 1, 2) of image a into image b on b warped onto a by the road
    homography ``H`` (ideal pixels a -> b), over the tracks' bounding box only.

    Returns (rb, ra2, ok) as ``track_forward_backward``: the tracks in b's raw pixels, the
    back-tracked pixels in a, and which converged both ways. A track that leaves the warped
    window or b's image is not ok.
    """
    q = ra.reshape(-1, 2)
    pad = window_px + 8  # LK window and a pyramid level's worth of context around the tracks
    h, w = a8.shape[:2]
    u0, v0 = (max(0, int(np.floor(q[:, i].min())) - pad) for i in (0, 1))
    u1 = min(w, int(np.ceil(q[:, 0].max())) + pad + 1)
    v1 = min(h, int(np.ceil(q[:, 1].max())) + pad + 1)
    U, V = np.meshgrid(np.arange(u0, u1, dtype=np.float64), np.arange(v0, v1, dtype=np.float64))
    grid = np.c_[U.ravel(), V.ravel()]
    # raw a -> ideal a -> H -> ideal b -> raw b, for every pixel of the box
    src = camera.distort_px(_apply_h(H, camera.undistort_px(grid)))
    mx = src[:, 0].reshape(U.shape).astype(np.float32)
    my = src[:, 1].reshape(U.shape).astype(np.float32)
    # Beyond b's border the warp repeats b's edge, as LK's own pyramids extend an image: a
    # window reaching past the border still tracks what b shows (a black border would fail
    # every track near it); tracks that end outside b are dropped below.
    bw = cv2.remap(b8, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    aw = np.ascontiguousarray(a8[v0:v1, u0:u1])
    off = np.array([u0, v0], np.float32)
    q0 = (q - off).astype(np.float32).reshape(-1, 1, 2)
    qb, ra2, ok = track_forward_backward(aw, bw, q0, q0, window_px, max_level=3, iterations=40)
    qb = qb.reshape(-1, 2)
    inside = (qb[:, 0] >= 0) & (qb[:, 0] <= u1 - u0 - 1) & (qb[:, 1] >= 0)
    inside &= qb[:, 1] <= v1 - v0 - 1
    ok &= inside & np.all(np.isfinite(qb), axis=1)
    # the warped pixel (x, y) of the box is b's raw pixel (mx, my) there: read the maps
    bu, bv = _bilinear(mx, qb), _bilinear(my, qb)
    bh, bw_ = b8.shape[:2]
    ok &= (bu >= 0) & (bu <= bw_ - 1) & (bv >= 0) & (bv <= bh - 1)
    rb = np.c_[bu, bv].astype(np.float32).reshape(-1, 1, 2)
    return rb, (ra2.reshape(-1, 2) + off).reshape(-1, 1, 2), ok


def _bilinear(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N,) bilinear samples of ``img`` (H, W) at (N, 2) positions x, y (clipped to the image)."""
    h, w = img.shape
    x = np.clip(np.nan_to_num(xy[:, 0].astype(np.float64)), 0, w - 1)
    y = np.clip(np.nan_to_num(xy[:, 1].astype(np.float64)), 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(int), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(int), max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def _none(why: str) -> None:
    log.debug("detection: dense measurement: no reading (%s)", why)
    return None


def as_u8(img: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) RGB image -> (H, W) uint8 grey (values clipped to 0-255)."""
    img = np.asarray(img)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img


def _sampson(E: np.ndarray, na: np.ndarray, nb: np.ndarray) -> np.ndarray:
    xa = np.column_stack([na, np.ones(len(na))])
    xb = np.column_stack([nb, np.ones(len(nb))])
    Ea = xa @ E.T
    Etb = xb @ E
    num = np.sum(xb * Ea, axis=1)
    den = np.sqrt(Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Etb[:, 0] ** 2 + Etb[:, 1] ** 2) + 1e-300
    return num / den
