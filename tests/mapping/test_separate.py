"""Segments after a no_overlap pair are kept off the ground already mapped (issue 28: real
photographs of several potholes must not fuse into one smeared map)."""

from __future__ import annotations

import numpy as np

from roadsurf.mapping import poses
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.separate import (
    _box,
    _boxes_overlap,
    _footprint_xy,
    keep_apart,
    segment_has_gps,
)
from tests.mapping.synth import failed_pair, make_synthetic


def _seg_boxes(traj, cam):
    return [
        _box(_footprint_xy(cam, traj.world_from_cam[traj.segment == s]))
        for s in range(int(traj.segment.max()) + 1)
    ]


def test_a_no_overlap_break_keeps_the_segments_apart() -> None:
    syn = make_synthetic(n=30, seed=2, with_gps=False)
    syn.pairs[14] = failed_pair(14, "no_overlap")
    traj, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, syn.pairs)
    assert traj.segment is not None and int(traj.segment.max()) == 1
    a, b = _seg_boxes(traj, syn.drive.camera)
    assert not _boxes_overlap(a, b)
    assert any("no_overlap" in w for w in rep.warnings)
    # the segment's road stays at the level of the one before (no fold, no step)
    z = traj.world_from_cam[:, 2, 3]
    assert abs(np.mean(z[traj.segment == 1]) - np.mean(z[traj.segment == 0])) < 0.05


def test_another_failure_keeps_the_constant_velocity_guess() -> None:
    """A pair lost to blur (too_few_matches) says nothing about overlap: the segment stays
    where the constant-velocity guess puts it, overlapping its neighbour like the truth."""
    syn = make_synthetic(n=30, seed=2, with_gps=False)
    syn.pairs[14] = failed_pair(14, "too_few_matches")
    traj, rep = poses.estimate_trajectory(MappingConfig(), syn.drive, syn.pairs)
    a, b = _seg_boxes(traj, syn.drive.camera)
    assert _boxes_overlap(a, b)
    assert not any("no_overlap" in w for w in rep.warnings)
    step = np.linalg.norm(traj.world_from_cam[15, :3, 3] - traj.world_from_cam[14, :3, 3])
    true = np.linalg.norm(syn.world_from_cam[15, :3, 3] - syn.world_from_cam[14, :3, 3])
    assert abs(step - true) < 0.1


def _world(rot: np.ndarray, ys: list[float]) -> np.ndarray:
    W = np.repeat(np.eye(4)[None], len(ys), axis=0)
    W[:, :3, :3] = rot
    W[:, 1, 3] = ys
    W[:, 2, 3] = 1.1
    return W


def _three_segments(status_2: str) -> tuple:
    """Segments of 5 frames: 0 at y 0-0.4 m, 1 (after a no_overlap pair) 20 m on, 2 (after a
    ``status_2`` pair) laid back over segment 0 by a wrong guess (spd2: frames 34-35 over
    0-4)."""
    syn = make_synthetic(n=15, seed=2, with_gps=False)
    ys = (
        [0.1 * k for k in range(5)] + [20 + 0.1 * k for k in range(5)] + [0.1 * k for k in range(5)]
    )
    W = _world(syn.world_from_cam[0, :3, :3], ys)
    segment = np.repeat([0, 1, 2], 5)
    pairs = [failed_pair(4, "no_overlap"), failed_pair(9, status_2)]
    pos_of = {k: k for k in range(15)}
    names = [f"{k:06d}.png" for k in range(15)]
    return syn.drive.camera, W, segment, pairs, pos_of, names


def test_without_gps_a_guess_over_older_ground_is_moved_apart_with_a_warning() -> None:
    cam, W, segment, pairs, pos_of, names = _three_segments("too_few_matches")
    W2, warns = keep_apart(W, segment, pairs, pos_of, cam, names)
    boxes = [_box(_footprint_xy(cam, W2[segment == s])) for s in range(3)]
    assert not _boxes_overlap(boxes[2], boxes[0])
    np.testing.assert_allclose(W2[segment < 2], W[segment < 2])  # the others stay
    # rigid: the segment's own shape is untouched
    np.testing.assert_allclose(np.diff(W2[10:, :3, 3], axis=0), np.diff(W[10:, :3, 3], axis=0))
    assert len(warns) == 1
    assert (
        "000010.png-000014.png (after a too_few_matches pair) over 000000.png-000004.png"
        in (warns[0])
    )


def test_a_segment_with_gps_is_never_moved() -> None:
    cam, W, segment, pairs, pos_of, names = _three_segments("too_few_matches")
    t = np.arange(15) * 0.1
    has = segment_has_gps(segment, t, np.array([1.05, 1.25]))  # fixes in segment 2 only
    assert has.tolist() == [False, False, True]
    W2, warns = keep_apart(W, segment, pairs, pos_of, cam, names, has_gps=has)
    np.testing.assert_allclose(W2, W)
    assert warns == []


def test_a_move_is_carried_to_the_guessed_segment_after_it() -> None:
    """Segment 1 (no_overlap) laid over segment 0 is moved; segment 2, guessed from segment 1
    across a blurred pair, moves with it and stays where the guess put it relative to 1."""
    syn = make_synthetic(n=15, seed=2, with_gps=False)
    ys = [0.1 * k for k in range(15)]  # all three laid end to end, 1 over 0's ground
    W = _world(syn.world_from_cam[0, :3, :3], ys)
    segment = np.repeat([0, 1, 2], 5)
    pairs = [failed_pair(4, "no_overlap"), failed_pair(9, "too_few_matches")]
    names = [f"{k:06d}.png" for k in range(15)]
    W2, warns = keep_apart(W, segment, pairs, {k: k for k in range(15)}, syn.drive.camera, names)
    shift = W2[5, :3, 3] - W[5, :3, 3]
    assert np.linalg.norm(shift) > 0.1
    np.testing.assert_allclose(W2[10:, :3, 3] - W[10:, :3, 3], np.tile(shift, (5, 1)), atol=1e-9)
    assert len(warns) == 1 and "no_overlap" in warns[0]
