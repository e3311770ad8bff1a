"""Bundle adjustment over feature tracks after the pose graph (issue 30; on by default,
``mapping.bundle_adjust``).

The pose graph solves every pair once; a road point seen by three frames is never optimised
jointly. Here the pairs' matches are chained into tracks (``mapping.tracks``) and the poses,
points, per-frame road planes and the GPS - camera time offset are refined together
(``mapping.bundle_problem``) with scipy's ``least_squares`` (trust-region reflective, sparse
analytic Jacobian, LSMR, robust loss ``cfg.robust_loss``).

Sliding window: overlapping windows of ``bundle_window_frames`` frames along the drive, each
solved once; the two frames before a window are held at their refined poses (they tie the
window to the part already solved), and a window's last ``bundle_overlap_frames`` frames are
solved again by the next window before they are final. Cost and memory grow linearly with the
drive. The pose graph's solution is the initial guess and a weak prior (the gauge where GPS is
weak); each window's points start triangulated from its current poses. GPS σ is loosened (never
tightened) from the pose graph's own GPS residuals, as in the pose graph; fixes further than
``gps_outlier_sigmas`` from the window's solution are dropped and the window solved again. The
GPS time offset is fitted over the whole drive and applied only when significant (its standard
error at least the bound the fixes' velocity changes allow). Finally the pose graph's placement
(position and heading) is kept at scales beyond ``bundle_placement_length_m`` (a window sees only
its own fixes). Each pair's own motion stays in the problem as the pose graph's factor (same σ).
Revisits: ``mapping.loops`` (loop pairs go to the pose graph, before and after the windows).
A rolling shutter (camera.yaml ``readout_s``): each observation is projected from the pose of its
raw row's time, the frame's pose moved on by its motion over the readout (from its neighbours'
current poses, ``core.rolling.frame_motion``, held in a window). The refined focal and k1 reach
the later stages through ``mapping.bundle_camera``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial.transform import Rotation

from roadsurf.core.geometry import invert_pose, up_in_cam
from roadsurf.core.parallel import one_blas_thread
from roadsurf.core.rolling import frame_motion
from roadsurf.io.drive import Drive
from roadsurf.mapping.bundle_gps import (
    fit_time_offset,
    gps_sigma_scale,
    keep_placement,
    time_offset_bound_s,
)
from roadsurf.mapping.bundle_problem import WindowProblem
from roadsurf.mapping.bundle_reduced import ReducedProblem, solve_reduced
from roadsurf.mapping.bundle_terms import WindowData, true_px_from_observed_px, unit_normal
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.grade import up_axes_in_cam
from roadsurf.mapping.pose_gps import GpsFixes
from roadsurf.mapping.tracks import (
    Tracks,
    build_tracks,
    initial_planes,
    thin_tracks,
    triangulate_w,
)
from roadsurf.reconstruction.rolling_shutter import row_times_s

if TYPE_CHECKING:
    from collections.abc import Sequence

    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)

# the algorithm's version, in the poses stage's fingerprint: a run resumed after a change
# recomputes its poses (2: relief weight per frame, the pairs' motions, heading placement; 4: a
# rolling shutter's rows each from their own pose, the pairs' translations follow the focal)
# 5: RS keeps the pose graph's mean tilt; 6: tracks.link_residuals_m; 7: its gross bound; 8: the
# points' steps on dense blocks, one BLAS thread; 9: sparse point products (8, 9: rounding level);
# 10: the pose graph's slope kept at the placement length (bundle_gps.keep_placement)
BUNDLE_VERSION = 10
N_ANCHOR = 2  # frames before a window held at their refined poses
MIN_OBS = 8  # a frame seeing fewer 3+-view track points keeps its pose graph pose
MIN_OFFSET_S = 0.005  # a smaller GPS time offset is not applied (s)
# ... nor one within this many standard errors of 0. The standard error counts the fixes' noise
# and its correlation, not the trajectory's own systematic errors (scale, grade, a tilted
# camera's pitch), which a time offset partly mimics along the track: a tilted RTK drive with
# no latency read -151 +- 43 ms (3.5 σ) and was moved 15 cm; a real 60 ms latency reads 11 σ.
TIME_OFFSET_SIGMAS = 5.0
MIN_SHARED = 8  # consecutive frames sharing fewer tracks get the constant-motion prior


@one_blas_thread
def refine_poses(
    cfg: MappingConfig,
    drive: Drive,
    t: np.ndarray,
    world: np.ndarray,
    pairs: list[PairResult],
    pos_of: dict[int, int],
    gps: GpsFixes | None,
    gps_used: np.ndarray | None,
    R_vehicle_from_cam: np.ndarray,
    grade_rad: np.ndarray | None = None,
    still: Sequence[PairResult] = (),
) -> tuple[np.ndarray, dict[str, Any]]:
    """(N, 4, 4) refined world_from_cam and a report (figures for poses_report.json).
    ``grade_rad`` (N,): the road's grade at each frame (``mapping.grade``; None: level), which
    tips the tilt prior's axis. On one BLAS thread: a window's dense algebra is small (~260
    unknowns); threads cost more than they gave (sample drive, 2 cores: 6.1 -> 3.3 CPU s).
    ``still``: consecutive frames of a stopped vehicle (``no_motion`` pairs, R = I, t = 0):
    no tracks tie them, so their motion (none) is a factor like an ok pair's."""
    t0 = time.perf_counter()
    n = len(t)
    tracks = build_tracks(
        pairs, pos_of, world, tol_m=cfg.bundle_track_tol_m, sigma_trans_m=cfg.visual_sigma_trans_m
    )
    cam = drive.camera
    tracks = thin_tracks(tracks, cfg.bundle_max_two_view, (cam.width, cam.height))
    if cam.readout_s > 0:  # a rolling shutter: each observation at its raw row's time
        raw_v = cam.distort_px(tracks.obs_px)[:, 1]
        tracks.obs_time_s = row_times_s(raw_v, cam.height, cam.readout_s)
    report: dict[str, Any] = {
        "n_tracks": tracks.n_tracks,
        "n_tracks_3plus": int(np.sum(tracks.length >= 3)),
        "n_inconsistent_tracks": tracks.n_inconsistent,
        "n_tracks_off_road": 0 if tracks.road is None else int(np.sum(~tracks.road)),
        "n_windows": 0,
        "gps_rejected": [],
    }
    if tracks.n_tracks == 0 or n < 2:
        report["skipped"] = "no tracks"
        return world, report
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    d_down = -up_in_cam(R_vehicle_from_cam)  # the road's normal (down) in the camera: d·X = h
    plane_nominal = np.array([-d_down[0], -d_down[1], cam.height_m]) / d_down[2]
    # per frame, the camera axis the tilt prior holds on world up (the grade tips it)
    n_up = up_axes_in_cam(
        R_vehicle_from_cam, np.zeros(n) if grade_rad is None else grade_rad, cfg.cross_fall_rad
    )
    used = np.ones(0 if gps is None else len(gps.t_s), bool)
    if gps is not None and gps_used is not None:
        used = gps_used.copy()
    # the fixes' real scatter (MAD) for the time-offset statistics; the windows' GPS weights are
    # only ever loosened, never tightened, as in the pose graph (which loosens only beyond 3x:
    # it fits all fixes at once, the bundle's windows a few each): tightening an RTK
    # receiver's HDOP σ to its residuals made each window's placement follow their noise
    # (potholes, RTK: aligned trajectory RMSE 6.4 mm tightened, 3.7 mm not)
    fit_scale = gps_sigma_scale(world, t, gps, used)
    gps_scale = max(1.0, fit_scale)
    report["gps_sigma_scale"] = gps_scale

    # the pairs' own motions, as the pose graph's factors at its σ (visual_sigma_*): tracks on a
    # forward-moving camera over a road pin a frame's pitch against the next ones weakly (a
    # bent "dome" window fits the pixels almost as well), and each pair's motion, solved with
    # its road plane, holds that direction. Measured (5-frame relative pitch error, highway):
    # pose graph 0.037°, bundle without them 0.100°, with them 0.059°
    rel_rot = {
        (pos_of[p.index_a], pos_of[p.index_b]): (
            np.asarray(p.R_b_from_a, float),
            np.asarray(p.t_b_from_a_m, float),
            unit_normal(p.plane, d_down),
        )
        for p in [*pairs, *still]
        if p.index_a in pos_of and p.index_b in pos_of
    }
    rest = (tracks, gps, K, n_up, plane_nominal, report, used, rel_rot)
    tau = 0.0
    if gps is not None and cfg.bundle_max_time_offset_s > 0:
        # the offset is fitted to a trajectory shaped by vision (GPS 10x looser): one fitted
        # to lagging fixes has already bent towards them
        loose, _ = _sweep(cfg, drive, t, world, 10.0 * gps_scale, *rest, 0.0)
        tau, se = fit_time_offset(loose, t, gps, used, fit_scale, cfg)
        se = max(se, time_offset_bound_s(world, t, gps, used, fit_scale))
        report["time_offset_se_s"] = se
        report["time_offset_estimate_s"] = tau  # before the test: kept, not applied below it
        if abs(tau) <= max(MIN_OFFSET_S, TIME_OFFSET_SIGMAS * se):
            tau = 0.0  # not significant
        report["gps_rejected"] = []
        report["n_windows"] = 0
    psi = kappa = 0.0
    if cfg.bundle_refine_focal or cfg.bundle_refine_k1:
        # per-window focal and k1 estimates with the calibration as prior; their medians (one
        # camera for the drive) are held below
        sf = cfg.bundle_focal_sigma if cfg.bundle_refine_focal else 0.0
        sk = cfg.bundle_k1_sigma if cfg.bundle_refine_k1 else 0.0
        _, st = _sweep(cfg, drive, t, world, gps_scale, *rest, tau, (0.0, sf), (0.0, sk))
        psis, kaps = st.pop("focal_log_scales"), st.pop("k1_corrections")
        report["gps_rejected"] = []
        report["n_windows"] = 0
        if cfg.bundle_refine_focal:
            psi = float(np.median(psis)) if psis else 0.0
            report["focal_scale"] = math.exp(psi)
            report["focal_scale_windows"] = [round(math.exp(v), 5) for v in psis]
        if cfg.bundle_refine_k1:
            kappa = float(np.median(kaps)) if kaps else 0.0
            report["k1"] = float(cam.dist[0]) + kappa
            report["k1_calibration"] = float(cam.dist[0])
            report["k1_windows"] = [round(float(cam.dist[0]) + v, 5) for v in kaps]
    cur, stats = _sweep(cfg, drive, t, world, gps_scale, *rest, tau, (psi, 0.0), (kappa, 0.0))
    stats.pop("focal_log_scales", None)
    stats.pop("k1_corrections", None)
    if tau == 0.0:  # (the pose graph placed the drive on lagging fixes otherwise)
        cur = keep_placement(cur, world, cfg.bundle_placement_length_m)
    report["time_offset_s"] = tau
    report.update(stats)
    report["elapsed_s"] = round(time.perf_counter() - t0, 3)
    moved = np.linalg.norm(cur[:, :3, 3] - world[:, :3, 3], axis=1)
    report["moved_m_median"] = float(np.median(moved))
    report["moved_m_max"] = float(np.max(moved))
    log.info(
        "bundle: %d tracks (%d seen 3+ times), %d windows, reprojection %s -> %s px, "
        "poses moved %.1f mm median, GPS time offset %.1f ms, %.1f s",
        tracks.n_tracks, report["n_tracks_3plus"], report["n_windows"],
        _px(report["reprojection_rms_px_initial"]), _px(report["reprojection_rms_px_final"]),
        1e3 * report["moved_m_median"], 1e3 * report["time_offset_s"], report["elapsed_s"],
    )  # fmt: skip
    return cur, report


