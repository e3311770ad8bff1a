"""A pair whose metric scale disagrees with the trajectory is rescaled to it (mapping.pairscale)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from roadsurf.mapping.pairscale import rescaled_pairs, scale_ratios
from tests.mapping.synth import REF, make_synthetic, true_trajectory


def _shrunk(p, s: float):  # noqa: ANN001, ANN202
    from roadsurf.mapping.pairscale import rescaled

    return rescaled(p, s)


def test_a_pair_read_short_is_rescaled_to_the_trajectory(caplog: pytest.LogCaptureFixture) -> None:
    syn = make_synthetic(n=12, seed=4)
    pairs = list(syn.pairs)
    pairs[5] = _shrunk(pairs[5], 0.971)  # a plane through a pothole: 2.9 % short
    traj = true_trajectory(syn, REF)
    report: list[str] = []
    with caplog.at_level(logging.WARNING):
        out = rescaled_pairs(pairs, traj, report)
    assert len(report) == 1 and "000005.png -> 000006.png (2." in report[0], report
    ratios = scale_ratios(out, traj)
    assert abs(ratios[5] / np.median(ratios) - 1.0) < 1e-3
    # points, plane offset, distances and covariances scale with the translation
    s = np.linalg.norm(out[5].t_b_from_a_m) / np.linalg.norm(pairs[5].t_b_from_a_m)
    assert 1.02 < s < 1.04
    np.testing.assert_allclose(out[5].points_cam_a_m, pairs[5].points_cam_a_m * s, rtol=1e-12)
    np.testing.assert_allclose(out[5].plane, pairs[5].plane * [1, 1, s], rtol=1e-12)
    np.testing.assert_allclose(out[5].plane_dist_m, pairs[5].plane_dist_m * s, rtol=1e-12)
    np.testing.assert_allclose(out[5].cov_m2, pairs[5].cov_m2 * s * s, rtol=1e-12)
    assert all(out[k] is pairs[k] for k in range(len(pairs)) if k != 5)
    assert "000005.png -> 000006.png" in caplog.text


def test_without_gps_the_pairs_are_left_alone() -> None:
    syn = make_synthetic(n=12, seed=4)
    pairs = list(syn.pairs)
    pairs[5] = _shrunk(pairs[5], 0.97)
    out = rescaled_pairs(pairs, true_trajectory(syn))
    assert all(a is b for a, b in zip(out, pairs, strict=True))


def test_scale_noise_within_a_percent_is_left_alone() -> None:
    syn = make_synthetic(n=12, seed=4)
    rng = np.random.default_rng(0)
    pairs = [_shrunk(p, 1.0 + 0.002 * rng.standard_normal()) for p in syn.pairs]
    out = rescaled_pairs(pairs, true_trajectory(syn, REF))
    assert all(a is b for a, b in zip(out, pairs, strict=True))


def test_a_pair_far_off_the_trajectory_is_left_as_solved() -> None:
    """24 % off is no plane tilted by a defect (1-5 %) but a trajectory resting on something
    else there (a rolling shutter left out of camera.yaml, a GPS-bridged gap)."""
    syn = make_synthetic(n=12, seed=4)
    pairs = list(syn.pairs)
    pairs[5] = _shrunk(pairs[5], 0.76)
    out = rescaled_pairs(pairs, true_trajectory(syn, REF))
    assert all(a is b for a, b in zip(out, pairs, strict=True))
