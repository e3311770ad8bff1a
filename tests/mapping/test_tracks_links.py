"""Track links between pairs whose own geometries are off (mapping.tracks.link_residuals_m): a
rolling-shutter pair's rotation is 0.04-0.38° and its scale up to 2 % off (30 fps sample drive,
20 ms readout), so its points sit up to ~2 cm from its neighbour's; the link check must drop
mismatches, not the correct tracks of a pair with a slightly wrong pose."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from roadsurf.mapping.tracks import build_tracks, link_residuals_m
from tests.mapping.bundle_synth import make_track_drive


def _drive_with_pair_errors(seed: int, rot_deg: float = 0.3, scale: float = 0.015):
    """The seeded track drive with each pair's points moved as its own pose and scale error
    would (a rotation of ``rot_deg`` about a random axis through camera a, a scale of 1 ±
    ``scale``): every match is correct."""
    n = 12
    syn = make_track_drive(n=n, seed=seed, gps_hz=1.0)
    rng = np.random.default_rng(seed + 100)
    for p in syn.pairs:
        axis = rng.normal(size=3)
        R = Rotation.from_rotvec(np.radians(rot_deg) * axis / np.linalg.norm(axis)).as_matrix()
        k = 1.0 + scale * rng.choice([-1.0, 1.0])
        p.points_cam_a_m = k * (np.asarray(p.points_cam_a_m) @ R.T)
    return syn, {i: i for i in range(n)}


def test_pairs_with_their_own_pose_errors_keep_their_tracks() -> None:
    for seed in (5, 6):
        syn, pos_of = _drive_with_pair_errors(seed)
        tr = build_tracks(syn.pairs, pos_of, syn.world_from_cam, tol_m=0.02)
        # the pairs disagree by up to a few cm, smoothly: no track is inconsistent (the point-
        # by-point comparison dropped 44-49 % of them)
        assert tr.n_inconsistent == 0, (seed, tr.n_inconsistent)
        assert np.sum(tr.length >= 3) > 0.5 * tr.n_tracks


def test_a_wrong_link_is_still_found_beside_pose_errors() -> None:
    syn, pos_of = _drive_with_pair_errors(5)
    clean = build_tracks(syn.pairs, pos_of, syn.world_from_cam, tol_m=0.02)
    # one pair puts 5 of its points 5 cm off (a wrong match RANSAC kept)
    p = syn.pairs[4]
    p.points_cam_a_m = p.points_cam_a_m.copy()
    p.points_cam_a_m[:5, 0] += 0.05
    bad = build_tracks(syn.pairs, pos_of, syn.world_from_cam, tol_m=0.02)
    assert 1 <= bad.n_inconsistent <= 5
    assert bad.n_tracks == clean.n_tracks - bad.n_inconsistent


def test_link_residuals_remove_an_affine_disagreement_only() -> None:
    rng = np.random.default_rng(0)
    a = np.column_stack([rng.uniform(-1, 1, 200), rng.uniform(0, 2, 200), np.zeros(200)])
    R = Rotation.from_rotvec([0.004, -0.003, 0.006]).as_matrix()
    b = 1.02 * a @ R.T + [0.01, -0.02, 0.015] + rng.normal(0, 0.001, a.shape)
    b[:3] += [0.0, 0.0, 0.03]  # three mismatches
    r = link_residuals_m(b, a, 0.02)
    assert np.all(r[:3] > 0.02)
    assert np.all(r[3:] < 0.006)
    assert np.linalg.norm(b - a, axis=1)[3:].max() > 0.02  # compared as they are: dropped
    # too few shared points to fit: compared as they are
    assert np.allclose(link_residuals_m(b[:5], a[:5], 0.02), np.linalg.norm(b[:5] - a[:5], axis=1))
