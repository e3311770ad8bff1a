"""Benchmark: two-frame photo pairs of potholes with a sideways baseline, no GPS (issue 29).

Each case renders a pair as Fan et al.'s stereo pothole sets are taken (one tilted camera
0.5 m above the road, the second frame moved along the camera's x axis; ``simulation.stereo``),
runs ``roadsurf run`` with the defaults (the mount estimated from the one pair) and scores the
run against the truth (``roadsurf.evaluation.pair``): pothole found, max depth error, RMS to
the true surface inside the pothole (target ≤ 2.2 mm), flat MAE.

    python -m benchmarks.stereo_pair [--cases pitch45_b12,...] [--work out/bench_stereo_pair]
    make bench-stereo_pair

Writes benchmarks/results/stereo_pair.json (figures + command, commit, machine, date).
"""

from __future__ import annotations

import argparse
import logging
import shutil
import time
from pathlib import Path
from typing import Any

from benchmarks._result import write_result
from roadsurf.evaluation.pair import score_pair
from roadsurf.pipeline.run import run_drive
from roadsurf.simulation.stereo import simulate_stereo_pair

# name: (baseline m, seed, SimConfig overrides)
CASES: dict[str, tuple[float, int, dict[str, Any]]] = {
    "pitch45_b12": (0.12, 7, {}),
    "pitch45_b12_s11": (0.12, 11, {}),
    "pitch45_b12_asphalt": (0.12, 7, {"texture": "asphalt"}),
    "pitch45_b06": (0.06, 7, {}),
    "pitch45_b20": (0.20, 7, {}),
    "pitch30_b12": (0.12, 7, {"mount_pitch_deg": 30.0}),
    "pitch55_b12": (0.12, 7, {"mount_pitch_deg": 55.0}),
    "pitch45_b12_jpg_noise": (0.12, 7, {"image_format": "jpg", "noise_sigma": 6.0}),
    "pitch45_b12_large": (0.12, 7, {"width": 1720, "height": 1030, "fx": 1400.0}),
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated case names")
    ap.add_argument("--work", type=Path, default=Path("out/bench_stereo_pair"))
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    rows = []
    for name in a.cases.split(","):
        if name not in CASES:
            raise SystemExit(f"unknown case {name!r}; known: {', '.join(CASES)}")
        baseline, seed, over = CASES[name]
        drive = simulate_stereo_pair(
            a.work / f"drive_{name}", baseline_m=baseline, seed=seed, **over
        )
        run = a.work / f"run_{name}"
        shutil.rmtree(run, ignore_errors=True)
        t0 = time.perf_counter()
        rep = run_drive(drive, run)
        wall = time.perf_counter() - t0
        row = {"case": name, "baseline_m": baseline, "seed": seed, **over, "run_s": round(wall, 2)}
        mount = rep.get("poses", {}).get("mount", {})
        row["mount_deg"] = [mount.get(k) for k in ("pitch_deg", "roll_deg", "yaw_deg")]
        row.update(score_pair(run, drive))
        rows.append(row)
        print(
            f"{name:24s} found {row['found']!s:5s} depth err "
            f"{_mm(row.get('depth_error_m'))} pothole RMS {_mm(row.get('pothole_rms_m'))} "
            f"(to the surface {_mm(row.get('pothole_surface_rms_m'))}) "
            f"flat MAE {_mm(row.get('flat_mae_m'))} ({wall:.1f} s)",
            flush=True,
        )
    write_result(a.json, "stereo_pair", {"cases": rows})
    return 0


def _mm(v: float | None) -> str:
    return "   -  " if v is None else f"{1e3 * v:6.2f}"


if __name__ == "__main__":
    raise SystemExit(main())
