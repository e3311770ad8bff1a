"""Feature tracks: the per-pair matches chained across consecutive frames (issue 30).

Frame k is image b of pair (k-1, k) and image a of pair (k, k+1). Both pairs matched the same
keypoints of frame k, undistorted the same way, so a keypoint matched in both pairs appears
with the same pixel position in ``px_b`` of the first and ``px_a`` of the second: chaining
them by position (within ``tol_px``) links the two matches into one track seen by three or more
frames. A link is kept only when both pairs put the point at the same place in the world (with
the given poses), else the whole track is dropped as inconsistent (a wrong match that passed one
pair's RANSAC). Each pair's points carry its own geometry's error (its rotation, scale and plane,
a rolling-shutter pair's row motion: 0.04-0.38° and up to 2 % on a 30 fps drive with a 20 ms
readout), the same for all its points and smooth across the road, so two correct pairs disagree
by an affine function of the position on the road (``link_residuals_m``); what is left is the
matches' own disagreement. Pixels are the pairs' undistorted ideal pixels (the camera's K
applies).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from roadsurf.core.fits import MAD_TO_SIGMA

if TYPE_CHECKING:
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)

# a pair's point further from the pair's road plane than this many robust σ (1.4826 MAD of the
# pair's plane distances, at least 1 mm) is not road: a pothole, crack or kerb point
ROAD_SIGMAS = 3.0
# a link's smooth disagreement is fitted where the two pairs share at least this many points (an
# affine map of the road plane has 3 coefficients per axis); fewer are compared as they are
MIN_LINK_FIT = 10
LINK_FIT_ROUNDS = 3  # refits without the points beyond the gate (mismatches do not steer it)


@dataclass
class Tracks:
    """Observations of road points across frames (frames by position in the drive's list)."""

    obs_frame: np.ndarray  # (M,) int frame position of each observation
    obs_track: np.ndarray  # (M,) int track of each observation
    obs_px: np.ndarray  # (M, 2) undistorted ideal pixels (px)
    point_w: np.ndarray  # (T, 3) world position of each track (mean of its pairs' points, m)
    length: np.ndarray  # (T,) frames that see the track
    n_inconsistent: int = 0  # tracks dropped because their pairs disagreed
    # (T,) bool: every pair that saw the track put it on its road plane (within ROAD_SIGMAS of
    # the pair's own relief scatter); None = all road. Defects and kerbs are not.
    road: np.ndarray | None = None
    # (M,) s: each observation's exposure time after its frame's (a rolling shutter's row time,
    # ``reconstruction.rolling_shutter.row_times_s``); None = a global shutter
    obs_time_s: np.ndarray | None = None

    @property
    def n_tracks(self) -> int:
        return int(len(self.point_w))

    def subset(self, keep: np.ndarray) -> Tracks:
        """The tracks where ``keep`` (T,) is True, renumbered 0..K-1."""
        keep = np.asarray(keep, bool)
        new_id = np.cumsum(keep) - 1
        o = keep[self.obs_track]
        return Tracks(
            self.obs_frame[o],
            new_id[self.obs_track[o]],
            self.obs_px[o],
            self.point_w[keep],
            self.length[keep],
            self.n_inconsistent,
            None if self.road is None else self.road[keep],
            None if self.obs_time_s is None else self.obs_time_s[o],
        )


def build_tracks(
    pairs: list[PairResult],
    pos_of: dict[int, int],
    world_from_cam: np.ndarray,
    *,
    tol_px: float = 0.05,
    tol_m: float = 0.02,
    sigma_trans_m: float = 0.0,
) -> Tracks:
    """Chain the ok consecutive pairs' matches into tracks.

    pos_of: Frame.index -> position in the drive's frame list; world_from_cam: (N, 4, 4) poses
    used to put each pair's points in the world (the pose graph's). tol_px: two pixel positions
    of one frame closer than this are the same keypoint (px); tol_m: a track two consecutive
    pairs of which put its point further apart than this, beyond the two pairs' smooth
    disagreement (``link_residuals_m``), is dropped (m). sigma_trans_m: a pair's stated σ of
    its metric translation (m; ``visual_sigma_trans_m``): the smooth disagreement is removed
    only up to ``LINK_GROSS_SIGMAS`` times the two pairs' relative σ (σ / baseline, in
    quadrature); beyond, the points are compared as they are (0: no bound)."""
    chain = sorted(
        (p for p in pairs if p.ok and p.index_a in pos_of and p.index_b in pos_of),
        key=lambda p: pos_of[p.index_a],
    )
    chain = [p for p in chain if pos_of[p.index_b] == pos_of[p.index_a] + 1 and p.n_points > 0]
    frames: list[np.ndarray] = []
    tracks: list[np.ndarray] = []
    pxs: list[np.ndarray] = []
    sum_w = np.zeros((0, 3))
    count = np.zeros(0, int)
    last_w = np.zeros((0, 3))  # the latest pair's point of each track (consistency check)
    bad = np.zeros(0, bool)
    road = np.zeros(0, bool)
    prev: tuple[int, np.ndarray, np.ndarray] | None = None  # (frame b, px_b, track ids)
    prev_rel = np.inf  # the previous pair's relative σ of its scale (σ / baseline)
    n_tracks = 0
    for p in chain:
        a, b = pos_of[p.index_a], pos_of[p.index_b]
        W = world_from_cam[a]
        pw = np.asarray(p.points_cam_a_m, float) @ W[:3, :3].T + W[:3, 3]
        m = len(pw)
        ids = np.full(m, -1, int)
        if prev is not None and prev[0] == a and len(prev[1]):
            d, j = cKDTree(prev[1]).query(np.asarray(p.px_a, float), distance_upper_bound=tol_px)
            hit = np.flatnonzero(np.isfinite(d))
            # one keypoint of frame a continues at most one track: the closest claim wins
            order = hit[np.argsort(d[hit], kind="stable")]
            _, first = np.unique(j[order], return_index=True)
            won = order[first]
            ids[won] = prev[2][j[won]]
        new = ids < 0
        k_new = int(new.sum())
        ids[new] = n_tracks + np.arange(k_new)
        n_tracks += k_new
        sum_w = np.concatenate([sum_w, np.zeros((k_new, 3))])
        count = np.concatenate([count, np.zeros(k_new, int)])
        last_w = np.concatenate([last_w, pw[new]])
        bad = np.concatenate([bad, np.zeros(k_new, bool)])
        road = np.concatenate([road, np.ones(k_new, bool)])
        pd = np.abs(np.asarray(p.plane_dist_m, float))
        if len(pd) == m and m:
            sig = max(MAD_TO_SIGMA * float(np.median(pd)), 1e-3)
            off = ids[pd > ROAD_SIGMAS * sig]
            road[off] = False
        old = ~new
        base = float(np.linalg.norm(np.asarray(p.t_b_from_a_m, float)))
        rel = sigma_trans_m / base if base > 0 and sigma_trans_m > 0 else np.inf
        g_max = LINK_GROSS_SIGMAS * float(np.hypot(prev_rel, rel))
        bad[ids[old]] |= link_residuals_m(pw[old], last_w[ids[old]], tol_m, g_max) > tol_m
        prev_rel = rel
        last_w[ids[old]] = pw[old]
        np.add.at(sum_w, ids, pw)
        np.add.at(count, ids, 1)
        # observations: image a only for new tracks (a continued track has it already)
        frames += [np.full(k_new, a), np.full(m, b)]
        tracks += [ids[new], ids]
        pxs += [np.asarray(p.px_a, float)[new], np.asarray(p.px_b, float)]
        prev = (b, np.asarray(p.px_b, float), ids)
    if n_tracks == 0:
        z = np.zeros(0, int)
        return Tracks(z, z, np.zeros((0, 2)), np.zeros((0, 3)), z)
    obs_frame = np.concatenate(frames)
    obs_track = np.concatenate(tracks)
    length = np.bincount(obs_track, minlength=n_tracks)
    out = Tracks(
        obs_frame, obs_track, np.concatenate(pxs), sum_w / count[:, None], length, road=road
    )
    if bad.any():
        out = out.subset(~bad)
        out.n_inconsistent = int(bad.sum())
        log.info("tracks: dropped %d inconsistent track(s)", out.n_inconsistent)
    return out


# a smooth disagreement between two pairs beyond this many σ of their stated relative metric
# uncertainty is a gross inconsistency, not one geometry's small error (measured, with the
# default 3 mm: simulated drives, rolling shutter and tilted included, at most 4.5 σ; the real
# spd2 photo series 4-20 σ, median 9, where linking moved its first stretch's masks ~40 px)
LINK_GROSS_SIGMAS = 5.0


def link_residuals_m(
    pw_b: np.ndarray, pw_a: np.ndarray, tol_m: float, max_gradient: float = np.inf
) -> np.ndarray:
    """(K,) m: how far two consecutive pairs disagree on each of K shared points beyond their
    geometries' smooth disagreement.

    pw_a: (K, 3) the earlier pair's points and pw_b: (K, 3) the later pair's, in the world (m).
    A pair's rotation, scale or plane error moves its road points by a linear function of their
    position, i.e. an affine function of the position on the road plane: the difference pw_b -
    pw_a is fitted by one (least squares on the points' two in-plane coordinates, refitted
    without the points beyond ``tol_m`` m) and the residual's length returned. Fewer than
    ``MIN_LINK_FIT`` points, or a fitted gradient (the linear part's largest singular value,
    m per m: the two pairs' relative scale and rotation error) above ``max_gradient``: the
    difference's length (pairs that disagree that much are not one geometry's small error)."""
    d = pw_b - pw_a
    if len(d) < MIN_LINK_FIT:
        return np.linalg.norm(d, axis=1)
    c = pw_a - pw_a.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    q = c @ vt[:2].T  # (K, 2) in-plane coordinates (m)
    A = np.column_stack([np.ones(len(q)), q])
    keep = np.ones(len(q), bool)
    r = np.linalg.norm(d, axis=1)
    for _ in range(LINK_FIT_ROUNDS):
        coef, *_ = np.linalg.lstsq(A[keep], d[keep], rcond=None)
        r = np.linalg.norm(d - A @ coef, axis=1)
        nxt = r <= tol_m
        if nxt.sum() < MIN_LINK_FIT or np.array_equal(nxt, keep):
            break
        keep = nxt
    if np.linalg.svd(coef[1:], compute_uv=False)[0] > max_gradient:
        return np.linalg.norm(d, axis=1)
    return r


def thin_tracks(
    tracks: Tracks, max_two_view_per_frame: int, image_size: tuple[int, int], seed: int = 0
) -> Tracks:
    """Keep every track seen by three or more frames and at most ``max_two_view_per_frame``
    two-view tracks per frame, spread over the image (one per grid cell, then at random):
    a pair's hundreds of two-view matches add little beyond its first hundred but cost time."""
    if max_two_view_per_frame <= 0:
        return tracks.subset(tracks.length >= 3)
    keep = tracks.length >= 3
    two = np.flatnonzero(tracks.length == 2)
    if len(two) == 0:
        return tracks
    # first observation of each two-view track: its frame and pixel
    first = np.full(tracks.n_tracks, -1, int)
    order = np.argsort(tracks.obs_track, kind="stable")
    t_sorted = tracks.obs_track[order]
    starts = order[np.r_[0, np.flatnonzero(np.diff(t_sorted)) + 1]]
    first[tracks.obs_track[starts]] = starts
    rng = np.random.default_rng(seed)
    w, h = image_size
    g = max(1, int(np.sqrt(max_two_view_per_frame)))
    fr = tracks.obs_frame[first[two]]
    px = tracks.obs_px[first[two]]
    cell = (np.clip(px[:, 0] / w * g, 0, g - 1).astype(int) * g) + np.clip(
        px[:, 1] / h * g, 0, g - 1
    ).astype(int)
    # random order, then by (frame, cell): the first of each (frame, cell) is spread evenly
    perm = rng.permutation(len(two))
    key = fr[perm] * (g * g) + cell[perm]
    o = perm[np.argsort(key, kind="stable")]
    key_o = fr[o] * (g * g) + cell[o]
    is_first = np.r_[True, key_o[1:] != key_o[:-1]]
    ranked = np.concatenate([o[is_first], o[~is_first]])  # spread ones first, then the rest
    taken = np.zeros(int(fr.max()) + 1 if len(fr) else 0, int)
    for i in ranked:
        if taken[fr[i]] < max_two_view_per_frame:
            taken[fr[i]] += 1
            keep[two[i]] = True
    return tracks.subset(keep)


def triangulate_w(
    obs_p: np.ndarray,
    obs_px: np.ndarray,
    R_world_from_cam: np.ndarray,
    C_world_m: np.ndarray,
    K: np.ndarray,
    n_points: int,
    *,
    steps: int = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """Points (P, 3) in the world from their observations, and a (P,) bool: well posed.

    obs_p: (M,) point of each observation; obs_px: (M, 2) ideal pixels; R_world_from_cam:
    (M, 3, 3) and C_world_m: (M, 3) the observing camera's rotation and centre (m); K: (3, 3).
    The rays' least-squares meeting point (midpoint), then ``steps`` Gauss-Newton steps on the
    reprojection error alone (no prior): the bundle adjustment's points must start where the
    current poses see them, not where another pose estimate put them."""
    Kinv = np.linalg.inv(K)
    ray_c = np.column_stack([obs_px, np.ones(len(obs_px))]) @ Kinv.T
    d = np.einsum("mij,mj->mi", R_world_from_cam, ray_c)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    A_o = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # (M, 3, 3) projector off the ray
    A = np.zeros((n_points, 3, 3))
    b = np.zeros((n_points, 3))
    np.add.at(A, obs_p, A_o)
    np.add.at(b, obs_p, np.einsum("mij,mj->mi", A_o, C_world_m))
    # well posed: the smallest eigenvalue of Σ(I - d dᵀ) is the rays' spread (sin² of parallax)
    ok = np.linalg.eigvalsh(A)[:, 0] > 1e-6
    A[~ok] += np.eye(3)
    X = np.linalg.solve(A, b[..., None])[..., 0]
    fx, fy = K[0, 0], K[1, 1]
    for _ in range(steps):
        v = X[obs_p] - C_world_m
        Xc = np.einsum("mji,mj->mi", R_world_from_cam, v)
        z = np.maximum(Xc[:, 2], 1e-6)
        r = np.column_stack(
            [fx * Xc[:, 0] / z + K[0, 2] - obs_px[:, 0], fy * Xc[:, 1] / z + K[1, 2] - obs_px[:, 1]]
        )
        zero = np.zeros(len(z))
        Jc = np.stack(
            [
                np.column_stack([fx / z, zero, -fx * Xc[:, 0] / z**2]),
                np.column_stack([zero, fy / z, -fy * Xc[:, 1] / z**2]),
            ],
            axis=1,
        )  # (M, 2, 3) d(pixel)/d(Xc)
        J = np.einsum("mki,mji->mkj", Jc, R_world_from_cam)  # d(pixel)/d(X world)
        H = np.zeros((n_points, 3, 3))
        g = np.zeros((n_points, 3))
        np.add.at(H, obs_p, np.einsum("mki,mkj->mij", J, J))
        np.add.at(g, obs_p, np.einsum("mki,mk->mi", J, r))
        H[~ok] += np.eye(3)
        H += 1e-9 * np.eye(3)
        X = X - np.linalg.solve(H, g[..., None])[..., 0]
    return X, ok


def initial_planes(
    R: np.ndarray,
    C: np.ndarray,
    X: np.ndarray,
    obs_f: np.ndarray,
    obs_p: np.ndarray,
    nominal: np.ndarray,
) -> np.ndarray:
    """Each frame's road plane Z = p0 X + p1 Y + p2 fitted to its points in its camera (one
    trimmed refit: potholes are not road); the mount's nominal plane when too few points."""
    out = np.tile(nominal, (len(R), 1))
    for f in range(len(R)):
        sel = obs_p[obs_f == f]
        if len(sel) < 10:
            continue
        Xc = (X[sel] - C[f]) @ R[f]
        A = np.column_stack([Xc[:, 0], Xc[:, 1], np.ones(len(Xc))])
        p, *_ = np.linalg.lstsq(A, Xc[:, 2], rcond=None)
        d = np.abs(A @ p - Xc[:, 2])
        keep = d <= max(3.0 * np.median(d), 1e-4)
        if keep.sum() >= 10:
            p, *_ = np.linalg.lstsq(A[keep], Xc[keep, 2], rcond=None)
        out[f] = p
    return out
