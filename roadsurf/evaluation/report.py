"""`roadsurf evaluate OUT --truth DRIVE/truth`: score a run folder against simulator truth.

Works on any run folder that follows the output contract (roadsurf or the SfM baseline):
``trajectory.geojson`` (Points with filename), ``surface.tif`` or ``surface.vrt``, and optionally
``dense_seams.npz`` or ``map_points.npz`` (for the seam step) and ``defects.geojson`` (scored by
``evaluation.detection.evaluate_detection``).

Figures (targets of issue 4 are printed as met / not met):
- trajectory horizontal RMSE (m) against truth/poses.csv, raw and after a 2D rigid alignment;
- relative drift over 5 m windows (% of distance travelled);
- surface height MAE / RMSE (m) on flat road and inside defects, after removing the absolute
  GPS offset with the 2D rigid alignment of the trajectory (raw figures too);
- coverage of the imaged corridor (union of the true camera footprints on the road);
- the largest seam step between neighbouring pair patches (``evaluation.seams``: the dense
  surface's per-pair samples, dense_seams.npz, else map_points.npz), its standard error.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

from roadsurf.core.atomic import read_json, write_json_atomic, write_text_atomic
from roadsurf.core.errors import RoadsurfError
from roadsurf.evaluation.detection import evaluate_detection
from roadsurf.evaluation.seams import seam_report
from roadsurf.evaluation.surface import surface_metrics
from roadsurf.evaluation.trajectory import (
    gps_noise_m,
    gps_rmse_m,
    run_trajectory,
    trajectory_metrics,
    truth_poses,
)
from roadsurf.io import drivefolder as df
from roadsurf.io import runfolder as rf

log = logging.getLogger(__name__)

# issue 4 targets: (metric key, comparison, threshold, description)
TARGETS_RTK = [
    ("trajectory_rmse_m", "<=", 0.03, "trajectory RMSE <= 3 cm (RTK GPS)"),
    ("surface.aligned.flat_mae_m", "<=", 0.0015, "flat-road height MAE <= 1.5 mm (RTK GPS)"),
    ("seam_step_max_m", "<=", 0.002, "seam step <= 2 mm"),
    ("coverage", ">=", 0.95, "coverage >= 95% of the imaged corridor"),
]
TARGETS_CONSUMER = [
    ("drift_5m_p95_pct", "<=", 1.0, "relative drift <= 1% over 5 m windows (95th percentile)"),
    (
        "trajectory_rmse_vs_gps_noise",
        "<=",
        1.0,
        "absolute RMSE no worse than the GPS's own error (ratio)",
    ),
]


def _check_frame_names(run_dir: Path, truth: dict[str, Any]) -> None:
    """A run without a trajectory is matched to the truth by its frames.csv names: another
    drive's truth (no name in common) is an error, not a table of zeros."""
    path = run_dir / rf.FRAME_LABELS_CSV
    if not path.is_file():
        return
    from roadsurf.io.formats import read_csv

    names = [r["filename"] for r in read_csv(path)]
    known = set(truth["filename"])
    n_known = sum(n in known for n in names)
    if names and n_known < min(2, len(names)):
        raise RoadsurfError(
            f"{path}: {n_known} of the run's {len(names)} frames ({', '.join(names[:2])}, ...) "
            f"have a row in the truth's poses.csv ({', '.join(list(truth['filename'])[:2])}, ...): "
            "evaluate a run of this drive against its own truth folder"
        )


def evaluate_run(run_dir: str | Path, truth_dir: str | Path) -> dict[str, Any]:
    """All mapping figures for one run folder; also writes RUN/evaluation.json and .md."""
    run_dir, truth_dir = Path(run_dir), Path(truth_dir)
    if not (truth_dir / df.TRUTH_POSES_CSV).is_file():
        raise RoadsurfError(
            f"{truth_dir}: no poses.csv; pass the simulator's truth folder (DRIVE/truth)"
        )
    scen = (
        read_json(truth_dir / df.TRUTH_SCENARIO_JSON)
        if (truth_dir / df.TRUTH_SCENARIO_JSON).is_file()
        else {}
    )
    crs = scen.get("crs")
    out: dict[str, Any] = {"run": str(run_dir), "truth": str(truth_dir), "crs": crs}
    out["scenario"] = scen.get("scenario")
    truth = truth_poses(truth_dir)
    est = run_trajectory(run_dir, crs)
    if est is None:
        out["warnings"] = ["no georeferenced trajectory.geojson: trajectory figures skipped"]
        align = None
        _check_frame_names(run_dir, truth)
    else:
        tr = trajectory_metrics(est, truth)
        out.update(tr["metrics"])
        align = tr["align"]
        gps_noise = gps_noise_m(truth_dir, scen)
        if gps_noise:
            out["gps_sigma_m"] = gps_noise
        par = scen.get("params", {})
        arm = par.get("gps_antenna_m")
        mount = tuple(float(par.get(f"mount_{k}_deg", 0.0)) for k in ("pitch", "roll", "yaw"))
        gps_rmse = gps_rmse_m(truth_dir, crs, tuple(arm) if arm else None, mount)  # type: ignore[arg-type]
        if gps_rmse:
            # the raw fixes' own error against the true antenna (noise + bias + jumps)
            out["gps_rmse_m"] = gps_rmse
            out["trajectory_rmse_vs_gps_noise"] = out["trajectory_rmse_m"] / gps_rmse
    # the imaged corridor is that of the frames the run placed (all frames without a trajectory)
    seen = set(est["filename"]) if est is not None else set(truth["filename"])
    surf = surface_metrics(run_dir, truth_dir, truth, align, crs, scen, seen)
    out["surface"] = surf.pop("metrics")
    out.update(surf)
    out.update(seam_report(run_dir))  # seam_step_max_m, _p95_m, seam_pairs, source, error
    out["cloud_points_per_m2"] = cloud_density(
        run_dir, out.get("measured_area_m2", out.get("observed_area_m2"))
    )
    out["targets"] = _targets(out, scen)
    if (run_dir / rf.DEFECTS_GEOJSON).is_file():
        try:
            out["detection"] = evaluate_detection(run_dir, truth_dir)
        except Exception as e:  # noqa: BLE001 - a detection scoring problem must not hide ours
            log.warning("detection evaluation failed: %s", e)
            out["detection_error"] = str(e)
    write_json_atomic(run_dir / rf.EVALUATION_JSON, out)
    write_text_atomic(run_dir / rf.EVALUATION_MD, markdown_table([out]))
    return out


