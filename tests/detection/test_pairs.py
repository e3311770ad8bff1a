"""detection.pairs with a lens-distorted camera: the pair's pixels are ideal (undistorted), the
image is raw, so the 2D refinement must read the image where each point really is."""

import cv2
import numpy as np

from roadsurf.detection.config import DetectionConfig, RefineConfig
from roadsurf.detection.pairs import _raw_px, analyse_pair
from roadsurf.io.drive import Camera
from roadsurf.reconstruction.types import PairResult

CAM = Camera(640, 480, 500.0, 500.0, 319.5, 239.5, 1.0, 15.0, (-0.3, 0.08, 0.0, 0.0, 0.0))
CAM_IDEAL = Camera(640, 480, 500.0, 500.0, 319.5, 239.5, 1.0, 15.0)


def test_raw_px_round_trips_and_is_identity_without_distortion():
    rng = np.random.default_rng(0)
    ideal = np.c_[rng.uniform(20, 620, 200), rng.uniform(20, 460, 200)]
    raw = _raw_px(ideal, CAM)
    assert np.abs(raw - ideal).max() > 10  # strong barrel distortion near the corners
    assert np.allclose(CAM.undistort_px(raw), ideal, atol=0.05)
    assert _raw_px(ideal, CAM_IDEAL) is ideal
    assert _raw_px(ideal, None) is ideal


def _pair_with_dark_shallow_defect() -> tuple[PairResult, np.ndarray, np.ndarray]:
    """Road plane 1 m below camera a; a shallow defect (15 mm: needs 2D support, below
    strong_factor x T_d) near a corner, dark in the raw image where the lens puts it."""
    rng = np.random.default_rng(1)
    u, v = np.meshgrid(np.arange(10, 630, 8.0), np.arange(10, 470, 8.0))
    ideal = np.c_[u.ravel(), v.ravel()]
    centre = np.array([60.0, 50.0])  # ideal pixel of the defect's centre
    inside = np.linalg.norm(ideal - centre, axis=1) < 22
    z = np.full(len(ideal), 1.0) + rng.normal(0, 0.0005, len(ideal))
    z[inside] += 0.015
    xy = (ideal - [CAM.cx, CAM.cy]) / CAM.fx * z[:, None]
    pair = PairResult(
        "a.png", "b.png", 0, 1, "rotation_aware", "ok",
        points_cam_a_m=np.c_[xy, z], px_a=ideal,
    )  # fmt: skip
    img = (128 + rng.normal(0, 4, (480, 640))).clip(0, 255).astype(np.uint8)
    raw_centre = _raw_px(centre[None], CAM)[0]
    r = int(np.round(np.linalg.norm(_raw_px((centre + [22, 0])[None], CAM)[0] - raw_centre)))
    cv2.circle(img, tuple(int(c) for c in np.round(raw_centre)), r, 60, -1)
    return pair, img, inside


def test_shallow_dark_defect_is_refined_at_its_raw_position():
    pair, img, inside = _pair_with_dark_shallow_defect()
    # the refinement is off by default (issue 29); this tests the option
    cfg = DetectionConfig(refine=RefineConfig(enabled=True))
    res = analyse_pair(pair, img, cfg, camera=CAM)
    assert res is not None
    assert res.candidate[inside].mean() > 0.9
    assert res.refined[inside].mean() > 0.9
    assert not res.refined[~inside].any()
    # Reading the raw image at the ideal pixels (the lens ignored) misses the dark region.
    wrong = analyse_pair(pair, img, cfg, camera=None)
    assert wrong.refined[inside].mean() < 0.5
