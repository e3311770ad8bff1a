"""benchmarks.meanshift: the comparison with scikit-learn on a tiny synthetic point set."""

from __future__ import annotations

import numpy as np

from benchmarks.meanshift import (
    VARIANTS,
    compare_calls,
    sklearn_mean_shift,
    sklearn_merge,
    table_markdown,
)
from roadsurf.detection.meanshift import merge_modes


def _disc(rng, c, r, n):
    a = rng.uniform(0, 2 * np.pi, n)
    rr = r * np.sqrt(rng.uniform(0, 1, n))
    return np.column_stack([c[0] + rr * np.cos(a), c[1] + rr * np.sin(a)])


def _calls():
    rng = np.random.default_rng(0)
    xy = np.vstack([_disc(rng, (0, 0), 0.1, 120), _disc(rng, (1.0, 0.2), 0.08, 80)])
    kw = {"max_iter": 50, "tol_m": 1e-3, "merge_m": 0.15}
    return [
        {"xy": xy, "window": 0.3, "weights": rng.uniform(0.01, 0.03, len(xy)), "kwargs": kw},
        {"xy": np.zeros((0, 2)), "window": 0.3, "weights": np.zeros(0), "kwargs": kw},
    ]


def test_sklearn_variants_split_two_separate_defects():
    xy = _calls()[0]["xy"]
    for v in VARIANTS:
        labels, centres = sklearn_mean_shift(xy, 0.3, variant=v)
        assert len(centres) == 2, v
        assert len(set(labels[:120])) == 1 and len(set(labels[120:])) == 1
    labels, centres = sklearn_mean_shift(np.zeros((0, 2)), 0.3)
    assert labels.shape == (0,) and centres.shape == (0, 2)


def test_sklearn_merge_cuts_like_scipy():
    rng = np.random.default_rng(4)
    for n in (1, 2, 7, 40):
        modes = rng.uniform(0, 1, (n, 2))
        a, b = merge_modes(modes, 0.15), sklearn_merge(modes, 0.15)
        # Same partition (the numbering may differ).
        pairs = set(zip(a.tolist(), b.tolist(), strict=True))
        assert len(pairs) == len(set(a.tolist())) == len(set(b.tolist()))


def test_compare_calls_and_table():
    res = compare_calls(_calls(), repeat=1)
    assert res["calls"] == 2 and res["points"] == 200
    assert res["clusters"]["ours"] == 2
    assert res["merge_same_partition"] == 1  # the empty call has nothing to merge
    for v in VARIANTS:
        assert res["ari_mean"][v] == 1.0
    e2e = {"predicted": 2, "matched": 2, "precision": 1.0, "recall": 1.0, "depth_mae_m": 0.001}
    doc = {
        "best_variant": "sk_half_grid",
        "drives": {"toy": {"compare": res, "end_to_end": {"ours": e2e, "sk_half_grid": e2e}}},
    }
    md = table_markdown(doc)
    assert "| toy | 2 | 200 | ours |" in md and "sk_half_grid" in md
