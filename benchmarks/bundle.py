"""Bundle adjustment (issue 30) on vs off on simulated drives: trajectory RMSE, drift over 5 m,
flat-road MAE and run time, from ``roadsurf simulate / run / evaluate``.

    make bench-bundle ARGS="--out /tmp/bench_bundle --scenario potholes highway rough-gps"
    python -m benchmarks.bundle --out /tmp/bench_bundle --scenario rough-gps-vib1
        --json benchmarks/results/bundle_vib1.json   (one command line)

Each scenario is simulated once (kept in --out/SCENARIO, reused when present) and run twice from
scratch (pose graph only, ``mapping: {bundle_adjust: false}``; pose graph then bundle adjustment,
``mapping: {bundle_adjust: true}``, the default).
Variants: ``rough-gps-vib1`` is rough-gps simulated with ``--set vibration_deg=1.0`` (issue 30's
"consumer GPS with 1° vibration" target; rough-gps itself has the simulator's default 0.3°).
Prints a markdown table, writes ``table.md`` in --out and the figures as JSON (--json, default
benchmarks/results/bundle.json): per run the evaluation's trajectory and surface figures, the
run and poses-stage times, and the bundle's own report (reprojection RMS, windows, time offset).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from benchmarks._result import write_result

METRICS = (
    ("trajectory_rmse_m", "traj. RMSE (mm)", 1e3),
    ("drift_5m_median_pct", "drift 5 m median (%)", 1.0),
    ("trajectory_rmse_aligned_m", "traj. RMSE aligned (mm)", 1e3),
    ("drift_5m_p95_pct", "drift 5 m p95 (%)", 1.0),
    ("flat_mae_m", "flat-road MAE (mm)", 1e3),  # surface.aligned
    ("seam_step_max_m", "seam step (mm)", 1e3),
)


# scenario variants: name -> (simulated scenario, extra ``roadsurf simulate`` arguments)
VARIANTS: dict[str, tuple[str, list[str]]] = {
    "rough-gps-vib1": ("rough-gps", ["--set", "vibration_deg=1.0"]),
}


def _cli(*args: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "roadsurf", *args], check=True, capture_output=True)
    return time.perf_counter() - t0


def _find(d: object, key: str) -> float | None:
    """The first value under ``key`` anywhere in a nested evaluation.json."""
    if isinstance(d, dict):
        if key in d and isinstance(d[key], int | float):
            return float(d[key])
        for v in d.values():
            got = _find(v, key)
            if got is not None:
                return got
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scenario", nargs="+", default=["potholes", "highway", "rough-gps"])
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args()
    figures: dict[str, dict[str, object]] = {}
    a.out.mkdir(parents=True, exist_ok=True)
    cfgs = {}
    for on in (False, True):
        cfgs[on] = a.out / f"bundle_{'on' if on else 'off'}.yaml"
        cfgs[on].write_text(f"mapping:\n  bundle_adjust: {'true' if on else 'false'}\n")
    rows = ["| scenario | BA | " + " | ".join(m[1] for m in METRICS) + " | run (s) | poses (s) |"]
    rows.append("|---" * (len(METRICS) + 4) + "|")
    for sc in a.scenario:
        drive = a.out / sc
        if not drive.is_dir():
            base, extra_sim = VARIANTS.get(sc, (sc, []))
            _cli("simulate", "--scenario", base, *extra_sim, "--out", str(drive))
        for on in (False, True):
            run = a.out / f"{sc}_{'on' if on else 'off'}"
            extra = ["--config", str(cfgs[on])]
            secs = _cli("run", str(drive), "--out", str(run), "--overwrite", *extra)
            _cli("evaluate", str(run), "--truth", str(drive / "truth"))
            ev = json.loads((run / "evaluation.json").read_text())
            rep = json.loads((run / "report.json").read_text())
            poses_s = rep["stages"]["poses"]["computed_s"]
            vals = []
            fig: dict[str, object] = {"run_s": round(secs, 1), "poses_s": poses_s}
            for key, _, f in METRICS:
                v = _find(ev.get("surface", {}).get("aligned", {}), key)
                v = _find(ev, key) if v is None else v
                vals.append("n/a" if v is None else f"{v * f:.3g}")
                fig[key] = v
            poses_rep = json.loads((run / "poses_report.json").read_text())
            fig["bundle"] = poses_rep.get("bundle", {})
            figures[f"{sc}_{'on' if on else 'off'}"] = fig
            rows.append(
                f"| {sc} | {'on' if on else 'off'} | " + " | ".join(vals) + f" | {secs:.1f} | "
                f"{poses_s:.2f} |"
            )
    table = "\n".join(rows)
    (a.out / "table.md").write_text(table + "\n")
    print(table)
    write_result(a.json, "bundle", {"table": table, "runs": figures})


if __name__ == "__main__":
    main()
