"""Dense crack depth (detection.crackdepth.dense_crack_depth): the parallax across a crack's centre
line, against a road band beside it, on a two-view render with true relief."""

import cv2
import numpy as np
import pytest

from roadsurf.core.geometry import invert_pose, transform_points
from roadsurf.detection.config import CrackConfig
from roadsurf.detection.crackdepth import PairView, dense_crack_depth
from roadsurf.io.drive import Camera, read_gray
from tests.detection.synthetic import Scene, Trough, build_two_view, poses

# 1.7 mm pixels: a 7 mm groove is about 4 px wide, like the simulator's cracks.
CAM = Camera(width=480, height=360, fx=600.0, fy=600.0, cx=239.5, cy=179.5, height_m=1.0, fps=10.0)
CFG = CrackConfig()
STEP_M = 0.25
ROAD = np.array([0.0, 0.0, CAM.height_m])  # road plane in camera a: Z = h


# 0.9 mm pixels: the same groove about 8 px wide (a 1280 px camera at 1.5 m, say).
CAM_FINE = Camera(
    width=880, height=660, fx=1100.0, fy=1100.0, cx=439.5, cy=329.5, height_m=1.0, fps=10.0
)


def _measure(tmp_path, trough: Trough, cam: Camera = CAM):
    """Dense depth of the trough's centre line (drawn from the truth) in the one pair."""
    drive, pairs, _ = build_two_view(Scene(troughs=[trough]), tmp_path, step_m=STEP_M, camera=cam)
    ga, gb = (read_gray(f) for f in drive.frames)
    ends = np.array([[trough.x0_m, trough.y0_m, 0.0], [trough.x1_m, trough.y1_m, 0.0]])
    P = transform_points(invert_pose(poses(2, step_m=STEP_M, h=cam.height_m)[0]), ends)
    px = (P @ cam.K.T)[:, :2] / P[:, 2:3]
    line = np.zeros(ga.shape, np.uint8)
    cv2.line(line, *(tuple(int(round(c)) for c in p) for p in px), 1, 1)
    view = PairView.of(pairs[0], gb, cam)
    assert view is not None
    width_px = trough.width_m * cam.fx / cam.height_m
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


@pytest.mark.parametrize("cam", [CAM, CAM_FINE], ids=["1.7mm_px", "0.9mm_px"])
def test_groove_darkest_at_its_floor_reads_a_real_share_of_its_depth(tmp_path, cam):
    """A groove shaded darkest at its floor (its walls shade it from the sky), at coarse and
    fine pixels: the dense reading is a lower bound (the LK window sees the rims) but a real
    share of the depth, about 44 %. (The test renderer now integrates the darkness over each
    pixel: with hard band edges the line snapped to the pixel grid and read 2.5 %.)"""
    groove = Trough(-0.15, 0.12, 0.15, 0.14, 0.007, 0.006, darker=0.5, dark_profile="floor")
    m = _measure(tmp_path, groove, cam)
    assert m is not None
    assert 0.3 * 0.006 <= m.depth_m.mean() <= 0.006 + 0.001
    assert m.sum_m / np.sqrt(m.var_m2) >= CFG.z_k


@pytest.mark.parametrize("cam", [CAM, CAM_FINE], ids=["1.7mm_px", "0.9mm_px"])
def test_line_darkest_at_its_centre_at_road_level_gets_no_depth(tmp_path, cam):
    line = Trough(-0.15, 0.12, 0.15, 0.14, 0.007, 0.0, darker=0.5, dark_profile="floor")
    m = _measure(tmp_path, line, cam)
    assert m is not None
    assert abs(m.depth_m.mean()) < 0.0005
    assert abs(m.sum_m / np.sqrt(m.var_m2)) < CFG.z_k


@pytest.mark.parametrize("dense", [True, False])
def test_crack_without_sparse_points_is_carried_by_its_dense_reading(tmp_path, dense):
    """Sparse features straddle a thin crack, so a piece often has none on it; its dense
    reading then carries it into the pooled test (dropped before, as without dense)."""
    import dataclasses

    from roadsurf.detection.config import DetectionConfig
    from roadsurf.detection.pairs import analyse_pair

    # 10 mm wide, 6 mm deep, darkest at its floor (wide and dark enough for the 2D detector)
    groove = Trough(-0.15, 0.12, 0.15, 0.14, 0.010, 0.006, darker=0.3, dark_profile="floor")
    drive, pairs, _ = build_two_view(Scene(troughs=[groove]), tmp_path, step_m=STEP_M, camera=CAM)
    ga, gb = (read_gray(f) for f in drive.frames)
    # no sparse point within 4 groove widths of the crack in image a
    ends = np.array([[groove.x0_m, groove.y0_m, 0.0], [groove.x1_m, groove.y1_m, 0.0]])
    P = transform_points(invert_pose(poses(2, step_m=STEP_M, h=CAM.height_m)[0]), ends)
    e = (P @ CAM.K.T)[:, :2] / P[:, 2:3]
    d = e[1] - e[0]
    rel = pairs[0].px_a - e[0]
    off = np.abs(rel[:, 0] * d[1] - rel[:, 1] * d[0]) / np.linalg.norm(d)
    far = off > 4 * groove.width_m * CAM.fx / CAM.height_m
    n = len(far)
    pr = dataclasses.replace(
        pairs[0],
        **{
            f.name: getattr(pairs[0], f.name)[far]
            for f in dataclasses.fields(pairs[0])
            if isinstance(getattr(pairs[0], f.name), np.ndarray)
            and getattr(pairs[0], f.name).shape[:1] == (n,)
        },
    )
    assert len(pr.px_a) < n
    base = DetectionConfig()
    cfg = dataclasses.replace(base, crack=dataclasses.replace(base.crack, dense=dense))
    m_per_px = CAM.height_m / CAM.fx
    res = analyse_pair(pr, ga, cfg, m_per_px=m_per_px, gray_b=gb, camera=CAM)
    assert res is not None and res.cracks is not None
    c = res.cracks
    if not dense:
        assert len(c.width_m) == 0
        return
    assert len(c.width_m) >= 1
    j = int(np.argmax(c.dense_n))
    assert c.n_points[j] == 0 and c.dense_n[j] >= CFG.min_points
    assert c.dense_sum_m[j] / np.sqrt(c.dense_var_m2[j]) >= CFG.z_k
    assert 0.0 < c.max_depth_m[j] <= 0.006 + 0.001
