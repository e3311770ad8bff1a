"""Seeded synthetic drives with shared road points, for the track and bundle tests.

Unlike ``tests.mapping.synth`` (independent points per pair), one set of road points lies on
the road and every frame sees the ones in its view, with one noisy keypoint position per
(frame, point): the two pairs a frame belongs to match the same keypoints, so matches chain
into tracks. The vehicle speeds up and slows down along an S-curve (a GPS time offset is then
observable), and the GPS fixes can lag the camera by a latency.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from roadsurf.core.camera import normalised_from_px
from roadsurf.core.fits import camera_plane_distance
from roadsurf.core.geometry import invert_pose, lla_from_enu, world_from_cam
from roadsurf.io.drive import Drive, Frame, GpsTrack
from roadsurf.reconstruction.geometry import triangulate
from roadsurf.reconstruction.types import STATUS_NO_MOTION, PairResult
from tests.mapping.synth import REF, camera


@dataclass
class TrackDrive:
    drive: Drive
    pairs: list[PairResult]
    world_from_cam: np.ndarray  # (N, 4, 4) true poses
    points_w: np.ndarray  # (P, 3) true road points
    pair_point_ids: list[np.ndarray]  # per pair: the true point of each match


def road_height(xy: np.ndarray, amp_m: float, wavelength_m: float) -> np.ndarray:
    """Height (m) of the undulating road at (K, 2) ENU positions: 0 for amp_m = 0."""
    k = 2 * np.pi / wavelength_m
    return amp_m * (np.sin(k * xy[:, 0]) + 0.5 * np.sin(k * xy[:, 1] + 1.0))


def _poses(
    n: int,
    fps: float,
    speed: float,
    rng: np.random.Generator,
    speed_variation: float = 0.3,
    undulation: tuple[float, float] = (0.0, 1.0),
    smooth_attitude: bool = False,
    stop_s: tuple[float, float] | None = None,
) -> tuple[np.ndarray, ...]:
    """Times, (N, 4, 4) poses, a dense (time, centre) path for interpolating GPS truth, the
    dense path's heading (deg) and (roll, pitch) (rad, on the dense times; NaN: drawn per frame).
    smooth_attitude: roll and pitch sway as the vehicle body does (one sinusoid each, 0.7-1.5 Hz,
    0.3° RMS), not independently per frame (a rolling shutter's rows then have a pose)."""
    dt = 1.0 / fps
    tt = np.arange(0.0, n / fps + 2.0, dt / 20)  # dense, from 0 (the first frame)
    v = speed * (1.0 + speed_variation * np.sin(2 * np.pi * tt / 2.5))  # ±30 % speed
    if stop_s is not None:  # the vehicle stands still (an abrupt stop)
        v[(tt >= stop_s[0]) & (tt < stop_s[1])] = 0.0
    s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(tt))])
    heading = 30.0 + 25.0 * np.sin(s / 6.0)  # degrees, S-curve
    b = np.radians(heading)
    step = np.column_stack([np.sin(b), np.cos(b), np.zeros_like(b)])
    pos = np.concatenate(
        [[np.zeros(3)], np.cumsum(0.5 * (step[1:] + step[:-1]) * np.diff(s)[:, None], 0)]
    )
    pos[:, 2] = 1.0 + road_height(pos[:, :2], *undulation)  # 1 m above the road
    t = np.arange(n) * dt
    att = np.full((len(tt), 2), np.nan)
    if smooth_attitude:
        f, ph = rng.uniform(0.7, 1.5, 2), rng.uniform(0, 2 * np.pi, 2)
        att = np.radians(0.3 * np.sqrt(2) * np.sin(2 * np.pi * f * tt[:, None] + ph))
    W = np.empty((n, 4, 4))
    for i in range(n):
        j = int(round(t[i] / (dt / 20)))
        roll, pitch = att[j] if smooth_attitude else np.radians(rng.normal(0, 0.3, 2))
        W[i] = world_from_cam(heading[j], roll, pitch, pos[j])
    return t, W, tt, pos, heading, att


