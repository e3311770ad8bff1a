"""Loop closure for revisits (mapping.loops, issue 30): the same lane driven twice, tied only by
GPS with a different bias on each pass, must come out as one road once the passes' frames are
matched (the two passes agree within 1 cm)."""

from __future__ import annotations

import dataclasses

import numpy as np

from roadsurf.core.geometry import invert_pose
from roadsurf.mapping import poses
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.loops import loop_candidates
from tests.mapping.loop_synth import make_revisit

CFG = MappingConfig(gps_sigma_m=0.5, bundle_max_time_offset_s=0.0)


def _pass_disagreement_m(W: np.ndarray, Wt: np.ndarray, n: int) -> float:
    """RMS over the lane of the error of pass 2's pose seen from pass 1's (m): how far apart the
    two passes put the same road."""
    e = []
    for k in range(0, n, 3):
        est = invert_pose(W[k]) @ W[n + k]
        true = invert_pose(Wt[k]) @ Wt[n + k]
        e.append(np.linalg.norm(est[:3, 3] - true[:3, 3]))
    return float(np.sqrt(np.mean(np.square(e))))


def test_candidates_are_gated_by_distance_and_time() -> None:
    t = np.arange(20.0)
    C = np.zeros((20, 3))
    C[:10, 1] = np.arange(10.0)  # pass 1 north
    C[10:, 1] = np.arange(10.0) + 0.3  # pass 2 the same way, 0.3 m on
    got = loop_candidates(t, C, gate_m=0.5, min_gap_s=5.0, stride=4, tries=1)
    assert got and all(j >= 10 and i < 10 and abs(C[j, 1] - C[i, 1]) <= 0.5 for i, j in got)
    assert len(got) <= 4  # a few per revisit, not one per frame
    assert len(loop_candidates(t, C, gate_m=1.5, min_gap_s=5.0, stride=4)) > len(got)
    C[10:, 0] = 5.0  # pass 2 on another road
    assert loop_candidates(t, C, gate_m=0.5, min_gap_s=5.0) == []
    assert loop_candidates(t, C, gate_m=0.5, min_gap_s=50.0) == []


def test_a_revisit_closes_the_loop() -> None:
    syn = make_revisit(n=20, seed=0)
    Wt = syn.world_from_cam
    open_, _ = poses.estimate_trajectory(CFG, syn.drive, syn.pairs)
    d_open = _pass_disagreement_m(open_.world_from_cam, Wt, syn.n)
    assert d_open > 0.1, d_open  # the passes' GPS biases keep them decimetres apart
    for ba in (False, True):
        cfg = dataclasses.replace(CFG, bundle_adjust=ba)
        closed, rep = poses.estimate_trajectory(cfg, syn.drive, syn.pairs, loop_match=syn.match)
        assert len(rep.bundle["loops"]) >= 2
        d_closed = _pass_disagreement_m(closed.world_from_cam, Wt, syn.n)
        assert d_closed < 0.01, (ba, d_closed)
