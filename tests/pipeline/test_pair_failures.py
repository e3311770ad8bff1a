"""Many failed pairs give a warning that names how many, why, and where the map's hole is
(``pipeline.run_checks.pair_failures_warning``)."""

from __future__ import annotations

from pathlib import Path

from roadsurf.pipeline.run_checks import pair_failures_warning
from roadsurf.reconstruction.types import PairResult


def _pairs(failed: set[int], n: int = 20) -> list[PairResult]:
    out = []
    for i in range(n):
        bad = i in failed
        status = "not_near_planar" if bad else "ok"
        reason = "homography outlier ratio 0.68 >= 0.5" if bad else ""
        out.append(
            PairResult(
                f"frame_{i:02d}.jpg", f"frame_{i + 1:02d}.jpg", i, i + 1, "x", status, reason
            )
        )
    return out


def test_many_failures_warn_with_counts_and_the_longest_gap(tmp_path: Path) -> None:
    w = pair_failures_warning(_pairs({2, 7, 8, 9, 15}), tmp_path)
    assert w is not None
    assert w.startswith("5 of 20 pairs failed (not_near_planar: 5)")
    assert "Longest run: 3 pairs, frame_07.jpg -> frame_10.jpg" in w
    assert "E.g. frame_02.jpg -> frame_03.jpg: homography outlier ratio 0.68" in w


def test_an_occasional_failure_is_not_warned(tmp_path: Path) -> None:
    assert pair_failures_warning(_pairs({4, 11}), tmp_path) is None  # 10 %: not more
    assert pair_failures_warning(_pairs(set()), tmp_path) is None
    assert pair_failures_warning([], tmp_path) is None
