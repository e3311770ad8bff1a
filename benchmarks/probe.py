"""Benchmark: does the fused run's audit probe see what a full pair sees?

For every ``step``-th consecutive pair of each drive, the probe (``reconstruction.probe``) and
the full pair (SIFT on both frames + ``reconstruct_features``, as the reconstruction stage
computes an isolated audit pair) run one after the other in this process, so their times are
comparable. Each full pair's frame a is labelled by the self-labelling rule (eq. 5.8-5.9,
``label_frame``: defect, ambiguous or clear); the probe *escalates* (the fused run then makes
it a full pair) when it fails or has more than ``audit_probe_max_deep_points`` points deeper
than ``audit_probe_depth_frac`` x Z^d. A *miss* is a pair whose full pair is not clear while
the probe did not escalate: the audit would have passed over depth a full pair sees.

``python -m benchmarks.probe DRIVE... [--step N] [--config YAML]`` (``make bench-probe``).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from roadsurf.detection.classifier.config import ClassifierConfig
from roadsurf.detection.classifier.guided import probe_depth_points
from roadsurf.detection.classifier.selflabel import figures_from_pairs, label_frame
from roadsurf.io.drive import load_drive, read_gray
from roadsurf.reconstruction import features as feat
from roadsurf.reconstruction.api import reconstruct_features
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.probe import probe_pair


@dataclass
class ProbeBenchRow:
    """One drive's figures."""

    drive: str
    pairs: int = 0
    probe_failed: int = 0
    full_not_clear: int = 0  # full pair's frame a is defect or ambiguous by the rule
    escalated: int = 0  # probe failed or showed some depth -> full pair in a fused run
    missed: int = 0  # full pair not clear, probe did not escalate
    false_escalations: int = 0  # probe escalated, full pair clear
    probe_s: float = 0.0  # total CPU-bound wall time of the probes (s)
    full_s: float = 0.0  # total wall time of the full pairs (s)
    missed_pairs: str = ""


def bench_probe(
    drives: list[Path],
    step: int = 1,
    rec_cfg: ReconstructionConfig | None = None,
    cls_cfg: ClassifierConfig | None = None,
    progress: bool = True,
) -> list[ProbeBenchRow]:
    """Probe against full pair on every ``step``-th pair of each drive -> one row per drive."""
    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    rec_cfg = rec_cfg or ReconstructionConfig()
    cls_cfg = cls_cfg or ClassifierConfig()
    rows = []
    for d in drives:
        drive = load_drive(d)
        h = drive.camera.height_m
        row = ProbeBenchRow(Path(d).name)
        fr = drive.frames
        missed = []
        for i in tqdm(range(0, len(fr) - 1, step), desc=row.drive, disable=not progress):
            a, b = fr[i], fr[i + 1]
            ga, gb = read_gray(a), read_gray(b)
            t0 = time.perf_counter()
            pr = probe_pair(ga, gb, drive.camera, rec_cfg)
            t1 = time.perf_counter()
            full = reconstruct_features(
                feat.detect(ga, rec_cfg.features),
                feat.detect(gb, rec_cfg.features),
                drive.camera,
                rec_cfg,
            )
            t2 = time.perf_counter()
            row.pairs += 1
            row.probe_s += t1 - t0
            row.full_s += t2 - t1
            if not full.ok:  # nothing to compare against
                continue
            full.frame_a, full.frame_b = a.filename, b.filename
            fig = figures_from_pairs([full], h, cls_cfg).get(a.filename)
            not_clear = label_frame(fig, None, cls_cfg)[0] != 0
            n_deep = probe_depth_points(pr, h, cls_cfg) if pr.ok else None
            esc = n_deep is None or n_deep > cls_cfg.audit_probe_max_deep_points
            row.probe_failed += not pr.ok
            row.full_not_clear += not_clear
            row.escalated += esc
            row.false_escalations += esc and not not_clear
            if not_clear and not esc:
                row.missed += 1
                missed.append(f"{a.index}-{b.index}")
        row.missed_pairs = " ".join(missed)
        rows.append(row)
    return rows


def report(rows: list[ProbeBenchRow]) -> str:
    """Markdown table of ``bench_probe`` rows."""
    out = [
        "| drive | pairs | probe failed | full pair not clear | escalated | missed "
        "| false escalations | probe ms/pair | full ms/pair | probe / full |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        n = max(1, r.pairs)
        out.append(
            f"| {r.drive} | {r.pairs} | {r.probe_failed} | {r.full_not_clear} | {r.escalated} "
            f"| {r.missed}{' (' + r.missed_pairs + ')' if r.missed else ''} "
            f"| {r.false_escalations} | {1e3 * r.probe_s / n:.0f} | {1e3 * r.full_s / n:.0f} "
            f"| {r.probe_s / max(r.full_s, 1e-9):.2f} |"
        )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.probe DRIVE...`` (``make bench-probe ARGS="DRIVE..."``)."""
    import argparse

    from benchmarks._result import write_result
    from roadsurf.pipeline.run import load_pipeline_config

    ap = argparse.ArgumentParser(
        description="The fused run's audit probe against a full pair on every pair: misses "
        "and time."
    )
    ap.add_argument("drives", nargs="+", type=Path, help="drive folders")
    ap.add_argument("--step", type=int, default=1, help="compare every step-th pair")
    ap.add_argument(
        "--config",
        type=Path,
        default=None,
        help="YAML config (reconstruction and classifier sections)",
    )
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    cfg = load_pipeline_config(a.config)
    rows = bench_probe(a.drives, a.step, cfg.reconstruction, cfg.classifier)
    table = report(rows)
    print(table)
    write_result(
        a.json, "probe", {"markdown": table, "rows": [dataclasses.asdict(r) for r in rows]}
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
