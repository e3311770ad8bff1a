"""Dense measurement of a candidate defect in one pair's own frame.

The reconstruction's sparse features rarely fall on a pothole's deepest spot (dark, smooth
floors hold few features), so depths measured from them read shallow. Inside each candidate
defect this module tracks a dense grid of pixels of image a into image b with pyramidal
Lucas-Kanade, initialised by the pair's road homography H, keeps forward-backward consistent
tracks that also agree with the pair's epipolar geometry, triangulates them with the pair's
metric R, t and K, and measures the defect against a robust plane through the dense road points
in a ring around it. Work is bounded by the defects, not the image: only the pixels inside a
candidate's outline (plus its ring) are tracked.

Thresholds are relative to the measured noise of each pair's dense points (forward-backward
error, epipolar residual, plane residual), so no setting is tied to one render.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from roadsurf.core.parallel import ordered_map
from roadsurf.detection.planefit import nanmedian_last, robust_plane, robust_sigma, signed_distance
from roadsurf.io.drive import Camera, GrayFrames
from roadsurf.reconstruction.features import track_forward_backward
from roadsurf.reconstruction.geometry import normalised_from_px, triangulate

log = logging.getLogger(__name__)


@dataclass
class PairDense:
    """One pair's dense points on and around one defect (grid frame; depths positive down)."""

    xy_m: np.ndarray  # (M, 2) grid-frame xy of the valid tracks inside the outline (+ edge band)
    depth_m: np.ndarray  # (M,) their depth below the pair's local road plane (m)
    spacing_m: float  # road distance between neighbouring tracked pixels (m)
    noise_m: float  # σ of the dense road points about their plane (m)


@dataclass
class DenseMeasure:
    """A defect measured from the dense points of all pairs that see it (metres)."""

    max_depth_m: float  # deepest cell of the 3 x 3 median-filtered dense depth grid
    mean_depth_m: float  # mean depth of the cells deeper than the rim threshold
    area_m2: float  # area of the cells deeper than the rim threshold
    volume_m3: float  # fill volume: depth summed over the cells inside the outline x cell area
    noise_m: float  # σ of the dense road points about their planes (median over pairs, m)
    coverage: float  # share of the outline's cells with a dense depth (0-1)
    n_pairs: int  # pairs that contributed
    origin_m: np.ndarray  # (2,) grid-frame xy of the dense grid's lower-left corner
    cell_m: float  # dense grid cell size (m)
    depth_grid_m: np.ndarray  # (ny, nx) combined depth per cell, NaN where no pair tracked it

    def depth_at(self, xy_m: np.ndarray) -> np.ndarray:
        """(N,) dense depth (m) of the cells holding grid-frame points (N, 2); NaN outside."""
        xy = np.asarray(xy_m, float).reshape(-1, 2)
        ny, nx = self.depth_grid_m.shape
        ix = np.floor((xy[:, 0] - self.origin_m[0]) / self.cell_m).astype(int)
        iy = np.floor((xy[:, 1] - self.origin_m[1]) / self.cell_m).astype(int)
        ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        out = np.full(len(xy), np.nan)
        out[ok] = self.depth_grid_m[iy[ok], ix[ok]]
        return out


def _distort(px: np.ndarray, camera: Camera) -> np.ndarray:
    """(N, 2) ideal pinhole pixels -> raw pixels of the camera (identity without distortion)."""
    if not camera.has_distortion or len(px) == 0:
        return px
    K = camera.K
    n = normalised_from_px(px, K)
    pts = np.column_stack([n, np.ones(len(n))]).reshape(-1, 1, 3)
    out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, np.asarray(camera.dist, float))
    return out.reshape(-1, 2)


def _undistort(px: np.ndarray, camera: Camera) -> np.ndarray:
    from roadsurf.reconstruction.features import undistort_px

    return undistort_px(px, camera)


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


