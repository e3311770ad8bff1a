"""Image-level API: a good synthetic pair reconstructs; bad pairs give a status, not a crash."""

from __future__ import annotations

import cv2
import numpy as np

from reconstruction.api import reconstruct_pair
from reconstruction.config import FeatureConfig, ReconstructionConfig
from reconstruction.types import STATUS_FAILED
from tests.reconstruction.conftest import render_pair, texture

CFG = ReconstructionConfig(features=FeatureConfig(max_features=1000))


def test_good_pair_is_metric_and_flat(cam) -> None:
    a, b = render_pair(cam, t_m=(0.1, 0.015, 0.0), theta_deg=(0.5, -0.5, 1.0), seed=1)
    res = reconstruct_pair(a, b, cam, CFG)
    assert res.ok, res.reason
    assert res.n_points > 200
    # metric: camera-to-plane distance is h, translation recovered in metres
    assert abs(np.median(res.points_cam_a_m[:, 2]) - cam.height_m) < 0.02
    np.testing.assert_allclose(res.t_b_from_a_m, [0.1, 0.015, 0.0], atol=0.01)
    assert np.median(np.abs(res.plane_dist_m)) < 0.003  # the rendered plane is flat
    assert res.cov_m2.shape == (res.n_points, 3, 3)


def test_no_overlap_gives_status(cam) -> None:
    a = texture((cam.height, cam.width), 1)
    b = texture((cam.height, cam.width), 2)  # a different piece of road
    res = reconstruct_pair(a, b, cam, CFG)
    assert not res.ok and res.status in STATUS_FAILED and res.reason


def test_blurred_pair_gives_status(cam) -> None:
    a, b = render_pair(cam, seed=3)
    a = cv2.GaussianBlur(a, (0, 0), 40)
    b = cv2.GaussianBlur(b, (0, 0), 40)
    res = reconstruct_pair(a, b, cam, CFG)
    assert not res.ok and res.status in STATUS_FAILED and res.reason


def test_textureless_pair_gives_status(cam) -> None:
    a = np.full((cam.height, cam.width), 128, np.uint8)
    res = reconstruct_pair(a, a.copy(), cam, CFG)
    assert res.status == "too_few_features" and res.reason
