"""The behaviour check's comparer: volatile fields and renamed caches pass, real changes fail."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from benchmarks.behaviour_check import compare


def _tree(root: Path, depth: float, digest: str, extra: bool = False) -> None:
    run = root / "runs" / "a"
    (run / "features").mkdir(parents=True)
    rep = {
        "counts": {"pairs": 3},
        "depth_m": depth,
        "timings_s": {"total": np.random.default_rng().random()},
    }
    (run / "report.json").write_text(json.dumps(rep))
    np.savez(run / "features" / f"000001_sift4000_{digest}.npz", kp=np.arange(4.0))
    np.savez(run / "p.npz", x=np.ones(3), timings_vals=np.random.default_rng().random(2))
    if extra:
        (run / "pairs.fingerprint").write_text("abc\n")


def test_identical_up_to_timings_and_cache_names(tmp_path: Path) -> None:
    _tree(tmp_path / "old", 0.0123, "deadbeef")
    _tree(tmp_path / "new", 0.0123, "0badf00d", extra=True)
    res = compare(tmp_path / "old", tmp_path / "new")
    assert res["different"] == {} and res["files"] == 3
    assert res["added"] == ["runs/a/pairs.fingerprint"]


def test_a_changed_number_is_reported(tmp_path: Path) -> None:
    _tree(tmp_path / "old", 0.0123, "deadbeef")
    _tree(tmp_path / "new", 0.0124, "deadbeef")
    assert list(compare(tmp_path / "old", tmp_path / "new")["different"]) == ["runs/a/report.json"]
