"""Image-level API: a good synthetic pair reconstructs; bad pairs give a status, not a crash."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from roadsurf.reconstruction.api import reconstruct_pair
from roadsurf.reconstruction.config import FeatureConfig, ReconstructionConfig
from roadsurf.reconstruction.types import STATUS_FAILED
from tests.reconstruction.conftest import render_pair, texture

CFG = ReconstructionConfig(features=FeatureConfig(max_features=1000))


def cam_img(cam) -> np.ndarray:
    return texture((cam.height, cam.width), 0)


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


@pytest.mark.parametrize("kind", ["orb", "akaze"])
def test_binary_features_reconstruct(cam, kind: str) -> None:
    if kind == "akaze" and not hasattr(cv2, "AKAZE_create"):
        from roadsurf.core.errors import ConfigError

        with pytest.raises(ConfigError, match="akaze"):
            reconstruct_pair(
                cam_img(cam),
                cam_img(cam),
                cam,
                ReconstructionConfig(features=FeatureConfig(kind="akaze")),
            )
        pytest.skip(f"AKAZE is not in OpenCV {cv2.__version__}")
    a, b = render_pair(cam, t_m=(0.1, 0.015, 0.0), seed=4)
    cfg = ReconstructionConfig(features=FeatureConfig(kind=kind, max_features=1500))
    res = reconstruct_pair(a, b, cam, cfg)
    assert res.ok, res.reason
    np.testing.assert_allclose(res.t_b_from_a_m, [0.1, 0.015, 0.0], atol=0.015)


def test_distorted_camera_is_undistorted(cam) -> None:
    """Keypoints of a distorted camera are undistorted before the geometry."""
    from dataclasses import replace

    dcam = replace(cam, dist=(-0.2, 0.05, 0.0, 0.0, 0.0))
    a, b = render_pair(cam, t_m=(0.1, 0.015, 0.0), seed=6)
    # distort both images with the OpenCV model (ideal -> distorted pixel positions)
    h, w = a.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    pts = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, dcam.K, np.array(dcam.dist), P=dcam.K).reshape(h, w, 2)
    a_d = cv2.remap(a, und[..., 0], und[..., 1], cv2.INTER_LINEAR)
    b_d = cv2.remap(b, und[..., 0], und[..., 1], cv2.INTER_LINEAR)
    res = reconstruct_pair(a_d, b_d, dcam, CFG)
    assert res.ok, res.reason
    assert np.median(np.abs(res.plane_dist_m)) < 0.003
    naive = reconstruct_pair(a_d, b_d, cam, CFG)  # ignoring the distortion bends the plane
    assert not naive.ok or np.median(np.abs(naive.plane_dist_m)) > np.median(
        np.abs(res.plane_dist_m)
    )


def test_no_motion_gives_status(cam) -> None:
    a, _ = render_pair(cam, seed=8)
    res = reconstruct_pair(a, a.copy(), cam, CFG)  # vehicle stopped: same view twice
    assert res.status == "no_motion" and "did not move" in res.reason
