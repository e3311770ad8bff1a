"""Benchmark: `roadsurf run` end to end on a drive (issue 29: at least 1.5 frames/s on 2 CPU
cores), with the process CPU time (user + system, all threads) of each stage beside its wall
time.

On a shared machine the wall time depends on the other jobs; the CPU time much less, so a
change is judged by the CPU time of runs alternated with a baseline's. Each run is a fresh
process (torch's import, ~1-3 CPU s, is part of a run) writing into a fresh folder.

    python -m benchmarks.run_speed [--drive data_samples/drive] [--runs 2] [--work DIR]
        [--config K.yaml] [--json OUT]

``frames_per_s_wall``: frames / wall time of the whole run; ``frames_per_s_2cores``: frames /
(CPU time / 2), the rate two idle cores would reach if the run kept both busy (an upper bound;
`make demo` on a quiet 2-core machine measured 1.87 cores busy on average at 1743a7f).
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks._result import write_result

STAGES = (
    ("reconstruction", "roadsurf.reconstruction.stage"),
    ("poses", "roadsurf.mapping.poses"),
    ("globalmap", "roadsurf.mapping.globalmap"),
    ("detection", "roadsurf.detection.stage"),
)


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def one_run(drive: str, out: str, config: str | None) -> dict[str, Any]:
    """Run the pipeline in this process; per stage (CPU s, wall s), and the totals."""
    import importlib

    t0, c0 = time.perf_counter(), _cpu_s()
    from roadsurf.pipeline.run import run_drive

    figures: dict[str, Any] = {"import_cpu_s": round(_cpu_s() - c0, 2)}
    for name, module in STAGES:
        mod = importlib.import_module(module)
        fn = mod.run

        def timed(*a: Any, _fn: Any = fn, _name: str = name, **k: Any) -> Any:
            c, w = _cpu_s(), time.perf_counter()
            try:
                return _fn(*a, **k)
            finally:
                figures[f"{_name}_cpu_s"] = round(_cpu_s() - c, 2)
                figures[f"{_name}_wall_s"] = round(time.perf_counter() - w, 2)

        mod.run = timed
    shutil.rmtree(out, ignore_errors=True)
    report = run_drive(drive, out, config_path=config)
    figures["total_cpu_s"] = round(_cpu_s() - c0, 2)
    figures["total_wall_s"] = round(time.perf_counter() - t0, 2)
    figures["frames"] = int(report["counts"]["frames"])
    return figures


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--drive", default="data_samples/drive")
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--work", default=None, help="run folders (default: a temporary folder)")
    ap.add_argument("--config", default=None)
    ap.add_argument("--json", default=None)
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)  # child: run into this folder
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(one_run(args.drive, args.one, args.config)))
        return
    work = Path(args.work or tempfile.mkdtemp(prefix="run_speed_"))
    runs = []
    for i in range(args.runs):
        cmd = [sys.executable, "-m", "benchmarks.run_speed", "--drive", args.drive]
        cmd += ["--one", str(work / f"run{i}")] + (["--config", args.config] if args.config else [])
        res = subprocess.run(cmd, capture_output=True, text=True, check=True)
        runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
        print(json.dumps(runs[-1]))
    med = {k: statistics.median(r[k] for r in runs) for k in runs[0] if k != "frames"}
    frames = runs[0]["frames"]
    figures = {
        "drive": args.drive,
        "frames": frames,
        "runs": runs,
        "median": med,
        "frames_per_s_wall": round(frames / med["total_wall_s"], 3),
        "frames_per_s_2cores": round(frames / (med["total_cpu_s"] / 2), 3),
    }
    print(json.dumps({k: v for k, v in figures.items() if k != "runs"}, indent=1))
    if args.json:
        write_result(args.json, "run_speed", figures)


if __name__ == "__main__":
    main()
