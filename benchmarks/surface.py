"""Benchmark: the dense surface against the sparse one (issue 29) on whole simulated drives.

Each drive (``SCENARIO`` or ``SCENARIO@PITCH`` for a tilted mount) is simulated once, run with
the defaults (dense surface), then its run folder is copied and the global map and detection
are recomputed with ``mapping: {surface_source: sparse}`` on the same pairs and poses; both are
scored by ``roadsurf evaluate``.

    python -m benchmarks.surface [--drives potholes,tilted@25,tilted@45,highway] [--work DIR]
    make bench-surface ARGS="--drives flat,varied,vibration"

Writes benchmarks/results/surface.json (figures + command, commit, machine, date).
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path
from typing import Any

from benchmarks._result import write_result
from benchmarks.tilted import _cli, figures

# the artifacts of the global map and detection: removed so the copy recomputes them
REDONE = ("map_report.json", "detection.json", "evaluation.json", "evaluation.md")
COLUMNS = [
    ("flat_mae_m", "flat MAE (mm)", 1e3),
    ("defect_height_mae_m", "in-defect MAE (mm)", 1e3),
    ("coverage", "coverage", 1.0),
    ("coverage_two_view", "two-view coverage", 1.0),
    ("frame_accuracy", "frame accuracy", 1.0),
    ("defect_precision", "defect precision", 1.0),
    ("defect_recall", "defect recall", 1.0),
    ("defect_depth_mae_m", "depth MAE (mm)", 1e3),
]


def simulate_args(spec: str, drive: Path, frames: int | None) -> list[str]:
    """``roadsurf simulate`` arguments of a drive spec ``SCENARIO[@PITCH]``."""
    scenario, _, pitch = spec.partition("@")
    args = ["simulate", "--scenario", scenario, "--out", str(drive)]
    if pitch:
        args += ["--mount-pitch", pitch]
    if frames:
        args += ["--frames", str(frames)]
    return args


def simulated(spec: str, drive: Path, frames: int | None, log: Path) -> Path:
    """The drive ``spec`` (``SCENARIO[@PITCH]``) in folder ``drive``, rendered once (reused when
    its truth is there)."""
    if not (drive / "truth").is_dir():
        _cli(*simulate_args(spec, drive, frames), log=log)
    return drive


def timed_run(
    drive: Path, run: Path, log: Path, config_text: str = "", reuse: Path | None = None
) -> float:
    """``roadsurf run`` of ``drive`` into a fresh ``run`` folder, or into a copy of the finished
    run ``reuse`` without its map and detection (``REDONE``: only those are recomputed), with
    ``config_text`` as --config when given (written next to the log). Returns the seconds."""
    shutil.rmtree(run, ignore_errors=True)
    if reuse is not None:
        shutil.copytree(reuse, run)
        for name in REDONE:
            (run / name).unlink(missing_ok=True)
    args = ["run", str(drive), "--out", str(run)]
    if config_text:
        cfg = log.with_suffix(".yaml")
        cfg.write_text(config_text)
        args += ["--config", str(cfg)]
    t0 = time.perf_counter()
    _cli(*args, log=log)
    return time.perf_counter() - t0


def run_drive(spec: str, work: Path, frames: int | None) -> dict[str, dict[str, Any]]:
    """Figures of one drive with the dense (default) and the sparse surface."""
    tag = spec.replace("@", "_")
    drive = simulated(spec, work / f"drive_{tag}", frames, work / f"simulate_{tag}.log")
    out: dict[str, dict[str, Any]] = {}
    for surface in ("dense", "sparse"):
        run = work / f"run_{tag}_{surface}"
        if surface == "dense":
            seconds = timed_run(drive, run, work / f"{tag}_dense.log")
        else:  # the same pairs and poses: only the global map and detection are recomputed
            seconds = timed_run(
                drive, run, work / f"{tag}_sparse.log", "mapping:\n  surface_source: sparse\n",
                reuse=work / f"run_{tag}_dense",
            )  # fmt: skip
        _cli("evaluate", str(run), "--truth", str(drive / "truth"), log=work / f"{tag}_eval.log")
        ev = json.loads((run / "evaluation.json").read_text())
        rep = json.loads((run / "report.json").read_text())
        fig = figures(ev, rep)
        fig.pop("warnings", None)
        fig["coverage_two_view"] = ev.get("coverage_two_view")
        out[surface] = fig | {"run_s": round(seconds, 1)}
        print(f"{spec} {surface}: {json.dumps(out[surface])}", flush=True)
    return out


def _fmt(v: float | None, scale: float) -> str:
    return "–" if v is None or v != v else f"{v * scale:.3g}"  # None or NaN: no such figure


def table(rows: dict[str, dict[str, dict[str, Any]]]) -> str:
    """Markdown: one row per drive, each cell 'sparse -> dense'."""
    out = [
        "| drive | " + " | ".join(c[1] for c in COLUMNS) + " |",
        "|---" * (len(COLUMNS) + 1) + "|",
    ]
    for spec, r in rows.items():
        cells = [
            f"{_fmt(r['sparse'].get(key), scale)} → {_fmt(r['dense'].get(key), scale)}"
            for key, _, scale in COLUMNS
        ]
        out.append(f"| {spec} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", default="potholes,tilted@25,tilted@45,highway",
                    help="SCENARIO or SCENARIO@PITCH, comma-separated")  # fmt: skip
    ap.add_argument("--frames", type=int, default=None, help="frames per drive (scenario's own)")
    ap.add_argument("--work", type=Path, default=Path("out/bench_surface"), help="work folder")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    rows = {spec: run_drive(spec, a.work, a.frames) for spec in a.drives.split(",")}
    md = table(rows)
    print(md)
    print(f"Wrote {write_result(a.json, 'surface', {'drives': rows, 'table_markdown': md})}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
