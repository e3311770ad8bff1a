"""`roadsurf bench loader` builds a repeated drive and reports both timings."""

from __future__ import annotations

from pathlib import Path

from benchmarks.drive_loader import bench_loader
from tests.io.drive_fixtures import make_drive


def test_bench_loader_table(tmp_path: Path) -> None:
    root = make_drive(tmp_path / "d", n=3, ext=".jpg")
    out = bench_loader(root, repeat=2, runs=1)
    # both modes load all 6 frames of the repeated drive
    assert "| 6 | True | 6 |" in out and "| 6 | False | 6 |" in out
