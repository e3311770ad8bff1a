"""The one camera model: pinhole intrinsics with OpenCV (Brown-Conrady) distortion.

Every stage projects, unprojects, distorts and casts footprints through this module. Pixel
coordinates have their origin at the centre of the top-left pixel (OpenCV convention); "ideal"
pixels are undistorted pinhole pixels, "raw" pixels are those of the recorded image. Metres and
radians throughout; ``world_from_cam`` is a (4, 4) pose in the local ENU frame (z up).

Several operations come in two numerical flavours that the pipeline has always used side by
side (OpenCV's routines and closed-form numpy); both are kept, named, so that results stay
bit-for-bit reproducible. They agree to ~1e-12 px.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import cv2
import numpy as np

from roadsurf.core.geometry import check_shape, vehicle_from_cam_rotation
from roadsurf.core.imagemask import ImageMask

# cv2.undistortPoints stopping rule of the simulator (renders): 30 iterations or 1e-9. The
# pipeline uses OpenCV's default (5 iterations), which is finer than the features' noise.
RENDER_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-9)


@dataclass(frozen=True)
class Camera:
    """Pinhole camera with OpenCV distortion. Pixels (px), metres (m)."""

    width: int  # image width (px)
    height: int  # image height (px)
    fx: float  # focal length x (px)
    fy: float  # focal length y (px)
    cx: float  # principal point x (px)
    cy: float  # principal point y (px)
    height_m: float  # nominal camera height above the road, h (m)
    fps: float  # frame rate (Hz)
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)  # k1,k2,p1,p2,k3
    model: str = "pinhole"
    # mount angles (deg): pitch forward from nadir, roll, yaw (core.geometry
    # .vehicle_from_cam_rotation); from camera.yaml / `roadsurf calibrate --ground`, or
    # estimated from the drive's road normals; None = not known (nadir assumed)
    mount_deg: tuple[float, float, float] | None = None
    # rolling-shutter readout time (s): the time the sensor takes to read its `height` rows,
    # row v (raw pixel, 0 = top) exposed readout_s * v / height after the frame's timestamp
    # (docs/reconstruction.md, "Rolling shutter"); 0 = global shutter
    readout_s: float = 0.0
    # pixels that never show the road (a burned-in stamp, the bonnet; camera.yaml 'mask',
    # core.imagemask); None = every pixel may be used
    mask: ImageMask | None = None
    # the GNSS antenna relative to the camera centre in the vehicle frame: [forward, left, up]
    # (m; camera.yaml 'gps_antenna_m', mapping.antenna); None = at the camera centre
    gps_antenna_m: tuple[float, float, float] | None = None

    def fingerprint_fields(self) -> dict[str, Any]:
        """The fields as stage fingerprints take them: the mask by its digest, and no 'mask'
        key at all without one (fingerprints of unmasked cameras are those of before); not the
        GPS antenna."""
        # the antenna moves no pixel: the poses' fingerprint takes it (mapping.poses)
        skip = ("mask", "gps_antenna_m")
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in skip}
        if self.mask is not None:
            d["mask"] = self.mask.digest
        return d

    def usable_px(self, px_raw: np.ndarray, margin_px: float | np.ndarray = 0.0) -> np.ndarray:
        """(N,) bool: raw pixels (N, 2) not within ``margin_px`` of the mask (all True without
        one; ``ImageMask.usable_at``)."""
        px = np.asarray(px_raw, float).reshape(-1, 2)
        if self.mask is None:
            return np.ones(len(px), bool)
        return self.mask.usable_at(px, margin_px)

    @property
    def vehicle_from_cam(self) -> np.ndarray:
        """(3, 3) R_vehicle_from_cam of the mount; identity (the nadir camera) when unknown."""
        if self.mount_deg is None:
            return np.eye(3)
        return vehicle_from_cam_rotation(*self.mount_deg)

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0 for d in self.dist)

    @property
    def dist_array(self) -> np.ndarray:
        """(5,) k1, k2, p1, p2, k3 as float64 (OpenCV's order)."""
        return np.asarray(self.dist, float)

    def ground_px_m(self) -> float:
        """Nominal ground sample distance at the image centre (m/px): h / fx for a nadir camera,
        larger for a tilted mount (``ground_px_m_at``)."""
        if self.mount_deg is None or not any(self.mount_deg):
            return self.height_m / self.fx
        return float(self.ground_px_m_at(np.array([[self.cx, self.cy]]))[0])

    def ground_px_m_at(self, px_ideal: np.ndarray) -> np.ndarray:
        """(N,) ground sample distance (m/px, square root of a pixel's area on the road) at
        ideal pixels (N, 2), for a level vehicle over a flat road at ``height_m``; NaN where
        the ray misses the road. Area = t² / (fx fy d_z), with t the ray's z-depth and d_z the
        vehicle-down component of the ray (x/z, y/z, 1)."""
        px = check_shape("px_ideal", np.asarray(px_ideal, float), (None, 2))
        d = np.column_stack([self.normalised_from_px(px), np.ones(len(px))])
        dz = d @ self.vehicle_from_cam[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(dz > 1e-9, self.height_m / dz, np.nan)
            return t / np.sqrt(self.fx * self.fy * dz)

    # ------------------------------------------------------------------ (un)projection
    def normalised_from_px(self, px_ideal: np.ndarray) -> np.ndarray:
        """(N, 2) ideal pixels -> (N, 2) normalised image coordinates x/z, y/z."""
        return normalised_from_px(px_ideal, self.K)

    def undistort_px(self, px_raw: np.ndarray) -> np.ndarray:
        """(N, 2) raw pixels -> (N, 2) float64 ideal pixels (identity without distortion).

        OpenCV's iterative inverse with its default stopping rule (5 iterations)."""
        px = np.asarray(px_raw, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion or len(px) == 0:
            return px
        und = cv2.undistortPoints(px.reshape(-1, 1, 2), self.K, self.dist_array, P=self.K)
        return und.reshape(-1, 2)

    def normalised_from_raw_px(
        self, px_raw: np.ndarray, criteria: tuple[int, int, float] | None = None
    ) -> np.ndarray:
        """(N, 2) raw pixels -> (N, 2) normalised coordinates, undistorting when needed.

        ``criteria``: cv2.undistortPoints' stopping rule (None: OpenCV's default; the simulator
        passes ``RENDER_UNDISTORT_CRITERIA``)."""
        px = np.asarray(px_raw, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion:
            return np.column_stack([(px[:, 0] - self.cx) / self.fx, (px[:, 1] - self.cy) / self.fy])
        if criteria is None:
            und = cv2.undistortPoints(px.reshape(-1, 1, 2), self.K, self.dist_array)
        else:
            und = cv2.undistortPoints(
                px.reshape(-1, 1, 2), self.K, self.dist_array, criteria=criteria
            )
        return und.reshape(-1, 2)

    def distort_px(self, px_ideal: np.ndarray) -> np.ndarray:
        """(N, 2) ideal pixels -> (N, 2) raw pixels, by cv2.projectPoints (identity without
        distortion; an empty array passes through)."""
        if not self.has_distortion or len(px_ideal) == 0:
            return px_ideal
        n = normalised_from_px(px_ideal, self.K)
        pts = np.column_stack([n, np.ones(len(n))]).reshape(-1, 1, 3)
        out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist_array)
        return out.reshape(-1, 2)

    def project(self, X_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points (..., 3) -> raw (distorted) pixel u, v (...), closed form.

        Works on grids of any leading shape; Z <= 1e-6 (behind or on the camera) gives NaN."""
        Z = X_cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(Z > 1e-6, X_cam[..., 0] / Z, np.nan)
            y = np.where(Z > 1e-6, X_cam[..., 1] / Z, np.nan)
        if self.has_distortion:
            k1, k2, p1, p2, k3 = self.dist
            r2 = x * x + y * y
            rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            x, y = (
                x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
            )
        return self.fx * x + self.cx, self.fy * y + self.cy

    # ------------------------------------------------------------------ footprints
    def footprint_corners_enu(self, world_from_cam: np.ndarray) -> np.ndarray | None:
        """(4, 2) ENU east/north of the image's outer corners on the road, or None.

        The road is the horizontal plane ``height_m`` below the camera centre; the corners are
        the pixel edges (-0.5 .. w-0.5) cast as ideal rays (distortion ignored: used for
        coverage and frame labels). None when a corner ray does not point down."""
        T = check_shape("world_from_cam", np.asarray(world_from_cam, float), (4, 4))
        w, h = self.width, self.height
        uv = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
        rays = np.linalg.solve(self.K, np.column_stack([uv, np.ones(4)]).T)  # (3, 4)
        rays_w = T[:3, :3] @ rays
        c = T[:3, 3]
        if np.any(rays_w[2] >= -1e-9):
            return None
        s = -self.height_m / rays_w[2]
        pts = c[:, None] + rays_w * s
        return pts[:2].T.copy()

    def footprint_grid_enu(
        self, world_from_cam: np.ndarray, road_z: float, n: int = 5
    ) -> np.ndarray:
        """(<= n*n, 3) ENU points where an n x n grid of pixel centres meets the plane
        z = road_z, distortion included; rays that miss the plane are dropped."""
        W = world_from_cam
        u = np.linspace(0, self.width - 1, n)
        v = np.linspace(0, self.height - 1, n)
        U, V = np.meshgrid(u, v)
        px = np.column_stack([U.ravel(), V.ravel()]).astype(np.float64)
        und = self.normalised_from_raw_px(px)
        rays = np.column_stack([und, np.ones(len(und))]) @ W[:3, :3].T
        c = W[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (road_z - c[2]) / rays[:, 2]
        lam = np.where(np.isfinite(lam) & (lam > 0), lam, np.nan)
        pts = c + lam[:, None] * rays
        return pts[np.all(np.isfinite(pts), axis=1)]


def normalised_from_px(px: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 2) ideal pixels -> (N, 2) normalised image coordinates x/z, y/z, given K (3, 3)."""
    px = check_shape("px", px, (None, 2))
    return np.stack(
        [(px[:, 0] - K[0, 2]) / K[0, 0], (px[:, 1] - K[1, 2]) / K[1, 1]], axis=1
    ).astype(float)


def px_from_cam(X: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 3) camera-frame points -> (N, 2) ideal pixels, given K (3, 3); no distortion."""
    X = check_shape("X", X, (None, 3))
    z = X[:, 2]
    return np.stack([K[0, 0] * X[:, 0] / z + K[0, 2], K[1, 1] * X[:, 1] / z + K[1, 2]], axis=1)


def capped_scale(scale: float, width: int, height: int, max_megapixels: float) -> float:
    """The scale (unitless) to resize a width x height px image by: ``scale``, lowered so the
    result holds at most ``max_megapixels`` (Mpx; 0 = no cap). A lowering to 0.95 x the
    requested scale or more is not applied: a few per cent smaller is not worth a resampling
    blur (640 x 480 stays whole under a 0.3 Mpx cap)."""
    s = float(scale)
    if max_megapixels > 0 and width * height > 0:
        cap = float(np.sqrt(max_megapixels * 1e6 / (width * height)))
        if cap < 0.95 * s:
            s = cap
    return s
