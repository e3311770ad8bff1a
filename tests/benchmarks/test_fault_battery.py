"""The fault battery's classifier on fabricated results, and two cheap real cases."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks._fault_kit import (
    BAD,
    Proc,
    Verdict,
    classify,
    error_line,
    report_warnings,
    traceback_line,
)
from benchmarks.fault_battery import CASES, _cut_drive, run_case, table

ROOT = Path(__file__).resolve().parents[2]
RICH_TB = """\
╭──────────── Traceback (most recent call last) ────────────╮
│ /work/main/roadsurf/cli/main.py:42 in run                   │
╰────────────────────────────────────────────────────────────╯
TypeError: 'NoneType' object is not iterable
"""


def _proc(rc: int = 0, stderr: str = "", **kw: object) -> Proc:
    return Proc(argv=["x"], rc=rc, stdout="", stderr=stderr, wall_s=1.0, **kw)  # type: ignore[arg-type]


def test_error_line_is_the_last_stderr_line() -> None:
    assert error_line("INFO loaded\n\nerror: camera.yaml line 3: bad\n") == (
        "error: camera.yaml line 3: bad"
    )
    assert error_line("   stopped: interrupted.\n") == "stopped: interrupted."
    assert error_line("error: first\nINFO after\n") is None
    assert traceback_line(RICH_TB) == "TypeError: 'NoneType' object is not iterable"
    assert traceback_line("error: fine\n") is None


@pytest.mark.parametrize(
    ("proc", "kw", "outcome"),
    [
        (_proc(2, "INFO x\nerror: gps.csv line 4: not UTF-8\n"), {"accept": {"error"}}, "error ok"),
        (_proc(130, "stopped: interrupted.\n"), {"accept": {"error"}}, "error ok"),
        (_proc(2, "error: refused\n"), {"accept": {"ok"}}, "BAD ERROR"),
        (_proc(1, "Killed\n"), {"accept": {"error"}}, "BAD ERROR"),
        (_proc(1, RICH_TB), {"accept": {"error"}}, "TRACEBACK"),
        # a traceback logged by a worker counts even when the CLI then ends with one line
        (_proc(2, "Traceback (most recent call last):\nOSError: x\nerror: disk full\n"), {"accept": {"error"}}, "TRACEBACK"),
        (_proc(0), {"accept": {"error"}}, "SILENT WRONG"),
        (_proc(0), {"accept": {"error", "warn"}, "warn_re": "height", "warnings": ["GPS ok"]}, "SILENT WRONG"),
        (_proc(0), {"accept": {"warn"}, "warn_re": "height_m", "warnings": ["height_m 1.10 m disagrees"]}, "warned ok"),
        (_proc(0), {"accept": {"ok"}, "check": lambda: None}, "ok"),
        (_proc(0), {"accept": {"ok"}, "check": lambda: "3 defects, not 6"}, "SILENT WRONG"),
        (_proc(0), {"accept": {"warn+ok"}, "warn_re": "pair", "warnings": ["0 of 11 pairs"], "check": lambda: None}, "warned ok"),
        (_proc(0), {"accept": {"warn+ok"}, "warn_re": "pair", "warnings": ["0 of 11 pairs"], "check": lambda: "labelled 0"}, "SILENT WRONG"),
        (_proc(0), {"accept": {"warn+ok"}, "warn_re": "pair", "check": lambda: None}, "SILENT WRONG"),
        (_proc(2, "error: x\n", drive_lost=["drive/frames.csv"]), {"accept": {"error"}}, "DATA LOST"),
        (_proc(0, drive_added=["drive/report.json"]), {"accept": {"ok"}}, "SILENT WRONG"),
        (_proc(130, "stopped: x\n", leftovers=["pid 7 rerun"]), {"accept": {"error"}}, "SILENT WRONG"),
        (_proc(-9, timed_out=True), {"accept": {"error"}}, "TIMEOUT"),
        (None, {"accept": {"ok"}, "check": lambda: None}, "ok"),
    ],
)  # fmt: skip
def test_classify(proc: Proc | None, kw: dict, outcome: str) -> None:
    assert classify(proc, **kw).outcome == outcome


def test_check_runs_only_on_exit_zero() -> None:
    def boom() -> str | None:
        raise AssertionError("check ran on a failed command")

    assert (
        classify(_proc(2, "error: x\n"), accept={"error", "ok"}, check=boom).outcome == "error ok"
    )


def test_case_folder_names_do_not_match_warning_patterns(tmp_path: Path) -> None:
    run = tmp_path / "cases" / "lat_lon_values_swapped" / "run"
    run.mkdir(parents=True)
    w = f"{run.parent}/drive/obd.csv: OBD speed disagrees with the GPS ground speed"
    (run / "report.json").write_text(json.dumps({"warnings": [w]}))
    assert report_warnings(run) == ["drive/obd.csv: OBD speed disagrees with the GPS ground speed"]
    v = classify(_proc(0), accept={"warn"}, warn_re="swap", warnings=report_warnings(run))
    assert v.outcome == "SILENT WRONG"


def test_table_counts_and_bold_bad_outcomes() -> None:
    rows = [
        (CASES[0], Verdict("error ok", 2, "error: a | b")),
        (CASES[1], Verdict("TRACEBACK", 1, "X")),
    ]
    text = table(rows)
    assert "**TRACEBACK**" in text and "a \\| b" in text
    assert "error ok 1" in text and "TRACEBACK 1" in text and "DATA LOST 0" in text


def test_cases_have_unique_names_covering_every_item() -> None:
    names = [c.name for c in CASES]
    assert len(names) == len(set(names)) and len(names) >= 30
    items = {i.strip() for c in CASES for i in c.item.split(",")}
    assert {str(i) for i in range(1, 10)} <= items


def test_two_real_cases_fail_with_one_line(tmp_path: Path) -> None:
    drive = tmp_path / "drive"
    _cut_drive(ROOT / "data_samples" / "drive", drive, 3)
    shared = {"drive": drive, "work": tmp_path}
    by_name = {c.name: c for c in CASES}
    for name in ("'~: 1' in --config", "--out an existing file"):
        v = run_case(by_name[name], tmp_path, shared)
        assert v.outcome == "error ok", (name, v)
        assert v.outcome not in BAD
