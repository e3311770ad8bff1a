"""Benchmark: peak RSS and time of `roadsurf run` on simulated drives of different lengths
(memory must grow with the corridor area, not frames × image size), plus the mapping stages
alone (poses + global map) and detection alone on the same drives.

    python -m benchmarks.mapping [--work DIR] [--frames 60,600] [--mapping-only] [--width PX]

(``make bench-mapping ARGS="..."``; was ``roadsurf bench mapping``). Each run is a separate
Python process, so its peak RSS (``ru_maxrss``) is its own.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

_CHILD = r"""
import json, resource, sys, time, logging
logging.basicConfig(level=logging.WARNING)
from pathlib import Path
from roadsurf.io.runfolder import RunFolder
mode, drive, out = sys.argv[1], sys.argv[2], sys.argv[3]
t0 = time.perf_counter()
if mode == "run":
    from roadsurf.pipeline import run_drive
    rep = run_drive(drive, out, overwrite=True)  # a full run, not a resumed one
    extra = {"timings_s": rep["timings_s"], "n_tiles": rep.get("map", {}).get("n_tiles")}
elif mode == "detection":  # detection only, on the cached pairs and map of a previous run
    from roadsurf.io.drive import load_drive
    from roadsurf.reconstruction.types import load_pair
    from roadsurf.mapping.types import load_trajectory
    from roadsurf.detection.config import DetectionConfig
    from roadsurf.detection import stage
    drive_ = load_drive(drive)
    pairs = [load_pair(p) for p in sorted(RunFolder(out).pairs_dir.glob("*.npz"))]
    t1 = time.perf_counter()
    stage.run(DetectionConfig(overwrite=True), drive_, pairs, load_trajectory(out), Path(out))
    extra = {"detection_s": time.perf_counter() - t1}
else:  # mapping stages only, on the pairs cached by a previous full run
    from roadsurf.io.drive import load_drive
    from roadsurf.reconstruction.types import load_pair
    from roadsurf.mapping.config import MappingConfig
    from roadsurf.mapping import poses, globalmap
    drive_ = load_drive(drive)
    pairs = [load_pair(p) for p in sorted(RunFolder(out).pairs_dir.glob("*.npz"))]
    cfg = MappingConfig(overwrite=True)
    t1 = time.perf_counter()
    traj = poses.run(cfg, drive_, pairs, out)
    t2 = time.perf_counter()
    prod = globalmap.run(cfg, drive_, pairs, traj, out)
    extra = {"poses_s": t2 - t1, "globalmap_s": time.perf_counter() - t2,
             "n_tiles": prod.n_tiles, "n_points": prod.n_points,
             "corridor_px": prod.mosaic_px}
extra["wall_s"] = time.perf_counter() - t0
extra["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
print("BENCH " + json.dumps(extra))
"""


def _child(mode: str, drive: Path, out: Path) -> dict[str, Any]:
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD, mode, str(drive), str(out)],
        capture_output=True,
        text=True,
        check=False,
    )
    for line in proc.stdout.splitlines():
        if line.startswith("BENCH "):
            return json.loads(line[6:])
    raise RuntimeError(f"bench child failed ({mode} {drive}):\n{proc.stderr[-3000:]}")


def run_benchmark(
    work: Path,
    frames: tuple[int, ...] = (60, 600),
    scenario: str = "long",
    full: bool = True,
    width: int = 640,
) -> dict[str, Any]:
    """Simulate ``scenario`` drives of each length (reused when present), run them, and return
    per-length figures plus a markdown table. ``width`` < 640 renders smaller images (same
    footprint: fx scales, no supersampling) so the 600-frame drive renders in reasonable time
    on 2 cores; both lengths then use the same image size."""
    from roadsurf.io.runfolder import RunFolder
    from roadsurf.simulation.scenarios import simulate

    work = Path(work)
    over: dict[str, Any] = {}
    tag = ""
    if width != 640:
        over = {
            "width": width,
            "height": width * 3 // 4,
            "fx": 600.0 * width / 640,
            "supersample": 1,
        }
        tag = f"_w{width}"
    rows = []
    for n in frames:
        drive = work / f"{scenario}{n}{tag}"
        if not (drive / "frames.csv").is_file():
            log.info("simulating %s with %d frames into %s", scenario, n, drive)
            simulate(scenario, drive, n_frames=n, **over)
        out = work / f"run_{scenario}{n}{tag}"
        row: dict[str, Any] = {"frames": n, "image": f"{width}x{width * 3 // 4}"}
        if full or not RunFolder(out).pairs_dir.is_dir():
            t0 = time.perf_counter()
            try:
                row["run"] = _child("run", drive, out)
            except RuntimeError as e:  # e.g. a later stage failed; the mapping figures still count
                log.warning("%s", e)
                row["run"] = {"error": str(e)[-500:]}
            row["run"]["bench_wall_s"] = time.perf_counter() - t0
        row["mapping"] = _child("mapping", drive, out)
        try:
            row["detection"] = _child("detection", drive, out)
        except RuntimeError as e:
            log.warning("%s", e)
            row["detection"] = {"error": str(e)[-500:]}
        rows.append(row)
    lines = [
        "| frames | image | `roadsurf run` peak RSS | run wall time | mapping-only peak RSS | "
        "poses | global map | tiles | corridor (imaged px) | detection-only peak RSS |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        run = r.get("run", {})
        m = r["mapping"]
        lines.append(
            f"| {r['frames']} | {r['image']} | {run.get('peak_rss_mb', float('nan')):.0f} MB | "
            f"{run.get('wall_s', float('nan')):.0f} s | {m['peak_rss_mb']:.0f} MB | "
            f"{m['poses_s']:.1f} s | {m['globalmap_s']:.1f} s | {m['n_tiles']} | "
            f"{m['corridor_px'] / 1e6:.1f} Mpx | "
            f"{r['detection'].get('peak_rss_mb', float('nan')):.0f} MB |"
        )
    md = "\n".join(lines) + "\n"
    res = {"rows": rows, "markdown": md}
    (work / "bench_mapping.json").write_text(json.dumps(res, indent=2))
    return res


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.mapping`` (``make bench-mapping``): the options of the former
    ``roadsurf bench mapping``; prints the table and writes results/mapping.json."""
    import argparse

    from benchmarks._result import write_result

    ap = argparse.ArgumentParser(
        description="Peak RSS of `roadsurf run` and of the mapping stages on simulated drives "
        "of each length."
    )
    ap.add_argument("--work", type=Path, default=Path("out/bench_mapping"), help="work folder")
    ap.add_argument("--frames", default="60,600", help="comma-separated drive lengths")
    full = ap.add_mutually_exclusive_group()
    full.add_argument(
        "--full", dest="full", action="store_true", default=True, help="also time `roadsurf run`"
    )
    full.add_argument("--mapping-only", dest="full", action="store_false")
    ap.add_argument("--width", type=int, default=640, help="image width of the drives (px)")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    res = run_benchmark(
        a.work, tuple(int(f) for f in a.frames.split(",")), full=a.full, width=a.width
    )
    print(res["markdown"])
    write_result(a.json, "mapping", res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
