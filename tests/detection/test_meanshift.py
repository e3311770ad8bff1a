"""Flat-kernel mean shift (eq. 5.11-5.12): merges pieces of one defect, splits separate ones."""

import numpy as np

from roadsurf.detection.meanshift import grid_seeds, mean_shift_flat, merge_modes


def _disc(rng, c, r, n):
    a = rng.uniform(0, 2 * np.pi, n)
    rr = r * np.sqrt(rng.uniform(0, 1, n))
    return np.column_stack([c[0] + rr * np.cos(a), c[1] + rr * np.sin(a)])


def test_two_separate_defects_split():
    rng = np.random.default_rng(0)
    pts = np.vstack([_disc(rng, (0, 0), 0.1, 300), _disc(rng, (1.0, 0.2), 0.08, 200)])
    labels, modes = mean_shift_flat(pts, 0.3)
    assert len(modes) == 2
    assert len(set(labels[:300])) == 1 and len(set(labels[300:])) == 1
    assert labels[0] != labels[-1]


def test_halves_seen_by_two_pairs_merge():
    rng = np.random.default_rng(1)
    d = _disc(rng, (0.5, 0.5), 0.12, 600)
    first, second = d[d[:, 1] < 0.5], d[d[:, 1] >= 0.5]
    # Two pairs saw one half each, with a small registration offset between them.
    pts = np.vstack([first, second + [0.004, -0.003]])
    labels, modes = mean_shift_flat(pts, 0.3)
    assert len(modes) == 1 and (labels == 0).all()


def test_window_size_decides():
    rng = np.random.default_rng(3)
    pts = np.vstack([_disc(rng, (0, 0), 0.03, 100), _disc(rng, (0.2, 0), 0.03, 100)])
    assert len(mean_shift_flat(pts, 0.1)[1]) == 2
    assert len(mean_shift_flat(pts, 0.5)[1]) == 1


def test_empty_input():
    labels, modes = mean_shift_flat(np.zeros((0, 2)), 0.3)
    assert labels.shape == (0,) and modes.shape == (0, 2)


def test_grid_seeds_are_cell_centres_of_mass():
    pts = np.array([[0.05, 0.05], [0.15, 0.05], [0.35, 0.05], [0.95, 0.95]])
    seeds = grid_seeds(pts, 0.3)
    assert np.allclose(seeds, [[0.1, 0.05], [0.35, 0.05], [0.95, 0.95]])
    # No cell holds 2 points but the first: min_points drops the others.
    assert np.allclose(grid_seeds(pts, 0.3, min_points=2), [[0.1, 0.05]])
    assert np.allclose(grid_seeds(pts, 0.3, min_points=3), [pts.mean(axis=0)])


def test_merge_modes_chains_within_merge_distance():
    modes = np.array([[0.0, 0.0], [0.1, 0.1], [0.2, 0.2], [1.0, 0.0]])
    groups = merge_modes(modes, 0.1)  # Chebyshev: 0.1 apart along the chain, 0.8 to the last
    assert groups[0] == groups[1] == groups[2] != groups[3]
    assert merge_modes(modes[:1], 0.1).tolist() == [0]
