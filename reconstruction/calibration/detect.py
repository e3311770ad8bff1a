"""Find a calibration board in one image: sub-pixel corner positions and their board-frame
coordinates."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from roadsurf.reconstruction.calibration.board import BoardSpec
from roadsurf.reconstruction.calibration.errors import CalibrationError

MIN_CHARUCO_CORNERS = 8  # fewer ChArUco corners constrain a view too weakly
_SUBPIX = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)


@dataclass(frozen=True)
class Detection:
    """Board corners found in one image."""

    image_px: np.ndarray  # (N, 2) float32 raw pixels (OpenCV origin: centre of top-left px)
    object_m: np.ndarray  # (N, 3) float32 board-frame positions (m)


def read_gray(path: Path) -> np.ndarray:
    """An image file as uint8 greyscale (colour is converted). Raises CalibrationError."""
    data = np.fromfile(str(path), np.uint8) if Path(path).is_file() else None
    img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data is not None and data.size else None
    if img is None:
        raise CalibrationError(f"{path}: not a readable image file. Check the path and format.")
    return img


def _checkerboard(gray: np.ndarray, spec: BoardSpec) -> np.ndarray | None:
    size = (spec.cols, spec.rows)
    flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCornersSB(gray, size, flags=flags)
    if not found:
        # the classic detector finds some boards the sector-based one misses
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(gray, size, flags=flags)
    if not found:
        return None
    # the sector-based corners carry a scale bias (+0.5% in fx on synthetic boards); the
    # saddle-point refinement removes it
    corners = cv2.cornerSubPix(gray, corners.astype(np.float32), (5, 5), (-1, -1), _SUBPIX)
    return corners.reshape(-1, 2)


def detect_board(gray: np.ndarray, spec: BoardSpec) -> Detection | None:
    """Sub-pixel board corners in a uint8 greyscale image, or None where the board is not
    found (a checkerboard must be seen whole; a ChArUco board needs >= 8 corners)."""
    if spec.kind == "checkerboard":
        px = _checkerboard(gray, spec)
        if px is None:
            return None
        return Detection(px.astype(np.float32), spec.object_points())
    board = spec.charuco_board()
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(gray)
    if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
        return None
    ids = ids.ravel()
    if board.checkCharucoCornersCollinear(ids):
        return None
    obj = spec.object_points()[ids]
    return Detection(corners.reshape(-1, 2).astype(np.float32), obj)
