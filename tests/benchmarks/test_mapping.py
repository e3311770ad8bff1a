"""`python -m benchmarks.mapping`: options, the per-length table and the result file, with the
simulator and the measured child processes replaced by stubs (the real ones take minutes)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

import benchmarks.mapping as bench


@pytest.fixture
def stubs(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, Path, Path]]:
    calls: list[tuple[str, Path, Path]] = []

    def simulate(scenario: str, drive: Path, n_frames: int, **over: Any) -> None:
        drive.mkdir(parents=True)
        (drive / "frames.csv").write_text("filename,timestamp_s\n")

    def child(mode: str, drive: Path, out: Path) -> dict[str, Any]:
        calls.append((mode, drive, out))
        if mode == "run":
            (out / "pairs").mkdir(parents=True, exist_ok=True)
            return {"peak_rss_mb": 500.0, "wall_s": 12.0}
        if mode == "mapping":
            return {
                "peak_rss_mb": 200.0,
                "poses_s": 0.5,
                "globalmap_s": 3.25,
                "n_tiles": 4,
                "corridor_px": 2.5e6,
            }
        return {"peak_rss_mb": 300.0}

    monkeypatch.setattr("roadsurf.simulation.scenarios.simulate", simulate)
    monkeypatch.setattr(bench, "_child", child)
    return calls


def test_table_and_work_files(tmp_path: Path, stubs: list[tuple[str, Path, Path]]) -> None:
    res = bench.run_benchmark(tmp_path, (5,), width=320)
    assert [m for m, _, _ in stubs] == ["run", "mapping", "detection"]
    assert stubs[0][1] == tmp_path / "long5_w320" and stubs[0][2] == tmp_path / "run_long5_w320"
    row = res["markdown"].splitlines()[2]
    assert row == (
        "| 5 | 320x240 | 500 MB | 12 s | 200 MB | 0.5 s | 3.2 s | 4 | 2.5 Mpx | 300 MB |"
    )
    assert json.loads((tmp_path / "bench_mapping.json").read_text())["markdown"] == res["markdown"]


def test_main_options_and_result_file(
    tmp_path: Path, stubs: list[tuple[str, Path, Path]], capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "mapping.json"
    work = tmp_path / "work"
    assert bench.main(["--work", str(work), "--frames", "3,4", "--json", str(out)]) == 0
    assert [m for m, _, _ in stubs] == ["run", "mapping", "detection"] * 2
    doc = json.loads(out.read_text())
    assert doc["benchmark"] == "mapping"
    assert [r["frames"] for r in doc["figures"]["rows"]] == [3, 4]
    assert "| 3 | 640x480 |" in capsys.readouterr().out
    # --mapping-only reuses the cached pairs of the first run: no second `roadsurf run`
    stubs.clear()
    bench.main(["--work", str(work), "--frames", "3", "--mapping-only", "--json", str(out)])
    assert [m for m, _, _ in stubs] == ["mapping", "detection"]
