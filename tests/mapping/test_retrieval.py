"""mapping.retrieval: the loop candidates' image retrieval (issue 30) on the sample drive's
frames, and the ranking it gives the candidates."""

from __future__ import annotations

from pathlib import Path

from roadsurf.io.drive import load_drive, read_gray
from roadsurf.mapping.retrieval import rank_candidates, retrieval_score
from roadsurf.reconstruction import features as feat
from roadsurf.reconstruction.config import ReconstructionConfig

SAMPLE = Path(__file__).resolve().parents[2] / "data_samples" / "drive"


def test_frames_that_share_ground_score_far_above_frames_that_do_not() -> None:
    drive = load_drive(SAMPLE)
    cfg = ReconstructionConfig().features
    f = {i: feat.detect(read_gray(drive.frames[i]), cfg) for i in (0, 1, 20, 40)}
    near = retrieval_score(f[0], f[1], cfg)
    far = [retrieval_score(f[0], f[j], cfg) for j in (20, 40)]
    assert near >= 30, near
    assert max(far) * 4 < near, (near, far)
    assert retrieval_score(f[0], f[1], cfg) == near  # deterministic


def test_each_later_frame_gets_its_best_candidate_first() -> None:
    cands = [(0, 10), (1, 10), (2, 10), (3, 11), (4, 11)]
    score = {(0, 10): 2, (1, 10): 90, (2, 10): 90, (3, 11): 5, (4, 11): 1}
    calls: list[tuple[int, int]] = []

    def s(i: int, j: int) -> int:
        calls.append((i, j))
        return score[(i, j)]

    ranked = rank_candidates(cands, s)
    assert ranked == [(1, 10), (2, 10), (0, 10), (3, 11), (4, 11)]  # ties keep the GPS order
    assert sorted(calls) == sorted(cands)  # each scored once
    assert rank_candidates([], s) == []
