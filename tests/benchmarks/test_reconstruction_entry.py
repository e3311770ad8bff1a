"""Entry points of `make bench-reconstruction` and `make bench-speed`, and a one-cell study."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

import benchmarks.reconstruction as bench_reconstruction
import benchmarks.speed as bench_speed
from benchmarks.reconstruction_report import evaluate_targets, summary_markdown
from benchmarks.reconstruction_study import BASE, Cell, aggregate, run_cell


def test_reconstruction_main_passes_the_old_cli_options(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    seen: dict[str, Any] = {}

    def fake(out: Path, **kw: Any) -> str:
        seen.update(out=out, **kw)
        return "report"

    monkeypatch.setattr(bench_reconstruction, "bench_reconstruction", fake)
    res = tmp_path / "r.json"
    argv = ["--out", str(tmp_path), "--quick", "--trials", "3", "--no-images", "--json", str(res)]
    assert bench_reconstruction.main(argv) == 0
    assert seen == {
        "out": tmp_path,
        "quick": True,
        "trials": 3,
        "workers": 2,
        "images": False,
        "frames": None,
        "study": True,
    }
    doc = json.loads(res.read_text())
    assert doc["benchmark"] == "reconstruction" and doc["figures"]["report"] == "report"


def test_speed_main_builds_the_config_and_verdict(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    seen: dict[str, Any] = {}

    def fake(out: Path, *, n_frames: int, repeats: int, cfg: Any) -> dict[str, Any]:
        seen.update(out=out, n_frames=n_frames, repeats=repeats, cfg=cfg)
        return {"markdown": "table\n", "drive": {"pairs_per_s": 6.0}}

    monkeypatch.setattr(bench_speed, "bench_speed", fake)
    res = tmp_path / "s.json"
    argv = ["--out", str(tmp_path), "--frames", "8", "--features", "orb", "--json", str(res)]
    assert bench_speed.main(argv) == 0
    assert seen["n_frames"] == 8 and seen["repeats"] == 5
    assert seen["cfg"].features.kind == "orb" and seen["cfg"].features.max_features > 0
    md = json.loads(res.read_text())["figures"]["markdown"]
    assert md.startswith("table\n") and "[MET] ≥ 5 pairs/s with orb" in md


def test_one_cell_study_aggregates_and_reports() -> None:
    cell = Cell("sigma@delta=0.1mm", 0.1, replace(BASE, n_points=60), ("proposed", "classic"))
    rows = run_cell(cell, n_trials=2)
    assert len(rows) == 4 and {r["method"] for r in rows} == {"proposed", "classic"}
    agg = aggregate(rows)
    assert [r["method"] for r in agg] == ["classic", "proposed"]
    targets = evaluate_targets(agg)
    assert targets[0][0].startswith("proposed ε < 1 mm")
    meta = {
        "command": "python -m benchmarks.reconstruction --quick",
        "cells": 1,
        "trials": 2,
        "n_points": 60,
        "seconds": 1.0,
        "machine": "test",
        "date": "today",
    }
    md = summary_markdown(agg, targets, meta)
    assert "| sigma@delta=0.1mm | 0.1 |" in md
