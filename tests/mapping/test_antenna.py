"""The GNSS antenna's lever arm (mapping.antenna): fixes of an antenna mounted off the camera are
moved onto the camera centre using the track's own direction of travel; camera.yaml's
gps_antenna_m is read and checked."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from roadsurf.core.errors import DriveFormatError
from roadsurf.io.drive import load_drive
from roadsurf.mapping.antenna import cam_from_antenna, cam_from_antenna_posed, travel_axes
from tests.io.drive_fixtures import camera_yaml, make_drive

ARM = np.array([-1.5, 0.3, 0.9])  # forward, left, up (m): behind, left of and above the camera


def _s_curve(n: int = 200, step_m: float = 0.4, grade: float = 0.04) -> tuple[np.ndarray, ...]:
    """Camera centres (n, 3) along an S-curve (radius ~25 m) on a grade, and each one's unit
    forward (n, 3) and left (n, 3) vehicle axes (no roll)."""
    s = np.arange(n) * step_m
    heading = 0.6 * np.sin(s / 12.0)  # rad from east, turning both ways
    d = np.column_stack([np.cos(heading), np.sin(heading)])
    xy = np.vstack([[0.0, 0.0], np.cumsum(d[:-1] * step_m, axis=0)])
    C = np.column_stack([xy, grade * s])
    fwd = np.column_stack([d, np.full(n, grade)])
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    left = np.column_stack([-d[:, 1], d[:, 0], np.zeros(n)])
    return C, fwd, left


def _antenna(C: np.ndarray, fwd: np.ndarray, left: np.ndarray, arm: np.ndarray) -> np.ndarray:
    up = np.cross(fwd, left)
    return C + arm[0] * fwd + arm[1] * left + arm[2] * up


@pytest.mark.parametrize("sigma_m", [0.02, 0.5])
def test_camera_centres_recovered_on_a_curving_grade(sigma_m: float) -> None:
    """The antenna over the point of the vehicle that does not slide sideways (the rear axle):
    its track's direction is the vehicle's heading."""
    rng = np.random.default_rng(3)
    A0, fwd, left = _s_curve()
    C = _antenna(A0, fwd, left, -ARM)  # the camera, -ARM from the antenna
    noise = rng.normal(0, sigma_m, C.shape)
    got = cam_from_antenna(A0 + noise, np.full(len(C), sigma_m), np.ones(len(C), bool), ARM)
    err = np.linalg.norm((got - noise - C)[10:-10], axis=1)  # the lever's own error
    # the direction over >= 5 m (10 σ) each side of noisy track: 1 cm on a 1.8 m arm with RTK,
    # inside σ with a consumer receiver
    assert np.median(err) < 0.01 + 0.6 * sigma_m, np.median(err)
    # against leaving the arm in: 1.8 m
    raw = np.linalg.norm((A0 - C)[10:-10], axis=1)
    assert np.median(raw) == pytest.approx(np.linalg.norm(ARM), rel=1e-6)


def test_an_antenna_ahead_of_the_no_slide_point_errs_by_the_curvature() -> None:
    """When the camera's track is the heading (the simulator's vehicle), the antenna 1.5 m
    behind it crabs by 1.5 m / R on a curve of radius R: the error stays within |arm| x 1.5 / R."""
    C, fwd, left = _s_curve()
    A = _antenna(C, fwd, left, ARM)
    got = cam_from_antenna(A, np.full(len(C), 0.02), np.ones(len(C), bool), ARM)
    err = np.linalg.norm((got - C)[10:-10], axis=1)
    kappa = 0.6 / 12.0  # the S-curve's largest curvature (1/m)
    assert err.max() < np.linalg.norm(ARM) * 1.5 * kappa * 1.2
    assert np.median(err) < 0.1


def test_travel_axes_follow_the_heading_and_the_grade() -> None:
    C, fwd, _ = _s_curve(grade=0.06)
    got, ok = travel_axes(C, np.full(len(C), 0.02), np.ones(len(C), bool))
    assert ok.all()
    ang = np.degrees(np.arccos(np.clip(np.sum(got * fwd, axis=1), -1, 1)))
    # a quadratic over ±5 m of a 20 m-radius S-curve: within a degree (3 cm on a 1.8 m arm)
    assert np.median(ang) < 1.0 and ang.max() < 2.0, (np.median(ang), ang.max())
    # without altitudes the forward axis is level
    flat, _ = travel_axes(C, np.full(len(C), 0.02), np.zeros(len(C), bool))
    assert np.abs(flat[:, 2]).max() == 0.0


def test_a_stop_takes_the_direction_of_the_nearest_travel() -> None:
    """A vehicle standing at a light: its fixes' noise walks about; they keep the heading of
    the travel before and after it instead of a random one."""
    rng = np.random.default_rng(5)
    x = np.concatenate([np.linspace(-20, 0, 50), np.zeros(30), np.linspace(0, 20, 50)])
    P = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    P[:, :2] += rng.normal(0, 0.02, (len(P), 2))
    fwd, ok = travel_axes(P, np.full(len(P), 0.02), np.zeros(len(P), bool))
    assert ok.all()
    assert np.all(fwd[:, 0] > 0.99), fwd[fwd[:, 0] <= 0.99]


def test_a_static_log_moves_the_fixes_down_only() -> None:
    P = np.zeros((10, 3)) + np.random.default_rng(1).normal(0, 0.01, (10, 3))
    got = cam_from_antenna(P, np.full(10, 0.02), np.ones(10, bool), ARM)
    assert np.allclose(got[:, :2], P[:, :2]) and np.allclose(got[:, 2], P[:, 2] - ARM[2])


def test_camera_yaml_gps_antenna(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d")
    assert load_drive(root).camera.gps_antenna_m is None
    (root / "camera.yaml").write_text(camera_yaml(gps_antenna_m="[-1.5, 0.3, 0.9]"))
    assert load_drive(root).camera.gps_antenna_m == (-1.5, 0.3, 0.9)
    for bad in ("[-150, 30, 90]", "[1.0, 2.0]", "0.9", "[1, x, 2]"):
        (root / "camera.yaml").write_text(camera_yaml(gps_antenna_m=bad))
        with pytest.raises(DriveFormatError, match=r"camera.yaml:\d+: camera.yaml 'gps_antenna_m'"):
            load_drive(root)


def test_the_solved_poses_give_the_heading_wherever_the_antenna_rides() -> None:
    """The simulator's kind of vehicle: the camera's own track is the heading, and the antenna
    1.5 m behind it crabs on the curve. From the track the lever errs by 1.5 m / R; from the
    vehicle's solved rotations (and a 20° forward mount) it is exact."""
    from roadsurf.core.geometry import vehicle_from_cam_rotation

    C, fwd, left = _s_curve()
    A = _antenna(C, fwd, left, ARM)
    up = np.cross(fwd, left)
    # vehicle axes (x right, y backward, z down) in ENU, then the camera on a 20° pitched mount
    R_wv = np.stack([-left, -fwd, -up], axis=2)
    R_vc = vehicle_from_cam_rotation(20.0, 0.0, 0.0)
    W = np.tile(np.eye(4), (len(C), 1, 1))
    W[:, :3, :3] = R_wv @ R_vc
    W[:, :3, 3] = C
    t = np.arange(len(C)) * 0.1
    got = cam_from_antenna_posed(A, t, t, W, R_vc, ARM)
    assert np.abs(got - C).max() < 1e-9
    # a fix between two frames takes the rotation between theirs
    Am = 0.5 * (A[:-1] + A[1:])
    mid = cam_from_antenna_posed(Am, t[:-1] + 0.05, t, W, R_vc, ARM)
    assert np.median(np.linalg.norm(mid - 0.5 * (C[:-1] + C[1:]), axis=1)) < 0.002
    # the track's first pass errs by the crab (the test above bounds it); this one does not
    first = cam_from_antenna(A, np.full(len(C), 0.02), np.ones(len(C), bool), ARM)
    assert np.linalg.norm(first - C, axis=1).max() > 0.05


