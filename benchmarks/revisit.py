"""Benchmark: a revisit closes its loop (issue 30). The ``revisit`` scenario (the same lane
driven twice, 20 s apart, consumer GPS with its own bias on each pass) is simulated once and run
twice with ``roadsurf run``: with the defaults (loop closure on) and with
``mapping: {bundle_loop_gate_m: 0}`` (no loop search); ``roadsurf evaluate`` scores both. The
figure of the issue is the passes' disagreement (``revisit_agreement_max_m``: the error of the
estimated offset between a frame and the frame of the other pass at the same place).

    python -m benchmarks.revisit [--work DIR] [--frames N]
    make bench-revisit

Writes benchmarks/results/revisit.json (figures + command, commit, machine, date).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from benchmarks._result import write_result
from benchmarks.surface import simulated, timed_run
from benchmarks.tilted import _cli

VARIANTS = {"loops": None, "no_loops": "mapping:\n  bundle_loop_gate_m: 0\n"}
KEYS = (
    "revisit_pairs",
    "revisit_agreement_m",
    "revisit_agreement_max_m",
    "trajectory_rmse_m",
    "trajectory_rmse_aligned_m",
    "drift_5m_median_pct",
    "gps_rmse_m",
    "coverage",
)


def _row(ev: dict[str, Any], report: dict[str, Any], seconds: float) -> dict[str, Any]:
    out = {k: ev.get(k) for k in KEYS}
    out["flat_mae_m"] = ((ev.get("surface") or {}).get("aligned") or {}).get("flat_mae_m")
    out["loops"] = len(((report.get("poses") or {}).get("bundle") or {}).get("loops") or [])
    out["run_s"] = seconds
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("out/bench_revisit"))
    ap.add_argument("--frames", type=int, default=None, help="frames (default: the scenario's)")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    drive = simulated("revisit", a.work / "drive", a.frames, a.work / "sim.log")
    rows: dict[str, Any] = {}
    for name, cfg_text in VARIANTS.items():
        run = a.work / name
        seconds = timed_run(drive, run, a.work / f"{name}.log", cfg_text or "")
        _cli("evaluate", str(run), "--truth", str(drive / "truth"), log=a.work / f"{name}_eval.log")
        ev = json.loads((run / "evaluation.json").read_text())
        report = json.loads((run / "report.json").read_text())
        rows[name] = _row(ev, report, seconds)
        print(name, json.dumps(rows[name]), flush=True)
    print("| figure | " + " | ".join(rows) + " |")
    print("|---|" + "---|" * len(rows))
    for k in (*KEYS, "flat_mae_m", "loops", "run_s"):
        print(f"| {k} | " + " | ".join(_fmt(r.get(k)) for r in rows.values()) + " |")
    path = write_result(a.json, "revisit", {"scenario": "revisit", "runs": rows})
    print(f"Wrote {path}")
    return 0


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


if __name__ == "__main__":
    raise SystemExit(main())
