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
