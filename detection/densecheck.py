"""Checks of one pair's dense tracks on its tracking grid (see ``densepair``): a track must agree
with its neighbours (``consistent``) and must not be part of an island or a narrow patch far
deeper than the road around it (``no_deep_patch``): tracks that slid together agree with each
other, not with the surface."""

from __future__ import annotations

import cv2
import numpy as np

from roadsurf.detection.planefit import nanmedian_last


def consistent(
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


def no_deep_patch(
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


def cell_area(g: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(N,) road area of each tracked pixel's grid cell (m²) from its neighbours' grid xy."""
    G = g.reshape(shape[0], shape[1], 2)
    du = np.gradient(G, axis=1)
    dv = np.gradient(G, axis=0)
    a = np.abs(du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0])
    return a.ravel()
