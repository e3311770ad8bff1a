"""The camera's mount: estimated from the drive's pairs, used by the pose graph, checked against
camera.yaml (issue 28)."""

from __future__ import annotations

import numpy as np
import pytest

from roadsurf.core.geometry import mount_angles_deg
from roadsurf.mapping import poses
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.mount import estimate_from_pairs
from tests.mapping.synth import make_synthetic
from tests.mapping.test_poses import _true_frame_positions

CFG = MappingConfig(gps_sigma_m=0.05)


def _errors(traj, syn) -> tuple[float, float]:
    """(position RMSE m, median rotation error deg) against the truth."""
    e, t = _true_frame_positions(traj, syn)
    d = e - t
    rmse = float(np.sqrt(np.mean(np.sum(d**2, axis=1))))
    Rs = np.einsum("nji,njk->nik", traj.world_from_cam[:, :3, :3], syn.world_from_cam[:, :3, :3])
    ang = np.degrees(np.arccos(np.clip((np.trace(Rs, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return rmse, float(np.median(ang))


@pytest.mark.parametrize("mount", [(25.0, 0.0, 2.0), (45.0, 0.0, -3.0)])
def test_mount_is_estimated_and_the_poses_are_right(mount) -> None:
    syn = make_synthetic(n=40, seed=4, gps_hz=5.0, gps_sigma_m=0.05, mount_deg=mount)
    est = estimate_from_pairs(syn.pairs)
    assert est is not None
    pitch, _, yaw = mount_angles_deg(est[0])
    assert pitch == pytest.approx(mount[0], abs=0.5)
    assert yaw == pytest.approx(mount[2], abs=1.0)
    traj, rep = poses.estimate_trajectory(CFG, syn.drive, syn.pairs)
    assert rep.mount["source"] == "estimated"
    assert traj.mount_deg is not None and traj.mount_deg[0] == pytest.approx(mount[0], abs=0.5)
    rmse, rot = _errors(traj, syn)
    assert rmse < 0.06 and rot < 1.0
    # the headings exported are the vehicle's, not the tilted camera's
    true_heading = 30.0
    assert abs(((traj.heading_deg[0] - true_heading) + 180) % 360 - 180) < 3.0


def test_a_nadir_assumption_on_a_tilted_camera_fails_and_warns() -> None:
    """Without the mount the poses are wrong: the test above can fail."""
    syn = make_synthetic(n=40, seed=4, gps_hz=5.0, gps_sigma_m=0.05, mount_deg=(25.0, 0.0, 0.0))
    cfg = MappingConfig(gps_sigma_m=0.05, estimate_mount=False)
    traj, rep = poses.estimate_trajectory(cfg, syn.drive, syn.pairs)
    _, rot = _errors(traj, syn)
    assert rot > 5.0
    assert rep.mount["source"] == "assumed nadir"
    assert any("assumed nadir" in w for w in rep.warnings)


def test_camera_yaml_mount_is_used_and_checked() -> None:
    syn = make_synthetic(n=30, seed=5, gps_hz=5.0, mount_deg=(25.0, 1.0, 0.0), mount_in_camera=True)
    traj, rep = poses.estimate_trajectory(CFG, syn.drive, syn.pairs)
    assert rep.mount["source"] == "camera.yaml" and not rep.warnings
    assert rep.mount["roll_deg"] == pytest.approx(1.0, abs=1e-6)
    assert _errors(traj, syn)[1] < 1.0
    # camera.yaml says 15 deg, the drive says 25 deg: a warning with both values
    wrong = make_synthetic(n=30, seed=5, gps_hz=5.0, mount_deg=(25.0, 1.0, 0.0))
    from dataclasses import replace

    wrong.drive.camera = replace(wrong.drive.camera, mount_deg=(15.0, 1.0, 0.0))
    _, rep = poses.estimate_trajectory(CFG, wrong.drive, wrong.pairs)
    msg = " ".join(rep.warnings)
    assert "disagrees" in msg and "(15.0, 1.0, 0.0)" in msg and "(24.9, 0.9" in msg


def test_nadir_drive_keeps_a_nadir_mount() -> None:
    syn = make_synthetic(n=30, seed=6, gps_hz=5.0)
    traj, rep = poses.estimate_trajectory(CFG, syn.drive, syn.pairs)
    assert abs(rep.mount["pitch_deg"]) < 0.5 and abs(rep.mount["yaw_deg"]) < 1.0
    assert not rep.warnings


def test_a_roll_beyond_any_cross_fall_is_applied_and_said() -> None:
    """A 4.5° roll (beyond mount_disagree_deg, 3°: no road's cross-fall) is applied with a
    warning that names it; keeping 0 left the whole roll in the poses."""
    syn = make_synthetic(n=40, seed=4, gps_hz=5.0, gps_sigma_m=0.05, mount_deg=(25.0, 4.5, 0.0))
    traj, rep = poses.estimate_trajectory(CFG, syn.drive, syn.pairs)
    assert rep.mount["roll_deg"] == pytest.approx(4.5, abs=0.5)
    assert _errors(traj, syn)[1] < 1.0
    assert any("camera roll of 4." in w and "applied" in w for w in rep.warnings)


def test_one_pair_gives_the_mount_with_a_warning() -> None:
    """A two-frame photo pair of a 45° camera: its one plane fit gives the tilt; assuming nadir
    put the road 45° off (a pothole read 49 mm deep for 30 mm, benchmarks/stereo_pair.py)."""
    syn = make_synthetic(n=2, seed=4, gps_hz=5.0, mount_deg=(45.0, 0.0, 0.0), with_gps=False)
    est = estimate_from_pairs(syn.pairs)
    assert est is not None and est[2] == 1
    assert mount_angles_deg(est[0])[0] == pytest.approx(45.0, abs=1.0)
    traj, rep = poses.estimate_trajectory(CFG, syn.drive, syn.pairs)
    assert rep.mount["source"] == "estimated" and rep.mount["n_pairs"] == 1
    assert any("rests on 1 pair(s)" in w for w in rep.warnings)
    # no GPS: the local frame's heading is free, its up axis is not
    up_est = traj.world_from_cam[0, :3, :3].T @ np.array([0.0, 0.0, 1.0])
    up_true = syn.world_from_cam[0, :3, :3].T @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(np.clip(up_est @ up_true, -1, 1))) < 1.0


@pytest.mark.parametrize("mount", [(0.0, 0.0, 0.0), (25.0, 1.0, 3.0), (45.0, 0.0, -2.0)])
@pytest.mark.parametrize("turn_deg", [-12.0, 0.0, 12.0])
def test_heading_on_a_turn_is_the_camera_a_heading(mount, turn_deg) -> None:
    """A vehicle on a circle (8 m radius, turning `turn_deg` between the frames): the chord to
    camera b points half-way through the turn; the heading at camera a is the mount's own
    forward axis, whatever the turn's direction (a one-way turn biased the yaw by half of it)."""
    from roadsurf.core.geometry import forward_in_cam, vehicle_from_cam_rotation, world_from_cam
    from roadsurf.mapping.mount import heading_at_a

    M = np.eye(4)
    M[:3, :3] = vehicle_from_cam_rotation(*mount)
    r, th = 8.0, np.radians(turn_deg)

    def pose(phi: float) -> np.ndarray:  # heading north at phi = 0, turning right for phi > 0
        if th == 0:
            c = np.array([0.0, 8.0 * phi, 1.1])
        else:
            c = np.array([r * (1 - np.cos(phi)), r * np.sin(phi), 1.1]) * [np.sign(th), 1, 1]
        return world_from_cam(np.degrees(phi) * np.sign(th), 0.0, 0.0, c) @ M

    Wa, Wb = pose(0.0), pose(abs(th) if th else 0.05)
    T = np.linalg.inv(Wb) @ Wa  # cam b from cam a
    c_b = Wa[:3, :3].T @ (Wb[:3, 3] - Wa[:3, 3])
    want = forward_in_cam(M[:3, :3])
    up = M[:3, :3].T @ np.array([0.0, 0.0, -1.0])  # the vehicle's up (-z) in camera a
    for f in (heading_at_a(T[:3, :3], c_b), heading_at_a(T[:3, :3], c_b, up)):
        assert np.degrees(np.arccos(np.clip(f @ want, -1, 1))) < 0.05


def test_heading_ignores_the_vibrations_pitch_between_the_frames() -> None:
    """Straight ahead, camera b pitched 2° by the vibration: only the turn about the road normal
    bends the path, so the heading stays the mount's forward axis."""
    from roadsurf.core.geometry import forward_in_cam, vehicle_from_cam_rotation, world_from_cam
    from roadsurf.mapping.mount import heading_at_a

    M = np.eye(4)
    M[:3, :3] = vehicle_from_cam_rotation(25.0, 0.0, 0.0)
    Wa = world_from_cam(0.0, 0.0, 0.0, np.array([0.0, 0.0, 1.1])) @ M
    Wb = world_from_cam(0.0, 0.0, np.radians(2.0), np.array([0.0, 0.4, 1.1])) @ M
    T = np.linalg.inv(Wb) @ Wa
    c_b = Wa[:3, :3].T @ (Wb[:3, 3] - Wa[:3, 3])
    up = M[:3, :3].T @ np.array([0.0, 0.0, -1.0])
    want = forward_in_cam(M[:3, :3])
    f = heading_at_a(T[:3, :3], c_b, up)
    assert np.degrees(np.arccos(np.clip(f @ want, -1, 1))) < 0.05
    g = heading_at_a(T[:3, :3], c_b)  # the whole rotation halved: off by half the pitch
    assert np.degrees(np.arccos(np.clip(g @ want, -1, 1))) > 0.5
