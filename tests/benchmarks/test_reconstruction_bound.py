"""The first-order bound of the parametric study against Monte Carlo."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.reconstruction_bound import epsilon_bound, ratio_to_plane
from roadsurf.core.camera import normalised_from_px
from roadsurf.reconstruction import geometry as g
from roadsurf.simulation.points import PointScene, simulate_points


@pytest.mark.parametrize("delta_m", [1e-4, 0.01])
def test_bound_matches_known_pose_monte_carlo(delta_m: float) -> None:
    """The first-order bound equals the Monte-Carlo ε of triangulating with the true pose."""

    scene = PointScene(delta_m=delta_m, sigma_px=0.2, n_points=100, theta_deg=(1, 1, 1))
    pp = simulate_points(scene, 7)
    bound = epsilon_bound(
        pp.X_a_m, pp.d_true_m, pp.h_measured_m, pp.R_b_from_a, pp.t_b_from_a_m, pp.K, 0.2
    )
    rng = np.random.default_rng(0)
    eps = []
    for _ in range(300):
        na = pp.px_a_true + rng.normal(0, 0.2, pp.px_a_true.shape)
        nb = pp.px_b_true + rng.normal(0, 0.2, pp.px_b_true.shape)
        X = g.triangulate(
            normalised_from_px(na, pp.K),
            normalised_from_px(nb, pp.K),
            pp.R_b_from_a,
            pp.t_b_from_a_m,
        )
        eps.append(np.mean(np.abs(pp.h_measured_m * ratio_to_plane(X) - pp.d_true_m)))
    assert abs(np.mean(eps) / bound - 1) < 0.05
