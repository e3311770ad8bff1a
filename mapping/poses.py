"""Pose of every frame: GPS + feature-chained stitching fused in one robust pose graph.

Dissertation Chapter 6 places frames between GPS fixes by chaining the pairwise transforms and
takes the heading from successive fixes (eq. 6.1, θ_k = arctan(−(x_k − x_{k−1})/(y_k − y_{k−1}))).
Here both sources go into one sparse robust least-squares problem over all frame poses
(world_from_cam in the local ENU frame):

- relative constraints from every ok pair's metric transform (cam_b_from_cam_a);
- absolute GPS constraints, each fix used as a measurement at its own timestamp: the predicted
  camera centre at the fix time is interpolated between the two frames around it, so no frame
  pose is ever interpolated from GPS;
- eq. 6.1 headings between successive fixes (weighted by the fix baseline);
- OBD speed (optional), a weak road-normal (tilt) prior, and a weak constant-velocity guess
  across failed pairs so the problem stays well posed;
- a robust loss, then a robust re-weighting (MAD of normalised residuals) and rejection of
  GPS fixes that disagree with the fused solution by more than ``gps_outlier_sigmas``.

Works through GPS gaps (vision carries), failed pairs (GPS bridges; if neither, a new segment
with a warning), and with no GPS at all (local frame, reference None, warning).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial.transform import Rotation

from roadsurf.core.atomic import read_json, write_json_atomic
from roadsurf.core.config import to_dict
from roadsurf.core.geometry import (
    EnuReference,
    enu_from_lla,
    heading_deg_from_displacement,
    invert_pose,
    world_from_cam,
)
from roadsurf.io.drive import Drive
from roadsurf.mapping.config import NOT_IN_FINGERPRINT, MappingConfig
from roadsurf.mapping.types import Trajectory, load_trajectory, save_trajectory

log = logging.getLogger(__name__)

POSES_REPORT = "poses_report.json"


@dataclass
class PoseReport:
    """What the pose fusion used, rejected and warned about (goes to report.json)."""

    n_frames: int = 0
    n_gps_fixes: int = 0
    n_gps_used: int = 0
    gps_outliers: list[dict[str, Any]] = field(default_factory=list)
    n_pairs_ok: int = 0
    n_pairs_failed: int = 0
    n_segments: int = 1
    gps_sigma_scale: float = 1.0
    visual_sigma_scale: float = 1.0
    cost_initial: float = float("nan")
    cost_final: float = float("nan")
    n_iterations: int = 0
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


# =========================================================================== entry point


def run(
    cfg: MappingConfig,
    drive: Drive,
    pairs: list[Any],
    run_dir: str | Path,
) -> Trajectory:
    """Fuse GPS and pairs into the trajectory; writes RUN/poses.npz, reference.json,
    trajectory.geojson and poses_report.json. Resumes when the inputs did not change."""
    from roadsurf.mapping.export import write_trajectory_csv, write_trajectory_geojson

    run_dir = Path(run_dir)
    key = _fingerprint(cfg, drive, pairs)
    rep_path = run_dir / POSES_REPORT
    if not cfg.overwrite and (run_dir / "poses.npz").is_file() and rep_path.is_file():
        try:
            if read_json(rep_path).get("fingerprint") == key:
                log.info("poses: inputs unchanged, reusing %s", run_dir / "poses.npz")
                traj = load_trajectory(run_dir)
                if not (run_dir / "trajectory.geojson").is_file():
                    write_trajectory_geojson(run_dir / "trajectory.geojson", traj, drive)
                return traj
        except (OSError, ValueError, KeyError) as e:
            log.info("poses: cached result unreadable (%s); recomputing", e)
    t0 = time.perf_counter()
    traj, report = estimate_trajectory(cfg, drive, pairs)
    save_trajectory(run_dir, traj)
    write_trajectory_geojson(run_dir / "trajectory.geojson", traj, drive)
    write_trajectory_csv(run_dir / "trajectory.csv", traj)
    elapsed = round(time.perf_counter() - t0, 3)  # kept for resumed runs' report.json
    write_json_atomic(rep_path, {"fingerprint": key, "elapsed_s": elapsed, **report.to_dict()})
    return traj


def _fingerprint(cfg: MappingConfig, drive: Drive, pairs: list[Any]) -> str:
    h = hashlib.sha256()
    c = {k: v for k, v in to_dict(cfg).items() if k not in NOT_IN_FINGERPRINT}
    h.update(json.dumps(c, sort_keys=True, default=str).encode())
    h.update(json.dumps([(f.filename, f.timestamp_s) for f in drive.frames]).encode())
    if drive.gps is not None:
        for a in (drive.gps.timestamp_s, drive.gps.lat_deg, drive.gps.lon_deg, drive.gps.hdop):
            h.update(np.ascontiguousarray(a, dtype=float).tobytes())
    for p in pairs:
        h.update(f"{p.index_a},{p.index_b},{p.status}".encode())
        h.update(np.ascontiguousarray(p.cam_b_from_cam_a, dtype=float).tobytes())
    return h.hexdigest()[:16]


# =========================================================================== estimation


@dataclass
class _Gps:
    t_s: np.ndarray  # (G,)
    enu_m: np.ndarray  # (G, 3)
    sigma_m: np.ndarray  # (G,) horizontal σ
    has_alt: np.ndarray  # (G,) bool
    orig_index: np.ndarray  # (G,) index into drive.gps


def estimate_trajectory(
    cfg: MappingConfig, drive: Drive, pairs: list[Any]
) -> tuple[Trajectory, PoseReport]:
    """Pure computation (no files): fused Trajectory and a PoseReport."""
    frames = drive.frames
    n = len(frames)
    rep = PoseReport(n_frames=n)
    if n == 0:
        raise ValueError("roadsurf.mapping.poses: the drive has no valid frame to place")
    t = np.array([f.timestamp_s for f in frames], float)
    pos_of = {f.index: i for i, f in enumerate(frames)}
    ok_pairs = [p for p in pairs if p.ok and p.index_a in pos_of and p.index_b in pos_of]
    rep.n_pairs_ok = len(ok_pairs)
    rep.n_pairs_failed = sum(1 for p in pairs if not p.ok)
    consecutive = {(pos_of[p.index_a], pos_of[p.index_b]): p for p in ok_pairs}

    # ---------------------------------------------------------------- GPS in ENU
    ref, gps = _gps_enu(cfg, drive, t, rep)

    # ---------------------------------------------------------------- visual components
    comp = np.zeros(n, int)
    for i in range(1, n):
        comp[i] = comp[i - 1] + (0 if (i - 1, i) in consecutive else 1)
    init = _initial_poses(cfg, t, comp, consecutive, gps, rep)

    # ---------------------------------------------------------------- segments
    segment, bridged_gaps = _segments(t, comp, gps, cfg.gps_bridge_s)
    rep.n_segments = int(segment.max()) + 1
    if rep.n_segments > 1:
        msg = (
            f"{rep.n_segments - 1} break(s) where neither a matched pair nor GPS ties consecutive "
            "frames; segments are placed by a constant-velocity guess"
        )
        log.warning("poses: %s", msg)
        rep.warnings.append(msg)

    # ---------------------------------------------------------------- robust fusion
    problem = _PoseGraph(cfg, t, init, ok_pairs, pos_of, gps, drive, comp)
    world = problem.solve(rep)

    # ---------------------------------------------------------------- sources
    has_visual = np.zeros(n, bool)
    for a, b in consecutive:
        has_visual[a] = has_visual[b] = True
    gps_comp = set()
    if gps is not None:
        for g_t in gps.t_s[problem.gps_used]:
            k = int(np.clip(np.searchsorted(t, g_t), 0, n - 1))
            gps_comp.add(comp[k])
            if k > 0:
                gps_comp.add(comp[k - 1])
    source = []
    for i in range(n):
        tied = comp[i] in gps_comp
        if has_visual[i]:
            source.append("fused" if tied else "visual")
        else:
            source.append("gps" if gps is not None else "visual")
    traj = Trajectory(
        filenames=[f.filename for f in frames],
        frame_indices=np.array([f.index for f in frames], np.int64),
        timestamp_s=t,
        world_from_cam=world,
        source=source,
        reference=ref,
        segment=segment,
    )
    del bridged_gaps
    return traj, rep


def _gps_enu(
    cfg: MappingConfig, drive: Drive, t: np.ndarray, rep: PoseReport
) -> tuple[EnuReference | None, _Gps | None]:
    g = drive.gps
    if g is None or len(g) == 0:
        msg = "no GPS: the map is in a local frame (no reference, no lat/lon or UTM exports)"
        log.warning("poses: %s", msg)
        rep.warnings.append(msg)
        return None, None
    rep.n_gps_fixes = len(g)
    alt = np.asarray(g.alt_m, float)
    has_alt = np.isfinite(alt)
    alt0 = float(alt[has_alt][0]) if has_alt.any() else 0.0
    ref = EnuReference(float(g.lat_deg[0]), float(g.lon_deg[0]), alt0)
    enu = enu_from_lla(g.lat_deg, g.lon_deg, np.where(has_alt, alt, alt0), ref)
    hdop = np.asarray(g.hdop, float)
    sigma = np.where(np.isfinite(hdop), hdop * cfg.gps_sigma_per_hdop_m, cfg.gps_sigma_m)
    sigma = np.maximum(sigma, cfg.gps_sigma_min_m)
    # fixes usable as measurements: inside the frame time span, or close enough to its ends
    # for the end frames' constant-velocity extrapolation (σ inflated by the acceleration)
    margin = _gps_margin_s(cfg, t)
    ts = np.asarray(g.timestamp_s, float)
    keep = (ts >= t[0] - margin) & (ts <= t[-1] + margin)
    outside_s = np.maximum(np.maximum(t[0] - ts, ts - t[-1]), 0.0)
    sigma = np.hypot(sigma, 0.5 * cfg.gap_accel_sigma_mps2 * outside_s**2)
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        msg = "GPS does not overlap the frame times: local frame only"
        log.warning("poses: %s", msg)
        rep.warnings.append(msg)
        return None, None
    gps = _Gps(
        t_s=np.asarray(g.timestamp_s, float)[idx],
        enu_m=enu[idx],
        sigma_m=sigma[idx],
        has_alt=has_alt[idx] & cfg.use_gps_altitude,
        orig_index=idx,
    )
    return ref, gps


def _gps_margin_s(cfg: MappingConfig, t: np.ndarray) -> float:
    """How far (s) before the first frame / after the last a GPS fix is still used."""
    dt_frame = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    return max(0.5 * dt_frame, float(cfg.gps_extrapolate_s))


def _interp_weights(t: np.ndarray, tq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For query times tq: index k of the frame before (k+1 after) and weight w of frame k+1."""
    n = len(t)
    if n == 1:
        return np.zeros(len(tq), int), np.zeros(len(tq))
    k = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, n - 2)
    w = (tq - t[k]) / np.maximum(t[k + 1] - t[k], 1e-9)
    return k, w


