"""A vehicle that stops (traffic lights, queues): the pairs of its standing frames fail as
``no_motion`` (the camera did not move) and must hold those frames together, not count as a
visual gap that a constant-velocity prior bridges. A fault battery found a realistic stop
pulling an RTK trajectory 9-10 cm apart around it (and the bundle 18 cm, 3.4° off)."""

from __future__ import annotations

import numpy as np
import pytest

from roadsurf.core.geometry import enu_from_lla, lla_from_enu
from roadsurf.mapping import poses
from roadsurf.mapping.config import MappingConfig
from roadsurf.reconstruction.types import STATUS_NO_MOTION
from tests.mapping.bundle_synth import make_track_drive
from tests.mapping.synth import REF

STOP_S = (1.0, 2.0)  # the vehicle stands still for 1 s (20 frames at 20 fps)


def _errors_m(status: str, bundle: bool) -> tuple[np.ndarray, object, object]:
    """Horizontal error (N,) m of each frame on a 60-frame drive with RTK GPS (2 cm) at 1 Hz
    and an abrupt stop, its standing pairs failed with ``status``; the trajectory, report."""
    td = make_track_drive(n=60, seed=4, gps_hz=1.0, stop_s=STOP_S, still_status=status)
    cfg = MappingConfig(bundle_adjust=bundle, gps_sigma_m=0.02)
    traj, rep = poses.estimate_trajectory(cfg, td.drive, td.pairs)
    lla = lla_from_enu(traj.positions_enu_m, traj.reference)
    p = enu_from_lla(lla[:, 0], lla[:, 1], lla[:, 2], REF)
    return np.linalg.norm((p - td.world_from_cam[:, :3, 3])[:, :2], axis=1), traj, rep


@pytest.mark.parametrize("bundle", [False, True])
def test_a_stopped_vehicle_keeps_its_trajectory(bundle: bool) -> None:
    err, traj, rep = _errors_m(STATUS_NO_MOTION, bundle)
    assert rep.n_pairs_still >= 18 and rep.n_segments == 1
    assert float(np.sqrt(np.mean(err**2))) < 0.03 and err.max() < 0.04
    # the standing frames stay in one place, facing one way
    t = traj.timestamp_s
    stand = (t > STOP_S[0]) & (t < STOP_S[1])
    assert np.ptp(traj.positions_enu_m[stand, :2], axis=0).max() < 0.01
    assert np.ptp(traj.heading_deg[stand]) < 0.3


def test_standing_pairs_as_plain_failures_pull_the_trajectory_apart() -> None:
    """The same drive with the standing pairs as ordinary failures (what a stop gave before
    ``no_motion``): the constant-velocity prior across the 'gap' carries the vehicle on."""
    old, _, _ = _errors_m("too_few_matches", False)
    new, _, _ = _errors_m(STATUS_NO_MOTION, False)
    assert old.max() > 5 * new.max()


def test_fixes_beyond_a_turning_end_weigh_by_its_turn() -> None:
    """Fixes outside the frames are tied to the end frames' straight extrapolation: at an end
    that turns faster than gap_accel_sigma_mps2 allows their σ grows by its own ½·a·Δt²; a
    straight end (vibration only) keeps them as they were."""
    import cv2

    from roadsurf.mapping.pose_gps import GpsFixes, widen_for_turns
    from roadsurf.reconstruction.types import PairResult

    cfg = MappingConfig()
    t = np.arange(20) / 15.0
    ts = np.array([-1.0, -0.2, 0.5, 1.0, t[-1] + 0.2, t[-1] + 1.0])
    gps = GpsFixes(ts, np.zeros((6, 3)), np.full(6, 0.05), np.ones(6, bool), np.arange(6))

    def pair(k: int, deg: float) -> tuple[int, PairResult]:
        R = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(deg)]))[0]  # about the normal
        return k, PairResult(
            "a",
            "b",
            k,
            k + 1,
            "rotation_aware",
            "ok",
            R_b_from_a=R,
            t_b_from_a_m=np.array([0, 0.4, 0]),
            plane=np.array([0.0, 0.0, 1.1]),
        )

    straight = [pair(k, 0.5) for k in range(19)]
    assert np.array_equal(widen_for_turns(cfg, gps, t, straight).sigma_m, gps.sigma_m)
    turning_end = [pair(k, 0.5 if k < 10 else 10.0) for k in range(19)]  # 15.7 m/s² there
    s = widen_for_turns(cfg, gps, t, turning_end).sigma_m
    assert np.array_equal(s[:4], gps.sigma_m[:4])  # the straight start and the fixes inside
    a = np.radians(10.0) * 0.4 * 15.0**2
    np.testing.assert_allclose(
        s[4:], np.hypot(0.05, 0.5 * a * np.array([0.2, 1.0]) ** 2), rtol=0.02
    )
    # with enough fixes within the frames, those beyond the turning end are not used at all
    many = np.array([-1.0, -0.2, *np.linspace(0.0, t[-1], 8), t[-1] + 0.2, t[-1] + 1.0])
    g8 = GpsFixes(many, np.zeros((12, 3)), np.full(12, 0.05), np.ones(12, bool), np.arange(12))
    kept = widen_for_turns(cfg, g8, t, turning_end)
    assert np.array_equal(kept.orig_index, np.arange(10))
