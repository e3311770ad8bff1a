"""Segments after a no_overlap pair are kept off the ground already mapped (issue 28: real
photographs of several potholes must not fuse into one smeared map)."""

from __future__ import annotations

import numpy as np

from roadsurf.mapping import poses
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.separate import _box, _boxes_overlap, _footprint_xy
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