def test_the_pose_stage_puts_the_camera_not_the_antenna_on_the_fixes() -> None:
    """The wiring: a synthetic drive whose fixes are an antenna 1.5 m behind, 0.3 m left of and
    0.9 m above a camera on a 25° mount (given, as camera.yaml would). The trajectory is the
    camera's; without the key it is the antenna's, 1.77 m off."""
    import dataclasses

    from roadsurf.mapping import poses
    from roadsurf.mapping.config import MappingConfig
    from tests.mapping.synth import make_synthetic
    from tests.mapping.test_poses import _true_frame_positions

    arm = (-1.5, 0.3, 0.9)
    syn = make_synthetic(n=60, seed=5, gps_hz=5.0, hdop=0.1, mount_deg=(25.0, 0.0, 0.0),
                         mount_in_camera=True, gps_antenna_m=arm)  # fmt: skip
    cfg = MappingConfig(bundle_adjust=False, gps_sigma_m=0.02)
    est, true = _true_frame_positions(poses.estimate_trajectory(cfg, syn.drive, syn.pairs)[0], syn)
    err = np.linalg.norm(est - true, axis=1)
    assert np.median(err) < 0.03, np.median(err)
    syn.drive.camera = dataclasses.replace(syn.drive.camera, gps_antenna_m=None)
    est, true = _true_frame_positions(poses.estimate_trajectory(cfg, syn.drive, syn.pairs)[0], syn)
    assert np.median(np.linalg.norm(est - true, axis=1)) > 1.5
