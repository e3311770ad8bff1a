"""core.rolling: the row a rolling-shutter frame sees a world point on, against a brute-force
search over the rows, and the frame motion from neighbouring poses."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from roadsurf.core.camera import Camera
from roadsurf.core.geometry import vehicle_from_cam_rotation
from roadsurf.core.rolling import frame_motion, raw_px_from_world

CAM = Camera(640, 480, 600.0, 610.0, 319.5, 239.5, 1.2, 15.0, (-0.21, 0.05, 1e-3, -5e-4, 0.0))


def pose(C: np.ndarray, R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, C
    return T


def world_from_cam_of_tilt(pitch_deg: float, yaw_deg: float = 0.0) -> np.ndarray:
    """Camera looking down (nadir) and forward along +y (north), tilted by pitch."""
    nadir = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # cam z down, y south
    turn = Rotation.from_euler("z", -yaw_deg, degrees=True).as_matrix()
    return turn @ nadir @ vehicle_from_cam_rotation(pitch_deg, 0.0, 0.0)


def brute_force_px(cam: Camera, X: np.ndarray, T0: np.ndarray, vel, om) -> np.ndarray:
    """(N, 2) raw pixels: for each point, the row whose exposure pose projects it onto itself,
    found on a 0.01-row grid (the truth the fixed point must reach)."""
    rows = np.arange(-1.0, cam.height + 1.0, 0.01)
    out = np.full((len(X), 2), np.nan)
    for k, x in enumerate(X):
        tau = rows * cam.readout_s / cam.height
        R = Rotation.from_rotvec(tau[:, None] * np.asarray(om)[None]).as_matrix() @ T0[:3, :3]
        C = T0[:3, 3] + tau[:, None] * np.asarray(vel)[None]
        Xc = np.einsum("nji,nj->ni", R, x[None] - C)
        u, v = cam.project(Xc)
        j = np.nanargmin(np.abs(v - rows))
        out[k] = u[j], v[j]
    return out


@pytest.mark.parametrize("pitch", [0.0, 30.0])
def test_rows_match_the_exposure_at_highway_speed(pitch: float) -> None:
    cam = dataclasses.replace(CAM, readout_s=0.02)
    rng = np.random.default_rng(3)
    T0 = pose(np.array([0.0, 0.0, 1.2]), world_from_cam_of_tilt(pitch))
    vel, om = np.array([0.0, 27.8, 0.0]), np.array([0.0, 0.0, np.radians(20.0)])  # 100 km/h, turn
    # road points that the frame sees somewhere in its exposure
    u0 = rng.uniform(40, 600, 60)
    v0 = rng.uniform(40, 440, 60)
    rays = cam.normalised_from_raw_px(np.column_stack([u0, v0]))
    d = np.column_stack([rays, np.ones(len(rays))]) @ T0[:3, :3].T
    X = T0[:3, 3] + d * (-T0[2, 3] / d[:, 2:3])
    X[:, 1] += 0.3  # the camera moves 0.55 m during readout
    truth = brute_force_px(cam, X, T0, vel, om)
    seen = np.isfinite(truth).all(1) & (truth[:, 1] > 0) & (truth[:, 1] < cam.height - 1)
    assert seen.sum() > 20
    u, v = raw_px_from_world(cam, X, T0, vel, om)
    err = np.hypot(u - truth[:, 0], v - truth[:, 1])[seen]
    assert np.max(err) < 0.05, err
    # the frame pose alone is tens of pixels off (the test can fail)
    ug, vg = raw_px_from_world(cam, X, T0)
    assert np.median(np.hypot(ug - truth[:, 0], vg - truth[:, 1])[seen]) > 10.0


def test_global_shutter_is_the_plain_projection() -> None:
    T0 = pose(np.array([1.0, 2.0, 1.2]), world_from_cam_of_tilt(10.0))
    X = np.array([[1.1, 2.3, 0.0], [0.8, 1.9, 0.01]])
    u, v = raw_px_from_world(CAM, X, T0, np.array([0.0, 30.0, 0.0]), np.zeros(3))
    ue, ve = CAM.project((X - T0[:3, 3]) @ T0[:3, :3])
    np.testing.assert_array_equal(u, ue)
    np.testing.assert_array_equal(v, ve)


def test_frame_motion_from_neighbours() -> None:
    t = np.array([0.0, 0.05, 0.10, 0.15])
    w = np.radians(12.0)  # rad/s about up
    poses = np.array(
        [
            pose(np.array([0.0, 20.0 * ti, 1.2]), world_from_cam_of_tilt(0.0, np.degrees(-w * ti)))
            for ti in t
        ]
    )
    vel, om = frame_motion(poses, t, 1)
    np.testing.assert_allclose(vel, [0.0, 20.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(om, [0.0, 0.0, w], atol=1e-9)
    vel, _ = frame_motion(poses, t, 0)  # one-sided at the ends
    np.testing.assert_allclose(vel, [0.0, 20.0, 0.0], atol=1e-9)
    # a segment break or a long gap: no neighbour, no motion
    vel, om = frame_motion(poses, t, 3, segment=np.array([0, 0, 0, 1]))
    assert not vel.any() and not om.any()
