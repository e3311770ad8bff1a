"""Track links between pairs that disagree grossly (mapping.tracks.LINK_GROSS_SIGMAS): the
smooth disagreement is removed only up to what the pairs' stated metric uncertainty explains;
pairs 20 % apart in scale are compared as they are, as before the smooth removal."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from roadsurf.mapping.tracks import build_tracks, link_residuals_m
from tests.mapping.test_tracks_links import _drive_with_pair_errors


def test_the_gradient_bound_compares_a_gross_disagreement_as_it_is() -> None:
    rng = np.random.default_rng(0)
    a = np.column_stack([rng.uniform(-1, 1, 200), rng.uniform(0, 2, 200), np.zeros(200)])
    R = Rotation.from_rotvec([0.004, -0.003, 0.006]).as_matrix()
    small = 1.02 * a @ R.T + [0.01, -0.02, 0.015]
    gross = 1.2 * a + [0.01, -0.02, 0.015]  # a 20 % scale disagreement
    assert np.all(link_residuals_m(small, a, 0.02, max_gradient=0.05) < 1e-9)
    assert np.all(link_residuals_m(gross, a, 0.02) < 1e-9)  # unbounded: smooth, removed
    raw = np.linalg.norm(gross - a, axis=1)
    assert np.allclose(link_residuals_m(gross, a, 0.02, max_gradient=0.05), raw)


def test_pairs_within_their_stated_uncertainty_keep_their_tracks_and_gross_ones_do_not() -> None:
    # 0.3° and 1.5 % per pair: within 5 σ of a 3 mm translation σ over a ~0.3 m baseline
    syn, pos_of = _drive_with_pair_errors(5)
    tr = build_tracks(syn.pairs, pos_of, syn.world_from_cam, tol_m=0.02, sigma_trans_m=0.003)
    assert tr.n_inconsistent == 0
    # 25 % per pair (an inconsistent scale): beyond it, the points compared as they are
    syn, pos_of = _drive_with_pair_errors(5, scale=0.25)
    free = build_tracks(syn.pairs, pos_of, syn.world_from_cam, tol_m=0.02)
    bound = build_tracks(syn.pairs, pos_of, syn.world_from_cam, tol_m=0.02, sigma_trans_m=0.003)
    assert free.n_inconsistent == 0
    assert bound.n_inconsistent > 0.3 * bound.n_tracks
