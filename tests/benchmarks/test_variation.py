"""The variation sweep's pure helpers: flags, the GPS outlier edit, figures, the table."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest

from benchmarks.variation import (
    figures,
    flags,
    log_warnings,
    prepend_lead_fixes,
    shift_gps_fixes,
    table,
)

GOOD = {
    "trajectory_rmse_m": 0.01,
    "flat_mae_m": 0.001,
    "coverage": 0.95,
    "defect_precision": 1.0,
    "defect_recall": 0.9,
    "frame_accuracy": 1.0,
}


def test_flags_name_each_figure_outside_its_limit_and_missing_ones() -> None:
    assert flags(GOOD) == []
    bad = GOOD | {"trajectory_rmse_m": 0.07, "coverage": 0.5, "frame_accuracy": None}
    got = flags(bad)
    assert len(got) == 3
    assert got[0].startswith("trajectory_rmse_m 0.07")
    assert any(g.startswith("coverage 0.5") for g in got)
    assert "frame_accuracy missing" in got
    assert flags(GOOD | {"flat_mae_m": float("nan")}) == ["flat_mae_m missing"]


def test_shift_gps_fixes_moves_three_fixes_by_the_distance(tmp_path: Path) -> None:
    p = tmp_path / "gps.csv"
    rows = [(0.2 * i, 43.65 + 1e-6 * i, -79.38, 96.0, 0.7) for i in range(20)]
    with open(p, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["timestamp_s", "lat", "lon", "alt_m", "hdop"])
        w.writerows(rows)
    moved = shift_gps_fixes(p, 6.0)
    assert moved == [6, 10, 14]
    with open(p, newline="") as f:
        out = list(csv.DictReader(f))
    assert len(out) == 20
    for i, r in enumerate(out):
        dn = (float(r["lat"]) - rows[i][1]) * 111_132.0
        de = (float(r["lon"]) - rows[i][2]) * 111_320.0 * math.cos(math.radians(rows[i][1]))
        want = 6.0 if i in moved else 0.0
        assert abs(math.hypot(dn, de) - want) < 0.01


def test_figures_count_missed_types_and_the_table_bolds_flagged_cells() -> None:
    ev = {
        "trajectory_rmse_m": 0.02,
        "coverage": 0.7,
        "detection": {
            "defects_raw": {
                "predicted": 5,
                "matched": 4,
                "precision": 0.8,
                "recall": 0.5,
                "target_recall": 1.0,
                "truth_by_type": {"pothole": 3, "crack": 2, "rut": 1},
                "matched_by_type": {"pothole": 3, "rut": 1},
            },
            "frames": {"accuracy": 0.95},
        },
    }
    fig = figures(ev, {"camera_mount": {"pitch_deg": 20.0, "roll_deg": 1.0, "yaw_deg": -2.0}})
    assert fig["missed_by_type"] == {"crack": 2}
    assert fig["false_alarms"] == 1
    assert fig["mount_used_deg"] == [20.0, 1.0, -2.0]
    row = {"what": "x", "run_rc": 0, **fig}
    row["flags"] = flags(row)
    md = table({"c": row})
    assert "**0.7**" in md and "2 crack" in md


def test_log_warnings_keeps_warning_lines_once_and_drops_runpy_noise(tmp_path: Path) -> None:
    log = tmp_path / "run.log"
    log.write_text(
        "<frozen runpy>:128: RuntimeWarning: 'roadsurf.cli.main' found in sys.modules after "
        "import of package 'roadsurf.cli'\n"
        "12:00:00 INFO roadsurf.pipeline.run: stage drive done\n"
        "12:00:01 WARNING roadsurf.mapping.mount: mount: roll 4.1 deg\n"
        "12:00:01 WARNING roadsurf.mapping.mount: mount: roll 4.1 deg\n"
    )
    assert log_warnings(log) == ["12:00:01 WARNING roadsurf.mapping.mount: mount: roll 4.1 deg"]


def test_prepend_lead_fixes_starts_the_log_far_away_on_its_clock(tmp_path: Path) -> None:
    p = tmp_path / "gps.csv"
    rows = [(10.0 + 0.2 * i, -16.5 + 1e-6 * i, -68.15, 3640.0, 0.7) for i in range(5)]
    with open(p, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["timestamp_s", "lat", "lon", "alt_m", "hdop"])
        w.writerows(rows)
    assert prepend_lead_fixes(p, 1000.0, seconds=10) == 10
    with open(p, newline="") as f:
        out = list(csv.DictReader(f))
    assert len(out) == 15
    t = [float(r["timestamp_s"]) for r in out]
    assert t[0] == 0.0 and all(b > a for a, b in zip(t, t[1:], strict=False))
    assert (float(out[10]["lat"]) - float(out[0]["lat"])) * 111_132.0 == pytest.approx(1000.0)
    assert float(out[10]["timestamp_s"]) == 10.0 and float(out[9]["lat"]) < float(out[10]["lat"])
