"""Feature tracks chained from the pairs' matches (mapping.tracks) on a seeded synthetic drive
whose frames share road points."""

from __future__ import annotations

import numpy as np

from roadsurf.mapping.tracks import build_tracks, thin_tracks, triangulate_w
from tests.mapping.bundle_synth import make_track_drive


def _setup(n: int = 12):
    syn = make_track_drive(n=n, seed=5, gps_hz=1.0)
    pos_of = {i: i for i in range(n)}
    return syn, pos_of


def test_tracks_follow_one_road_point_across_frames() -> None:
    syn, pos_of = _setup()
    tr = build_tracks(syn.pairs, pos_of, syn.world_from_cam, tol_px=0.05, tol_m=0.05)
    assert tr.n_inconsistent == 0
    assert np.sum(tr.length >= 3) > 0.5 * tr.n_tracks  # most points are seen 3+ times here
    # every observation of a track is the same true point: its world position agrees
    d = np.linalg.norm(tr.point_w[:, None, :2] - syn.points_w[None, :, :2], axis=2)
    nearest = d.argmin(1)
    assert np.median(d.min(1)) < 0.01
    for p, ids in zip(syn.pairs, syn.pair_point_ids, strict=True):
        o = np.flatnonzero(tr.obs_frame == p.index_b)
        got = nearest[tr.obs_track[o]]
        # the track seen at this pixel in frame b belongs to the pair's true point there
        pb = {tuple(np.round(x, 6)): j for x, j in zip(p.px_b, ids, strict=True)}
        truth = np.array([pb.get(tuple(np.round(x, 6)), -1) for x in tr.obs_px[o]])
        known = truth >= 0
        assert np.mean(got[known] == truth[known]) > 0.98
    # a track never has two observations in one frame
    key = tr.obs_track * 1000 + tr.obs_frame
    assert len(np.unique(key)) == len(key)


def test_a_wrong_link_drops_the_track() -> None:
    syn, pos_of = _setup()
    clean = build_tracks(syn.pairs, pos_of, syn.world_from_cam, tol_m=0.02)
    # one pair puts 5 of its points 10 cm off (a wrong match RANSAC kept)
    p = syn.pairs[4]
    p.points_cam_a_m = p.points_cam_a_m.copy()
    p.points_cam_a_m[:5, 0] += 0.10
    bad = build_tracks(syn.pairs, pos_of, syn.world_from_cam, tol_m=0.02)
    assert 1 <= bad.n_inconsistent <= 5
    assert bad.n_tracks == clean.n_tracks - bad.n_inconsistent


def test_thinning_keeps_long_tracks_and_caps_two_view_ones() -> None:
    syn, pos_of = _setup()
    tr = build_tracks(syn.pairs, pos_of, syn.world_from_cam)
    th = thin_tracks(tr, 5, (syn.drive.camera.width, syn.drive.camera.height))
    assert np.sum(th.length >= 3) == np.sum(tr.length >= 3)
    two = th.length == 2
    first_frame = np.array([th.obs_frame[th.obs_track == k].min() for k in np.flatnonzero(two)])
    assert np.bincount(first_frame).max() <= 5
    # observations and points stay consistent after renumbering
    assert th.obs_track.max() == th.n_tracks - 1
    assert np.array_equal(np.bincount(th.obs_track), th.length)


def test_points_are_triangulated_from_the_given_poses() -> None:
    # the bundle's points start where its current poses see them: with the true poses the
    # true points (keypoint noise 0.2 px on a 640 px image), not the pairs' points (scale 0.5 %
    # off each: ~5 mm at 1 m)
    syn = make_track_drive(n=12, seed=5, gps_hz=1.0, width_px=640, density_per_m2=60)
    pos_of = {i: i for i in range(12)}
    tr = build_tracks(syn.pairs, pos_of, syn.world_from_cam, tol_px=0.05, tol_m=0.05)
    tr = tr.subset(tr.length >= 3)
    W = syn.world_from_cam[tr.obs_frame]
    cam = syn.drive.camera
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    X, ok = triangulate_w(tr.obs_track, tr.obs_px, W[:, :3, :3], W[:, :3, 3], K, tr.n_tracks)
    assert ok.all()
    d = np.linalg.norm(X[:, None, :] - syn.points_w[None], axis=2).min(1)
    assert np.median(d) < 0.002, np.median(d)
    d_pairs = np.linalg.norm(tr.point_w[:, None, :] - syn.points_w[None], axis=2).min(1)
    assert np.median(d) < 0.5 * np.median(d_pairs)
    assert np.median(np.abs(X[:, 2])) < 0.002  # on the road z = 0
    # a ray pair that never parts (one observation twice) is not well posed
    _, ok1 = triangulate_w(
        np.array([0, 0]), tr.obs_px[[0, 0]], W[[0, 0], :3, :3], W[[0, 0], :3, 3], K, 1
    )
    assert not ok1[0]


def test_points_off_the_road_plane_are_not_road() -> None:
    # a pair that puts some points 3 cm below its road plane (a pothole; the rest scatter 1 mm):
    # their tracks are not held to the road plane by the bundle
    syn, pos_of = _setup()
    rng = np.random.default_rng(0)
    p = syn.pairs[4]
    p.plane_dist_m = rng.normal(0, 0.001, p.n_points)
    hole = np.arange(0, p.n_points, 10)
    p.plane_dist_m[hole] = -0.03
    tr = build_tracks(syn.pairs, pos_of, syn.world_from_cam, tol_px=0.05, tol_m=0.05)
    assert tr.road is not None
    # the tracks through the pair's observations in frame b (= index_b)
    o = np.flatnonzero(tr.obs_frame == p.index_b)
    px = tr.obs_px[o]
    is_hole = np.zeros(p.n_points, bool)
    is_hole[hole] = True
    d = np.linalg.norm(px[:, None] - np.asarray(p.px_b)[None], axis=2)
    near = d.argmin(1)
    ok = d.min(1) < 1e-6
    assert not tr.road[tr.obs_track[o][ok & is_hole[near]]].any()
    assert tr.road[tr.obs_track[o][ok & ~is_hole[near]]].mean() > 0.98
    assert tr.subset(tr.length >= 2).road is not None
