"""Pooling, table and docs section of `roadsurf bench detection` (no simulation here)."""

from roadsurf.detection.bench import DOC_BEGIN, DOC_END, _pool, table_markdown, update_docs


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
    p = _pool([a, b])
    assert (p["TP"], p["TN"], p["FP"], p["FN"]) == (5, 30, 1, 1)
    assert p["accuracy"] == 35 / 37
    assert p["defect_precision"] == 2 / 3 and p["defect_recall"] == 1.0
    assert abs(p["depth_mae_m"] - 0.003) < 1e-12 and abs(p["depth_bias_m"] - 0.001) < 1e-12
    assert abs(p["area_median_rel_err"] - 0.2) < 1e-12
    assert p["distractor_false_alarms"] == 1


def test_table_lists_methods_and_targets():
    p = _pool([_res(5, 20, 0, 0, 2, 2, 2, [0.001, -0.001], [0.05, 0.1])])
    q = _pool([_res(2, 18, 2, 3, 6, 2, 1, [0.01], [0.6], fa=2)])
    md = table_markdown({"rotation_aware": p, "classic": q}, {"map (product)": p})
    assert "| | rotation_aware | classic |" in md
    assert "frame accuracy >= 99%: 100.0% — **met**" in md
    assert "no defects on distractors: 0 — **met**" in md
    assert "| map (product) | 5/20/0/0 |" in md


def test_update_docs_rewrites_only_its_section(tmp_path):
    doc = tmp_path / "benchmarks.md"
    doc.write_text("# Benchmarks\n\n## mapping\n\nkeep me\n", encoding="utf-8")
    update_docs(doc, "TABLE ONE", "roadsurf bench detection", 60.0, (("flat", 1, 10),))
    update_docs(doc, "TABLE TWO", "roadsurf bench detection", 60.0, (("flat", 1, 10),))
    text = doc.read_text(encoding="utf-8")
    assert "keep me" in text and "TABLE TWO" in text and "TABLE ONE" not in text
    assert text.count(DOC_BEGIN) == 1 and text.count(DOC_END) == 1


def test_update_docs_says_when_only_detection_was_rerun(tmp_path):
    doc = tmp_path / "benchmarks.md"
    update_docs(
        doc, "T", "roadsurf bench detection --detection-only", 1800.0, (("flat", 1, 10),), 90.0
    )
    text = doc.read_text(encoding="utf-8")
    assert "detection stage re-run alone" in text and "1.5 min wall" in text
    assert "load average" in text and "30 min for a cold run" in text


def test_detection_only_needs_the_runs(tmp_path):
    import pytest

    from roadsurf.core.errors import RoadsurfError
    from roadsurf.detection.bench import redetect

    (tmp_path / "run").mkdir()
    with pytest.raises(RoadsurfError, match="without --detection-only"):
        redetect(tmp_path / "run", tmp_path / "drive")
