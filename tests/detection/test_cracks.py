"""Cracks: thin dark lines confirmed by 3D points just below the road (detection.cracks)."""

import numpy as np
import pytest

from roadsurf.detection import stage
from roadsurf.detection.config import CrackConfig, DetectionConfig
from roadsurf.detection.crackfilter import thin_dark_components
from roadsurf.detection.crackmap import cluster_cracks, crack_defects, crack_evidence
from tests.detection.synthetic import Pothole, Scene, Trough, build

CFG = DetectionConfig()


def _run(tmp_path, scene):
    drive, pairs, traj = build(scene, tmp_path / "drive")
    return stage.run(CFG, drive, pairs, traj, tmp_path / "run")


def test_crack_is_detected_once_and_typed(tmp_path):
    crack = Trough(-0.2, 0.7, 0.25, 1.1, 0.012, 0.004, darker=0.45)
    res = _run(tmp_path, Scene(troughs=[crack], potholes=[Pothole(0.0, 1.8, 0.12, 0.03)]))
    cracks = [d for d in res.defects if d.type == "crack"]
    assert len(cracks) == 1, res.table()
    c = cracks[0]
    assert c.length_m == pytest.approx(np.hypot(0.45, 0.4), rel=0.3)
    assert c.width_m < 0.03
    assert 0.0 < c.max_depth_m < 0.008
    assert c.severity in ("low", "medium", "high") and c.frames
    # its centroid is its outline's, as for every defect type: on a straight groove, inside it
    import shapely

    outline = shapely.Polygon(c.outline_xy_m)
    assert np.allclose(c.centroid_xy_m, outline.centroid.coords[0])
    assert outline.contains(shapely.Point(c.centroid_xy_m))
    # Cracks shallower than the frame-label depth do not make defect frames by themselves.
    assert [d.type for d in res.defects].count("pothole") == 1


def test_dark_line_without_depth_is_not_a_crack(tmp_path):
    """A tar seam / painted dark line: same 2D look, no depth -> the 3D test vetoes it."""
    from roadsurf.io.drive import read_gray

    seam = Trough(-0.2, 0.7, 0.25, 1.1, 0.012, 0.0, darker=0.45)
    scene = Scene(troughs=[seam], lane_x_m=-0.35, shadow_x_m=0.3)
    drive, pairs, traj = build(scene, tmp_path / "drive")
    # The 2D detector does see the seam: the veto is the 3D test's doing.
    m_per_px = drive.camera.height_m / drive.camera.fx
    seen = [thin_dark_components(read_gray(f), m_per_px, CrackConfig())[1] for f in drive.frames]
    assert any(seen)
    res = stage.run(CFG, drive, pairs, traj, tmp_path / "run")
    assert res.defects == []


def test_thin_dark_components_keeps_lines_not_blobs():
    rng = np.random.default_rng(0)
    g = (120 + rng.normal(0, 6, (200, 300))).clip(0, 255).astype(np.uint8)
    g[100:102, 40:260] = 50  # a 2 px dark line, 220 px long
    g[20:45, 20:45] = 50  # a dark blob (pothole-like): too wide for the top-hat / not thin
    lab, keep, widths, _ = thin_dark_components(g, 0.002, CrackConfig())
    assert len(keep) == 1
    ys, xs = np.nonzero(lab == keep[0])
    assert ys.min() >= 97 and ys.max() <= 104 and xs.max() - xs.min() > 180
    assert widths[0] < 5


def test_pooled_evidence_and_clustering():
    cfg = CrackConfig()
    # 20 points 1 mm deep with σ 1 mm: z = 20e-3 / sqrt(20e-6) = 4.5 -> confirmed.
    assert crack_evidence(0.020, 20, 18, 20 * 1e-6, cfg)[0]
    # Same points at road level on average: not confirmed.
    assert not crack_evidence(0.0, 20, 10, 20 * 1e-6, cfg)[0]
    # Too few points, even if deep.
    assert not crack_evidence(0.02, 3, 3, 3 * 1e-6, cfg)[0]
    xy = np.array([[0.0, 0.0], [0.05, 0.0], [0.10, 0.0], [1.0, 1.0]])
    lab = cluster_cracks(xy, 0.06)
    assert lab[0] == lab[1] == lab[2] != lab[3]


def _crack_pair(depth_m: float):
    """One pair holding one confirmed-looking crack piece 0.4 m long, its 3D points
    ``depth_m`` deep (20 points, σ 1 mm)."""
    from roadsurf.detection.cracks import PairCracks
    from roadsurf.detection.pairs import PairDefects

    x = np.linspace(-0.2, 0.2, 40)
    xyz = np.c_[x, np.zeros_like(x), np.full_like(x, 1.0)]
    c = PairCracks(
        xyz, np.zeros(len(x), int), np.array([0.005]), np.array([20 * depth_m]), np.array([20]),
        np.array([20]), np.array([20 * 1e-6]), np.array([depth_m]),
    )  # fmt: skip
    z = np.zeros(3)
    return PairDefects(0, "000000.png", z.astype(bool), z.astype(bool), z, 0.008, 0.001, 0.0, 0.0,
                       cracks=c)  # fmt: skip


def test_crack_evidence_from_a_failed_reconstruction_is_vetoed():
    """A thin dark line whose 3D points lie decimetres below the road (what a failed
    reconstruction gives, e.g. the `classic` baseline) is no crack: deeper than any defect the
    plane fit accepts (`plane.max_depth_m`). The same piece 4 mm deep is one."""
    from roadsurf.detection.mapframe import MapFrame
    from roadsurf.mapping.types import Trajectory
    from tests.detection.synthetic import poses

    traj = Trajectory(["000000.png"], np.arange(1), np.zeros(1), poses(1), ["gps"], None)
    args = (traj, {"000000.png": 0}, MapFrame.create(None), {}, [])
    ok = crack_defects(CFG, {0: _crack_pair(0.004)}, *args)
    assert [d.type for d in ok] == ["crack"] and ok[0].max_depth_m == pytest.approx(0.004)
    assert crack_defects(CFG, {0: _crack_pair(0.8)}, *args) == []
