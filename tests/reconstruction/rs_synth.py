"""Seeded synthetic matches of a moving camera over a bumpy road, with an optional rolling
shutter and turns (no images).

The vehicle drives at constant speed from (0, 0) with grid heading ``heading0_deg``, turning at
a constant rate (``yaw_rate_dps``; 0 = straight) and sliding sideways (``lateral_mps``, a lane
change); the camera sits ``CAM_H`` above the road on ``mount``. Camera poses are built like the
pipeline's: vehicle pose (``core.geometry.world_from_cam``) times the mount. With a rolling
shutter, each point's row time τ solves τ = readout · v(pose(t + τ)) / height (fixed point)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from roadsurf.core.camera import Camera, normalised_from_px, px_from_cam
from roadsurf.core.geometry import vehicle_from_cam_rotation
from roadsurf.reconstruction import geometry as g

W, H_PX, F_PX, CAM_H = 640, 480, 600.0, 1.1  # image (px), focal length (px), height (m)
# (forward, right, amplitude m, sigma m) of the bumps (+) and dips (-), relative to camera a's
# ground point and heading; the dips are pothole-like, all in the overlap that a 10 ms
# readout leaves at 25 m/s and 60 fps (0.23-0.44 m ahead)
BUMPS = ((0.34, 0.15, -0.04, 0.05), (0.32, -0.3, -0.025, 0.04), (0.15, 0.35, 0.015, 0.05))
FLAT_M = 1e-5  # points with less relief than this are the flat part (m)


@dataclass
class Pair:
    camera: Camera
    px_a: np.ndarray  # (N, 2) observed pixels (noisy; rolling-shutter rows if readout_s > 0)
    px_b: np.ndarray  # (N, 2) ... in b (mismatches where ``bad``)
    bad: np.ndarray  # (N,) bool: a random pixel (a mismatch)
    relief_m: np.ndarray  # (N,) true height above the road plane (m)
    R_b_from_a: np.ndarray  # true relative pose at the frames' timestamps (row 0)
    t_b_from_a_m: np.ndarray
    up_cam_a: np.ndarray  # (3,) the road's up normal in camera a
    frame_dt_s: float
    X_cam_a: np.ndarray  # (N, 3) true points in camera a at its timestamp (m)


def rotation_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def make_pair(
    *,
    speed_mps: float = 25.0,
    fps: float = 60.0,
    readout_s: float = 0.0,
    yaw_rate_dps: float = 0.0,
    lateral_mps: float = 0.0,
    mount: tuple[float, float, float] = (0.0, 0.0, 0.0),
    mount_known: bool = False,
    roll_rate_dps: float = 0.0,
    pitch_rate_dps: float = 0.0,
    heading0_deg: float = 20.0,
    seed: int = 0,
    n: int = 600,
    noise_px: float = 0.3,
    bad_share: float = 0.1,
) -> Pair:
    rng = np.random.default_rng(seed)
    dt = 1.0 / fps
    cam = Camera(W, H_PX, F_PX, F_PX, (W - 1) / 2, (H_PX - 1) / 2, CAM_H, fps, readout_s=readout_s)
    if mount_known:
        cam = replace(cam, mount_deg=mount)
    M = np.eye(4)
    M[:3, :3] = vehicle_from_cam_rotation(*mount)
    w_yaw = math.radians(yaw_rate_dps)

    def pose(tt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3, 3) world_from_cam rotations and (N, 3) centres at times tt (N,): vectorised
        ``world_from_cam(heading, roll, pitch, C) @ mount``."""
        tt = np.atleast_1d(np.asarray(tt, float))
        h0 = math.radians(heading0_deg)
        hd = h0 + w_yaw * tt
        if abs(w_yaw) > 1e-12:  # along the arc of a constant-rate turn
            r = speed_mps / w_yaw
            e, nn = r * (math.cos(h0) - np.cos(hd)), r * (np.sin(hd) - math.sin(h0))
        else:
            e, nn = speed_mps * tt * math.sin(h0), speed_mps * tt * math.cos(h0)
        e = e + lateral_mps * tt * np.cos(hd)  # sideways (right of travel)
        nn = nn - lateral_mps * tt * np.sin(hd)
        fwd = np.stack([np.sin(hd), np.cos(hd), 0 * hd], 1)
        rgt = np.stack([np.cos(hd), -np.sin(hd), 0 * hd], 1)
        dn = np.broadcast_to([0.0, 0.0, -1.0], fwd.shape)
        Rv = np.stack([rgt, -fwd, dn], 2)  # core.geometry.world_from_vehicle_rotation
        roll, pitch = math.radians(roll_rate_dps) * tt, math.radians(pitch_rate_dps) * tt
        Rrp = Rotation.from_euler("ZYX", np.stack([0 * tt, roll, pitch], 1)).as_matrix()
        C = np.stack([e, nn, np.full_like(tt, CAM_H)], 1)
        return Rv @ Rrp @ M[:3, :3], C

    def observe(Xw: np.ndarray, t0: float) -> tuple[np.ndarray, np.ndarray]:
        """Pixels of world points in the frame stamped t0 (row times solved) and their τ."""
        tau = np.zeros(len(Xw))
        for _ in range(40 if readout_s > 0 else 1):
            R, C = pose(t0 + tau)
            Xc = np.einsum("nji,nj->ni", R, Xw - C)
            px = px_from_cam(Xc, cam.K)
            tau = readout_s * np.clip(px[:, 1], -H_PX, 2 * H_PX) / H_PX
        return px, tau

    (Ra, Ca), (Rb, Cb) = pose(0.0), pose(dt)
    Ta, Tb = np.eye(4), np.eye(4)
    Ta[:3, :3], Ta[:3, 3], Tb[:3, :3], Tb[:3, 3] = Ra[0], Ca[0], Rb[0], Cb[0]
    h0 = math.radians(heading0_deg)
    fwd, right = np.array([math.sin(h0), math.cos(h0)]), np.array([math.cos(h0), -math.sin(h0)])
    ground0 = Ta[:2, 3]

    def relief(xy: np.ndarray) -> np.ndarray:
        d = xy - ground0
        f, r = d @ fwd, d @ right
        z = np.zeros(len(xy))
        for f0, r0, amp, s in BUMPS:
            z += amp * np.exp(-((f - f0) ** 2 + (r - r0) ** 2) / (2 * s * s))
        return np.where(np.abs(z) < FLAT_M, 0.0, z)

    # Road points cast from pixels of camera a (global-shutter rays: only the sampling).
    px = rng.uniform([0, 0], [W - 1, H_PX - 1], (3 * n, 2))
    ray = np.column_stack([normalised_from_px(px, cam.K), np.ones(len(px))]) @ Ta[:3, :3].T
    ok = ray[:, 2] < -0.05
    s = -Ta[2, 3] / ray[ok, 2]
    Xw = Ta[:3, 3] + s[:, None] * ray[ok]
    Xw[:, 2] = relief(Xw[:, :2])
    pa, _ = observe(Xw, 0.0)
    pb, _ = observe(Xw, dt)
    inside = np.all((pa >= 0) & (pa <= [W - 1, H_PX - 1]), axis=1)
    inside &= np.all((pb >= 0) & (pb <= [W - 1, H_PX - 1]), axis=1)
    Xw, pa, pb = Xw[inside][:n], pa[inside][:n], pb[inside][:n]
    m = len(Xw)
    pa = pa + rng.normal(0, noise_px, pa.shape)
    pb = pb + rng.normal(0, noise_px, pb.shape)
    bad = np.zeros(m, bool)
    bad[rng.choice(m, int(bad_share * m), replace=False)] = True
    pb[bad] = rng.uniform([0, 0], [W - 1, H_PX - 1], (int(bad.sum()), 2))
    R = Tb[:3, :3].T @ Ta[:3, :3]
    t = Tb[:3, :3].T @ (Ta[:3, 3] - Tb[:3, 3])
    Xa = (Xw - Ta[:3, 3]) @ Ta[:3, :3]
    up = Ta[:3, :3].T @ np.array([0, 0, 1.0])
    return Pair(cam, pa, pb, bad, Xw[:, 2], R, t, up, dt, Xa)


def heights(pair: Pair, res) -> np.ndarray:  # noqa: ANN001 - a PairResult
    """Estimated height above the road of the result's points (m; plane_dist_m's sign: + up)."""
    return res.plane_dist_m


def oracle_heights(pair: Pair, px_a: np.ndarray, px_b: np.ndarray) -> np.ndarray:
    """Heights above the true road of matches triangulated with the TRUE pose (global shutter):
    the pixel noise's share."""
    K = pair.camera.K
    X = g.triangulate(normalised_from_px(px_a, K), normalised_from_px(px_b, K),
                      pair.R_b_from_a, pair.t_b_from_a_m)  # fmt: skip
    return CAM_H + X @ pair.up_cam_a
