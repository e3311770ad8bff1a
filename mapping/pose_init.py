"""Initial guess of every frame pose and the segments of the drive.

Each visual component (frames chained by ok pairs) is placed on GPS by a robust 2D rigid fit,
or on the GPS track when vision broke, or by a constant-velocity guess from a placed
neighbour. A gap between components is bridged when GPS ties both sides; otherwise it starts a
new segment.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from roadsurf.core.fits import fit_rigid_2d
from roadsurf.core.geometry import forward_in_cam, invert_pose, world_from_cam
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.pose_gps import GpsFixes, gps_at, gps_margin_s, gps_track_yaw, interp_weights
from roadsurf.mapping.types import PoseReport

if TYPE_CHECKING:
    from roadsurf.reconstruction.types import PairResult


def chain(
    comp_frames: np.ndarray,
    consecutive: dict[tuple[int, int], PairResult],
    R_vehicle_from_cam: np.ndarray | None = None,
) -> np.ndarray:
    """Chain the pair transforms over one component: (M, 4, 4) poses, the first one that of a
    level vehicle at heading 0 carrying the camera on its mount (R_vehicle_from_cam (3, 3);
    None = nadir)."""
    W = np.empty((len(comp_frames), 4, 4))
    W[0] = world_from_cam(0.0)
    if R_vehicle_from_cam is not None:
        W[0, :3, :3] = W[0, :3, :3] @ R_vehicle_from_cam
    for j in range(1, len(comp_frames)):
        a, b = comp_frames[j - 1], comp_frames[j]
        W[j] = W[j - 1] @ invert_pose(consecutive[(a, b)].cam_b_from_cam_a)
    return W


def _yaw_matrix(yaw_rad: float) -> np.ndarray:
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def _robust_rigid_2d(
    src: np.ndarray, dst: np.ndarray, sigma: np.ndarray, cfg: MappingConfig
) -> tuple[float, np.ndarray]:
    """RANSAC over pairs of fixes, then a weighted fit on the inliers (GPS outliers/jumps)."""
    m = len(src)
    thr = np.maximum(3.0 * sigma, 0.05)
    rng = np.random.default_rng(0)
    cand = [(i, j) for i in range(m) for j in range(i + 1, m)]
    if len(cand) > 300:
        cand = [tuple(rng.choice(m, 2, replace=False)) for _ in range(300)]
    best, best_inl = None, None
    for i, j in cand:
        ds, dd = src[j] - src[i], dst[j] - dst[i]
        if np.linalg.norm(ds) < cfg.heading_min_baseline_m:
            continue
        yaw = math.atan2(dd[1], dd[0]) - math.atan2(ds[1], ds[0])
        R2 = _yaw_matrix(yaw)[:2, :2]
        tr = 0.5 * (dst[i] + dst[j]) - R2 @ (0.5 * (src[i] + src[j]))
        r = np.linalg.norm(src @ R2.T + tr - dst, axis=1)
        inl = r <= thr
        score = (inl.sum(), -np.sum(np.minimum(r / thr, 1.0)))
        if best is None or score > best:
            best, best_inl = score, inl
    inl = best_inl if best_inl is not None and best_inl.sum() >= 2 else np.ones(m, bool)
    fit = fit_rigid_2d(src[inl], dst[inl], 1.0 / sigma[inl] ** 2)
    return fit.yaw_rad, fit.t


def initial_poses(
    cfg: MappingConfig,
    t: np.ndarray,
    comp: np.ndarray,
    consecutive: dict[tuple[int, int], PairResult],
    gps: GpsFixes | None,
    rep: PoseReport,
    R_vehicle_from_cam: np.ndarray | None = None,
) -> np.ndarray:
    """Chain each visual component, then place it on GPS (robust 2D rigid fit) or, without
    enough GPS, by a constant-velocity guess from its placed neighbour. R_vehicle_from_cam
    (3, 3) is the camera's mount (None = nadir)."""
    n = len(t)
    W = np.zeros((n, 4, 4))
    n_comp = int(comp.max()) + 1
    R_vc = np.eye(3) if R_vehicle_from_cam is None else np.asarray(R_vehicle_from_cam, float)
    fwd_cam = forward_in_cam(R_vc)
    chains = [chain(np.flatnonzero(comp == c), consecutive, R_vc) for c in range(n_comp)]
    placed = np.zeros(n_comp, bool)

    for c in range(n_comp):
        fr = np.flatnonzero(comp == c)
        C = chains[c]
        if gps is None:
            continue
        dt = float(np.median(np.diff(t))) if n > 1 else 1.0
        # the drive's end components also take the fixes just outside the frames
        lo = gps_margin_s(cfg, t) if fr[0] == 0 else 0.5 * dt
        hi = gps_margin_s(cfg, t) if fr[-1] == n - 1 else 0.5 * dt
        sel = (gps.t_s >= t[fr[0]] - lo) & (gps.t_s <= t[fr[-1]] + hi)
        if not sel.any():
            continue
        g_en = gps.enu_m[sel]
        if len(fr) > 1:
            k, w = interp_weights(t[fr], gps.t_s[sel])
            cp = (1 - w)[:, None] * C[k, :3, 3] + w[:, None] * C[k + 1, :3, 3]
        else:
            cp = np.repeat(C[:1, :3, 3], sel.sum(), axis=0)
        spread = np.ptp(cp[:, :2], axis=0).max() if len(cp) > 1 else 0.0
        if len(cp) >= 2 and spread >= cfg.heading_min_baseline_m:
            yaw, tr = _robust_rigid_2d(cp[:, :2], g_en[:, :2], gps.sigma_m[sel], cfg)
            T = _yaw_matrix(yaw)
            T[:2, 3] = tr
        else:
            # one fix (or no spread): heading from the GPS track around it (eq. 6.1)
            tc = float(np.mean(gps.t_s[sel]))
            yaw = gps_track_yaw(gps, tc, cfg.heading_min_baseline_m)
            if yaw is None:
                continue
            chain_heading = _heading_rad(C[len(C) // 2], fwd_cam)
            T = _yaw_matrix(yaw - chain_heading)
            if len(fr) == 1:
                # a lone frame: the GPS track at its own time (the fix is up to half a frame
                # interval away, i.e. centimetres at speed)
                T[:2, 3] = gps_at(gps, float(t[fr[0]]))[:2] - T[:2, :2] @ C[0, :2, 3]
            else:
                T[:2, 3] = g_en[:, :2].mean(0) - (T[:2, :2] @ cp[:, :2].T).T.mean(0)
        T[2, 3] = (
            float(np.mean(g_en[gps.has_alt[sel], 2] - cp[gps.has_alt[sel], 2]))
            if gps.has_alt[sel].any()
            else 0.0
        )
        W[fr] = T @ C
        placed[c] = True

    if gps is not None and len(gps.t_s) >= 2:
        # vision broke and no fix falls inside: place on the GPS track interpolated at the
        # frame times (a fallback guess only; the pose graph then weighs it weakly)
        for c in np.flatnonzero(~placed):
            fr = np.flatnonzero(comp == c)
            tc = float(np.mean(t[fr]))
            yaw = gps_track_yaw(gps, tc, cfg.heading_min_baseline_m)
            if yaw is None:
                continue
            C = chains[c]
            T = _yaw_matrix(yaw - _heading_rad(C[len(C) // 2], fwd_cam))
            pos = gps_at(gps, tc)
            mid = np.mean(C[:, :3, 3], axis=0)
            T[:3, 3] = pos - T[:3, :3] @ mid
            if not gps.has_alt.any():
                T[2, 3] = 0.0
            W[fr] = T @ C
            placed[c] = True
    if not placed.any():
        # no GPS anywhere usable: local frame anchored at the first component
        W[comp == 0] = chains[0]
        placed[0] = True
    # constant-velocity guesses for unplaced components, forwards then backwards
    for c in range(1, n_comp):
        if not placed[c] and placed[c - 1]:
            _place_after(W, t, comp, c, chains[c], consecutive)
            placed[c] = True
    for c in range(n_comp - 2, -1, -1):
        if not placed[c] and placed[c + 1]:
            _place_before(W, t, comp, c, chains[c], consecutive)
            placed[c] = True
    return W


def _heading_rad(T: np.ndarray, fwd_cam: np.ndarray) -> float:
    """Yaw (counter-clockwise from east, radians) of the vehicle's forward direction, given
    forward (3,) in camera coordinates (core.geometry.forward_in_cam)."""
    fwd = T[:3, :3] @ fwd_cam
    return math.atan2(fwd[1], fwd[0])


def _step_motion(
    t: np.ndarray, i: int, consecutive: dict[tuple[int, int], PairResult]
) -> np.ndarray:
    """Constant-velocity guess of cam_{i+1}_from_cam_i from the nearest ok pair (time-scaled)."""
    best = None
    for (a, b), p in consecutive.items():
        d = min(abs(a - i), abs(b - (i + 1)))
        if best is None or d < best[0]:
            best = (d, a, b, p)
    if best is None:
        return np.eye(4)
    _, a, b, p = best
    T = p.cam_b_from_cam_a.copy()
    ratio = (t[i + 1] - t[i]) / max(t[b] - t[a], 1e-9)
    rv = Rotation.from_matrix(T[:3, :3]).as_rotvec() * ratio
    T[:3, :3] = Rotation.from_rotvec(rv).as_matrix()
    T[:3, 3] *= ratio
    return T


def _place_after(
    W: np.ndarray,
    t: np.ndarray,
    comp: np.ndarray,
    c: int,
    C: np.ndarray,
    consecutive: dict[tuple[int, int], PairResult],
) -> None:
    fr = np.flatnonzero(comp == c)
    prev = fr[0] - 1
    first = W[prev] @ invert_pose(_step_motion(t, prev, consecutive))
    W[fr] = first @ invert_pose(C[0]) @ C


def _place_before(
    W: np.ndarray,
    t: np.ndarray,
    comp: np.ndarray,
    c: int,
    C: np.ndarray,
    consecutive: dict[tuple[int, int], PairResult],
) -> None:
    fr = np.flatnonzero(comp == c)
    nxt = fr[-1] + 1
    last = W[nxt] @ _step_motion(t, fr[-1], consecutive)
    W[fr] = last @ invert_pose(C[-1]) @ C


def segments(
    t: np.ndarray, comp: np.ndarray, gps: GpsFixes | None, bridge_s: float
) -> tuple[np.ndarray, list[int]]:
    """Segment id per frame: a gap between components is bridged when GPS ties both sides (a
    fix inside the gap, fixes within both neighbouring components, or fixes within
    ``bridge_s`` before and after the gap)."""
    n = len(t)
    seg = np.zeros(n, int)
    bridged: list[int] = []
    n_comp = int(comp.max()) + 1
    if n_comp == 1:
        return seg, bridged
    has_fix = np.zeros(n_comp, bool)
    if gps is not None:
        dt = float(np.median(np.diff(t)))
        for c in range(n_comp):
            fr = np.flatnonzero(comp == c)
            has_fix[c] = bool(
                np.any((gps.t_s >= t[fr[0]] - 0.5 * dt) & (gps.t_s <= t[fr[-1]] + 0.5 * dt))
            )
    s = 0
    for i in range(1, n):
        if comp[i] != comp[i - 1]:
            inside = gps is not None and bool(np.any((gps.t_s > t[i - 1]) & (gps.t_s < t[i])))
            # GPS close on both sides (near the drive's ends one side is enough: those few
            # frames are extrapolated from a GPS-tied neighbour)
            near = gps is not None and bool(
                (
                    np.any((gps.t_s <= t[i - 1]) & (gps.t_s >= t[i - 1] - bridge_s))
                    or t[i - 1] - t[0] <= bridge_s
                )
                and (
                    np.any((gps.t_s >= t[i]) & (gps.t_s <= t[i] + bridge_s))
                    or t[-1] - t[i] <= bridge_s
                )
                and np.any(np.abs(gps.t_s - t[i]) <= bridge_s)
            )
            if inside or near or (has_fix[comp[i - 1]] and has_fix[comp[i]]):
                bridged.append(i)
            else:
                s += 1
        seg[i] = s
    return seg, bridged
