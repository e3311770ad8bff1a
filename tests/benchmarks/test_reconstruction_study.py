"""The study's paired rotation_aware-vs-colmap comparison, on hand-made trial rows."""

from __future__ import annotations

import numpy as np

from benchmarks.reconstruction_study import paired_vs_colmap


def _rows(eps_ra: np.ndarray, eps_colmap: np.ndarray, sweep: str = "s") -> list[dict]:
    rows = []
    for k, (a, c) in enumerate(zip(eps_ra, eps_colmap, strict=True)):
        rows.append({"sweep": sweep, "x": 1.0, "trial": k, "method": "rotation_aware", "eps_mm": a})
        rows.append({"sweep": sweep, "x": 1.0, "trial": k, "method": "colmap", "eps_mm": c})
    return rows


def test_paired_flags_consistent_small_loss_but_not_a_tie() -> None:
    rng = np.random.default_rng(0)
    base = rng.uniform(0.6, 0.8, 20)  # trial-to-trial spread far above the method difference
    jitter = rng.normal(0.0, 3e-4, 20)
    worse = paired_vs_colmap(_rows(base * (1.002 + jitter), base))[0]
    tie = paired_vs_colmap(_rows(base * (1.0 + jitter), base))[0]
    assert worse["p_colmap_better"] < 1e-6  # 0.2 % every trial: real, though medians barely move
    assert worse["logratio_ci_lo"] > 0
    assert tie["p_colmap_better"] > 0.01
    assert tie["logratio_ci_lo"] < 0 < tie["logratio_ci_hi"]


def test_paired_counts_a_lone_failure_as_worse() -> None:
    a = np.full(10, 0.5)
    a[3] = np.nan  # rotation_aware failed, colmap did not
    r = paired_vs_colmap(_rows(a, np.full(10, 0.6)))[0]
    assert r["fails_only_method"] == 1
    assert r["p_colmap_better"] == 0.0
    assert r["share_not_worse"] == 0.9
