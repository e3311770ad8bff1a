"""A crack's sparse depths against its local road (detection.cracks._local_depths)."""

import dataclasses

import numpy as np
import pytest

from roadsurf.detection.config import CrackConfig
from roadsurf.detection.cracks import _local_depths

CFG = CrackConfig(local_road_m=0.1)


def _scene(seed: int, tilt_err: float, n_road: int = 4000):
    """Road points over 2 m x 2 m (camera X, Y), a crack along X = 0.6 m (Y 0.2..0.8 m), 4 mm
    below the road, 40 points on it; the pair's plane misses the road by ``tilt_err`` * Y
    (a tilt error: an offset growing towards the far field) plus 1 mm point noise."""
    rng = np.random.default_rng(seed)
    road_xy = rng.uniform([-1.0, -1.0], [1.0, 1.0], (n_road, 2))
    crack_xy = np.c_[0.6 + rng.normal(0, 0.001, 40), rng.uniform(0.2, 0.8, 40)]
    xy = np.r_[road_xy, crack_xy]
    true_depth = np.r_[np.zeros(n_road), np.full(40, 0.004)]
    dist = -true_depth + tilt_err * xy[:, 1] + rng.normal(0, 0.001, len(xy))
    P = np.c_[xy, np.full(len(xy), 2.0)]
    near = np.r_[np.zeros(n_road, bool), np.ones(40, bool)]
    road = ~near
    line = np.c_[np.full(60, 0.6), np.linspace(0.2, 0.8, 60)]
    return P, dist, road, near, line


def test_local_road_removes_a_far_field_plane_bias():
    # the pair's plane 5 mm off at Y = 0.5 m: the crack reads 1 mm *above* the road against it
    P, dist, road, near, line = _scene(0, 0.01)
    glob = -dist[near]
    assert glob.mean() < -0.0005
    d, var = _local_depths(P, dist, road, near, line, 0.001, CFG)
    se = np.sqrt(var) / len(d)
    assert d.mean() == pytest.approx(0.004, abs=3 * se)
    # its variance: n sigma^2 plus the reference's own share, not less
    assert var > len(d) * 0.0009**2


def test_local_road_z_is_calibrated_on_flat_road():
    """No crack (points at road level): z = sum d / sqrt(var) is standard normal."""
    z = []
    for seed in range(200):
        P, dist, road, near, line = _scene(seed, 0.006, n_road=1500)
        dist[near] -= -0.004  # the crack points back at road level
        d, var = _local_depths(P, dist, road, near, line, 0.001, CFG)
        z.append(d.sum() / np.sqrt(var))
    z = np.asarray(z)
    assert abs(z.mean()) < 0.25 and 0.8 < z.std() < 1.2


def test_too_few_local_road_points_fall_back_to_the_pair_plane():
    P, dist, road, near, line = _scene(1, 0.006, n_road=30)
    d, var = _local_depths(P, dist, road, near, line, 0.001, CFG)
    assert np.array_equal(d, -dist[near]) and var == pytest.approx(40 * 0.001**2)
    off = dataclasses.replace(CFG, local_road_m=0.0)  # the default: the pair's plane, bit for bit
    assert CrackConfig().local_road_m == 0.0
    P, dist, road, near, line = _scene(1, 0.006)
    d, var = _local_depths(P, dist, road, near, line, 0.001, off)
    assert np.array_equal(d, -dist[near]) and var == pytest.approx(40 * 0.001**2)


def test_crack_points_scattering_more_than_the_road_weigh_less():
    """Features sliding along a crack that runs with the parallax: +-10 mm on the crack, 1 mm on
    the road. Their own scatter, not the road's noise, is their standard error."""
    P, dist, road, near, line = _scene(2, 0.0)
    rng = np.random.default_rng(3)
    dist[near] += rng.choice([-0.01, 0.01], near.sum())
    own = dataclasses.replace(CFG, own_scatter=True)
    d, var = _local_depths(P, dist, road, near, line, 0.001, own)
    assert var >= len(d) * np.std(d, ddof=1) ** 2
    assert abs(d.sum() - 0.004 * len(d)) / np.sqrt(var) < 3.0