def road_homography(pair: Any, road: np.ndarray) -> np.ndarray | None:
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
    poly: Any,
    gray_a: np.ndarray,
    gray_b: np.ndarray,
    pair: Any,
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
    (``_no_deep_patch``).
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
    if (inside & use).sum() < 10 or (ring & use).sum() < 30:
        return _none("too little of the defect in both images")
    a8, b8 = _as_u8(gray_a), _as_u8(gray_b)
    ra = _distort(pa[use], camera).astype(np.float32).reshape(-1, 1, 2)
    rb0 = _distort(pb0[use], camera).astype(np.float32).reshape(-1, 1, 2)
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
    na = normalised_from_px(_undistort(ra.reshape(-1, 2), camera), K)
    nb = normalised_from_px(_undistort(rb.reshape(-1, 2), camera), K)
    epi = np.abs(_sampson(_skew(t) @ R, na, nb)) * camera.fx
    ok &= epi <= np.median(epi[ok]) + 3.0 * max(robust_sigma(epi[ok]), 0.02)
    P = triangulate(na, nb, R, t)
    ok &= P[:, 2] > 0
    gi = g[use]
    ins_u, ring_u = inside[use], ring[use]
    road_ok = ok & ring_u
    if road_ok.sum() < 30 or (ok & ins_u).sum() < 10:
        return _none("too few valid tracks")
    lev = P[road_ok] if road_cam_m is None else np.vstack([P[road_ok], road_cam_m])
    plane = robust_plane(lev, iterations=4)
    if plane is None:
        return _none("no road plane")
    d = -signed_distance(P, plane)  # positive below the road
    noise = max(robust_sigma(d[road_ok]), 1e-4)
    # A track that slid along the epipolar line (weak texture along it, e.g. a rut running
    # with the direction of travel) passes both checks above with a wildly wrong depth. Drop
    # depths no road defect has (the plane fit's own mismatch bound) and spikes that disagree
    # with their neighbours on the tracking grid: a real surface is continuous at 2 px.
    ok &= np.abs(d) <= max_depth_m
    ok &= _consistent(d, ok, use, U.shape, noise)
    # A small patch of tracks that slid together agrees with itself in the 5 x 5 check; against
    # the road around it (patch_window_m) it stands out as a narrow, far deeper hole.
    spacing = float(np.sqrt(np.median(_cell_area(g, U.shape)[use])))
    half = int(np.clip(round(patch_window_m / max(spacing, 1e-6) / 2), 2, 10))
    ok &= _no_deep_patch(d, ok, use, U.shape, noise, half)
    road_ok = ok & ring_u
    if road_ok.sum() < 30 or (ok & ins_u).sum() < 10:
        return _none("too few consistent tracks")
    sel = ok & ins_u
    return PairDense(gi[sel], d[sel], spacing, noise)


