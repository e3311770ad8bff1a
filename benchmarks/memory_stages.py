"""Per-stage memory of one in-process `roadsurf run` (issue 31 #10: which stage peaks, and what
it holds).

    python -m benchmarks.memory_stages DRIVE --out RUN [--tracemalloc] [--interval S] [--json F]

Runs ``roadsurf.pipeline.run.run_drive(DRIVE, RUN, overwrite=True)`` in this process while a
thread samples the resident set (``VmRSS`` of /proc/self/status) every ``--interval`` seconds;
the stage running at each sample is known from the run's observer calls (called at each
stage's end). Per stage: the peak RSS while it ran and the RSS at its end. With
``--tracemalloc``, also the peak of Python-traced memory (NumPy arrays included) while it ran,
and the 12 source lines holding the most traced memory at its end (slows the run ~2x).
Linux only (/proc).
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import threading
import time
import tracemalloc
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

_REPORT_OF = {"globalmap": "map_report.json", "detection": "detection.json"}
STAGES = ("drive", "reconstruction", "poses", "globalmap", "detection", "report")


def rss_mb() -> tuple[float, float]:
    """(VmRSS, VmHWM) of this process in MB (NaN where /proc is missing)."""
    vals = {"VmRSS": float("nan"), "VmHWM": float("nan")}
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            key = line.split(":", 1)[0]
            if key in vals:
                vals[key] = float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return vals["VmRSS"], vals["VmHWM"]


class StageSampler:
    """Peak RSS per stage from a sampling thread; stages advance on observer calls."""

    def __init__(self, interval_s: float = 0.05, trace: bool = False) -> None:
        self.interval_s = interval_s
        self.trace = trace
        self.stage = STAGES[0]
        self.rows: dict[str, dict[str, Any]] = {}
        self._peak = 0.0
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._t0 = time.perf_counter()
        self._snap: tracemalloc.Snapshot | None = None
        self._snap_mb = 0.0

    def _loop(self) -> None:
        last_snap = 0.0
        while not self._stop.wait(self.interval_s):
            rss, _ = rss_mb()
            with self._lock:
                self._peak = max(self._peak, rss)
            now = time.perf_counter()
            if self.trace and now - last_snap > 1.0:
                last_snap = now
                cur, _ = tracemalloc.get_traced_memory()
                if cur > 1.05 * self._snap_mb * 1e6:
                    # the largest traced state of this stage so far: what it holds near its peak
                    self._snap = tracemalloc.take_snapshot()
                    self._snap_mb = cur / 1e6

    def start(self) -> None:
        if self.trace:
            tracemalloc.start(1)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        if self.trace:
            tracemalloc.stop()

    def __call__(self, stage: str, result: Any) -> None:
        """The run's observer: ``stage`` has just finished."""
        rss, hwm = rss_mb()
        with self._lock:
            peak = max(self._peak, rss)
            self._peak = rss
        row: dict[str, Any] = {
            "peak_rss_mb": round(peak, 1),
            "end_rss_mb": round(rss, 1),
            "hwm_so_far_mb": round(hwm, 1),
            "t_end_s": round(time.perf_counter() - self._t0, 1),
            "gc_objects": len(gc.get_objects()),
        }
        if self.trace:
            cur, tpeak = tracemalloc.get_traced_memory()
            row["traced_end_mb"] = round(cur / 1e6, 1)
            row["traced_peak_mb"] = round(tpeak / 1e6, 1)
            snap = tracemalloc.take_snapshot()
            if self._snap is not None and self._snap_mb * 1e6 > cur:
                snap = self._snap  # near the stage's peak rather than at its end
                row["top_at_traced_mb"] = round(self._snap_mb, 1)
            self._snap, self._snap_mb = None, 0.0
            row["top"] = [
                f"{s.size / 1e6:8.1f} MB {s.count:8d} {s.traceback[0].filename}:"
                f"{s.traceback[0].lineno}"
                for s in snap.statistics("lineno")[:12]
            ]
            tracemalloc.reset_peak()
        self.rows[stage] = row
        log.info("%s: %s", stage, {k: v for k, v in row.items() if k != "top"})
        for line in row.get("top", []):
            log.info("    %s", line)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Per-stage RSS of an in-process roadsurf run.")
    ap.add_argument("drive", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--interval", type=float, default=0.05, help="RSS sampling period (s)")
    ap.add_argument("--tracemalloc", action="store_true", help="trace Python allocations")
    ap.add_argument("--json", type=Path, default=None, help="write the rows here")
    ap.add_argument(
        "--recompute", default="",
        help="resume OUT, recomputing only these stages (comma-separated: globalmap,detection)",
    )  # fmt: skip
    ap.add_argument("--log-level", default="INFO", help="the run's logging level (the CLI's: INFO)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=a.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    log.setLevel(logging.INFO)
    from roadsurf.pipeline.run import run_drive

    sampler = StageSampler(a.interval, a.tracemalloc)
    sampler.start()
    try:
        if a.recompute:
            for st in a.recompute.split(","):
                (a.out / _REPORT_OF[st]).unlink(missing_ok=True)
        run_drive(a.drive, a.out, overwrite=not a.recompute, observers=[sampler])
    finally:
        sampler.stop()
    res = {"drive": str(a.drive), "peak_rss_mb": round(rss_mb()[1], 1), "stages": sampler.rows}
    print(json.dumps({k: v for k, v in res.items()}, indent=1))
    if a.json is not None:
        a.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
