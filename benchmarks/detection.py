"""Benchmark: the dissertation's Table 4.2 on simulator drives (was `roadsurf bench detection`).

The same detector runs on the reconstructions of the ``proposed`` method and the ``classic``
and ``colmap`` baselines, over a fixed set of simulated drives (several seeds; flat, potholes,
rough-GPS, highway). Per method it pools the frame confusion counts, defect matches, depth and
area errors and false alarms on distractors over all drives and prints the table with the issue 5
targets as met / not met (``benchmarks.detection_table``).

Beyond the dissertation, it also shows the effect of the adaptive T_b on the dissertation's
per-pair frame decision (2D + 3D refinement alone, no map), against the fixed T_b, on the
proposed reconstructions (detection re-run only; pairs and maps are reused).

    python -m benchmarks.detection [--work DIR] [--quick] [--methods M,...] [--detection-only]
    make bench-detection ARGS="--quick"

Writes WORK/bench_detection.json (per-method figures) and benchmarks/results/detection.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.detection_table import pool, table_markdown
from roadsurf.core.atomic import read_json, write_json_atomic
from roadsurf.core.errors import RoadsurfError
from roadsurf.detection import stage
from roadsurf.detection.config import DetectionConfig, RefineConfig
from roadsurf.detection.planefit import recursive_plane_fit
from roadsurf.detection.refine import binarise
from roadsurf.evaluation.detection import evaluate_detection
from roadsurf.io.drive import load_drive, read_gray
from roadsurf.io.runfolder import (
    MAP_POINTS,
    PAIRS_DIR,
    POSES_NPZ,
    REFERENCE_JSON,
    SURFACE_TIF,
    SURFACE_VRT,
    TILES_DIR,
)
from roadsurf.mapping.bundle_camera import later_stage_inputs
from roadsurf.mapping.types import load_trajectory
from roadsurf.pipeline import run_drive
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.types import load_pair
from roadsurf.simulation.scenarios import simulate

log = logging.getLogger(__name__)

# (scenario, seed, frames): fixed so that the table is reproducible.
DRIVES: tuple[tuple[str, int, int], ...] = (
    ("flat", 101, 30),
    ("potholes", 202, 40),
    ("potholes", 212, 40),
    ("rough-gps", 404, 50),
    ("highway", 505, 40),
)
QUICK_DRIVES: tuple[tuple[str, int, int], ...] = (("flat", 101, 12), ("potholes", 202, 20))
# The product's method first (rotation-aware variant of the proposed method), then baselines.
METHODS: tuple[str, ...] = ("rotation_aware", "proposed", "classic", "colmap")

# the pairs' plane trim when the bundle's refined intrinsics re-derive them (the run's default)
TRIM_K = ReconstructionConfig().plane_trim_k


def _drive(out: Path, scenario: str, seed: int, n: int) -> Path:
    d = out / "drives" / f"{scenario}_s{seed}_n{n}"
    if not (d / "truth" / "frame_labels.csv").exists():
        log.info("bench detection: simulating %s seed %d (%d frames)", scenario, seed, n)
        simulate(scenario, d, seed=seed, n_frames=n)
    return d


def _variant(run_dir: Path, drive_dir: Path, name: str, **cfg_changes: Any) -> Path:
    """Re-run detection only, with changed config, into RUN/../<run>_<name> (maps reused)."""
    out = run_dir.parent / f"{run_dir.name}_{name}"
    out.mkdir(parents=True, exist_ok=True)
    for f in (SURFACE_TIF, SURFACE_VRT, MAP_POINTS, POSES_NPZ, REFERENCE_JSON):
        src = run_dir / f
        if src.exists() and not (out / f).exists():
            os.symlink(src.resolve(), out / f)
    # surface.vrt points at tiles relative to the run folder; link those too.
    for tiles in run_dir.glob(f"{TILES_DIR}*"):
        if not (out / tiles.name).exists():
            os.symlink(tiles.resolve(), out / tiles.name)
    refine = cfg_changes.pop("refine", RefineConfig())
    cfg = dataclasses.replace(DetectionConfig(), refine=refine, **cfg_changes)
    drive = load_drive(drive_dir)
    pairs = [load_pair(p) for p in sorted((run_dir / PAIRS_DIR).glob("*.npz"))]
    traj = load_trajectory(run_dir)
    drive, pairs = later_stage_inputs(drive, pairs, traj, run_dir, TRIM_K)
    stage.run(cfg, drive, pairs, traj, out)
    return out


def redetect(run_dir: Path, drive_dir: Path) -> Path:
    """Re-run the detection stage alone, in place, on a finished run (its pairs, poses and map
    are reused; the defaults of ``DetectionConfig``, as ``roadsurf run`` uses them)."""
    if not (run_dir / POSES_NPZ).exists():
        raise RoadsurfError(
            f"{run_dir}: no poses.npz; run `python -m benchmarks.detection` once without "
            "--detection-only to make the runs"
        )
    drive = load_drive(drive_dir)
    pairs = [load_pair(p) for p in sorted((run_dir / PAIRS_DIR).glob("*.npz"))]
    traj = load_trajectory(run_dir)
    drive, pairs = later_stage_inputs(drive, pairs, traj, run_dir, TRIM_K)
    stage.run(DetectionConfig(overwrite=True), drive, pairs, traj, run_dir)
    return run_dir


def binarisation_stats(run_dir: Path, drive_dir: Path, mode: str) -> dict[str, int]:
    """How T_b splits the 3D classes: dark pixels at 3D road points (false dark: shadows,
    exposure) and at 3D defect points deeper than 2 T_d (hits), summed over a run's pairs."""
    cfg = DetectionConfig()
    rcfg = RefineConfig(binarise=mode)  # type: ignore[arg-type]
    drive = load_drive(drive_dir)
    frames = {f.filename: f for f in drive.frames}
    out = {"road": 0, "road_dark": 0, "defect": 0, "defect_dark": 0}
    for path in sorted((run_dir / PAIRS_DIR).glob("*.npz")):
        p = load_pair(path)
        if not p.ok or p.n_points < cfg.plane.min_points or p.frame_a not in frames:
            continue
        fit = recursive_plane_fit(np.asarray(p.points_cam_a_m, float), cfg.plane)
        if not np.isfinite(fit.threshold_m):
            continue
        road = ~fit.candidate & (np.abs(fit.dist_m) < fit.threshold_m)
        deep = fit.dist_m <= -2 * fit.threshold_m
        dark = binarise(read_gray(frames[p.frame_a]), rcfg, road_px=np.asarray(p.px_a)[road])
        h, w = dark.shape
        uv = np.round(np.asarray(p.px_a, float)).astype(int)
        uv[:, 0] = np.clip(uv[:, 0], 0, w - 1)
        uv[:, 1] = np.clip(uv[:, 1], 0, h - 1)
        at = dark[uv[:, 1], uv[:, 0]]
        out["road"] += int(road.sum())
        out["road_dark"] += int((at & road).sum())
        out["defect"] += int(deep.sum())
        out["defect_dark"] += int((at & deep).sum())
    return out


