"""Seeded synthetic drives for the mapping tests: known poses -> GPS fixes and PairResults.

The road is the ENU plane z = road_z(x, y) (flat unless a bump function is given); the camera
rides ``height_m`` above it looking down, on a gently curving path.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.geometry import (
    EnuReference,
    invert_pose,
    lla_from_enu,
    vehicle_from_cam_rotation,
    world_from_cam,
)
from roadsurf.io.drive import Drive, Frame, GpsTrack, ObdLog
from roadsurf.mapping.types import Trajectory
from roadsurf.reconstruction.types import PairResult

REF = EnuReference(43.6532, -79.3832, 100.0)  # Toronto: UTM 17N, EPSG:32617


@dataclass
class Synthetic:
    drive: Drive
    pairs: list[PairResult]
    world_from_cam: np.ndarray  # (N, 4, 4) true poses (ENU)
    ref: EnuReference
    gps_enu_true: np.ndarray  # (G, 3) true camera centres at fix times


def true_poses(
    n: int,
    fps: float,
    speed_mps: float,
    height_m: float,
    rng: np.random.Generator,
    curvature_per_m: float = 0.01,
    tilt_deg: float = 0.3,
    mount_deg: tuple[float, float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    M = np.eye(4)
    if mount_deg is not None:  # the camera on a tilted mount: world_from_vehicle @ mount
        M[:3, :3] = vehicle_from_cam_rotation(*mount_deg)
    t = np.arange(n) / fps
    s = speed_mps * t
    heading = 30.0 + np.degrees(curvature_per_m * s) * np.sin(s / 15.0)  # gentle S-curve
    W = np.empty((n, 4, 4))
    pos = np.zeros(3)
    for i in range(n):
        if i:
            ds = s[i] - s[i - 1]
            b = np.radians(0.5 * (heading[i] + heading[i - 1]))
            pos = pos + ds * np.array([np.sin(b), np.cos(b), 0.0])
        roll, pitch = np.radians(rng.normal(0, tilt_deg, 2))
        W[i] = world_from_cam(heading[i], roll, pitch, pos + [0, 0, height_m]) @ M
    return t, W


def camera(width: int = 160, height: int = 120, height_m: float = 1.0, fps: float = 20.0) -> Camera:
    f = 0.9 * width
    return Camera(width, height, f, f, width / 2 - 0.5, height / 2 - 0.5, height_m, fps)


def make_pair(
    i: int,
    Wa: np.ndarray,
    Wb: np.ndarray,
    cam: Camera,
    rng: np.random.Generator,
    rot_noise_deg: float = 0.02,
    trans_noise_m: float = 0.001,
    n_pts: int = 200,
    road_z: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    px_margin: float | None = None,
) -> PairResult:
    """An ok PairResult a=i -> b=i+1 with noisy relative pose and road points seen by both.

    With ``px_margin`` (px), the points are only those at least that far inside BOTH images, like
    matches that stop short of the image borders (then fewer than ``n_pts`` may remain)."""
    T = invert_pose(Wb) @ Wa  # cam_b_from_cam_a
    dR = _small_rot(rng.normal(0, np.radians(rot_noise_deg), 3))
    T_noisy = T.copy()
    T_noisy[:3, :3] = dR @ T[:3, :3]
    T_noisy[:3, 3] += rng.normal(0, trans_noise_m, 3)
    # road points: sample pixels of image a, intersect rays with the road
    m = 0.0 if px_margin is None else float(px_margin)
    u = rng.uniform(m, cam.width - 1 - m, n_pts)
    v = rng.uniform(m, cam.height - 1 - m, n_pts)
    rays = np.column_stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones(n_pts)])
    rays_w = rays @ Wa[:3, :3].T
    c = Wa[:3, 3]
    lam = -c[2] / rays_w[:, 2]  # flat road z = 0 first
    pts_w = c + lam[:, None] * rays_w
    if road_z is not None:
        for _ in range(3):  # refine intersection with the bumpy road
            z = road_z(pts_w[:, 0], pts_w[:, 1])
            lam = (z - c[2]) / rays_w[:, 2]
            pts_w = c + lam[:, None] * rays_w
    pts_a = (pts_w - Wa[:3, 3]) @ Wa[:3, :3]
    pts_b = pts_a @ T[:3, :3].T + T[:3, 3]
    px_a = np.column_stack([u, v])
    px_b = np.column_stack(
        [cam.fx * pts_b[:, 0] / pts_b[:, 2] + cam.cx, cam.fy * pts_b[:, 1] / pts_b[:, 2] + cam.cy]
    )
    if px_margin is not None:  # seen by image b too, as far inside its borders
        lo, hi = np.array([m, m]), np.array([cam.width - 1 - m, cam.height - 1 - m])
        keep = np.all((px_b >= lo) & (px_b <= hi), axis=1)
        pts_a, pts_b, px_a, px_b = pts_a[keep], pts_b[keep], px_a[keep], px_b[keep]
        n_pts = int(keep.sum())
    A = np.column_stack([pts_a[:, 0], pts_a[:, 1], np.ones(n_pts)])
    plane, *_ = np.linalg.lstsq(A, pts_a[:, 2], rcond=None)
    d = (plane[0] * pts_a[:, 0] + plane[1] * pts_a[:, 1] - pts_a[:, 2] + plane[2]) / np.sqrt(
        plane[0] ** 2 + plane[1] ** 2 + 1
    )
    return PairResult(
        frame_a=f"{i:06d}.png",
        frame_b=f"{i + 1:06d}.png",
        index_a=i,
        index_b=i + 1,
        method="proposed",
        status="ok",
        points_cam_a_m=pts_a,
        px_a=px_a,
        px_b=px_b,
        cov_m2=np.tile(np.eye(3) * 1e-8, (n_pts, 1, 1)),
        plane_dist_m=-np.abs(d) * 0 + d,
        plane=plane,
        R_b_from_a=T_noisy[:3, :3],
        t_b_from_a_m=T_noisy[:3, 3],
        n_matches=n_pts,
        n_inliers=n_pts,
    )


def failed_pair(i: int, reason: str = "too_few_matches") -> PairResult:
    return PairResult(
        frame_a=f"{i:06d}.png",
        frame_b=f"{i + 1:06d}.png",
        index_a=i,
        index_b=i + 1,
        method="proposed",
        status=reason,
        reason="synthetic failure",
    )


def _small_rot(w: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(w).as_matrix()


def make_synthetic(
    n: int = 60,
    seed: int = 0,
    fps: float = 20.0,
    speed_mps: float = 5.0,
    gps_hz: float = 1.0,
    gps_sigma_m: float = 0.02,
    gps_time_offset_s: float = 0.37,
    gps_gap_s: tuple[float, float] | None = None,
    gps_margin_s: float = 0.0,
    gps_outliers: dict[int, tuple[float, float]] | None = None,
    with_gps: bool = True,
    hdop: float | None = None,
    failed: tuple[int, ...] = (),
    with_obd: bool = False,
    root: Path | None = None,
    road_z: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    mount_deg: tuple[float, float, float] | None = None,
    mount_in_camera: bool = False,
    gps_antenna_m: tuple[float, float, float] | None = None,
) -> Synthetic:
    """mount_deg: the camera's true mount (pitch, roll, yaw) degrees (None = nadir);
    mount_in_camera: also give it in the Camera (as camera.yaml would); gps_antenna_m: the
    fixes are those of an antenna at [forward, left, up] m from the camera (given in the Camera,
    as camera.yaml would)."""
    rng = np.random.default_rng(seed)
    cam = camera(fps=fps)
    if mount_deg is not None and mount_in_camera:
        cam = replace(cam, mount_deg=mount_deg)
    if gps_antenna_m is not None:
        cam = replace(cam, gps_antenna_m=gps_antenna_m)
    t, W = true_poses(n, fps, speed_mps, cam.height_m, rng, mount_deg=mount_deg)
    root = root or Path("/nonexistent-synthetic-drive")
    frames = [
        Frame(i, f"{i:06d}.png", root / "frames" / f"{i:06d}.png", float(t[i])) for i in range(n)
    ]
    pairs = [
        failed_pair(i) if i in failed else make_pair(i, W[i], W[i + 1], cam, rng, road_z=road_z)
        for i in range(n - 1)
    ]
    gps = None
    g_true = np.zeros((0, 3))
    if with_gps:
        tg = np.arange(gps_time_offset_s - 1.0, t[-1] + 1.0, 1.0 / gps_hz)
        tg = tg[(tg >= t[0] - gps_margin_s) & (tg <= t[-1] + gps_margin_s)]
        if gps_gap_s is not None:
            tg = tg[(tg < gps_gap_s[0]) | (tg > gps_gap_s[1])]
        # true camera centre at fix time: interpolate the true path (dense frames, tiny error)
        # (outside the frames: extrapolated at the end frames' velocity, i.e. constant speed)
        g_true = np.column_stack([_interp_extrap(tg, t, W[:, j, 3]) for j in range(3)])
        ant = g_true
        if gps_antenna_m is not None:
            from roadsurf.core.geometry import vehicle_from_cam_rotation, vehicle_from_flu

            R_vc = vehicle_from_cam_rotation(*(mount_deg or (0.0, 0.0, 0.0)))
            near = np.clip(np.searchsorted(t, tg), 0, n - 1)  # the frame at or after each fix
            R_wv = W[near, :3, :3] @ R_vc.T
            ant = g_true + R_wv @ vehicle_from_flu(gps_antenna_m)
        meas = ant + rng.normal(0, gps_sigma_m, g_true.shape) * [1, 1, 1.5]
        for k, (de, dn) in (gps_outliers or {}).items():
            meas[k, :2] += [de, dn]
        lla = lla_from_enu(meas, REF)
        gps = GpsTrack(
            timestamp_s=tg,
            lat_deg=lla[:, 0],
            lon_deg=lla[:, 1],
            alt_m=lla[:, 2],
            hdop=np.full(len(tg), np.nan if hdop is None else hdop),
        )
    obd = None
    if with_obd:
        obd = ObdLog(timestamp_s=t.copy(), speed_mps=np.full(n, speed_mps) + rng.normal(0, 0.05, n))
    drive = Drive(root=root, camera=cam, frames=frames, gps=gps, obd=obd)
    return Synthetic(drive, pairs, W, REF, g_true)


def true_trajectory(syn: Synthetic, reference: EnuReference | None = None) -> Trajectory:
    """The synthetic drive's true poses as a trajectory (``reference``: its GPS origin, None =
    a local frame); any drive with ``.drive`` and ``.world_from_cam`` will do."""
    n = len(syn.drive.frames)
    return Trajectory(
        filenames=[f.filename for f in syn.drive.frames],
        frame_indices=np.arange(n),
        timestamp_s=np.array([f.timestamp_s for f in syn.drive.frames]),
        world_from_cam=syn.world_from_cam,
        source=["fused"] * n,
        reference=reference,
    )


def _interp_extrap(tq: np.ndarray, t: np.ndarray, v: np.ndarray) -> np.ndarray:
    out = np.interp(tq, t, v)
    lo, hi = tq < t[0], tq > t[-1]
    out[lo] = v[0] + (v[1] - v[0]) / (t[1] - t[0]) * (tq[lo] - t[0])
    out[hi] = v[-1] + (v[-1] - v[-2]) / (t[-1] - t[-2]) * (tq[hi] - t[-1])
    return out


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Procedural asphalt-like RGB texture of ENU coordinates (metres) -> (..., 3) uint8."""
    v = (
        0.5
        + 0.18 * np.sin(x * 37.0) * np.cos(y * 23.0)
        + 0.12 * np.sin(x * 91.0 + y * 57.0)
        + 0.1 * np.sign(np.sin(x * 7.0 + 1.3)) * np.sign(np.sin(y * 5.0))
    )
    v = np.clip(v, 0.02, 0.98)
    return np.stack([v * 230, v * 220, v * 200], axis=-1).astype(np.uint8)


