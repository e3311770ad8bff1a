"""`python -m benchmarks.memory`: the per-length table, the ratio and the result file, with the
simulator and the measured runs stubbed (real ones take minutes); one real child for the
rusage plumbing."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

import benchmarks.memory as bench


def test_table_ratio_and_result_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    runs: list[tuple[Path, Path, Path | None, dict[str, str] | None]] = []

    def simulate_drive(work: Path, frames: int, width: int, scenario: str = "long") -> Path:
        return work / f"{scenario}{frames}_w{width}"

    def measure_run(
        drive: Path, out: Path, pythonpath: Path | None = None, env: dict[str, str] | None = None
    ) -> dict[str, Any]:
        runs.append((drive, out, pythonpath, env))
        return {"peak_rss_mb": 400.0 if "100" in drive.name else 460.0, "wall_s": 9.0, "rc": 0}

    monkeypatch.setattr(bench, "simulate_drive", simulate_drive)
    monkeypatch.setattr(bench, "measure_run", measure_run)
    res_file = tmp_path / "memory.json"
    rc = bench.main(
        ["--frames", "100,400", "--width", "320", "--work", str(tmp_path), "--json",
         str(res_file), "--env", "MALLOC_ARENA_MAX=2"]
    )  # fmt: skip
    assert rc == 0
    assert [r[1].name for r in runs] == ["run_long100_w320", "run_long400_w320"]
    assert all(r[3] == {"MALLOC_ARENA_MAX": "2"} for r in runs)
    res = json.loads(res_file.read_text())
    figures = res.get("figures", res)
    assert figures["ratio_longest_to_shortest"] == pytest.approx(1.15)
    assert figures["within_20_percent"] is True
    assert "| 400 | 320x240 | 460 MB | 1.15x |" in figures["markdown"]


def test_measure_run_reports_the_childs_own_peak_and_exit_code(tmp_path: Path) -> None:
    res = bench.measure_run(tmp_path / "no_such_drive", tmp_path / "out")
    assert res["rc"] != 0 and "no_such_drive" in res["error"]
    assert 10 < res["peak_rss_mb"] < 2000


def test_env_reaches_the_child(tmp_path: Path) -> None:
    """--env is set in the measured child: Python refuses a bad PYTHONHASHSEED at start-up."""
    res = bench.measure_run(tmp_path / "d", tmp_path / "o", env_extra={"PYTHONHASHSEED": "x"})
    assert res["rc"] != 0 and "PYTHONHASHSEED" in res["error"]
