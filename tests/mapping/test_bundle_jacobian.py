"""The bundle window's analytic Jacobian (mapping.bundle_problem.WindowProblem) against central
finite differences, on a window of a seeded synthetic drive with every factor on (reprojection,
road plane, camera height, GPS, the pairs' motions, focal and k1), with a global and a rolling
shutter."""

from __future__ import annotations

import numpy as np
import pytest

from roadsurf.mapping.bundle_problem import WindowProblem
from tests.mapping.bundle_synth import recorded_window


@pytest.fixture(scope="module", params=[0.0, 0.03], ids=["global", "rolling"])
def problem(request: pytest.FixtureRequest) -> WindowProblem:
    # a global shutter, and a 30 ms readout (each observation from its row's pose)
    p = recorded_window(4, request.param)
    assert (p.d.obs_time_s is not None) == (request.param > 0)
    return p


def test_the_jacobian_matches_finite_differences(problem: WindowProblem) -> None:
    rng = np.random.default_rng(0)
    x = 1e-4 * rng.standard_normal(problem.n)  # off the start, small angles
    J = problem.jac(x).toarray()
    # every camera-side column (poses, planes, focal, k1) and a sample of the points'
    cols = np.unique(np.r_[np.arange(problem.point_col0), rng.choice(problem.n, 30)])
    h = 1e-6
    for c in cols:
        e = np.zeros(problem.n)
        e[c] = h
        fd = (problem.fun(x + e) - problem.fun(x - e)) / (2 * h)
        scale = max(float(np.abs(fd).max()), float(np.abs(J[:, c]).max()), 1e-6)
        assert np.abs(J[:, c] - fd).max() <= 2e-3 * scale, int(c)
