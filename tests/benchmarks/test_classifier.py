"""benchmarks.classifier: scoring against truth, the markdown table and the entry point."""

from __future__ import annotations

import pytest

from benchmarks.classifier import main
from benchmarks.classifier_drives import LONG_DRIVE, TEST_DRIVES, TRAIN_DRIVES, shortened
from benchmarks.classifier_report import to_markdown
from benchmarks.classifier_score import score


def test_score_breaks_false_positives_down_by_distractor() -> None:
    truth = {"a": 1, "b": 0, "c": 0, "d": 0}
    pred = {"a": 1, "b": 1, "c": 1, "d": 0}
    m = score(pred, truth, {"b": {"shadow", "lane_marking"}, "d": {"oil_stain"}})
    assert (m["TP"], m["FP"], m["TN"], m["FN"]) == (1, 2, 1, 0)
    assert m["fp_with_distractor"] == {"shadow": 1, "lane_marking": 1}
    assert m["fp_on_plain_road"] == 1  # c: a false positive with nothing in view


def test_markdown_has_a_row_per_test_drive_and_method() -> None:
    truth = {"a": 1, "b": 0}
    m = {**score({"a": 1, "b": 0}, truth, {}), "s_per_frame": 0.5, "cpu_s_per_frame": 0.25}
    res = {
        "tests": {
            "t": {
                "frames": 2,
                "defect_frames": 1,
                "cnn": m,
                "fused": m,
                "physics": {**m, "s_per_frame": 1.0},
                "time_ratio_fused_over_physics": 0.5,
                "cpu_time_ratio_fused_over_physics": 0.5,
                "fused_sources": {"cnn": 1, "3d": 1, "fused": 0},
                "pairs_reconstructed": {"physics": 1, "fused": 1},
            }
        },
        "balance": {
            "before_augmentation": {"non-defect": 1, "defect": 1},
            "after_augmentation": {"non-defect": 1, "defect": 2},
            "dropped_frames": {},
        },
        "self_labels_vs_truth": {"train": {**m, "frames_labelled": 2, "frames_total": 2}},
        "model": {"best_epoch": 1, "train_time_s": 1.0, "val_metrics": {"val_accuracy": 1.0}},
    }
    md = to_markdown(res)
    rows = [r for r in md.splitlines() if r.startswith("| t (1/2 defect)")]
    assert [r.split(" | ")[1] for r in rows] == ["image-only CNN", "fused CNN+3D", "3D only"]
    assert rows[0].endswith("| 100.0 | 100.0 | 100.0 | 1/1/0/0 | 0/0/0 | 0.500 | 0.250 |")
    assert "fused/physics time = 0.50 (wall)" in md


def test_quick_drives_are_shorter_and_the_entry_point_parses_its_options() -> None:
    assert all(shortened(s, 30).n_frames <= 30 for s in (*TRAIN_DRIVES, *TEST_DRIVES))
    assert shortened(LONG_DRIVE, 80).n_frames == 80
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
