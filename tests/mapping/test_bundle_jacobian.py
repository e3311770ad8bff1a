"""The bundle window's analytic Jacobian (mapping.bundle_problem.WindowProblem) against central
finite differences, on a window of a seeded synthetic drive with every factor on (reprojection,
road plane, camera height, GPS, the pairs' motions, focal and k1), with a global and a rolling
shutter."""

from __future__ import annotations

import numpy as np
import pytest

from roadsurf.mapping import bundle, poses
from roadsurf.mapping.bundle_problem import WindowProblem
from roadsurf.mapping.config import MappingConfig
from tests.mapping.bundle_synth import make_track_drive


@pytest.fixture(scope="module", params=[0.0, 0.03], ids=["global", "rolling"])
def problem(
    monkeypatch_module: pytest.MonkeyPatch, request: pytest.FixtureRequest
) -> WindowProblem:
    seen: list[WindowProblem] = []

    class Recording(WindowProblem):
        def __init__(self, d):  # type: ignore[no-untyped-def]
            super().__init__(d)
            seen.append(self)

    monkeypatch_module.setattr(bundle, "WindowProblem", Recording)
    # a global shutter, and a 30 ms readout (each observation from its row's pose)
    syn = make_track_drive(n=12, seed=4, density_per_m2=30, readout_s=request.param)
    cfg = MappingConfig(
        gps_sigma_m=0.02,
        bundle_max_time_offset_s=0.0,
        bundle_refine_focal=True,
        bundle_refine_k1=True,
        bundle_window_frames=13,
    )
    poses.estimate_trajectory(cfg, syn.drive, syn.pairs)
    assert seen, "no bundle window was built"
    assert (seen[-1].d.obs_time_s is not None) == (request.param > 0)
    return seen[-1]


@pytest.fixture(scope="module")
def monkeypatch_module() -> pytest.MonkeyPatch:  # type: ignore[misc]
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


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
