"""Camera height and mount angles from one image of a board lying flat on the road.

Vehicle frame (that of a nadir camera, as everywhere in roadsurf): x to the vehicle's right,
y backward, z down into the road. Mount angles give the camera's rotation in it:

    R_vehicle_from_cam = Rz(yaw) @ Ry(roll) @ Rx(pitch)   (core.geometry.rotation_from_euler_xyz)

pitch > 0 tilts the optical axis forward from nadir, roll > 0 tilts it to the right, yaw > 0
turns it clockwise seen from above. All zero: the nadir camera of ``core.geometry.world_from_cam``
(image top = forward). The board's edges must be laid parallel to the vehicle's axes; which
way round it lies does not matter: of its four in-plane orientations the one with |yaw| <= 45°
is taken, so the yaw is the camera's turn relative to the board's edges.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from roadsurf.core.geometry import mount_angles_deg, vehicle_from_cam_rotation
from roadsurf.reconstruction.calibration.board import BoardSpec
from roadsurf.reconstruction.calibration.detect import detect_board
from roadsurf.reconstruction.calibration.errors import CalibrationError

MAX_GROUND_RMS_PX = 1.0  # a worse board fit means a bent board or wrong intrinsics


@dataclass(frozen=True)
class Mount:
    """Camera height above the road (m) and mount angles (degrees)."""

    height_m: float
    pitch_deg: float
    roll_deg: float
    yaw_deg: float
    rms_px: float  # reprojection error of the board pose
    n_corners: int


# one convention, one place: the mount rotation lives in core.geometry
rotation_vehicle_from_cam = vehicle_from_cam_rotation


def _quarter_turn(k: int) -> np.ndarray:
    """(3, 3) rotation by k * 90° about z."""
    c, s = round(math.cos(k * math.pi / 2)), round(math.sin(k * math.pi / 2))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def mount_from_ground(
    gray: np.ndarray,
    spec: BoardSpec,
    K: np.ndarray,
    dist: np.ndarray,
    board_thickness_m: float = 0.0,
) -> Mount:
    """Height and mount angles of a calibrated camera (K (3, 3), dist (5,)) from a uint8 image
    of ``spec`` lying flat on the road. Raises CalibrationError when the board is not found or
    fits poorly."""
    det = detect_board(gray, spec)
    if det is None:
        raise CalibrationError(
            "the board was not found in the --ground image. Photograph the whole board lying "
            "flat on the road, sharp and evenly lit, from the mounted camera."
        )
    obj = det.object_m.astype(np.float64)
    img = det.image_px.astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise CalibrationError("the board pose in the --ground image could not be solved.")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    if rms > MAX_GROUND_RMS_PX:
        raise CalibrationError(
            f"the board in the --ground image fits with {rms:.2f} px RMS (limit "
            f"{MAX_GROUND_RMS_PX:g} px): is it flat, and are the intrinsics of this camera?"
        )
    R_cb = cv2.Rodrigues(rvec)[0]  # cam_from_board
    t = tvec.ravel()
    n = R_cb[:, 2]  # board z in the camera frame
    dist_m = abs(float(n @ t))  # camera centre to the board plane
    R_bc = R_cb.T  # board_from_cam
    if float(n @ t) < 0:  # board z points at the camera: a mirrored corner order
        R_bc = np.diag([1.0, -1.0, -1.0]) @ R_bc
    best = min(
        (mount_angles_deg(_quarter_turn(k) @ R_bc) for k in range(4)), key=lambda a: abs(a[2])
    )
    return Mount(
        height_m=dist_m + board_thickness_m,
        pitch_deg=best[0],
        roll_deg=best[1],
        yaw_deg=best[2],
        rms_px=rms,
        n_corners=len(obj),
    )
