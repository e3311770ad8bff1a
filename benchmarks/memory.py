"""Benchmark: peak RSS of `roadsurf run` against the drive's length (issue 31 #10: memory must
stay flat in the number of frames; the target is a 3,000-frame drive within 20 % of a
300-frame drive).

    python -m benchmarks.memory [--frames 300,3000] [--width PX] [--work DIR] [--pythonpath TREE]
                                [--env NAME=VALUE ...]

(``make bench-memory ARGS="..."``). Each drive of the ``long`` scenario is simulated once (reused
when present) and run by ``python -m roadsurf run --overwrite`` in its own child process; the
child's own peak RSS comes from ``os.wait4`` (its ``ru_maxrss``), so the lengths never mix.
``--width`` < 640 renders smaller images with the same road footprint (fx scales, no
supersampling), which keeps long drives affordable on a small machine; every length then uses
the same image size. ``--pythonpath`` runs another checkout (e.g. the commit before a fix);
``--env`` sets variables for the child only (e.g. ``MALLOC_ARENA_MAX=2``, to compare malloc
settings).
"""

from __future__ import annotations

import argparse
import logging
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


def simulate_drive(work: Path, frames: int, width: int, scenario: str = "long") -> Path:
    """The simulated drive of ``frames`` frames at image ``width`` (rendered once)."""
    from roadsurf.simulation.scenarios import simulate

    over: dict[str, Any] = {}
    tag = ""
    if width != 640:
        over = {"width": width, "height": width * 3 // 4, "fx": 600.0 * width / 640}
        over["supersample"] = 1
        tag = f"_w{width}"
    drive = work / f"{scenario}{frames}{tag}"
    if not (drive / "frames.csv").is_file():
        log.info("simulating %s with %d frames into %s", scenario, frames, drive)
        simulate(scenario, drive, n_frames=frames, **over)
    return drive


def measure_run(
    drive: Path, out: Path, pythonpath: Path | None = None, env_extra: dict[str, str] | None = None
) -> dict[str, Any]:
    """Run ``roadsurf run DRIVE --out OUT --overwrite`` in a child (with ``env_extra`` set);
    its peak RSS (MB), wall time (s) and exit code."""
    env = dict(os.environ) | dict(env_extra or {})
    cwd = None
    if pythonpath is not None:
        env["PYTHONPATH"] = str(Path(pythonpath).resolve())
        cwd = str(Path(pythonpath).resolve())
    cmd = [sys.executable, "-m", "roadsurf", "run", str(drive.resolve()), "--out",
           str(out.resolve()), "--overwrite"]  # fmt: skip
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd, env=env, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    # stderr is read before waiting (a full pipe would block the child); os.wait4, not
    # proc.wait, so that the child's own rusage comes back
    err = proc.stderr.read() if proc.stderr is not None else ""
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    res = {
        "peak_rss_mb": round(usage.ru_maxrss / 1024.0, 1),
        "wall_s": round(time.perf_counter() - t0, 1),
        "rc": proc.returncode,
    }
    if proc.returncode != 0:
        res["error"] = err[-500:]
    return res


def run_benchmark(
    work: Path,
    frames: tuple[int, ...] = (300, 3000),
    width: int = 640,
    pythonpath: Path | None = None,
    env_extra: dict[str, str] | None = None,
) -> dict[str, Any]:
    """Peak RSS per drive length, its ratio to the shortest drive, and a markdown table."""
    work = Path(work)
    rows: list[dict[str, Any]] = []
    for n in frames:
        drive = simulate_drive(work, n, width)
        row: dict[str, Any] = {"frames": n, "image": f"{width}x{width * 3 // 4}"}
        row |= measure_run(drive, work / f"run_{drive.name}", pythonpath, env_extra)
        rows.append(row)
        log.info("%d frames: %s", n, row)
    base = rows[0]["peak_rss_mb"] if rows else float("nan")
    lines = [
        "| frames | image | peak RSS of `roadsurf run` | vs the shortest | wall time | exit |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        r["ratio"] = round(r["peak_rss_mb"] / base, 3) if base else float("nan")
        lines.append(
            f"| {r['frames']} | {r['image']} | {r['peak_rss_mb']:.0f} MB | "
            f"{r['ratio']:.2f}x | {r['wall_s']:.0f} s | {r['rc']} |"
        )
    ratio = rows[-1]["ratio"] if rows else float("nan")
    return {
        "rows": rows,
        "ratio_longest_to_shortest": ratio,
        "within_20_percent": bool(ratio <= 1.2),
        "pythonpath": str(pythonpath) if pythonpath is not None else None,
        "env": dict(env_extra or {}),
        "markdown": "\n".join(lines) + "\n",
    }


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.memory`` (``make bench-memory``): prints the table and writes
    results/memory.json."""
    from benchmarks._result import write_result

    ap = argparse.ArgumentParser(
        description="Peak RSS of `roadsurf run` on simulated drives of each length."
    )
    ap.add_argument("--work", type=Path, default=Path("out/bench_memory"), help="work folder")
    ap.add_argument("--frames", default="300,3000", help="comma-separated drive lengths")
    ap.add_argument("--width", type=int, default=640, help="image width of the drives (px)")
    ap.add_argument("--pythonpath", type=Path, default=None, help="run another checkout")
    ap.add_argument(
        "--env", action="append", default=[], metavar="NAME=VALUE",
        help="environment variable for the runs (repeatable), e.g. MALLOC_ARENA_MAX=2",
    )  # fmt: skip
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    bad = [e for e in a.env if "=" not in e or not e.split("=", 1)[0]]
    if bad:
        ap.error(f"--env takes NAME=VALUE, got {bad[0]!r}")
    env_extra = dict(e.split("=", 1) for e in a.env)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    frames = tuple(int(f) for f in a.frames.split(","))
    res = run_benchmark(a.work, frames, a.width, a.pythonpath, env_extra)
    print(res["markdown"])
    print(
        f"longest / shortest: {res['ratio_longest_to_shortest']:.2f}x "
        f"({'within' if res['within_20_percent'] else 'NOT within'} 20 %)"
    )
    write_result(a.json, "memory", res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