def _px(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def _sweep(
    cfg: MappingConfig,
    drive: Drive,
    t: np.ndarray,
    world: np.ndarray,
    gps_scale: float,
    tracks: Tracks,
    gps: GpsFixes | None,
    K: np.ndarray,
    n_up: np.ndarray,
    plane_nominal: np.ndarray,
    report: dict[str, Any],
    used: np.ndarray,
    rel_rot: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]],
    tau: float,
    focal: tuple[float, float] = (0.0, 0.0),
    k1: tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, dict[str, Any]]:
    """All windows along the drive with the GPS time offset tau held: refined poses, figures."""
    n = len(t)
    cur = world.copy()  # latest estimate of every pose
    pts = tracks.point_w.copy()  # latest estimate of every track point
    W, n_over = cfg.bundle_window_frames, cfg.bundle_overlap_frames
    if W <= n_over + N_ANCHOR:
        raise ValueError(
            f"mapping.bundle_window_frames={W} must exceed bundle_overlap_frames={n_over} + "
            f"{N_ANCHOR}"
        )
    s = 0
    cost0 = cost1 = 0.0
    rms0: list[float] = []
    rms1: list[float] = []
    psis: list[float] = []
    kaps: list[float] = []
    done = 0  # frames [0, done) hold refined poses (final or from the previous window)
    while True:
        e = min(s + W, n)
        final_to = n if e == n else e - n_over
        if done > 0 and e > done:
            # frames the previous window did not reach follow its last frame's correction, so
            # the window starts without a step at the junction
            corr = cur[done - 1] @ invert_pose(world[done - 1])
            cur[done:e] = corr[None] @ world[done:e]
        res = _solve_window(
            cfg, drive, t, s, e, cur, world, pts, tracks, gps, used, gps_scale, tau, K,
            n_up, plane_nominal, report, rel_rot, focal, k1,
        )  # fmt: skip
        if res is not None:
            if focal[1] > 0:
                psis.append(res["psi"])
            if k1[1] > 0:
                kaps.append(res["kappa"])
            cost0 += res["cost0"]
            cost1 += res["cost1"]
            rms0.append(res["rms0"])
            rms1.append(res["rms1"])
        report["n_windows"] += 1
        done = e
        if e == n:
            break
        s = final_to - N_ANCHOR
    stats = {
        "cost_initial": cost0,
        "cost_final": cost1,
        # None: no window had a frame to refine (JSON has no NaN)
        "reprojection_rms_px_initial": float(np.median(rms0)) if rms0 else None,
        "reprojection_rms_px_final": float(np.median(rms1)) if rms1 else None,
        "focal_log_scales": psis,
        "k1_corrections": kaps,
    }
    return cur, stats