def _chain(comp_frames: np.ndarray, consecutive: dict[tuple[int, int], Any]) -> np.ndarray:
    """Chain the pair transforms over one component: (M, 4, 4) poses, first = level, heading 0."""
    W = np.empty((len(comp_frames), 4, 4))
    W[0] = world_from_cam(0.0)
    for j in range(1, len(comp_frames)):
        a, b = comp_frames[j - 1], comp_frames[j]
        W[j] = W[j - 1] @ invert_pose(consecutive[(a, b)].cam_b_from_cam_a)
    return W


def _yaw_matrix(yaw_rad: float) -> np.ndarray:
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def _rigid_2d(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[float, np.ndarray]:
    """Weighted 2D rigid fit dst ≈ R(yaw) src + t; returns (yaw_rad, t (2,))."""
    w = w / w.sum()
    ms, md = w @ src, w @ dst
    S = ((src - ms) * w[:, None]).T @ (dst - md)
    yaw = math.atan2(S[0, 1] - S[1, 0], S[0, 0] + S[1, 1])
    R = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    return yaw, md - R @ ms


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
    return _rigid_2d(src[inl], dst[inl], 1.0 / sigma[inl] ** 2)


def _initial_poses(
    cfg: MappingConfig,
    t: np.ndarray,
    comp: np.ndarray,
    consecutive: dict[tuple[int, int], Any],
    gps: _Gps | None,
    rep: PoseReport,
) -> np.ndarray:
    """Chain each visual component, then place it on GPS (robust 2D rigid fit) or, without
    enough GPS, by a constant-velocity guess from its placed neighbour."""
    n = len(t)
    W = np.zeros((n, 4, 4))
    n_comp = int(comp.max()) + 1
    chains = [_chain(np.flatnonzero(comp == c), consecutive) for c in range(n_comp)]
    placed = np.zeros(n_comp, bool)

    for c in range(n_comp):
        fr = np.flatnonzero(comp == c)
        C = chains[c]
        if gps is None:
            continue
        dt = float(np.median(np.diff(t))) if n > 1 else 1.0
        # the drive's end components also take the fixes just outside the frames
        lo = _gps_margin_s(cfg, t) if fr[0] == 0 else 0.5 * dt
        hi = _gps_margin_s(cfg, t) if fr[-1] == n - 1 else 0.5 * dt
        sel = (gps.t_s >= t[fr[0]] - lo) & (gps.t_s <= t[fr[-1]] + hi)
        if not sel.any():
            continue
        g_en = gps.enu_m[sel]
        if len(fr) > 1:
            k, w = _interp_weights(t[fr], gps.t_s[sel])
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
            yaw = _gps_track_yaw(gps, tc, cfg.heading_min_baseline_m)
            if yaw is None:
                continue
            chain_heading = _heading_rad(C[len(C) // 2])
            T = _yaw_matrix(yaw - chain_heading)
            if len(fr) == 1:
                # a lone frame: the GPS track at its own time (the fix is up to half a frame
                # interval away, i.e. centimetres at speed)
                T[:2, 3] = _gps_at(gps, float(t[fr[0]]))[:2] - T[:2, :2] @ C[0, :2, 3]
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
            yaw = _gps_track_yaw(gps, tc, cfg.heading_min_baseline_m)
            if yaw is None:
                continue
            C = chains[c]
            T = _yaw_matrix(yaw - _heading_rad(C[len(C) // 2]))
            pos = _gps_at(gps, tc)
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


def _gps_at(gps: _Gps, tq: float) -> np.ndarray:
    """(3,) GPS track at time tq: linear between fixes, extrapolated from the end pairs."""
    ts, p = gps.t_s, gps.enu_m
    if len(ts) == 1:
        return p[0].copy()
    k = int(np.clip(np.searchsorted(ts, tq) - 1, 0, len(ts) - 2))
    w = (tq - ts[k]) / max(ts[k + 1] - ts[k], 1e-9)
    return (1 - w) * p[k] + w * p[k + 1]


def _heading_rad(T: np.ndarray) -> float:
    """Yaw (counter-clockwise from east, radians) of the vehicle's forward direction."""
    fwd = -T[:3, 1]
    return math.atan2(fwd[1], fwd[0])


def _gps_track_yaw(gps: _Gps, tc: float, min_base_m: float) -> float | None:
    """Counter-clockwise-from-east yaw of the GPS track around time tc (eq. 6.1 chord)."""
    order = np.argsort(np.abs(gps.t_s - tc))
    for j in order[1:]:
        d = gps.enu_m[j, :2] - gps.enu_m[order[0], :2]
        if np.linalg.norm(d) >= min_base_m:
            if gps.t_s[j] < gps.t_s[order[0]]:
                d = -d
            return math.atan2(d[1], d[0])
    return None


def _step_motion(t: np.ndarray, i: int, consecutive: dict[tuple[int, int], Any]) -> np.ndarray:
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


def _place_after(W, t, comp, c, C, consecutive) -> None:  # noqa: ANN001 - private helper
    fr = np.flatnonzero(comp == c)
    prev = fr[0] - 1
    first = W[prev] @ invert_pose(_step_motion(t, prev, consecutive))
    W[fr] = first @ invert_pose(C[0]) @ C


def _place_before(W, t, comp, c, C, consecutive) -> None:  # noqa: ANN001 - private helper
    fr = np.flatnonzero(comp == c)
    nxt = fr[-1] + 1
    last = W[nxt] @ _step_motion(t, fr[-1], consecutive)
    W[fr] = last @ invert_pose(C[-1]) @ C


def _segments(
    t: np.ndarray, comp: np.ndarray, gps: _Gps | None, bridge_s: float
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


# =========================================================================== the pose graph


def _robust_weights(r: np.ndarray, loss: str, c: float) -> np.ndarray:
    """IRLS weights w(r) = ρ'(r²)/1 for the named robust loss with scale c (σ units)."""
    z = (r / c) ** 2
    if loss == "cauchy":
        return 1.0 / (1.0 + z)
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + z)
    if loss == "huber":
        return np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1e-300)))
    if loss == "arctan":
        return 1.0 / (1.0 + z**2)
    return np.ones_like(r)


def _robust_cost(r: np.ndarray, loss: str, c: float) -> float:
    z = (r / c) ** 2
    if loss == "cauchy":
        rho = np.log1p(z)
    elif loss == "soft_l1":
        rho = 2.0 * (np.sqrt(1.0 + z) - 1.0)
    elif loss == "huber":
        rho = np.where(z <= 1.0, z, 2.0 * np.sqrt(z) - 1.0)
    elif loss == "arctan":
        rho = np.arctan(z)
    else:
        rho = z
    return float(0.5 * c * c * np.sum(rho))


def _color_columns(S: sp.csr_matrix) -> np.ndarray:
    """Greedy colouring of columns so that no two columns of one colour share a row."""
    C = (S.T.astype(np.int32) @ S.astype(np.int32)).tocsr()
    n = S.shape[1]
    colors = -np.ones(n, int)
    for j in range(n):
        used = set(colors[C.indices[C.indptr[j] : C.indptr[j + 1]]].tolist())
        k = 0
        while k in used:
            k += 1
        colors[j] = k
    return colors


class _PoseGraph:
    """Sparse robust least squares over x = [φ_i (3), p_i (3)] per frame, with
    R_i = Exp(φ_i) R0_i and p_i the camera centre in ENU."""

    def __init__(
        self,
        cfg: MappingConfig,
        t: np.ndarray,
        init: np.ndarray,
        ok_pairs: list[Any],
        pos_of: dict[int, int],
        gps: _Gps | None,
        drive: Drive,
        comp: np.ndarray,
    ) -> None:
        self.cfg, self.t, self.n = cfg, t, len(t)
        self.R0 = Rotation.from_matrix(init[:, :3, :3])
        self.p0 = init[:, :3, 3].copy()
        self.gps = gps
        self.gps_used = np.ones(0 if gps is None else len(gps.t_s), bool)
        self.gps_scale = 1.0
        self.vis_scale = 1.0

        # relative constraints: ok pairs + constant-velocity guesses across failed pairs
        ia, ib, Rm, tm, st, sr = [], [], [], [], [], []
        for p in ok_pairs:
            a, b = pos_of[p.index_a], pos_of[p.index_b]
            T = p.cam_b_from_cam_a
            ia.append(a), ib.append(b), Rm.append(T[:3, :3]), tm.append(T[:3, 3])
            st.append(
                cfg.visual_sigma_trans_m + cfg.visual_sigma_trans_rel * np.linalg.norm(T[:3, 3])
            )
            sr.append(math.radians(cfg.visual_sigma_rot_deg))
        self.n_vis = len(ia)
        for i in range(self.n - 1):
            if comp[i] != comp[i + 1]:
                # the initial guess already holds the best motion across the gap (chained
                # constant velocity, or the GPS track when vision broke)
                T = invert_pose(init[i + 1]) @ init[i]
                ia.append(i), ib.append(i + 1), Rm.append(T[:3, :3]), tm.append(T[:3, 3])
                st.append(cfg.gap_sigma_m), sr.append(math.radians(cfg.gap_sigma_rot_deg))
        self.ia, self.ib = np.array(ia, int), np.array(ib, int)
        self.Rm_inv = Rotation.from_matrix(np.array(Rm).reshape(-1, 3, 3)).inv() if ia else None
        self.tm = np.array(tm, float).reshape(-1, 3)
        self.st = np.array(st, float)
        self.sr = np.array(sr, float)

        # constant-velocity prior on frames beside a visual gap (triples i-1, i, i+1)
        gap = np.zeros(self.n, bool)
        if self.n >= 3 and cfg.gap_accel_sigma_mps2 > 0:
            brk = comp[1:] != comp[:-1]  # no ok pair between i and i+1
            gap[1:-1] = brk[:-1] | brk[1:]
        self.cv_i = np.flatnonzero(gap)
        dt1 = np.maximum(t[self.cv_i] - t[self.cv_i - 1], 1e-6) if len(self.cv_i) else t[:0]
        dt2 = np.maximum(t[self.cv_i + 1] - t[self.cv_i], 1e-6) if len(self.cv_i) else t[:0]
        self.cv_dt1, self.cv_dt2 = dt1, dt2
        # velocity change over the triple vs σ_a × the time between the two velocity samples
        self.cv_s = max(cfg.gap_accel_sigma_mps2, 1e-9) * 0.5 * (dt1 + dt2)

        # road-normal (tilt) prior per frame, in camera coordinates (pointing up, at the camera)
        n_up = np.tile([0.0, 0.0, -1.0], (self.n, 1))
        for p in ok_pairs if cfg.tilt_prior_axis == "road_normal" else []:
            pl = np.asarray(p.plane, float)
            if np.all(np.isfinite(pl)):
                v = np.array([pl[0], pl[1], -1.0])
                n_up[pos_of[p.index_a]] = v / np.linalg.norm(v)
        self.n_up = n_up
        self.s_tilt = math.radians(cfg.tilt_sigma_deg)

        # GPS: interpolation indices and eq. 6.1 headings
        if gps is not None:
            self.gk, self.gw = _interp_weights(t, gps.t_s)
            self._build_headings()
        # OBD speed at pair mid-times
        self.obd_v = None
        if cfg.use_obd and drive.obd is not None and len(drive.obd.timestamp_s) > 1 and self.n > 1:
            tm_mid = 0.5 * (t[1:] + t[:-1])
            inside = (tm_mid >= drive.obd.timestamp_s[0]) & (tm_mid <= drive.obd.timestamp_s[-1])
            v = np.interp(tm_mid, drive.obd.timestamp_s, drive.obd.speed_mps)
            self.obd_idx = np.flatnonzero(inside)
            self.obd_v = v[self.obd_idx]
        # gauge: without GPS, pin frame 0 (position, heading); without altitude, pin its height
        if gps is None:
            self.pin = [0, 1, 2, 3, 4, 5]
        elif not bool(np.any(gps.has_alt)):
            self.pin = [5]
        else:
            self.pin = []

    def _build_headings(self) -> None:
        g, cfg = self.gps, self.cfg
        hk, hth, hs = [], [], []
        for j in range(len(g.t_s) - 1):
            d = g.enu_m[j + 1, :2] - g.enu_m[j, :2]
            L = float(np.linalg.norm(d))
            if L < cfg.heading_min_baseline_m:
                continue
            comp_heading = float(heading_deg_from_displacement(d[0], d[1]))  # eq. 6.1, compass
            tmid = 0.5 * (g.t_s[j] + g.t_s[j + 1])
            k = int(np.argmin(np.abs(self.t - tmid)))
            if abs(self.t[k] - tmid) > 0.5 * (g.t_s[j + 1] - g.t_s[j]):
                continue
            sig = max(
                math.radians(cfg.heading_sigma_deg),
                math.atan(math.sqrt(g.sigma_m[j] ** 2 + g.sigma_m[j + 1] ** 2) / L),
            )
            hk.append(k), hth.append(math.radians(comp_heading)), hs.append(sig)
        self.hk = np.array(hk, int)
        self.hth = np.array(hth, float)
        self.hs = np.array(hs, float)

    # ---------------------------------------------------------------- residuals
    def _poses(self, x: np.ndarray) -> tuple[Rotation, np.ndarray]:
        X = x.reshape(self.n, 6)
        R = Rotation.from_rotvec(X[:, :3]) * self.R0
        return R, self.p0 + X[:, 3:]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        R, p = self._poses(x)
        out = []
        if len(self.ia):
            Ra, Rb = R[self.ia], R[self.ib]
            Rpred = Rb.inv() * Ra  # cam_b_from_cam_a
            rrot = (self.Rm_inv * Rpred).as_rotvec()
            tpred = Rb.inv().apply(p[self.ia] - p[self.ib])
            vis = np.ones(len(self.ia))
            vis[: self.n_vis] = self.vis_scale
            out.append((rrot / (self.sr * vis)[:, None]).ravel())
            out.append(((tpred - self.tm) / (self.st * vis)[:, None]).ravel())
        # tilt prior: road normal maps to world up
        up_w = R.apply(self.n_up)
        out.append((up_w[:, :2] / self.s_tilt).ravel())
        if self.gps is not None:
            g = self.gps
            u = self.gps_used
            k, w = self.gk[u], self.gw[u]
            k1 = np.minimum(k + 1, self.n - 1)
            pred = (1 - w)[:, None] * p[k] + w[:, None] * p[k1]
            s = g.sigma_m[u] * self.gps_scale
            out.append(((pred[:, :2] - g.enu_m[u, :2]) / s[:, None]).ravel())
            alt = g.has_alt[u]
            out.append(
                (pred[alt, 2] - g.enu_m[u][alt, 2]) / (s[alt] * self.cfg.gps_vertical_sigma_factor)
            )
            if len(self.hk):
                fwd = -R[self.hk].as_matrix()[:, :, 1]
                comp = np.arctan2(fwd[:, 0], fwd[:, 1])
                dh = np.angle(np.exp(1j * (comp - self.hth)))
                out.append(dh / self.hs)
        if len(self.cv_i):
            i = self.cv_i
            dv = (p[i + 1] - p[i]) / self.cv_dt2[:, None] - (p[i] - p[i - 1]) / self.cv_dt1[:, None]
            out.append((dv / self.cv_s[:, None]).ravel())
        if self.obd_v is not None and len(self.obd_idx):
            i = self.obd_idx
            sp_ = np.linalg.norm(p[i + 1] - p[i], axis=1) / np.maximum(
                self.t[i + 1] - self.t[i], 1e-9
            )
            out.append((sp_ - self.obd_v) / self.cfg.obd_sigma_mps)
        if len(self.pin):
            out.append(x[:6][self.pin] / 1e-3)
        return np.concatenate(out)

    def sparsity(self) -> sp.csr_matrix:
        """Which parameters each residual row depends on (for grouped finite differences)."""
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        r0 = 0

        def add(frames_per_row: list[np.ndarray], nrep: int, blocks: slice) -> None:
            nonlocal r0
            m = len(frames_per_row[0])
            base = np.arange(m) * nrep
            cols_in = np.arange(6)[blocks]
            for rr in range(nrep):
                for fr in frames_per_row:
                    for c in cols_in:
                        rows.append(r0 + base + rr)
                        cols.append(fr * 6 + c)
            r0 += m * nrep

        if len(self.ia):
            add([self.ia, self.ib], 3, slice(0, 3))  # rotation residuals
            add([self.ia, self.ib], 3, slice(0, 6))  # translation residuals
        add([np.arange(self.n)], 2, slice(0, 3))
        if self.gps is not None:
            u = self.gps_used
            k = self.gk[u]
            k1 = np.minimum(k + 1, self.n - 1)
            add([k, k1], 2, slice(3, 6))
            alt = self.gps.has_alt[u]
            if alt.any():
                add([k[alt], k1[alt]], 1, slice(3, 6))
            if len(self.hk):
                add([self.hk], 1, slice(0, 3))
        if len(self.cv_i):
            add([self.cv_i - 1, self.cv_i, self.cv_i + 1], 3, slice(3, 6))
        if self.obd_v is not None and len(self.obd_idx):
            add([self.obd_idx, self.obd_idx + 1], 1, slice(3, 6))
        if len(self.pin):
            add([np.zeros(1, int)], len(self.pin), slice(0, 0))  # rows only
            rows.append(r0 - len(self.pin) + np.arange(len(self.pin)))
            cols.append(np.array(self.pin, int))
        rr = np.concatenate(rows) if rows else np.zeros(0, int)
        cc = np.concatenate(cols) if cols else np.zeros(0, int)
        S = sp.coo_matrix((np.ones(len(rr)), (rr, cc)), shape=(r0, 6 * self.n))
        return (S.tocsr() > 0).astype(np.int8)

    # ---------------------------------------------------------------- solve
    def _lsq(self, x0: np.ndarray, rep: PoseReport) -> np.ndarray:
        """Levenberg-Marquardt with iteratively re-weighted robust loss, sparse normal
        equations and a coloured finite-difference Jacobian (a few residual evaluations)."""
        S = self.sparsity().tocoo()
        r = self.residuals(x0)
        if S.shape[0] != len(r):
            raise RuntimeError(f"pose graph: sparsity rows {S.shape[0]} != residuals {len(r)}")
        colors = _color_columns(S.tocsr())
        loss, c = self.cfg.robust_loss, self.cfg.robust_scale
        x = x0.copy()
        cost = _robust_cost(r, loss, c)
        if not math.isfinite(rep.cost_initial):
            rep.cost_initial = cost
        lam = 1e-3
        h = 1e-6
        for _it in range(self.cfg.max_nfev):
            w = _robust_weights(r, loss, c)
            vals = np.empty(len(S.row))
            for g in range(colors.max() + 1):
                cols = np.flatnonzero(colors == g)
                xp = x.copy()
                xp[cols] += h
                d = (self.residuals(xp) - r) / h
                m = colors[S.col] == g
                vals[m] = d[S.row[m]]
            J = sp.csr_matrix((vals, (S.row, S.col)), shape=S.shape)
            JtW = J.T.multiply(w[None, :]).tocsr()
            A = (JtW @ J).tocsc()
            grad = JtW @ r
            dA = A.diagonal()
            improved = False
            for _ in range(10):
                M = A + sp.diags(lam * np.maximum(dA, 1e-9) + 1e-12)
                dx = -spla.spsolve(M.tocsc(), grad)
                x_new = x + dx
                r_new = self.residuals(x_new)
                cost_new = _robust_cost(r_new, loss, c)
                rep.n_iterations += 1
                if np.isfinite(cost_new) and cost_new <= cost:
                    improved = True
                    break
                lam *= 4.0
            if not improved:
                break
            rel = (cost - cost_new) / max(cost, 1e-12)
            x, r, cost = x_new, r_new, cost_new
            lam = max(lam / 3.0, 1e-9)
            if rel < 1e-9 or np.max(np.abs(dx)) < 1e-9:
                break
        rep.cost_final = cost
        return x

    def solve(self, rep: PoseReport) -> np.ndarray:
        x = np.zeros(6 * self.n)
        x = self._lsq(x, rep)
        if self.gps is not None and len(self.gps.t_s):
            for _ in range(2):
                changed = self._reweight(x, rep)
                if not changed:
                    break
                x = self._lsq(x, rep)
        rep.gps_sigma_scale = self.gps_scale
        rep.visual_sigma_scale = self.vis_scale
        if self.gps is not None:
            rep.n_gps_used = int(self.gps_used.sum())
            bad = np.flatnonzero(~self.gps_used)
            rep.gps_outliers = [
                {"gps_index": int(self.gps.orig_index[j]), "timestamp_s": float(self.gps.t_s[j])}
                for j in bad
            ]
            if len(bad):
                log.warning("poses: rejected %d GPS fix(es) as outliers", len(bad))
        R, p = self._poses(x)
        W = np.tile(np.eye(4), (self.n, 1, 1))
        W[:, :3, :3] = R.as_matrix()
        W[:, :3, 3] = p
        return W

    def _gps_errors_m(self, x: np.ndarray) -> np.ndarray:
        _, p = self._poses(x)
        k, w = self.gk, self.gw
        k1 = np.minimum(k + 1, self.n - 1)
        pred = (1 - w)[:, None] * p[k] + w[:, None] * p[k1]
        return np.linalg.norm(pred[:, :2] - self.gps.enu_m[:, :2], axis=1)

    def _reweight(self, x: np.ndarray, rep: PoseReport) -> bool:
        """Robust σ rescaling (MAD of normalised GPS residuals) and GPS outlier rejection."""
        e = self._gps_errors_m(x) / self.gps.sigma_m  # horizontal error in units of σ
        old_used = self.gps_used.copy()
        old_scale = self.gps_scale
        old_vis = self.vis_scale
        if self.cfg.adapt_sigmas and self.gps_used.sum() >= 8:
            # A 2D error norm with per-axis σ has median ≈ 1.1774 σ (Rayleigh). Only GPS that is
            # clearly worse than its σ says (> 3×) is loosened. The reverse (an RTK receiver
            # reporting HDOP) is left alone: residuals after the fit are biased low, and
            # tightening GPS would over-weight it against vision (measured: worse drift).
            s = float(np.median(e[self.gps_used]) / 1.1774)
            if s > 3.0:
                self.gps_scale = float(np.clip(s, 1.0, 20.0))
        thr = self.cfg.gps_outlier_sigmas * self.gps_scale
        self.gps_used = e <= thr
        if self.gps_used.sum() < min(2, len(e)):
            self.gps_used = old_used
        return (
            not np.array_equal(old_used, self.gps_used)
            or abs(math.log(max(self.gps_scale, 1e-9) / max(old_scale, 1e-9))) > 0.2
            or abs(math.log(max(self.vis_scale, 1e-9) / max(old_vis, 1e-9))) > 0.2
        )
