"""`roadsurf evaluate` of a run without a trajectory against another drive's truth is an error
naming both sets of frame names, not a table of zeros."""

from __future__ import annotations

from pathlib import Path

import pytest

from roadsurf.core.errors import RoadsurfError
from roadsurf.evaluation.report import evaluate_run

TRUTH = Path(__file__).resolve().parents[2] / "data_samples" / "drive" / "truth"


def test_run_of_another_drive_is_refused(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "frames.csv").write_text(
        "filename,defect,p_defect,source\n000000.jpg,1,0.9,3d\n000001.jpg,0,0.1,3d\n"
    )
    with pytest.raises(RoadsurfError, match=r"0 of the run's 2 frames \(000000.jpg.*poses.csv"):
        evaluate_run(run, TRUTH)