def cloud_density(run_dir: Path, observed_m2: float | None) -> float | None:
    """Points of RUN/cloud.ply (its PLY header's vertex count) per m² of the observed surface
    (the cells of surface.tif with a value); None without either."""
    path = run_dir / rf.CLOUD_PLY
    if not observed_m2 or not path.is_file():
        return None
    with open(path, "rb") as f:
        for _ in range(64):
            line = f.readline().decode("ascii", "replace").split()
            if line[:2] == ["element", "vertex"]:
                return int(line[2]) / observed_m2
            if line[:1] == ["end_header"]:
                break
    return None


# --------------------------------------------------------------------------- targets / report


def _get(d: dict[str, Any], key: str) -> Any:
    for k in key.split("."):
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


# issue 30: a drive that passes the same place twice
TARGET_REVISIT = ("revisit_agreement_max_m", "<=", 0.01, "a revisit's passes agree within 1 cm")


def _targets(out: dict[str, Any], scen: dict[str, Any]) -> list[dict[str, Any]]:
    sig = out.get("gps_sigma_m")
    rtk = sig is not None and sig <= 0.05
    targets = TARGETS_RTK if rtk else TARGETS_CONSUMER + TARGETS_RTK[2:]
    if out.get("revisit_pairs"):
        targets = [*targets, TARGET_REVISIT]
    res = []
    for key, op, thr, desc in targets:
        v = _get(out, key)
        met = None
        if isinstance(v, (int, float)) and math.isfinite(v):
            met = v <= thr if op == "<=" else v >= thr
        res.append({"target": desc, "metric": key, "value": v, "threshold": thr, "met": met})
    return res


def _fmt(v: Any, key: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    if key.endswith("_m"):
        return f"{v * 1000:.2f} mm" if abs(v) < 0.1 else f"{v:.3f} m"
    if key.endswith("_pct"):
        return f"{v:.2f} %"
    if key.endswith("_per_m2"):
        return f"{v:,.0f}"
    if key.startswith("coverage") or key.endswith(("accuracy", "precision", "recall")):
        return f"{v * 100:.1f} %"
    return f"{v:.3g}" if isinstance(v, float) else str(v)


ROWS = [
    ("gps_rmse_m", "GPS fixes' own RMSE (for reference)"),
    ("trajectory_rmse_m", "trajectory RMSE (raw)"),
    ("trajectory_rmse_aligned_m", "trajectory RMSE (after 2D rigid alignment)"),
    ("drift_5m_median_pct", "relative drift over 5 m, median"),
    ("drift_5m_p95_pct", "relative drift over 5 m, 95th pct"),
    ("revisit_agreement_m", "revisit: the passes' disagreement, median"),
    ("revisit_agreement_max_m", "revisit: the passes' disagreement, max"),
    ("surface.aligned.flat_mae_m", "flat-road height MAE (aligned)"),
    ("surface.aligned.flat_rmse_m", "flat-road height RMSE (aligned)"),
    ("surface.aligned.defect_mae_m", "in-defect height MAE (aligned)"),
    ("surface.aligned.defect_rmse_m", "in-defect height RMSE (aligned)"),
    ("surface.raw.flat_mae_m", "flat-road height MAE (raw)"),
    ("surface.raw.defect_mae_m", "in-defect height MAE (raw)"),
    ("coverage", "coverage of the imaged corridor"),
    ("coverage_measured", "coverage of the imaged corridor by measured cells (count > 0)"),
    ("coverage_two_view", "coverage of the part seen by two consecutive frames"),
    ("coverage_two_view_measured", "... by measured cells (count > 0)"),
    ("coverage_two_view_share", "share of the corridor seen by two consecutive frames"),
    ("cloud_points_per_m2", "cloud.ply density (points per m² of observed surface)"),
    ("seam_step_max_m", "largest seam step between patches"),
    ("detection.frames.accuracy", "detection: frame accuracy"),
    ("detection.defects.precision", "detection: defect precision"),
    ("detection.defects.recall", "detection: defect recall"),
    ("detection.defects.depth_mae_m", "detection: defect depth MAE"),
]


def markdown_table(results: list[dict[str, Any]], names: list[str] | None = None) -> str:
    """Side-by-side markdown table of one or more evaluations (e.g. roadsurf vs SfM)."""
    names = names or [Path(r["run"]).name for r in results]
    lines = ["| metric | " + " | ".join(names) + " |", "|---|" + "---|" * len(results)]
    for key, label in ROWS:
        lines.append(f"| {label} | " + " | ".join(_fmt(_get(r, key), key) for r in results) + " |")
    lines.append("")
    for name, r in zip(names, results, strict=True):
        for t in r.get("targets", []):
            mark = "n/a" if t["met"] is None else ("met" if t["met"] else "NOT met")
            lines.append(f"- {name}: {t['target']}: {mark} ({_fmt(t['value'], t['metric'])})")
    return "\n".join(lines) + "\n"