def make_track_drive(
    n: int = 50,
    seed: int = 0,
    fps: float = 20.0,
    speed_mps: float = 4.0,
    px_sigma: float = 0.2,
    rot_noise_deg: float = 0.05,
    trans_noise_m: float = 0.002,
    scale_noise: float = 0.005,
    gps_hz: float = 10.0,
    gps_sigma_m: float = 0.02,
    gps_latency_s: float = 0.0,
    gps_outliers: dict[int, tuple[float, float]] | None = None,
    density_per_m2: float = 120.0,
    speed_variation: float = 0.3,
    width_px: int = 160,
    undulation_m: float = 0.0,
    undulation_wavelength_m: float = 3.0,
    k1: float = 0.0,
    readout_s: float = 0.0,
    focal_error: float = 0.0,
    stop_s: tuple[float, float] | None = None,
    still_status: str = STATUS_NO_MOTION,
) -> TrackDrive:
    """undulation_m: amplitude of the road's smooth relief (m, 0 = the flat road z = 0); k1: the
    lens's radial distortion (−, OpenCV's k1): the keypoints are the true lens's (normalised x
    times 1 + k1 r²), the drive's camera has none (camera.yaml's k1 = 0). readout_s: a rolling
    shutter (s, first to last row; the drive's camera has it): a keypoint on row v is where the
    camera was readout_s v / height after the frame's time on the true path (position and
    heading; the frame's roll and pitch), the pairs' points and motions stay at the frames'
    times. focal_error: the drive's camera (camera.yaml) has a focal length 1 + focal_error
    times the lens's, and each pair was solved with it, as the reconstruction does: its
    points triangulated from its pixels with that K and its (noisy) motion, then scaled so
    that its road plane lies the camera height below (α = h / d_c). stop_s: the vehicle stands
    still from..to (s); the pairs of its standing frames fail with ``still_status``."""
    rng = np.random.default_rng(seed)
    cam = camera(width=width_px, height=width_px * 3 // 4, fps=fps)
    und = (undulation_m, undulation_wavelength_m)
    t, W, tt, path, heading, att = _poses(
        n, fps, speed_mps, rng, speed_variation, und, smooth_attitude=readout_s > 0,
        stop_s=stop_s,
    )  # fmt: skip
    if readout_s > 0:
        cam = dataclasses.replace(cam, readout_s=readout_s)
    # road points around the path
    lo = path[:, :2].min(0) - 1.0
    hi = path[:, :2].max(0) + 1.0
    npts = int(density_per_m2 * np.prod(hi - lo))
    P = np.column_stack([rng.uniform(lo[0], hi[0], npts), rng.uniform(lo[1], hi[1], npts)])
    d = np.min(np.linalg.norm(P[:, None, :] - path[None, ::20, :2], axis=2), axis=1)
    P = P[d < 1.0]
    pts = np.column_stack([P, road_height(P, *und)])
    # one keypoint per (frame, visible point)
    kp: list[dict[int, np.ndarray]] = []
    m = 3.0
    for i in range(n):
        uv, Xc = _keypoints(cam, pts, W[i], t[i], tt, np.c_[path, heading, att], k1)
        vis = (
            (Xc[:, 2] > 0.1)
            & (uv[:, 0] > m)
            & (uv[:, 0] < cam.width - 1 - m)
            & (uv[:, 1] > m)
            & (uv[:, 1] < cam.height - 1 - m)
        )
        ids = np.flatnonzero(vis)
        kp.append(
            dict(zip(ids.tolist(), uv[ids] + rng.normal(0, px_sigma, (len(ids), 2)), strict=True))
        )
    pairs, pair_ids = [], []
    for i in range(n - 1):
        ids = np.array(sorted(set(kp[i]) & set(kp[i + 1])), int)
        T = invert_pose(W[i + 1]) @ W[i]
        if np.linalg.norm(T[:3, 3]) < 1e-6:  # standing: depth is unobservable, the pair fails
            pairs.append(PairResult(f"{i:06d}.png", f"{i + 1:06d}.png", i, i + 1, "proposed",
                                    still_status, "the camera did not move"))  # fmt: skip
            pair_ids.append(np.zeros(0, int))
            continue
        k = 1.0 + rng.normal(0, scale_noise)
        w = rng.normal(0, np.radians(rot_noise_deg), 3)
        Rn = Rotation.from_rotvec(w).as_matrix() @ T[:3, :3]
        tn = k * T[:3, 3] + rng.normal(0, trans_noise_m, 3)
        Xa = k * ((pts[ids] - W[i][:3, 3]) @ W[i][:3, :3])
        pa = np.array([kp[i][j] for j in ids]).reshape(-1, 2)
        pb = np.array([kp[i + 1][j] for j in ids]).reshape(-1, 2)
        if focal_error:
            Kc = cam.K * [[1 + focal_error], [1 + focal_error], [1]]
            Xa = triangulate(normalised_from_px(pa, Kc), normalised_from_px(pb, Kc), Rn, tn)
        A = np.column_stack([Xa[:, 0], Xa[:, 1], np.ones(len(ids))])
        plane, *_ = np.linalg.lstsq(A, Xa[:, 2], rcond=None)
        if focal_error:
            alpha = cam.height_m / camera_plane_distance(plane)
            Xa, tn, plane = alpha * Xa, alpha * tn, plane * [1, 1, alpha]
        pairs.append(
            PairResult(
                frame_a=f"{i:06d}.png",
                frame_b=f"{i + 1:06d}.png",
                index_a=i,
                index_b=i + 1,
                method="proposed",
                status="ok",
                points_cam_a_m=Xa,
                px_a=pa,
                px_b=pb,
                cov_m2=np.tile(np.eye(3) * 1e-8, (len(ids), 1, 1)),
                plane_dist_m=np.zeros(len(ids)),
                plane=plane,
                R_b_from_a=Rn,
                t_b_from_a_m=tn,
                n_matches=len(ids),
                n_inliers=len(ids),
                match_idx=np.arange(len(ids)),
            )
        )
        pair_ids.append(ids)
    # GPS: a fix stamped tg is where the camera was at tg - latency
    tg = np.arange(0.0, t[-1] + 1e-9, 1.0 / gps_hz)
    true_g = np.column_stack([np.interp(tg - gps_latency_s, tt, path[:, k]) for k in range(3)])
    meas = true_g + rng.normal(0, gps_sigma_m, true_g.shape)
    for j, (de, dn) in (gps_outliers or {}).items():
        meas[j, :2] += [de, dn]
    if focal_error:
        cam = dataclasses.replace(cam, fx=cam.fx * (1 + focal_error), fy=cam.fy * (1 + focal_error))
    drive = synthetic_drive(cam, t, gps_from_enu(tg, meas))
    return TrackDrive(drive, pairs, W, pts, pair_ids)


def _keypoints(
    cam,  # type: ignore[no-untyped-def]
    pts: np.ndarray,
    W: np.ndarray,
    t: float,
    tt: np.ndarray,
    path: np.ndarray,
    k1: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(P, 2) true pixels and (P, 3) camera points of the road points in the frame at time t
    with pose W. With a rolling shutter each point is seen from the true path (dense times tt,
    rows east, north, up, heading deg, roll, pitch rad) at its row's time: the row's fixed
    point, a few plain iterations (the readout's motion is a fraction of the footprint)."""
    v = np.zeros(len(pts))
    for _ in range(6 if cam.readout_s > 0 else 1):
        if cam.readout_s > 0:
            tq = t + cam.readout_s * v / cam.height
            q = np.column_stack([np.interp(tq, tt, path[:, k]) for k in range(6)])
            # world_from_cam: heading (compass, clockwise) about world up, then pitch, roll
            Rq = (
                Rotation.from_rotvec(np.outer(-np.radians(q[:, 3]), [0, 0, 1.0]))
                * Rotation.from_matrix(world_from_cam(0.0)[:3, :3])
                * Rotation.from_euler("xyz", np.column_stack([q[:, 5], q[:, 4], 0 * tq]))
            ).as_matrix()
            Xc = np.einsum("pji,pj->pi", Rq, pts - q[:, :3])
        else:
            Xc = (pts - W[:3, 3]) @ W[:3, :3]
        xn = Xc[:, :2] / Xc[:, 2:3]
        r2 = np.sum(xn**2, axis=1)
        xn = xn * (1.0 + k1 * r2)[:, None]
        uv = xn * [cam.fx, cam.fy] + [cam.cx, cam.cy]
        # beyond the radius where r (1 + k1 r²) turns back (k1 < 0), far points fold into view
        uv[1.0 + 3.0 * k1 * r2 <= 0.0] = -1.0
        v = np.clip(uv[:, 1], 0, cam.height)
    return uv, Xc


def gps_from_enu(tg: np.ndarray, meas_enu: np.ndarray) -> GpsTrack:
    """A GPS track of fixes at times tg (N,) s and ENU positions (N, 3) m (no HDOP)."""
    lla = lla_from_enu(meas_enu, REF)
    return GpsTrack(
        timestamp_s=tg, lat_deg=lla[:, 0], lon_deg=lla[:, 1], alt_m=lla[:, 2],
        hdop=np.full(len(tg), np.nan),
    )  # fmt: skip


def synthetic_drive(cam, t: np.ndarray, gps: GpsTrack) -> Drive:  # type: ignore[no-untyped-def]
    """A Drive of frames at times t (N,) s with no image files (the pairs are given)."""
    root = Path("/nonexistent-synthetic-drive")
    frames = [Frame(i, f"{i:06d}.png", root / f"{i:06d}.png", float(t[i])) for i in range(len(t))]
    return Drive(root=root, camera=cam, frames=frames, gps=gps, obd=None)


def recorded_window(seed: int, readout_s: float):  # type: ignore[no-untyped-def]
    """The last bundle window (a ``mapping.bundle_problem.WindowProblem``) that
    ``poses.estimate_trajectory`` builds on a seeded 12-frame track drive with every factor on
    (reprojection, road plane, camera height, GPS, the pairs' motions, focal and k1), one window
    for the whole drive; ``readout_s`` > 0: a rolling shutter."""
    import pytest

    from roadsurf.mapping import bundle, poses
    from roadsurf.mapping.bundle_problem import WindowProblem
    from roadsurf.mapping.config import MappingConfig

    seen: list[WindowProblem] = []

    class Recording(WindowProblem):
        def __init__(self, d):  # type: ignore[no-untyped-def]
            super().__init__(d)
            seen.append(self)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(bundle, "WindowProblem", Recording)
        syn = make_track_drive(n=12, seed=seed, density_per_m2=30, readout_s=readout_s)
        cfg = MappingConfig(
            gps_sigma_m=0.02,
            bundle_max_time_offset_s=0.0,
            bundle_refine_focal=True,
            bundle_refine_k1=True,
            bundle_window_frames=13,
        )
        poses.estimate_trajectory(cfg, syn.drive, syn.pairs)
    if not seen:
        raise AssertionError("no bundle window was built")
    return seen[-1]
