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


def test_gps_fixes_are_the_antennas_and_camera_yaml_says_where_it_is(tmp_path) -> None:
    """gps_antenna_m puts the fixes on the vehicle's antenna (1.5 m behind, 0.9 m above the
    camera: they trail the camera centre along the heading and sit above it), and roadsurf's
    own correction (mapping.antenna) brings them back onto the camera centre."""
    from roadsurf.core.geometry import EnuReference, enu_from_lla
    from roadsurf.mapping.antenna import cam_from_antenna
    from roadsurf.simulation.scenarios import write_camera_yaml
    from roadsurf.simulation.sensors import simulate_gps

    arm = (-1.5, 0.3, 0.9)
    logs = []
    for a in ((0.0, 0.0, 0.0), arm):
        cfg = make_config("potholes", gps_sigma_m=0.0, gps_bias_m=0.0, gps_antenna_m=a, **SMALL)
        world = build_world(cfg, 202, 36)
        logs.append(simulate_gps(world, np.random.default_rng(1)))
    ref = EnuReference(float(logs[0].lat_deg[0]), float(logs[0].lon_deg[0]), 0.0)
    cam, ant = (enu_from_lla(g.lat_deg, g.lon_deg, g.alt_m, ref) for g in logs)
    d = ant - cam
    travel = np.gradient(cam[:, :2], axis=0)
    travel /= np.linalg.norm(travel, axis=1, keepdims=True)
    along = np.sum(d[:, :2] * travel, axis=1)
    left = travel[:, 0] * d[:, 1] - travel[:, 1] * d[:, 0]
    assert np.allclose(along, -1.5, atol=0.03) and np.allclose(left, 0.3, atol=0.03)
    # the vehicle pitches with the 1 % grade and 0.3° of vibration: 1.5 m behind, 1.5 + 0.8 cm
    assert np.allclose(d[:, 2], 0.9 - 0.015, atol=0.03)
    back = cam_from_antenna(ant, np.full(len(ant), 0.02), np.ones(len(ant), bool), np.array(arm))
    assert np.median(np.linalg.norm(back - cam, axis=1)) < 0.02
    write_camera_yaml(cfg, tmp_path)
    assert "gps_antenna_m: [-1.5, 0.3, 0.9]" in (tmp_path / "camera.yaml").read_text()
