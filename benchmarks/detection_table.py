"""Pooling and the markdown table of the detection benchmark (``benchmarks.detection``).

Per method the per-drive evaluations (``roadsurf.evaluation.detection.evaluate_detection``) are
pooled (``pool``: summed counts, errors over all matched defects) and shown side by side with the
issue 5 targets as met / not met (``table_markdown``).
"""

from __future__ import annotations

from typing import Any

import numpy as np


def pool(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Pool per-drive evaluations: sums of counts, errors over all matched defects."""
    tp = sum(r["frames"]["TP"] for r in results)
    tn = sum(r["frames"]["TN"] for r in results)
    fp = sum(r["frames"]["FP"] for r in results)
    fn = sum(r["frames"]["FN"] for r in results)
    d = [r["defects"] for r in results]
    pred = sum(x["predicted"] for x in d)
    truth = sum(x["truth"] for x in d)
    matched = sum(x["matched"] for x in d)
    tgt = sum(x["target_truth"] for x in d)
    tgt_hit = sum(round(x["target_recall"] * x["target_truth"]) for x in d if x["target_truth"])
    m = [mm for x in d for mm in x["matches"]]
    derr = np.array([mm["depth_err_m"] for mm in m])
    rel = np.array(
        [abs(mm["depth_err_m"]) / mm["truth_depth_m"] for mm in m if mm["truth_depth_m"] > 0]
    )
    aerr = np.array([mm["area_rel_err"] for mm in m if np.isfinite(mm["area_rel_err"])])

    by_type_t: dict[str, int] = {}
    by_type_m: dict[str, int] = {}
    for x in d:
        for k, v in x.get("truth_by_type", {}).items():
            by_type_t[k] = by_type_t.get(k, 0) + v
        for k, v in x.get("matched_by_type", {}).items():
            by_type_m[k] = by_type_m.get(k, 0) + v

    def div(a: float, b: float) -> float:
        return a / b if b else float("nan")

    p, rcl = div(matched, pred), div(matched, truth)
    return {
        "frames": tp + tn + fp + fn,
        "TP": tp,
        "TN": tn,
        "FP": fp,
        "FN": fn,
        "accuracy": div(tp + tn, tp + tn + fp + fn),
        "precision": div(tp, tp + fp),
        "recall": div(tp, tp + fn),
        "defects_pred": pred,
        "defects_truth": truth,
        "defects_matched": matched,
        "defect_precision": p,
        "defect_recall": rcl,
        "defect_f1": div(2 * p * rcl, p + rcl) if matched else 0.0,
        "target_recall": div(tgt_hit, tgt),
        "target_truth": tgt,
        "depth_mae_m": float(np.mean(np.abs(derr))) if len(derr) else float("nan"),
        "depth_bias_m": float(np.mean(derr)) if len(derr) else float("nan"),
        "depth_rel_err": float(np.mean(rel)) if len(rel) else float("nan"),
        "area_median_rel_err": float(np.median(aerr)) if len(aerr) else float("nan"),
        "recall_by_type": {k: f"{by_type_m.get(k, 0)}/{v}" for k, v in sorted(by_type_t.items())},
        "distractor_false_alarms": sum(x["distractor_false_alarms"] for x in d),
        "distractors": sum(x["distractors"] for x in d),
    }


def _fmt(v: Any, pct: bool = False, mm: bool = False) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "n/a"
    if pct:
        return f"{100 * v:.1f}%"
    if mm:
        return f"{1000 * v:.2f}"
    return str(v)


TARGETS: tuple[tuple[str, str, str, Any], ...] = (
    # (pooled key, text, kind, threshold)
    ("accuracy", "frame accuracy >= 99%", "ge", 0.99),
    ("precision", "frame precision >= 97%", "ge", 0.97),
    ("recall", "frame recall >= 97%", "ge", 0.97),
    ("target_recall", "pothole (>= 25 mm, >= 150 mm) recall >= 95%", "ge", 0.95),
    ("defect_precision", "defect precision >= 95%", "ge", 0.95),
    ("distractor_false_alarms", "no defects on distractors", "le", 0),
    ("depth_mae_m", "depth MAE <= 3 mm", "le", 0.003),
    ("area_median_rel_err", "median area error <= 15%", "le", 0.15),
)


def _met(v: Any, kind: str, thr: Any) -> bool:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return False
    return v >= thr if kind == "ge" else v <= thr


def table_markdown(
    pooled: dict[str, dict[str, Any]],
    tb: dict[str, dict[str, Any]],
    bstats: dict[str, dict[str, int]] | None = None,
) -> str:
    """The Table 4.2-style comparison, the T_b comparison and the targets, as markdown."""
    methods = list(pooled)
    rows = [
        ("frames (TP/TN/FP/FN)", lambda p: f"{p['TP']}/{p['TN']}/{p['FP']}/{p['FN']}"),
        ("frame accuracy", lambda p: _fmt(p["accuracy"], pct=True)),
        ("frame precision", lambda p: _fmt(p["precision"], pct=True)),
        ("frame recall", lambda p: _fmt(p["recall"], pct=True)),
        (
            "defects found / true / matched",
            lambda p: f"{p['defects_pred']}/{p['defects_truth']}/{p['defects_matched']}",
        ),
        ("defect precision", lambda p: _fmt(p["defect_precision"], pct=True)),
        ("defect recall (all types)", lambda p: _fmt(p["defect_recall"], pct=True)),
        (
            "found per type",
            lambda p: ", ".join(f"{k} {v}" for k, v in p.get("recall_by_type", {}).items()),
        ),
        ("defect F1", lambda p: _fmt(p["defect_f1"], pct=True)),
        ("pothole recall (>= 25 mm, >= 150 mm)", lambda p: _fmt(p["target_recall"], pct=True)),
        ("depth MAE (mm)", lambda p: _fmt(p["depth_mae_m"], mm=True)),
        ("depth bias (mm)", lambda p: _fmt(p["depth_bias_m"], mm=True)),
        ("relative depth error", lambda p: _fmt(p["depth_rel_err"], pct=True)),
        ("median area error", lambda p: _fmt(p["area_median_rel_err"], pct=True)),
        (
            "false alarms on distractors",
            lambda p: f"{p['distractor_false_alarms']} (of {p['distractors']})",
        ),
    ]
    out = ["| | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for name, fn in rows:
        out.append(f"| {name} | " + " | ".join(fn(pooled[m]) for m in methods) + " |")
    if tb:
        out += [
            "",
            "Effect of T_b on the dissertation's per-pair frame decision (refined points only, "
            f"`frame_label: pair`), {methods[0]} reconstructions; the product's map-based label "
            "for reference:",
            "",
            "| frame label | TP/TN/FP/FN | accuracy | precision | recall |",
            "|---|---|---|---|---|",
        ]
        for name, p in tb.items():
            out.append(
                f"| {name} | {p['TP']}/{p['TN']}/{p['FP']}/{p['FN']} | "
                f"{_fmt(p['accuracy'], pct=True)} | {_fmt(p['precision'], pct=True)} | "
                f"{_fmt(p['recall'], pct=True)} |"
            )
    if bstats:
        out += [
            "",
            "Binarisation alone (pixels of the 3D classes that T_b calls dark; ideal: 0% of road, "
            "100% of defects deeper than 2 T_d):",
            "",
            "| T_b | road points dark (false) | defect points dark (hits) |",
            "|---|---|---|",
        ]
        for mode, st in bstats.items():
            fr = st["road_dark"] / st["road"] if st["road"] else float("nan")
            hr = st["defect_dark"] / st["defect"] if st["defect"] else float("nan")
            out.append(
                f"| {mode} | {_fmt(fr, pct=True)} of {st['road']} | "
                f"{_fmt(hr, pct=True)} of {st['defect']} |"
            )
    if methods:
        p = pooled[methods[0]]
        out += ["", f"Issue 5 targets ({methods[0]}, the product's default):", ""]
        for key, text, kind, thr in TARGETS:
            v = p[key]
            shown = (
                _fmt(v, mm=True) + " mm"
                if key == "depth_mae_m"
                else str(v)
                if key == "distractor_false_alarms"
                else _fmt(v, pct=True)
            )
            out.append(f"- {text}: {shown} — **{'met' if _met(v, kind, thr) else 'not met'}**")
    return "\n".join(out)
