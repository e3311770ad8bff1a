"""benchmarks/surface.py: drive specs, the sparse -> dense table and the result file (the runs
themselves are the pipeline's, tested elsewhere)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

import benchmarks.surface as bench


def test_simulate_args_of_a_tilted_spec(tmp_path: Path) -> None:
    assert bench.simulate_args("tilted@45", tmp_path / "d", 12)[2:] == [
        "tilted", "--out", str(tmp_path / "d"), "--mount-pitch", "45", "--frames", "12",
    ]  # fmt: skip
    assert "--mount-pitch" not in bench.simulate_args("flat", tmp_path / "d", None)


def test_table_and_result_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def run_drive(spec: str, work: Path, frames: int | None) -> dict[str, dict[str, Any]]:
        return {"dense": {"flat_mae_m": 0.00108, "coverage": 0.956},
                "sparse": {"flat_mae_m": 0.00163, "coverage": None}}  # fmt: skip

    monkeypatch.setattr(bench, "run_drive", run_drive)
    out = tmp_path / "surface.json"
    assert bench.main(["--drives", "potholes,tilted@25", "--work", str(tmp_path),
                       "--json", str(out)]) == 0  # fmt: skip
    res = json.loads(out.read_text())
    md = res.get("figures", res)["table_markdown"]
    assert "| tilted@25 | 1.63 → 1.08 |" in md and "– → 0.956" in md
    assert "command" in res and "commit" in res
