"""The simulated vehicle's body rolls with the road's cross slope when asked
(``SimConfig.roll_with_road``, simulation.world), as a real one does."""

from __future__ import annotations

import math

import numpy as np

from roadsurf.simulation.build import build_world
from roadsurf.simulation.scenarios import make_config

SMALL = {"width": 160, "height": 120, "fx": 150.0, "vibration_deg": 0.0, "undulation_m": 0.0}


def _across_tilt(roll_with_road: bool, cross_slope: float) -> np.ndarray:
    """(n,) the slope of each frame's vehicle up axis towards the vehicle's right (m/m)."""
    cfg = make_config("potholes", roll_with_road=roll_with_road, cross_slope=cross_slope, **SMALL)
    world = build_world(cfg, 7, 12)
    out = []
    for t in world.frame_times:
        p = world.pose(float(t))
        up = p.R @ np.array([0.0, 0.0, -1.0])  # nadir: the vehicle's up is the camera's -z
        h = math.radians(p.heading_deg)
        right = np.array([math.cos(h), -math.sin(h), 0.0])
        out.append(float(up @ right) / float(up[2]))
    return np.array(out)


def test_the_body_rolls_with_the_cross_slope() -> None:
    # a road falling 3 % to the right: the up axis leans right by 3 %
    assert np.allclose(_across_tilt(True, 0.03), 0.03, atol=1e-3)
    assert np.allclose(_across_tilt(True, -0.02), -0.02, atol=1e-3)
    # the reference drives keep the body level across
    assert np.allclose(_across_tilt(False, 0.03), 0.0, atol=1e-3)
