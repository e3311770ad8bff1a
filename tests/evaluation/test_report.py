"""evaluate_run (the `roadsurf evaluate` stage) and its markdown report."""

from __future__ import annotations

from pathlib import Path

import pytest

from roadsurf.core.atomic import read_json
from roadsurf.core.errors import RoadsurfError
from roadsurf.detection import stage
from roadsurf.detection.config import DetectionConfig
from roadsurf.evaluation.report import evaluate_run, markdown_table
from roadsurf.io.formats import read_csv, write_csv
from roadsurf.mapping.types import save_trajectory
from tests.detection.synthetic import Pothole, Scene, build, write_truth


def test_markdown_table_formats_units_and_targets() -> None:
    res = {
        "run": "/x/run_a",
        "trajectory_rmse_m": 0.0123,
        "drift_5m_median_pct": 0.5,
        "coverage": 0.9,
        "surface": {"aligned": {"flat_mae_m": float("nan")}},
        "targets": [
            {"target": "t1", "metric": "trajectory_rmse_m", "value": 0.0123, "met": True},
            {"target": "t2", "metric": "coverage", "value": 0.9, "met": False},
            {"target": "t3", "metric": "seam_step_max_m", "value": None, "met": None},
        ],
    }
    md = markdown_table([res])
    assert md.splitlines()[0] == "| metric | run_a |"
    assert "| trajectory RMSE (raw) | 12.30 mm |" in md
    assert "| relative drift over 5 m, median | 0.50 % |" in md
    assert "| coverage of the imaged corridor | 90.0 % |" in md
    assert "| flat-road height MAE (aligned) | n/a |" in md
    assert "- run_a: t1: met (12.30 mm)" in md
    assert "- run_a: t2: NOT met (90.0 %)" in md
    assert "- run_a: t3: n/a (n/a)" in md
    assert markdown_table([res, res], names=["a", "b"]).startswith("| metric | a | b |")


def test_evaluate_run_needs_the_truth_poses(tmp_path: Path) -> None:
    with pytest.raises(RoadsurfError, match="poses.csv"):
        evaluate_run(tmp_path / "run", tmp_path)


def test_evaluate_run_scores_the_detections(tmp_path: Path) -> None:
    scene = Scene(potholes=[Pothole(0.1, 1.0, 0.15, 0.03)])
    drive, pairs, traj = build(scene, tmp_path / "drive")
    truth = tmp_path / "truth"
    write_truth(scene, truth, traj)
    # the full truth pose columns the trajectory evaluation reads
    rows = read_csv(truth / "poses.csv")
    write_csv(
        truth / "poses.csv",
        ["filename", "easting_m", "northing_m", "up_m", "qw", "qx", "qy", "qz", "heading_deg"],
        [(r["filename"], r["easting_m"], r["northing_m"], 0, 1, 0, 0, 0, 0) for r in rows],
    )
    run_dir = tmp_path / "run"
    save_trajectory(run_dir, traj)
    stage.run(DetectionConfig(), drive, pairs, traj, run_dir)
    out = evaluate_run(run_dir, truth)
    # no trajectory.geojson, surface raster nor map points: those figures are skipped
    assert out["warnings"] == ["no georeferenced trajectory.geojson: trajectory figures skipped"]
    assert out["surface"] == {"note": "no surface raster or no truth residual"}
    assert out["seam_pairs"] == 0
    d = out["detection"]["defects"]
    assert (d["predicted"], d["truth"], d["matched"]) == (1, 1, 1)
    assert read_json(run_dir / "evaluation.json")["detection"]["defects"]["matched"] == 1
    assert "| detection: defect recall | 100.0 % |" in (run_dir / "evaluation.md").read_text()