def _solve_window(
    cfg: MappingConfig,
    drive: Drive,
    t: np.ndarray,
    s: int,
    e: int,
    cur: np.ndarray,
    world_pg: np.ndarray,
    pts: np.ndarray,
    tracks: Tracks,
    gps: GpsFixes | None,
    used: np.ndarray,
    gps_scale: float,
    tau: float,
    K: np.ndarray,
    n_up: np.ndarray,
    plane_nominal: np.ndarray,
    report: dict[str, Any],
    rel_rot: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]],
    focal: tuple[float, float] = (0.0, 0.0),
    k1: tuple[float, float] = (0.0, 0.0),
) -> dict[str, float] | None:
    """Refine frames [s, e) in place in ``cur`` and their points in ``pts``."""
    F = e - s
    o = (tracks.obs_frame >= s) & (tracks.obs_frame < e)
    cnt = np.bincount(tracks.obs_track[o], minlength=tracks.n_tracks)
    o &= cnt[tracks.obs_track] >= 2
    if not o.any():
        return None
    tr_ids, obs_p = np.unique(tracks.obs_track[o], return_inverse=True)
    obs_f = tracks.obs_frame[o] - s
    # a frame's pose is refined only where it sees points that three or more frames see: a
    # two-view track repeats its pair's own matches, which the pose graph already holds (on
    # drives whose pairs share no keypoints the bundle moved the pose graph's rotations from
    # 0.19° to 0.31° off with two-view tracks alone)
    multi = np.bincount(obs_p, minlength=len(tr_ids))[obs_p] >= 3
    n_obs = np.bincount(obs_f[multi], minlength=F)
    free = n_obs >= MIN_OBS
    if s > 0:
        free[:N_ANCHOR] = False
    if not free.any():
        return None
    R0, C0 = cur[s:e, :3, :3].copy(), cur[s:e, :3, 3].copy()
    # the points start where the window's current poses see them (a point placed by other poses
    # sits centimetres off after the previous window moved its frames, and the robust loss then
    # treats its reprojections as outliers)
    Kf = K.copy()  # with the focal length the window starts from
    Kf[:2, :2] *= math.exp(focal[0])
    # ... and the k1 correction it starts from
    px_tri = true_px_from_observed_px(tracks.obs_px[o], Kf, k1[0])
    Ro, Co = R0[obs_f], C0[obs_f]
    vel = omega = obs_time = None
    if tracks.obs_time_s is not None:
        # a rolling shutter: each frame's motion over its readout from its neighbours' current
        # poses (held in the window), each observation seen from its row's pose
        mot = [frame_motion(cur, t, i) for i in range(s, e)]
        vel, omega = np.array([m_[0] for m_ in mot]), np.array([m_[1] for m_ in mot])
        obs_time = tracks.obs_time_s[o]
        a = omega[obs_f] * obs_time[:, None]
        Ro = Rotation.from_rotvec(a).as_matrix() @ Ro
        Co = Co + vel[obs_f] * obs_time[:, None]
    X0, tri_ok = triangulate_w(obs_p, px_tri, Ro, Co, Kf, len(tr_ids))
    X0[~tri_ok] = pts[tr_ids][~tri_ok]
    planes0 = initial_planes(R0, C0, X0, obs_f, obs_p, plane_nominal)
    # consecutive frames tied by too few tracks: the current relative motion as a prior
    shared = np.zeros(max(F - 1, 0), int)
    for i in range(F - 1):
        a = set(obs_p[obs_f == i].tolist())
        shared[i] = len(a.intersection(obs_p[obs_f == i + 1].tolist()))
    gap_i = np.flatnonzero(shared < MIN_SHARED)
    # GPS fixes inside the window's time span
    if gps is not None:
        # ... and, at the drive's ends, the fixes just outside it (extrapolated, σ inflated)
        lo = -np.inf if s == 0 else t[s]
        hi = np.inf if e == len(t) else t[e - 1]
        g = np.flatnonzero((gps.t_s >= lo) & (gps.t_s <= hi))
        gps_t, gps_enu, gps_sig = gps.t_s[g], gps.enu_m[g], gps.sigma_m[g]
        gps_alt, g_used = gps.has_alt[g], used[g]
    else:
        g = np.zeros(0, int)
        gps_t, gps_enu, gps_sig = np.zeros(0), np.zeros((0, 3)), np.zeros(0)
        gps_alt, g_used = np.zeros(0, bool), np.zeros(0, bool)
    # the pairs inside the window (consecutive frames)
    rel_i = np.array([i for i in range(F - 1) if (s + i, s + i + 1) in rel_rot], int)
    rel_R = np.array([rel_rot[(s + i, s + i + 1)][0] for i in rel_i]).reshape(-1, 3, 3)
    rel_t = np.array([rel_rot[(s + i, s + i + 1)][1] for i in rel_i]).reshape(-1, 3)
    rel_n = np.array([rel_rot[(s + i, s + i + 1)][2] for i in rel_i]).reshape(-1, 3)
    sig_t = cfg.visual_sigma_trans_m + cfg.visual_sigma_trans_rel * np.linalg.norm(rel_t, axis=1)
    obd_i, obd_v = np.zeros(0, int), np.zeros(0)
    if cfg.use_obd and drive.obd is not None and len(drive.obd.timestamp_s) > 1 and F > 1:
        tm = 0.5 * (t[s + 1 : e] + t[s : e - 1])
        inside = (tm >= drive.obd.timestamp_s[0]) & (tm <= drive.obd.timestamp_s[-1])
        obd_i = np.flatnonzero(inside)
        obd_v = np.interp(tm[obd_i], drive.obd.timestamp_s, drive.obd.speed_mps)
    data = WindowData(
        K=K,
        t=t[s:e],
        R0=R0,
        C0=C0,
        free=free,
        C_prior=world_pg[s:e, :3, 3],
        planes0=planes0,
        n_up=n_up[s:e],
        obs_f=obs_f,
        obs_p=obs_p,
        obs_px=tracks.obs_px[o],
        X0=X0,
        gps_t=gps_t,
        gps_enu=gps_enu,
        gps_sigma=gps_sig,
        gps_has_alt=gps_alt,
        gap_i=gap_i,
        obd_i=obd_i,
        obd_v=obd_v,
        height_m=drive.camera.height_m,
        sigma_px=cfg.bundle_pixel_sigma_px,
        sigma_relief_m=cfg.bundle_relief_sigma_m,
        sigma_height_m=cfg.bundle_height_sigma_m,
        sigma_prior_m=cfg.bundle_prior_sigma_m,
        sigma_tilt_rad=math.radians(cfg.tilt_sigma_deg),
        sigma_gap_m=cfg.gap_sigma_m,
        sigma_gap_rad=math.radians(cfg.gap_sigma_rot_deg),
        sigma_obd_mps=cfg.obd_sigma_mps,
        vertical_factor=cfg.gps_vertical_sigma_factor,
        tau0=tau,
        sigma_tau_s=0.0,  # held; estimated over the drive (fit_time_offset)
        on_road=None if tracks.road is None else tracks.road[tr_ids],
        rel_i=rel_i,
        rel_R=rel_R,
        sigma_rel_rad=math.radians(cfg.visual_sigma_rot_deg),
        rel_t=rel_t,
        rel_n=rel_n,
        sigma_rel_m=sig_t,
        focal0=focal[0],
        sigma_focal=focal[1],
        k1_0=k1[0],
        sigma_k1=k1[1],
        obs_time_s=obs_time,
        vel=vel,
        omega=omega,
    )
    prob = WindowProblem(data)
    prob.gps_used = g_used.copy()
    prob.gps_scale = gps_scale
    red = ReducedProblem(prob, cfg.robust_loss, cfg.robust_scale)
    theta = np.zeros(red.n)
    m = len(obs_f)
    r = red.fun(theta)  # the points triangulated from the initial poses
    rms0 = float(np.sqrt(np.mean(r[: 2 * m] ** 2)) * cfg.bundle_pixel_sigma_px)
    cost0 = float(0.5 * np.sum(r**2))
    for _ in range(3):
        theta = solve_reduced(red, theta, cfg)
        if not len(gps_t):
            break
        err = prob.gps_errors(red.full_x(theta))
        ok = g_used & (err <= cfg.gps_outlier_sigmas)
        if np.array_equal(ok, prob.gps_used) or ok.sum() < 2:
            break
        prob.gps_used = ok
        dX = red.dX
        red = ReducedProblem(prob, cfg.robust_loss, cfg.robust_scale)  # residuals changed
        red.dX = dX
    x = red.full_x(theta)
    r = prob.fun(x)
    R, C, _, P, _ = prob.unpack(x)
    fr = np.flatnonzero(free)
    cur[s + fr, :3, :3] = R[fr]
    cur[s + fr, :3, 3] = C[fr]
    pts[tr_ids] = P
    for j in np.flatnonzero(g_used & ~prob.gps_used):
        rec = {"gps_index": int(gps.orig_index[g[j]]), "timestamp_s": float(gps_t[j])}  # type: ignore[union-attr]
        if rec not in report["gps_rejected"]:
            report["gps_rejected"].append(rec)
    return {
        "psi": prob.focal_log_scale(x),
        "kappa": prob.k1_correction(x),
        "cost0": cost0,
        "cost1": float(0.5 * np.sum(r**2)),
        "rms0": rms0,
        "rms1": float(np.sqrt(np.mean(r[: 2 * m] ** 2)) * cfg.bundle_pixel_sigma_px),
    }


def with_motions_of(
    pairs: list[PairResult], pos_of: dict[int, int], world_from_cam: np.ndarray
) -> list[PairResult]:
    """Copies of the pairs with their relative pose (R_b_from_a, t_b_from_a_m) taken from the
    (N, 4, 4) poses: the bundle's motions as pose-graph constraints."""
    out = []
    for p in pairs:
        T = invert_pose(world_from_cam[pos_of[p.index_b]]) @ world_from_cam[pos_of[p.index_a]]
        out.append(dataclasses.replace(p, R_b_from_a=T[:3, :3], t_b_from_a_m=T[:3, 3]))
    return out
