"""Markdown of the classifier benchmark's results (Table 5.2 style)."""

from __future__ import annotations

import json
from typing import Any


def _pct(v: Any) -> str:
    try:
        return f"{100 * float(v):.1f}" if v == v else "n/a"
    except (TypeError, ValueError):
        return "n/a"


def _secs(v: Any) -> str:
    return f"{float(v):.3f}" if isinstance(v, (int, float)) and v == v else "n/a"


def to_markdown(res: dict[str, Any]) -> str:
    """Table 5.2-style markdown of ``bench_classifier`` results."""
    lines = [
        "| test drive | method | acc % | prec % | rec % | TP/TN/FP/FN | FP with lane/shadow/oil "
        "| s per image (wall) | CPU s per image |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in res["tests"].items():
        for key, label in (
            ("cnn", "image-only CNN"),
            ("fused", "fused CNN+3D"),
            ("fused_3d_confirms", "fused, 3D confirms CNN defects"),
            ("fused_no_audit", "fused without audit/growth (same run; time not measured)"),
            ("physics", "3D only"),
        ):
            if key not in r:
                continue
            m = r[key]
            fpd = m.get("fp_with_distractor", {})
            lines.append(
                f"| {name} ({r['defect_frames']}/{r['frames']} defect) | {label} | "
                f"{_pct(m['accuracy'])} | {_pct(m['precision'])} | {_pct(m['recall'])} | "
                f"{m['TP']}/{m['TN']}/{m['FP']}/{m['FN']} | "
                f"{fpd.get('lane_marking', 0)}/{fpd.get('shadow', 0)}/{fpd.get('oil_stain', 0)} | "
                f"{_secs(m['s_per_frame'])} | {_secs(m['cpu_s_per_frame'])} |"
            )
    lines.append("")
    for name, r in res["tests"].items():
        lines.append(
            f"- {name}: fused/physics time = {r['time_ratio_fused_over_physics']:.2f} (wall), "
            f"{r['cpu_time_ratio_fused_over_physics']:.2f} (CPU); fused "
            f"sources {r['fused_sources']}; pairs reconstructed {r['pairs_reconstructed']}; "
            f"stage wall s {r.get('stage_timings_s')}; load avg (start, end) "
            f"{r.get('load_avg_1min')}"
        )
        sc = r.get("screening") or {}
        if sc.get("frames_with_3d_by_reason") is not None:
            lines.append(
                f"- {name}: frames sent to 3D by reason {sc['frames_with_3d_by_reason']} "
                f"({sc.get('rounds')} reconstruction round(s), {sc.get('pairs_reconstructed')} pairs)"
            )
        c = r.get("cnn_confidence")
        if c:
            lines.append(
                f"- {name}: CNN sure (p <= 1 - threshold) on {c['clear_frames_confident']} of "
                f"{c['clear_frames']} clear frames; sure and wrong on "
                f"{len(c['confident_wrong'])} frames {c['confident_wrong']}"
            )
    b = res["balance"]
    lines.append(
        f"- training set: before augmentation {b['before_augmentation']}, after "
        f"{b['after_augmentation']}, dropped {b['dropped_frames']}"
    )
    for name, m in res["self_labels_vs_truth"].items():
        lines.append(
            f"- self-labels {name}: {m['frames_labelled']}/{m['frames_total']} frames labelled, "
            f"accuracy {_pct(m['accuracy'])} %, precision {_pct(m['precision'])} %, "
            f"recall {_pct(m['recall'])} % vs truth"
        )
    mm = res["model"]
    if mm.get("calibration"):
        lines.append(f"- calibration: {json.dumps(mm['calibration'])}")
    lines.append(
        f"- CNN: best epoch {mm['best_epoch']}, training {mm['train_time_s']} s, validation "
        f"{json.dumps({k: v for k, v in (mm['val_metrics'] or {}).items() if k.startswith('val_') and k[4:] in ('accuracy', 'precision', 'recall')})}"
    )
    return "\n".join(lines) + "\n"
