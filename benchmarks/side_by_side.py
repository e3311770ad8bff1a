"""Benchmark: one drive, four reconstructions side by side (issues 29 and 30): roadsurf with its
defaults (dense surface, bundle adjustment), roadsurf without the bundle adjustment (the pose
graph alone), roadsurf with the sparse surface (same pairs and poses as the default run, the map
and detection redone) and pycolmap's incremental SfM (``roadsurf sfm-baseline``), all scored
by one ``roadsurf evaluate`` call.

    python -m benchmarks.side_by_side [--scenario potholes] [--frames N] [--work DIR]
    make bench-side_by_side ARGS="--scenario potholes"
    python -m benchmarks.side_by_side --rescore   # score the runs in --work again

Writes benchmarks/results/side_by_side.json (the evaluation table and figures + command,
commit, machine, date) and WORK/evaluation.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path
from typing import Any

from benchmarks._result import write_result
from benchmarks.surface import simulated, timed_run
from benchmarks.tilted import _cli

# (name, config YAML or None, how the run is made)
RUNS = (
    ("roadsurf", None),
    ("roadsurf_no_ba", "mapping:\n  bundle_adjust: false\n"),
    ("roadsurf_sparse", "mapping:\n  surface_source: sparse\n"),
)
KEYS = (
    "trajectory_rmse_m",
    "trajectory_rmse_aligned_m",
    "drift_5m_median_pct",
    "drift_5m_p95_pct",
    "coverage",
    "coverage_two_view",
    "seam_step_max_m",
    "cloud_points_per_m2",
)


def _figures(ev: dict[str, Any], seconds: float) -> dict[str, Any]:
    out = {k: ev.get(k) for k in KEYS}
    aligned = (ev.get("surface") or {}).get("aligned") or {}
    out["flat_mae_m"] = aligned.get("flat_mae_m")
    out["defect_height_mae_m"] = aligned.get("defect_mae_m")
    det = ev.get("detection") or {}
    d = det.get("defects_raw") or det.get("defects") or {}
    out["defect_precision"], out["defect_recall"] = d.get("precision"), d.get("recall")
    out["run_s"] = seconds
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="potholes", help="simulator scenario")
    ap.add_argument("--frames", type=int, default=None, help="frames (the scenario's own)")
    ap.add_argument("--work", type=Path, default=Path("out/bench_side_by_side"))
    ap.add_argument("--no-sfm", action="store_true", help="skip the pycolmap baseline")
    ap.add_argument("--rescore", action="store_true", help="only evaluate the runs in --work")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    drive = simulated(a.scenario, a.work / "drive", a.frames, a.work / "simulate.log")
    seconds: dict[str, float] = {}
    outs: list[Path] = []
    if a.rescore:  # the runs of an earlier call, scored again (their times from its result)
        outs = [a.work / n for n, _ in RUNS] + ([] if a.no_sfm else [a.work / "pycolmap"])
        old = a.json or Path(__file__).parent / "results" / "side_by_side.json"
        if old.is_file():
            runs = json.loads(old.read_text())["figures"]["runs"]
            seconds = {k: v.get("run_s", float("nan")) for k, v in runs.items()}
    for name, cfg_text in () if a.rescore else RUNS:
        run = a.work / name
        # the sparse surface on the default run's pairs and poses: map and detection redone
        reuse = a.work / "roadsurf" if name == "roadsurf_sparse" else None
        seconds[name] = timed_run(drive, run, a.work / f"{name}.log", cfg_text or "", reuse)
        outs.append(run)
    if not a.no_sfm and not a.rescore:
        sfm = a.work / "pycolmap"
        shutil.rmtree(sfm, ignore_errors=True)
        t0 = time.perf_counter()
        _cli("sfm-baseline", str(drive), "--out", str(sfm), log=a.work / "pycolmap.log")
        seconds["pycolmap"] = time.perf_counter() - t0
        outs.append(sfm)
    _cli("evaluate", *map(str, outs), "--truth", str(drive / "truth"),
         log=a.work / "evaluate.log")  # fmt: skip
    table = (a.work / "evaluate.log").read_text()
    (a.work / "evaluation.md").write_text(table)
    rows = {}
    for run in outs:
        ev = json.loads((run / "evaluation.json").read_text())
        rows[run.name] = _figures(ev, seconds.get(run.name, float("nan")))
    print(table)
    res = {"scenario": a.scenario, "runs": rows, "table_markdown": table}
    print(f"Wrote {write_result(a.json, 'side_by_side', res)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
