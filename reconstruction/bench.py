"""Entry points of ``roadsurf bench reconstruction`` and ``roadsurf bench speed``.

Each returns the printable report; the files go to the output folder (CSV, PNG, markdown).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from roadsurf.core.atomic import write_text_atomic
from roadsurf.reconstruction.io_helpers import write_rows_csv


def bench_reconstruction(
    out: Path,
    *,
    quick: bool = False,
    trials: int | None = None,
    workers: int = 2,
    images: bool = True,
    work: Path | None = None,
    frames: int | None = None,
    study: bool = True,
) -> str:
    """Parametric study (point level) + rendered drives (image level). Returns the report.

    study=False re-runs only the rendered-drive part and keeps the study's summary.md part.
    """
    from roadsurf.reconstruction.study import run_study

    out = Path(out)
    lines: list[str] = []
    prev = out / "summary.md"
    prev_md = prev.read_text(encoding="utf-8") if prev.is_file() else ""
    if study:
        st = run_study(out, quick=quick, trials=trials, workers=workers)
        lines = ["Parametric study (point level):"]
        lines += [
            f"  [{'MET' if ok else 'NOT MET'}] {name}: {detail}"
            for name, ok, detail in st["targets"]
        ]
        md = "## Point-level study\n\n" + st["summary"]
    else:
        md = prev_md.split("\n## Rendered drives")[0]
    if images:
        from roadsurf.reconstruction.bench_images import bench_images

        work = Path(work or Path(tempfile.gettempdir()) / "roadsurf_bench_drives")
        n = frames or (12 if quick else 30)
        rows, summary, img_md = bench_images(work, n_frames=n)
        write_rows_csv(out / "images_pairs.csv", rows)
        write_rows_csv(out / "images_summary.csv", summary)
        md += "\n## Rendered drives\n\n" + img_md
        lines.append("Rendered drives (50% overlap):")
        for s in summary:
            lines.append(
                f"  {s['drive']:26s} {s['method']:15s} success {s['success']:6.1%}  "
                f"points {s['points_median']:5.0f}  RMSE flat {s['rmse_flat_mm']:6.2f} mm  "
                f"pothole {s['rmse_pothole_mm']:6.2f} mm"
            )
        ours = [s for s in summary if s["method"] in ("proposed", "rotation_aware")]
        worst = min((s["success"] for s in ours), default=float("nan"))
        lines.append(
            f"  [{'MET' if worst >= 0.99 else 'NOT MET'}] success ≥ 99% at 50% overlap: worst {worst:.1%}"
        )
    elif "\n## Rendered drives" in prev_md:  # keep the previous image-level part
        md += "\n## Rendered drives" + prev_md.split("\n## Rendered drives", 1)[1]
    write_text_atomic(out / "summary.md", md)
    lines.append(f"Wrote {out}/study_cells.csv, figures fig3_*.png and summary.md")
    return "\n".join(lines)


def bench_speed_report(
    out: Path,
    *,
    frames: int = 60,
    repeats: int = 5,
    max_features: int | None = None,
    kind: str = "sift",
) -> str:
    """Speed benchmark; returns the markdown report (also OUT/speed.md)."""
    from dataclasses import replace

    from roadsurf.reconstruction.bench_speed import bench_speed
    from roadsurf.reconstruction.config import ReconstructionConfig

    base = ReconstructionConfig()
    mf = max_features or base.features.max_features
    cfg = replace(base, features=replace(base.features, kind=kind, max_features=mf))  # type: ignore[arg-type]
    res = bench_speed(Path(out), n_frames=frames, repeats=repeats, cfg=cfg)
    d = res["drive"]
    verdict = "MET" if d["pairs_per_s"] >= 5 else "NOT MET"
    return (
        res["markdown"]
        + f"\n[{verdict}] ≥ 5 pairs/s with {kind} on this machine: {d['pairs_per_s']:.2f} pairs/s\n"
    )
