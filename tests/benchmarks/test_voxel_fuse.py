"""`python -m benchmarks.voxel_fuse`: the open3d candidate gives voxel_fuse's arrays, and the
table and result file, with the run-folder input replaced by a random cloud."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import benchmarks.voxel_fuse as bench
from roadsurf.mapping.cloud import voxel_fuse


def _cloud(n: int = 3000, seed: int = 0) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(0, 0.2, (n, 3)) * [1.0, 1.0, 0.05] + [500.0, -20.0, -1.1]
    rgb = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    return {"xyz": xyz, "rgb": rgb, "frame_idx": rng.integers(0, 40, n), "voxel_m": 0.004}


def test_open3d_candidate_gives_the_same_arrays() -> None:
    pytest.importorskip("open3d")
    c = _cloud()
    args = (c["xyz"], c["rgb"], c["frame_idx"], c["voxel_m"])
    a, b = voxel_fuse(*args), bench.voxel_fuse_open3d(*args)
    assert len(a[0]) < len(c["xyz"])  # some voxels hold several points
    for x, y in zip(a, b, strict=True):
        assert x.dtype == y.dtype
        np.testing.assert_array_equal(x, y)


def test_repeated_copies_share_no_voxel() -> None:
    c = _cloud(500)
    big = bench.repeated(c, 3)
    assert len(big["xyz"]) == 1500
    y = np.sort(big["xyz"][:, 1])
    gaps = np.diff(y)
    assert np.sum(gaps > 0.9) == 2  # three copies 1 m apart: no voxel holds two of them
    np.testing.assert_array_equal(big["frame_idx"][500:1000], c["frame_idx"])


def test_main_prints_the_table_and_writes_the_result(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("open3d")
    monkeypatch.setattr(bench, "fuse_input", lambda run, drive=None: _cloud(800))
    monkeypatch.setattr(bench, "open3d_import_s", lambda: 0.5)
    out = tmp_path / "r.json"
    assert (
        bench.main([str(tmp_path / "runA"), "--repeats", "1", "--scale", "2", "--json", str(out)])
        == 0
    )
    text = capsys.readouterr().out
    assert "| runA | 800 |" in text and "| runA x2 | 1600 |" in text
    assert "import in a fresh process: 0.50 s" in text
    doc = json.loads(out.read_text())
    assert doc["benchmark"] == "voxel_fuse"
    assert [r["name"] for r in doc["figures"]["rows"]] == ["runA", "runA x2"]
    assert all(r["identical"] for r in doc["figures"]["rows"])
