"""Benchmark: the reconstruction study (``make bench-reconstruction``).

``python -m benchmarks.reconstruction [--out DIR] [--quick] ...``: the point-level parametric
study (Figs. 3.6-3.12, the first-order bound, issue 3's targets; ``reconstruction_study``) and
the accuracy on rendered simulator drives (``reconstruction_images``). The CSV files, figures
and summary.md go to the output folder; the printed report and figures also go to
benchmarks/results/reconstruction.json.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from benchmarks.reconstruction_study import write_rows_csv
from roadsurf.core.atomic import write_text_atomic


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
    from benchmarks.reconstruction_study import run_study

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
        from benchmarks.reconstruction_images import bench_images

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


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.reconstruction`` (``make bench-reconstruction ARGS="..."``)."""
    import argparse

    from benchmarks._result import write_result

    ap = argparse.ArgumentParser(
        description="Parametric study (Figs. 3.6-3.12, bound, targets) and rendered-drive accuracy."
    )
    ap.add_argument(
        "--out",
        "-o",
        type=Path,
        default=Path("docs/img/reconstruction"),
        help="folder for CSV, figures, summary.md",
    )
    ap.add_argument("--quick", action="store_true", help="fewer cells, trials and frames")
    ap.add_argument("--trials", type=int, default=None, help="Monte-Carlo trials per cell")
    ap.add_argument("--workers", type=int, default=2, help="worker processes")
    ap.add_argument(
        "--images",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also evaluate rendered drives",
    )
    ap.add_argument("--frames", type=int, default=None, help="frames per rendered drive")
    ap.add_argument(
        "--study",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="run the point-level study",
    )
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    report = bench_reconstruction(
        a.out,
        quick=a.quick,
        trials=a.trials,
        workers=a.workers,
        images=a.images,
        frames=a.frames,
        study=a.study,
    )
    print(report)
    write_result(a.json, "reconstruction", {"out": str(a.out), "report": report})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
