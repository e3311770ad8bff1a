"""Calibration boards: the ``--board`` specification, the board's 3D corner positions and a
printable texture of it (for the synthetic renders).

Board frame: metres, x along the board's columns, y along its rows (down the printed page),
z = x × y, into the board when it is seen printed side up. Checkerboard corners are the inner
corners, row by row, with the first inner corner at the origin; ChArUco corners are OpenCV's
(origin at the board's top-left outer corner, ids row by row).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from roadsurf.reconstruction.calibration.errors import BoardSpecError

BOARD_FORMS = (
    "checkerboard:COLSxROWS:SQUARE_M (inner corners, e.g. checkerboard:9x6:0.025) or "
    "charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT (squares, e.g. charuco:7x5:0.04:0.03:DICT_5X5_100)"
)


@dataclass(frozen=True)
class BoardSpec:
    """A calibration board. ``cols``/``rows``: inner corners of a checkerboard, squares of a
    ChArUco board. Lengths in metres."""

    kind: str  # "checkerboard" or "charuco"
    cols: int
    rows: int
    square_m: float
    marker_m: float = 0.0  # ChArUco only
    dictionary: str = ""  # ChArUco only, an OpenCV name such as DICT_5X5_100

    @property
    def text(self) -> str:
        """The specification as given on the command line (normalised)."""
        head = f"{self.kind}:{self.cols}x{self.rows}:{self.square_m:g}"
        if self.kind == "charuco":
            return f"{head}:{self.marker_m:g}:{self.dictionary}"
        return head

    @property
    def n_corners(self) -> int:
        if self.kind == "charuco":
            return (self.cols - 1) * (self.rows - 1)
        return self.cols * self.rows

    def object_points(self) -> np.ndarray:
        """(n_corners, 3) float32 board-frame corner positions (m), indexed by corner id."""
        if self.kind == "charuco":
            return np.asarray(self.charuco_board().getChessboardCorners(), np.float32)
        c, r = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        xy = np.column_stack([c.ravel(), r.ravel()]) * self.square_m
        return np.column_stack([xy, np.zeros(len(xy))]).astype(np.float32)

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, d)

    def outline_m(self) -> tuple[float, float, float, float]:
        """Board-frame extent (x0, y0, x1, y1) of the printed squares (m)."""
        s = self.square_m
        if self.kind == "charuco":
            return 0.0, 0.0, self.cols * s, self.rows * s
        return -s, -s, self.cols * s, self.rows * s


def _bad(text: str, why: str) -> BoardSpecError:
    return BoardSpecError(f"--board {text!r}: {why}. Expected {BOARD_FORMS}.")


def _length(text: str, field: str, value: str) -> float:
    try:
        v = float(value)
    except ValueError:
        raise _bad(text, f"{field} {value!r} is not a number") from None
    if not math.isfinite(v) or v <= 0:
        raise _bad(text, f"{field} must be a positive length in metres, got {value}")
    if v >= 1.0:
        raise _bad(text, f"{field} is in metres (e.g. 0.025 for 25 mm), got {value}")
    return v


def parse_board(text: str) -> BoardSpec:
    """Parse ``checkerboard:9x6:0.025`` or ``charuco:7x5:0.04:0.03:DICT_5X5_100``.

    Raises BoardSpecError (one line) naming what is wrong and the accepted forms."""
    parts = [p.strip() for p in str(text).strip().split(":")]
    kind = parts[0].lower()
    if kind in ("chessboard", "checker"):
        kind = "checkerboard"
    if kind not in ("checkerboard", "charuco"):
        raise _bad(text, f"unknown board type {parts[0]!r}")
    want = 3 if kind == "checkerboard" else 5
    if len(parts) != want:
        raise _bad(text, f"a {kind} takes {want - 1} fields after the type, got {len(parts) - 1}")
    cols_s, sep, rows_s = parts[1].lower().partition("x")
    if not (sep and cols_s.isdigit() and rows_s.isdigit()):
        raise _bad(text, f"size {parts[1]!r} must be COLSxROWS, e.g. 9x6")
    cols, rows = int(cols_s), int(rows_s)
    square = _length(text, "square size", parts[2])
    if kind == "checkerboard":
        if min(cols, rows) < 3:
            raise _bad(text, f"a checkerboard needs at least 3x3 inner corners, got {cols}x{rows}")
        return BoardSpec(kind, cols, rows, square)
    if min(cols, rows) < 3:
        raise _bad(text, f"a ChArUco board needs at least 3x3 squares, got {cols}x{rows}")
    marker = _length(text, "marker size", parts[3])
    if marker >= square:
        raise _bad(text, f"marker size {marker:g} m must be smaller than the square {square:g} m")
    name = parts[4].upper()
    if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise _bad(text, f"unknown ArUco dictionary {parts[4]!r} (OpenCV names like DICT_5X5_100)")
    n_markers = (cols * rows) // 2
    size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0]
    if n_markers > size:
        raise _bad(text, f"{name} has {size} markers but a {cols}x{rows} board needs {n_markers}")
    return BoardSpec(kind, cols, rows, square, marker, name)


def board_texture(spec: BoardSpec, px_per_square: int = 120) -> tuple[np.ndarray, float, float]:
    """A printable image of the board with a one-square white margin.

    Returns (uint8 image (H, W), x0_m, y0_m): the board-frame position of the image's top-left
    pixel edge; the scale is ``px_per_square / square_m`` pixels per metre."""
    s, pps = spec.square_m, int(px_per_square)
    x0, y0, x1, y1 = spec.outline_m()
    nx, ny = round((x1 - x0) / s), round((y1 - y0) / s)
    if spec.kind == "charuco":
        img = spec.charuco_board().generateImage(((nx + 2) * pps, (ny + 2) * pps), marginSize=pps)
    else:
        r, c = np.mgrid[0 : ny * pps, 0 : nx * pps] // pps
        squares = np.where((r + c) % 2 == 0, 0, 255).astype(np.uint8)
        img = np.full(((ny + 2) * pps, (nx + 2) * pps), 255, np.uint8)
        img[pps:-pps, pps:-pps] = squares
    return img, x0 - s, y0 - s
