"""Dense crack depth (detection.cracks.dense_crack_depth): the parallax across a crack's centre
line, against a road band beside it, on a two-view render with true relief."""

import cv2
import numpy as np

from detection.config import CrackConfig
from detection.cracks import PairView, dense_crack_depth
from roadsurf.drive import Camera, read_gray
from roadsurf.geometry import invert_pose, transform_points
from tests.detection.synthetic import Scene, Trough, build_two_view, poses

# 1.7 mm pixels: a 7 mm groove is about 4 px wide, like the simulator's cracks.
CAM = Camera(width=480, height=360, fx=600.0, fy=600.0, cx=239.5, cy=179.5, height_m=1.0, fps=10.0)
CFG = CrackConfig()
STEP_M = 0.25
ROAD = np.array([0.0, 0.0, CAM.height_m])  # road plane in camera a: Z = h


def _measure(tmp_path, trough: Trough):
    """Dense depth of the trough's centre line (drawn from the truth) in the one pair."""
    drive, pairs, _ = build_two_view(Scene(troughs=[trough]), tmp_path, step_m=STEP_M, camera=CAM)
    ga, gb = (read_gray(f) for f in drive.frames)
    ends = np.array([[trough.x0_m, trough.y0_m, 0.0], [trough.x1_m, trough.y1_m, 0.0]])
    P = transform_points(invert_pose(poses(2, step_m=STEP_M, h=CAM.height_m)[0]), ends)
    px = (P @ CAM.K.T)[:, :2] / P[:, 2:3]
    line = np.zeros(ga.shape, np.uint8)
    cv2.line(line, *(tuple(int(round(c)) for c in p) for p in px), 1, 1)
    view = PairView.of(pairs[0], gb, CAM)
    assert view is not None
    width_px = trough.width_m * CAM.fx / CAM.height_m
    return dense_crack_depth(line.astype(bool), width_px, ga, view, ROAD, CFG)


def test_groove_gets_a_significant_dense_depth(tmp_path):
    # 6 mm deep, 7 mm wide, across the direction of travel (full parallax across it).
    m = _measure(tmp_path, Trough(-0.15, 0.12, 0.15, 0.14, 0.007, 0.006, darker=0.5))
    assert m is not None
    z = m.sum_m / np.sqrt(m.var_m2)
    assert z >= CFG.z_k, (z, m.noise_m, m.n_eff)
    assert m.n_eff >= CFG.min_points
    assert 0.0 < m.depth_m.mean() <= 0.006 + 0.001  # a lower bound of the true depth


def test_painted_dark_line_at_road_level_gets_no_depth(tmp_path):
    m = _measure(tmp_path, Trough(-0.15, 0.12, 0.15, 0.14, 0.007, 0.0, darker=0.5))
    assert m is not None  # measured ...
    assert abs(m.sum_m / np.sqrt(m.var_m2)) < CFG.z_k  # ... and at road level


def test_crack_along_the_direction_of_travel_gives_no_dense_reading(tmp_path):
    """LK's aperture: the parallax runs along such a crack, so no depth is read (not faked)."""
    assert _measure(tmp_path, Trough(0.02, 0.0, 0.03, 0.25, 0.007, 0.006, darker=0.5)) is None
