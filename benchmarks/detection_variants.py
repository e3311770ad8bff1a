"""Benchmark: the detection stage alone, re-run with config variants on finished runs (issue 29
part 3: cracks on the dense surface, and which 2D heuristics the dense default still needs).

Each RUN (a finished ``roadsurf run`` of DRIVE, e.g. from ``make bench-surface``) is re-detected
into RUN_<variant> (map artifacts linked, not copied) with each variant's config changes, scored
by ``roadsurf.evaluation.detection.evaluate_detection`` against DRIVE/truth, and the cracks'
measured fields are listed next to the truth's.

    python -m benchmarks.detection_variants --runs NAME=RUN:DRIVE[,NAME=RUN:DRIVE...] \
        [--variants default,no_refine,...] [--json out/variants.json]

Variants (``VARIANTS``): ``default`` (DetectionConfig()), ``no_crack_raster``,
``no_refine`` / ``refine`` (dark-region refinement off / on), ``no_rut_scan``, ``no_ruts``, ``no_dense_crack``.
Writes benchmarks/results/detection_variants.json unless --json is given.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Any

from benchmarks._result import write_result
from roadsurf.detection import stage
from roadsurf.detection.config import DetectionConfig
from roadsurf.evaluation.detection import evaluate_detection
from roadsurf.io.drive import load_drive
from roadsurf.mapping.bundle_camera import later_stage_inputs
from roadsurf.mapping.types import load_trajectory
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.types import load_pair

# what a re-detection reads from the finished run (linked into the variant's folder)
LINKED = ("surface.tif", "surface.vrt", "map_points.npz", "poses.npz", "reference.json", "tiles")


def _cfg(name: str) -> DetectionConfig:
    d = DetectionConfig()
    r = dataclasses.replace
    table = {  # built on demand: an older checkout lacks some fields (a baseline run)
        "default": lambda: d,
        "no_crack_raster": lambda: r(d, crack=r(d.crack, raster=False)),
        "no_refine": lambda: r(d, refine=r(d.refine, enabled=False)),
        "refine": lambda: r(d, refine=r(d.refine, enabled=True)),  # the default before 29
        "no_rut_scan": lambda: r(d, rut=r(d.rut, scan_step_m=0.0)),
        "no_ruts": lambda: r(d, rut=r(d.rut, enabled=False)),
        "no_dense_crack": lambda: r(d, crack=r(d.crack, dense=False)),
    }
    if name not in table:
        raise SystemExit(f"unknown variant {name!r}; known: {', '.join(table)}")
    return table[name]()


VARIANTS = (
    "default",
    "no_crack_raster",
    "no_refine",
    "refine",
    "no_rut_scan",
    "no_ruts",
    "no_dense_crack",
)


def redetect(run_dir: Path, drive_dir: Path, variant: str) -> Path:
    """Detection of ``run_dir``'s pairs and map with ``variant``'s config, into a sibling folder."""
    out = run_dir.parent / f"{run_dir.name}_{variant}"
    out.mkdir(parents=True, exist_ok=True)
    for name in LINKED:
        src = run_dir / name
        if src.exists() and not (out / name).exists():
            os.symlink(src.resolve(), out / name)
    cfg = dataclasses.replace(_cfg(variant), overwrite=True)
    drive = load_drive(drive_dir)
    traj = load_trajectory(run_dir)
    pairs = [load_pair(p) for p in sorted((run_dir / "pairs").glob("*.npz"))]
    # the camera on the mount the run's poses used, with the bundle's refined intrinsics
    drive, pairs = later_stage_inputs(
        drive, pairs, traj, run_dir, ReconstructionConfig().plane_trim_k
    )
    stage.run(cfg, drive, pairs, traj, out)
    return out


def score(out: Path, drive_dir: Path) -> dict[str, Any]:
    """Frame and defect figures, and the cracks found (with their measurement source)."""
    ev = evaluate_detection(out, drive_dir / "truth")
    d, f = ev.get("defects_raw") or {}, ev.get("frames") or {}
    feats = json.loads((out / "defects.geojson").read_text())["features"]
    cracks = [
        {k: x["properties"].get(k) for k in ("max_depth_m", "width_m", "length_m", "measured_on",
                                              "profiles")}
        for x in feats
        if x["properties"]["type"] == "crack"
    ]  # fmt: skip
    return {
        "frame_precision": f.get("precision"),
        "frame_recall": f.get("recall"),
        "frame_accuracy": f.get("accuracy"),
        "defect_precision": d.get("precision"),
        "defect_recall": d.get("recall"),
        "predicted": d.get("predicted"),
        "matched_by_type": d.get("matched_by_type"),
        "truth_by_type": d.get("truth_by_type"),
        "depth_mae_m": d.get("depth_mae_m"),
        "distractor_false_alarms": d.get("distractor_false_alarms"),
        # true cracks >= 3 mm wide and deep: detected, and with length within 20 %
        "crack_target": d.get("crack_target"),
        "crack_matches": [
            {k: m.get(k) for k in ("truth_id", "depth_err_m", "length_rel_err", "width_err_m")}
            for m in d.get("matches") or []
            if m.get("truth_type") == "crack"
        ],
        "cracks": cracks,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", required=True, help="NAME=RUN:DRIVE, comma-separated")
    ap.add_argument("--variants", default="default", help=f"comma-separated of {VARIANTS}")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    rows: dict[str, dict[str, Any]] = {}
    for spec in a.runs.split(","):
        name, _, paths = spec.partition("=")
        run, _, drive = paths.partition(":")
        for v in a.variants.split(","):
            t0 = time.perf_counter()
            out = redetect(Path(run), Path(drive), v)
            fig = score(out, Path(drive)) | {"detect_s": round(time.perf_counter() - t0, 1)}
            rows.setdefault(name, {})[v] = fig
            print(f"{name} {v}: {json.dumps(fig)}", flush=True)
    print(f"Wrote {write_result(a.json, 'detection_variants', {'runs': rows})}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
