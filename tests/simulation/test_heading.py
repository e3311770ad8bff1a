"""The simulated vehicle's nose follows its path: it does not crab (simulation.world)."""

from __future__ import annotations

import math

import numpy as np

from roadsurf.simulation.build import build_world
from roadsurf.simulation.scenarios import make_config

SMALL = {"width": 160, "height": 120, "fx": 150.0}


def _nose_minus_travel_deg(lateral_wander_m: float, seed: int) -> np.ndarray:
    """(n - 1,) the heading minus the direction of travel between consecutive frames (deg),
    with the yaw noise off (its own short wiggles are left to the vehicle)."""
    cfg = make_config("potholes", lateral_wander_m=lateral_wander_m, yaw_noise_deg=0.0, **SMALL)
    world = build_world(cfg, seed, 36)
    poses = [world.pose(float(t)) for t in world.frame_times]
    c = np.array([p.C for p in poses])
    d = np.diff(c[:, :2], axis=0)
    travel = np.degrees(np.arctan2(d[:, 0], d[:, 1]))  # compass: x east, y north
    mid = np.array(
        [0.5 * (a.heading_deg + b.heading_deg) for a, b in zip(poses[:-1], poses[1:], strict=True)]
    )
    return (mid - travel + 180.0) % 360.0 - 180.0


def test_the_heading_follows_the_lateral_wander() -> None:
    for seed in (202, 3):
        off = _nose_minus_travel_deg(0.04, seed)
        # a 4 cm wander turns the path by up to ~0.5 deg; the nose turns with it
        assert np.max(np.abs(off)) < 0.05, off
        assert abs(float(np.mean(off))) < 0.02
    # the test can fail: the path itself turns off the road's heading by more than that
    cfg = make_config("potholes", yaw_noise_deg=0.0, **SMALL)
    slope = build_world(cfg, 202, 36).lateral_slope()
    assert math.degrees(math.atan(float(np.max(np.abs(slope))))) > 0.2