def combine_dense(
    poly: Any,
    got: list[PairDense],
    *,
    edge_m: float,
    rim_k: float,
    rim_floor_m: float,
    extrapolate: bool = True,
) -> DenseMeasure | None:
    """Grid the pairs' dense depths on one cell grid (one pair's mean per cell, then the median
    over the pairs that saw the cell) and measure the defect on it: the deepest cell of the 3 x 3
    median (one bad track cannot set it), the area and mean depth of the cells deeper than the
    rim (max(rim floor, rim_k σ)), the fill volume. A defect no single pair saw whole is
    measured whole from the pairs that saw its parts."""
    from shapely import contains_xy

    if not got:
        return None
    c = max(p.spacing_m for p in got)
    core = poly.buffer(edge_m)
    x0, y0, x1, y1 = core.bounds
    nx, ny = int(np.ceil((x1 - x0) / c)) + 1, int(np.ceil((y1 - y0) / c)) + 1
    vals: list[np.ndarray] = []
    for p in got:
        ix = np.clip(((p.xy_m[:, 0] - x0) / c).astype(int), 0, nx - 1)
        iy = np.clip(((p.xy_m[:, 1] - y0) / c).astype(int), 0, ny - 1)
        s = np.zeros(nx * ny)
        n = np.zeros(nx * ny)
        np.add.at(s, iy * nx + ix, p.depth_m)
        np.add.at(n, iy * nx + ix, 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            vals.append(np.where(n > 0, s / n, np.nan))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        D = np.nanmedian(np.vstack(vals), axis=0).reshape(ny, nx)
    cx = x0 + (np.arange(nx) + 0.5) * c
    cy = y0 + (np.arange(ny) + 0.5) * c
    CX, CY = np.meshgrid(cx, cy)
    in_core = contains_xy(core, CX, CY)
    in_poly = contains_xy(poly, CX, CY)
    Dm = _nanmedian3(D)
    seen = in_core & np.isfinite(D)
    if not (in_poly & np.isfinite(Dm)).any():
        return None
    max_d = float(np.nanmax(np.where(in_poly, Dm, np.nan)))
    noise = float(np.median([p.noise_m for p in got]))
    rim = max(rim_floor_m, rim_k * noise)
    cover = float(seen.sum()) / max(int(in_core.sum()), 1)
    dv = D[seen]
    deep = dv >= rim
    # Cells no pair tracked count at the share of the tracked ones.
    area = float(deep.sum()) * c * c / max(cover, 1e-6)
    if extrapolate:
        # The outline is where the depth reaches 0, which noise hides: the area deeper than t
        # falls about linearly as t grows from 0 (any smooth rim), so the areas at the rim
        # threshold and at twice it extrapolate to the area at depth 0.
        a2 = float((dv >= 2 * rim).sum()) * c * c / max(cover, 1e-6)
        area = min(2 * area - a2, float(in_core.sum()) * c * c)
    vol = float(np.clip(dv, 0, None).sum()) * c * c / max(cover, 1e-6)
    mean = float(dv[deep].mean()) if deep.any() else 0.0
    return DenseMeasure(
        max_depth_m=max_d,
        mean_depth_m=mean,
        area_m2=area,
        volume_m3=vol,
        noise_m=noise,
        coverage=cover,
        n_pairs=len(got),
        origin_m=np.array([x0, y0]),
        cell_m=c,
        depth_grid_m=np.where(in_core, D, np.nan),
    )


def _consistent(
    d: np.ndarray, ok: np.ndarray, use: np.ndarray, shape: tuple[int, int], noise_m: float
) -> np.ndarray:
    """(K,) mask over the used tracks: depth within max(6 σ, 5 mm, 25 %) of the median of its
    valid neighbours in a 5 x 5 window of the tracking grid (``shape``). A steep wall between
    floor and rim may lose a cell or two; the floor and the rim, which set the measures, stay."""
    G, idx = _track_grid(d, ok, use, shape)
    pad = np.pad(G, 2, constant_values=np.nan)
    win = np.lib.stride_tricks.sliding_window_view(pad, (5, 5)).reshape(-1, 25)[idx]
    med = nanmedian_last(win)
    n = np.isfinite(win).sum(axis=-1)
    tol = np.maximum(np.maximum(6.0 * noise_m, 0.005), 0.25 * np.abs(med))
    # Needs a few neighbours to judge; an isolated track has no support either way.
    return (n >= 5) & (np.abs(d - med) <= tol)


def _no_deep_patch(
    d: np.ndarray,
    ok: np.ndarray,
    use: np.ndarray,
    shape: tuple[int, int],
    noise_m: float,
    half: int,
    min_support: float = 0.2,
) -> np.ndarray:
    """(K,) mask over the used tracks, judged in a (2 half + 1)² window of the tracking grid:
    False for a track

    - in an island: fewer than ``min_support`` of the window's tracked pixels kept a valid
      track. Where LK failed around it (motion blur, a steep wall's occlusion), the few tracks
      that survived slid there together and agree with each other, not with the road;
    - or deeper than the 75th percentile of the window's valid tracks by more than
      max(6 σ, 5 mm, 25 %): a patch of wrong tracks covering less than a quarter of the window
      cannot move that percentile. A pothole floor wider than that sets it, so the floor stays,
      also next to a vertical wall.

    Only the deep side is judged, from 5 mm down (a deep patch sets the max depth; a shallow
    one is bounded by the rim). Losing a low-texture floor to the island rule leaves a partial
    reading, and the sparse points measure it instead: shallow, never invented depth."""
    G, idx = _track_grid(d, ok, use, shape)
    w = 2 * half + 1

    def box(m: np.ndarray) -> np.ndarray:  # window sums, zero outside the grid
        return cv2.boxFilter(m, -1, (w, w), normalize=False, borderType=cv2.BORDER_CONSTANT)

    used = np.zeros(shape[0] * shape[1], np.float32)
    used[idx] = 1.0
    n_used = box(used.reshape(shape)).ravel()[idx]
    n_ok = box(np.isfinite(G).astype(np.float32)).ravel()[idx]
    island = ok & (n_ok < min_support * np.maximum(n_used, 1.0))
    # The percentile only for tracks that could fail it (tol >= 5 mm), on at most 11 x 11
    # samples of the window (a stride on wide windows): a sort per track is the cost here.
    cand = np.flatnonzero(ok & ~island & (d > 0.005))
    deep = np.zeros(len(idx), bool)
    if len(cand):
        step = max(1, int(round(half / 5)))
        pad = np.pad(G, half, constant_values=np.nan)
        win = np.lib.stride_tricks.sliding_window_view(pad, (w, w))[:, :, ::step, ::step]
        rc = np.unravel_index(idx[cand], shape)
        v = win[rc[0], rc[1]].reshape(len(cand), -1)
        n = np.isfinite(v).sum(axis=-1)
        srt = np.sort(np.where(np.isfinite(v), v, np.inf), axis=-1)  # NaN last
        q = srt[np.arange(len(srt)), np.maximum(np.floor(0.75 * (n - 1)).astype(int), 0)]
        tol = np.maximum(np.maximum(6.0 * noise_m, 0.005), 0.25 * np.abs(q))
        deep[cand] = (n >= 8) & (d[cand] > q + tol)
    return ~(island | deep)


def _track_grid(
    d: np.ndarray, ok: np.ndarray, use: np.ndarray, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """The valid depths on the tracking grid, (H, W) with NaN elsewhere, and the flat grid
    index of each used track (K,)."""
    grid = np.full(shape[0] * shape[1], np.nan)
    idx = np.flatnonzero(use)
    grid[idx[ok]] = d[ok]
    return grid.reshape(shape), idx


def _none(why: str) -> None:
    log.debug("detection: dense measurement: no reading (%s)", why)
    return None


def _as_u8(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], float)


def _sampson(E: np.ndarray, na: np.ndarray, nb: np.ndarray) -> np.ndarray:
    xa = np.column_stack([na, np.ones(len(na))])
    xb = np.column_stack([nb, np.ones(len(nb))])
    Ea = xa @ E.T
    Etb = xb @ E
    num = np.sum(xb * Ea, axis=1)
    den = np.sqrt(Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Etb[:, 0] ** 2 + Etb[:, 1] ** 2) + 1e-300
    return num / den


def _nanmedian3(D: np.ndarray) -> np.ndarray:
    """3 x 3 median ignoring NaN (NaN where the centre is NaN or fewer than 5 valid)."""
    p = np.pad(D, 1, constant_values=np.nan)
    h, w = D.shape
    stack = np.stack([p[i : i + h, j : j + w] for i in range(3) for j in range(3)])
    n = np.isfinite(stack).sum(axis=0)
    m = nanmedian_last(np.moveaxis(stack, 0, -1))
    m[(n < 5) | ~np.isfinite(D)] = np.nan
    return m


def _cell_area(g: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(N,) road area of each tracked pixel's grid cell (m²) from its neighbours' grid xy."""
    G = g.reshape(shape[0], shape[1], 2)
    du = np.gradient(G, axis=1)
    dv = np.gradient(G, axis=0)
    a = np.abs(du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0])
    return a.ravel()


class DenseContext:
    """What the dense measurement needs from the run: the pairs, each ok pair's sparse points in
    the grid frame with their road flags, and the images (read on demand, a few kept)."""

    def __init__(
        self,
        drive: Any,
        pairs: list[Any],
        pair_grid: list[tuple[int, np.ndarray, np.ndarray]],
        sparse_noise_m: float,
        workers: int = 1,
    ) -> None:
        self.camera: Camera = drive.camera
        self.pairs = pairs
        self.pair_grid = pair_grid  # (pair index, grid xy (N, 2), road (N,) bool)
        # σ of the pairs' sparse road points (median over the run): dense tracks much noisier
        # than the sparse matches of the same images have failed (wrong LK minima).
        self.sparse_noise_m = sparse_noise_m
        self.workers = max(1, int(workers))  # threads over the pairs that see one defect
        # bounded memory: a defect is seen by a few pairs, a neighbour shares their frames
        self._frames = GrayFrames(drive.frames, 9, "detection: dense measurement skips a frame")

    def gray(self, filename: str) -> np.ndarray | None:
        """The frame's grey image, or None when it is not in the drive or cannot be read."""
        return self._frames.get(filename)


def measure_defect_dense(
    poly: Any, ctx: DenseContext, cfg: Any, rim_floor_m: float, max_depth_m: float = 0.25
) -> DenseMeasure | None:
    """Dense measurement of the defect inside ``poly`` from every pair whose sparse points
    reach it (``measure_dense`` per pair, ``combine_dense`` over them); None when no pair gives
    a dense reading. The caller checks ``coverage`` (a partial reading may miss the bottom)."""
    from shapely import contains_xy

    x0, y0, x1, y1 = poly.bounds
    seeing = []
    for k, xy, road in ctx.pair_grid:
        near = (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)
        if near.sum() >= 3 and contains_xy(poly, xy[near, 0], xy[near, 1]).any():
            seeing.append((k, xy, road))

    def one(item: tuple[int, np.ndarray, np.ndarray]) -> PairDense | None:
        k, xy, road = item
        p = ctx.pairs[k]
        ga, gb = ctx.gray(p.frame_a), ctx.gray(p.frame_b)
        if ga is None or gb is None:
            return None
        # Level on the dense ring and the pair's sparse road points: a pair seeing part of a
        # large defect sees part of its ring only, the sparse road spans its whole overlap.
        pair_road = np.asarray(p.points_cam_a_m, float)[road]
        m = measure_dense(
            poly, ga, gb, p, xy, road, ctx.camera,
            ring_m=cfg.ring_m, edge_m=cfg.edge_m, step_px=cfg.step_px, window_px=cfg.window_px,
            road_cam_m=pair_road, max_depth_m=max_depth_m, patch_window_m=cfg.patch_window_m,
        )  # fmt: skip
        if m is not None:
            log.debug(
                "detection: dense pair %s-%s: %d tracks, depth %.1f..%.1f mm, noise %.2f mm",
                p.frame_a, p.frame_b, len(m.depth_m), 1000 * m.depth_m.min(),
                1000 * m.depth_m.max(), 1000 * m.noise_m,
            )  # fmt: skip
        return m

    # Pairs are independent and LK releases the GIL; results come back in pair order.
    got = [
        m
        for m in ordered_map(one, seeing, min(ctx.workers, len(seeing)))
        if m is not None and m.noise_m <= cfg.max_noise_k * ctx.sparse_noise_m
    ]
    res = combine_dense(
        poly, got, edge_m=cfg.edge_m, rim_k=cfg.rim_noise_k, rim_floor_m=rim_floor_m,
        extrapolate=cfg.area_extrapolate,
    )  # fmt: skip
    return res
