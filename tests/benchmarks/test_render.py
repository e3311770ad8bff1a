"""`make bench-render`: the render benchmark times a tiny in-memory drive and writes a result."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.render import bench_render, main


def test_bench_render_figures() -> None:
    res = bench_render("flat", 2, width=160, height=120, fx=150.0)
    assert res["frames"] == 2 and res["image"] == "160x120"
    assert float(res["s_per_frame_median"]) > 0 and int(res["tiles_made"]) > 0


def test_main_writes_result(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "render.json"
    rc = main(["--scenario", "flat", "--frames", "2", "--width", "160", "--height", "120",
               "--json", str(out)])  # fmt: skip
    assert rc == 0
    doc = json.loads(out.read_text(encoding="utf-8"))
    assert doc["benchmark"] == "render" and doc["figures"]["image"] == "160x120"
    assert "s_per_frame_median" in capsys.readouterr().out
