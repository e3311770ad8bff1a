"""Pooling, table and options of the detection benchmark (no simulation here)."""

from pathlib import Path

import pytest

from benchmarks.detection import METHODS, parser, redetect
from benchmarks.detection_table import pool, table_markdown
from roadsurf.core.errors import RoadsurfError


def _res(tp, tn, fp, fn, pred, truth, matched, errs, areas, fa=0):
    return {
        "frames": {"TP": tp, "TN": tn, "FP": fp, "FN": fn},
        "defects": {
            "predicted": pred,
            "truth": truth,
            "matched": matched,
            "target_truth": truth,
            "target_recall": matched / truth if truth else float("nan"),
            "distractor_false_alarms": fa,
            "distractors": 3,
            "matches": [
                {"depth_err_m": e, "truth_depth_m": 0.04, "area_rel_err": a}
                for e, a in zip(errs, areas, strict=True)
            ],
        },
    }


def test_pool_sums_counts_and_pools_errors():
    a = _res(5, 20, 0, 1, 2, 2, 2, [-0.002, 0.004], [0.1, 0.3])
    b = _res(0, 10, 1, 0, 1, 0, 0, [], [], fa=1)
    p = pool([a, b])
    assert (p["TP"], p["TN"], p["FP"], p["FN"]) == (5, 30, 1, 1)
    assert p["accuracy"] == 35 / 37
    assert p["defect_precision"] == 2 / 3 and p["defect_recall"] == 1.0
    assert abs(p["depth_mae_m"] - 0.003) < 1e-12 and abs(p["depth_bias_m"] - 0.001) < 1e-12
    assert abs(p["area_median_rel_err"] - 0.2) < 1e-12
    assert p["distractor_false_alarms"] == 1


def test_table_lists_methods_and_targets():
    p = pool([_res(5, 20, 0, 0, 2, 2, 2, [0.001, -0.001], [0.05, 0.1])])
    q = pool([_res(2, 18, 2, 3, 6, 2, 1, [0.01], [0.6], fa=2)])
    md = table_markdown({"rotation_aware": p, "classic": q}, {"map (product)": p})
    assert "| | rotation_aware | classic |" in md
    assert "frame accuracy >= 99%: 100.0% — **met**" in md
    assert "no defects on distractors: 0 — **met**" in md
    assert "| map (product) | 5/20/0/0 |" in md


def test_options_are_those_of_the_removed_cli_command():
    a = parser().parse_args([])
    assert a.work == Path("out/bench_detection") and not a.quick and not a.detection_only
    assert (
        tuple(a.methods.split(","))
        == METHODS
        == ("rotation_aware", "proposed", "classic", "colmap")
    )
    a = parser().parse_args(["--work", "w", "--quick", "--methods", "classic", "--detection-only"])
    assert (a.work, a.quick, a.methods, a.detection_only) == (Path("w"), True, "classic", True)


def test_detection_only_needs_the_runs(tmp_path):
    (tmp_path / "run").mkdir()
    with pytest.raises(RoadsurfError, match="without --detection-only"):
        redetect(tmp_path / "run", tmp_path / "drive")
