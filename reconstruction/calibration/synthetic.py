"""Synthetic board images with known intrinsics, distortion and board poses (for tests and
benchmarks of the calibration).

Rendering is by inverse mapping: every output (sub-)pixel is undistorted to a ray, the ray meets
the board plane, and the board texture is sampled there; 3x3 supersampling anti-aliases.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from roadsurf.core.camera import RENDER_UNDISTORT_CRITERIA, Camera
from roadsurf.core.geometry import rotation_from_euler_xyz
from roadsurf.reconstruction.calibration.board import BoardSpec, board_texture

BACKGROUND = 110  # grey level around the board


@functools.lru_cache(maxsize=4)
def _rays(camera: Camera, supersample: int) -> np.ndarray:
    """(H*ss, W*ss, 2) normalised rays of the sub-pixel sample points of a raw image."""
    ss = supersample
    off = (np.arange(ss) + 0.5) / ss - 0.5
    u = (np.arange(camera.width)[:, None] + off[None, :]).ravel()
    v = (np.arange(camera.height)[:, None] + off[None, :]).ravel()
    U, V = np.meshgrid(u, v)
    px = np.column_stack([U.ravel(), V.ravel()])
    n = camera.normalised_from_raw_px(px, criteria=RENDER_UNDISTORT_CRITERIA)
    return n.reshape(len(v), len(u), 2)


@functools.lru_cache(maxsize=4)
def _texture(spec: BoardSpec, px_per_square: int) -> tuple[np.ndarray, float, float]:
    return board_texture(spec, px_per_square)


def render_board(
    camera: Camera,
    spec: BoardSpec,
    cam_from_board: np.ndarray,
    supersample: int = 3,
    blur_sigma_px: float = 0.0,
    noise_grey: float = 0.0,
    seed: int = 0,
    px_per_square: int = 120,
) -> np.ndarray:
    """uint8 (H, W) image of the board seen by ``camera`` with the (4, 4) board-to-camera pose
    (metres); optional Gaussian blur (px) and seeded grey-level noise."""
    ss = int(supersample)
    rays = _rays(camera, ss)
    tex, x0, y0 = _texture(spec, int(px_per_square))
    R, t = cam_from_board[:3, :3], cam_from_board[:3, 3]
    c_b = -R.T @ t  # camera centre in the board frame
    d = np.concatenate([rays, np.ones(rays.shape[:2] + (1,))], axis=2) @ R  # rays, board frame
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -c_b[2] / d[..., 2]
    ok = np.isfinite(lam) & (lam > 0)
    scale = px_per_square / spec.square_m
    mx = np.where(ok, (c_b[0] + lam * d[..., 0] - x0) * scale - 0.5, -1e6).astype(np.float32)
    my = np.where(ok, (c_b[1] + lam * d[..., 1] - y0) * scale - 0.5, -1e6).astype(np.float32)
    hi = cv2.remap(
        tex.astype(np.float32),
        mx,
        my,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float(BACKGROUND),
    )
    img = hi.reshape(camera.height, ss, camera.width, ss).mean(axis=(1, 3))
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    if noise_grey > 0:
        img = img + np.random.default_rng(seed).normal(0.0, noise_grey, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _inside(camera: Camera, spec: BoardSpec, T: np.ndarray, margin_px: float) -> bool:
    x0, y0, x1, y1 = spec.outline_m()
    s = spec.square_m
    xs, ys = np.linspace(x0 - s, x1 + s, 12), np.linspace(y0 - s, y1 + s, 12)
    edge = [(x, y) for x in xs for y in (ys[0], ys[-1])] + [
        (x, y) for y in ys for x in (xs[0], xs[-1])
    ]
    g = np.array([(x, y, 0.0) for x, y in edge])
    X = g @ T[:3, :3].T + T[:3, 3]
    if np.any(X[:, 2] <= 0.05):
        return False
    u, v = camera.project(X)
    return bool(
        np.all((u > margin_px) & (u < camera.width - 1 - margin_px))
        and np.all((v > margin_px) & (v < camera.height - 1 - margin_px))
    )


def calibration_poses(
    camera: Camera, spec: BoardSpec, n: int = 15, seed: int = 0, fill: float = 0.55
) -> list[np.ndarray]:
    """``n`` (4, 4) board-to-camera poses: the board tilted 10-40° about varied axes, spread
    over the image (a 3x3 grid of aim points, centre first), filling about ``fill`` of the
    image width; each whole board (with its margin) inside the image."""
    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = spec.outline_m()
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    dist = camera.fx * (x1 - x0) / (fill * camera.width)
    aims = [(0.5, 0.5), (0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)]
    aims += [(0.5, 0.25), (0.5, 0.75), (0.25, 0.5), (0.75, 0.5)]
    poses: list[np.ndarray] = []
    tries = 0
    while len(poses) < n:
        tries += 1
        if tries > 2000 * n:
            raise RuntimeError("could not place the board inside the image; lower `fill`")
        au, av = aims[len(poses) % len(aims)]
        u = camera.width * (au + rng.uniform(-0.08, 0.08))
        v = camera.height * (av + rng.uniform(-0.08, 0.08))
        tilt = math.radians(rng.uniform(10.0, 40.0))
        axis = rng.uniform(0.0, 2 * math.pi)
        R = rotation_from_euler_xyz(
            tilt * math.cos(axis), tilt * math.sin(axis), math.radians(rng.uniform(-20, 20))
        )
        ray = np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = ray / np.linalg.norm(ray) * dist * rng.uniform(0.9, 1.15) - R @ centre
        if _inside(camera, spec, T, 3.0):
            poses.append(T)
    return poses


def ground_pose(
    spec: BoardSpec,
    height_m: float,
    pitch_deg: float,
    roll_deg: float = 0.0,
    yaw_deg: float = 0.0,
) -> np.ndarray:
    """(4, 4) board-to-camera pose of a board lying flat on the road, its x axis to the
    vehicle's right and y axis backward (z into the road), seen by a camera ``height_m`` above
    the board with the mount angles of ``mount.rotation_vehicle_from_cam``; the optical axis
    meets the road at the board's centre."""
    R_vc = rotation_from_euler_xyz(
        math.radians(pitch_deg), math.radians(roll_deg), math.radians(yaw_deg)
    )
    x0, y0, x1, y1 = spec.outline_m()
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    axis = R_vc[:, 2]  # optical axis in the vehicle (= board) frame, z down
    c = centre - axis * (height_m / axis[2])
    T = np.eye(4)
    T[:3, :3] = R_vc.T
    T[:3, 3] = -R_vc.T @ c
    return T