def write_images(syn: Synthetic, root: Path, broken: tuple[int, ...] = ()) -> Synthetic:
    """Render every frame (flat road z = 0, procedural texture) as PNG under root/frames; frames
    in ``broken`` get a truncated file. Returns a Synthetic whose frames point there."""
    import cv2

    cam = syn.drive.camera
    (root / "frames").mkdir(parents=True, exist_ok=True)
    u, v = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)
    frames = []
    for f, W in zip(syn.drive.frames, syn.world_from_cam, strict=True):
        rw = rays @ W[:3, :3].T
        lam = -W[2, 3] / rw[..., 2]
        p = W[:3, 3] + lam[..., None] * rw
        img = texture(p[..., 0], p[..., 1])
        path = root / "frames" / f.filename
        cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        if f.index in broken:
            path.write_bytes(path.read_bytes()[:60])
        frames.append(Frame(f.index, f.filename, path, f.timestamp_s))
    syn.drive.frames = frames
    syn.drive.root = root
    return syn


def write_drive(syn: Synthetic, root: Path, broken: tuple[int, ...] = ()) -> Path:
    """Write a complete drive folder (camera.yaml, frames/, frames.csv, gps.csv) for load_drive."""
    import yaml

    write_images(syn, root, broken=broken)
    cam = syn.drive.camera
    (root / "camera.yaml").write_text(
        yaml.safe_dump(
            {
                "model": "pinhole",
                "width": cam.width,
                "height": cam.height,
                "fx": cam.fx,
                "fy": cam.fy,
                "cx": cam.cx,
                "cy": cam.cy,
                "height_m": cam.height_m,
                "fps": cam.fps,
            }
        )
    )
    lines = ["filename,timestamp_s"] + [f"{f.filename},{f.timestamp_s!r}" for f in syn.drive.frames]
    (root / "frames.csv").write_text("\n".join(lines) + "\n")
    g = syn.drive.gps
    if g is not None:
        rows = ["timestamp_s,lat,lon,alt_m"] + [
            f"{t!r},{la:.10f},{lo:.10f},{al:.4f}"
            for t, la, lo, al in zip(g.timestamp_s, g.lat_deg, g.lon_deg, g.alt_m, strict=True)
        ]
        (root / "gps.csv").write_text("\n".join(rows) + "\n")
    return root