def run_benchmark(
    out: str | Path,
    *,
    quick: bool = False,
    methods: tuple[str, ...] = METHODS,
    drives: tuple[tuple[str, int, int], ...] | None = None,
    detection_only: bool = False,
) -> dict[str, Any]:
    """Run (or resume) the benchmark into ``out``; returns pooled results per method.

    Each drive is simulated once; each (drive, method) is a full `roadsurf run` into
    OUT/runs/<drive>_<method>, which resumes from its cached pairs when re-run. With
    ``detection_only`` the runs must exist: only their detection stage is re-run (minutes
    instead of the cold run's half hour), e.g. after a change to ``detection/``.
    """
    t0 = time.perf_counter()
    out = Path(out)
    drives = drives or (QUICK_DRIVES if quick else DRIVES)
    per: dict[str, list[dict[str, Any]]] = {m: [] for m in methods}
    tb: dict[str, list[dict[str, Any]]] = {
        "map (product)": [],
        "pair, adaptive T_b": [],
        "pair, fixed T_b": [],
    }
    failures: list[str] = []
    bstats: dict[str, dict[str, int]] = {}
    for scenario, seed, n in drives:
        drive_dir = _drive(out, scenario, seed, n)
        for m in methods:
            run_dir = out / "runs" / f"{drive_dir.name}_{m}"
            try:
                if detection_only:
                    redetect(run_dir, drive_dir)
                else:
                    run_drive(drive_dir, run_dir, method=m)
                res = evaluate_detection(run_dir, drive_dir / "truth")
            except Exception as e:  # noqa: BLE001 - a failing baseline is reported, not fatal
                log.error("bench detection: %s on %s failed: %s", m, drive_dir.name, e)
                failures.append(f"{m} on {drive_dir.name}: {e}")
                continue
            write_json_atomic(run_dir / "detection_eval.json", res)
            per[m].append(res)
            if m == methods[0]:
                tb["map (product)"].append(res)
                for name, mode in (
                    ("pair, adaptive T_b", "adaptive"),
                    ("pair, fixed T_b", "fixed"),
                ):
                    v = _variant(
                        run_dir, drive_dir, f"pair_{mode}", frame_label="pair",
                        refine=RefineConfig(binarise=mode),
                    )  # fmt: skip
                    tb[name].append(evaluate_detection(v, drive_dir / "truth"))
                for mode in ("adaptive", "fixed"):
                    st = binarisation_stats(run_dir, drive_dir, mode)
                    acc = bstats.setdefault(mode, dict.fromkeys(st, 0))
                    for k, v in st.items():
                        acc[k] += v
    pooled = {m: pool(r) for m, r in per.items() if r}
    tb_pooled = {k: pool(v) for k, v in tb.items() if v}
    body = table_markdown(pooled, tb_pooled, bstats)
    if failures:
        body += "\n\nFailed runs: " + "; ".join(failures)
    wall = time.perf_counter() - t0
    # The cold-run time (simulation and every run): the longest wall seen in this work folder.
    prev = out / "bench_detection.json"
    cold = max(wall, float(read_json(prev).get("cold_wall_s", 0.0))) if prev.exists() else wall
    summary = {
        "pooled": pooled,
        "t_b": tb_pooled,
        "binarisation": bstats,
        "failures": failures,
        "drives": [list(d) for d in drives],
        "machine": platform.platform(),
        "wall_s": wall,
        "cold_wall_s": cold,
        "markdown": body,
    }
    write_json_atomic(out / "bench_detection.json", summary)
    return summary


def parser() -> argparse.ArgumentParser:
    """The options of the removed `roadsurf bench detection`, without ``--docs``."""
    ap = argparse.ArgumentParser(
        description="Table 4.2: the detector on proposed, classic and colmap reconstructions "
        "of simulator drives."
    )
    ap.add_argument(
        "--work",
        type=Path,
        default=Path("out/bench_detection"),
        help="work folder (simulated drives, runs, results)",
    )
    ap.add_argument("--quick", action="store_true", help="two short drives")
    ap.add_argument(
        "--methods",
        default=",".join(METHODS),
        help="comma-separated reconstruction methods (first = product)",
    )
    ap.add_argument(
        "--detection-only",
        action="store_true",
        help="re-run only the detection stage on the runs in --work",
    )
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    return ap


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.detection [options]`` (``make bench-detection``)."""
    from benchmarks._result import write_result

    a = parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    res = run_benchmark(
        a.work,
        quick=a.quick,
        methods=tuple(m.strip() for m in a.methods.split(",")),
        detection_only=a.detection_only,
    )
    print(res["markdown"])
    print(f"Total {res['wall_s']:.0f} s; details in {a.work}/bench_detection.json")
    write_result(a.json, "detection", res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
