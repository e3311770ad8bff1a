"""Parametric study (dissertation Table 3.1, Figs. 3.6-3.12) on the point-level simulator.

Part of ``python -m benchmarks.reconstruction``: the Table 3.1 sweeps, Monte-Carlo trials of
every estimator against the first-order bound, their aggregation and the paired comparison
with colmap. Targets, figures and summary.md are in ``benchmarks.reconstruction_report``.
"""

from __future__ import annotations

import csv
import io
import logging
import os
import platform
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from benchmarks.reconstruction_bound import epsilon_bound
from benchmarks.reconstruction_report import evaluate_targets, make_plots, summary_markdown
from roadsurf.core.atomic import atomic_path, write_text_atomic
from roadsurf.core.fits import camera_plane_distance
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.estimators import estimate_matches
from roadsurf.reconstruction.types import PairResult
from roadsurf.simulation.points import PointPair, PointScene, simulate_points

log = logging.getLogger(__name__)


def epsilon(res: PairResult, pp: PointPair) -> float:
    """Eq. 3.36 error (m): ε = (1/N) Σ |ĥ · d̂_i/d̂_c − d_i| over the points the method returned.

    d̂_i/d̂_c is scale-free, so ĥ (the measured height, = Z_m when δ_h = 0) restores metres.
    The stereo baseline is metric by itself, so its d̂_i are compared directly. NaN on failure.
    """
    if not res.ok or res.n_points == 0:
        return float("nan")
    d_true = pp.d_true_m[res.match_idx]
    if res.method == "stereo":
        return float(np.mean(np.abs(res.plane_dist_m - d_true)))
    r = res.plane_dist_m / camera_plane_distance(res.plane)
    return float(np.mean(np.abs(pp.h_measured_m * r - d_true)))


# ----------------------------------------------------------------------------- the sweeps

BASE = PointScene()  # δ = 0.1 mm, σ = 0.1 px, Z_m = 1.1 m, θ = 0, δ_h = 0, t = (200, 30, 0) mm
POINT_METHODS = ("proposed", "proposed_noiter", "rotation_aware", "classic", "colmap")
SIGMAS = (0.001, 0.005, 0.01, 0.05, 0.1, 0.2)
DELTAS_M = (0.0001, 0.005, 0.01)
Z_MS = (0.5, 0.8, 1.1, 1.4, 1.7)
THETAS = (0.05, 0.1, 0.5, 1.0, 2.0, 5.0)
DELTA_HS_M = (0.0002, 0.001, 0.005, 0.01, 0.02)


@dataclass(frozen=True)
class Cell:
    """One point of a sweep: a scene, the methods to run, and where it is plotted."""

    sweep: str  # sigma | z_m | theta_x | theta_y | theta_z | theta_xyz | delta_h
    x: float  # swept value in the plot's unit (px, mm or deg)
    scene: PointScene
    methods: tuple[str, ...]


def build_cells(quick: bool = False, n_points: int = 200) -> list[Cell]:
    """The Table 3.1 sweeps. quick keeps the corners of each sweep."""
    sig = (0.01, 0.1, 0.2) if quick else SIGMAS
    dl = (0.0001, 0.01) if quick else DELTAS_M
    zs = (0.5, 1.1, 1.7) if quick else Z_MS
    th = (0.1, 1.0, 5.0) if quick else THETAS
    dh = (0.001, 0.02) if quick else DELTA_HS_M
    base = replace(BASE, n_points=n_points)
    cells: list[Cell] = []
    for d in dl:
        for s in sig:
            cells.append(
                Cell(
                    f"sigma@delta={d * 1e3:g}mm",
                    s,
                    replace(base, delta_m=d, sigma_px=s),
                    POINT_METHODS,
                )
            )
        for z in zs:
            cells.append(
                Cell(
                    f"z_m@delta={d * 1e3:g}mm",
                    z * 1e3,
                    replace(base, delta_m=d, z_m=z),
                    POINT_METHODS,
                )
            )
        for h in dh:
            cells.append(
                Cell(
                    f"delta_h@delta={d * 1e3:g}mm",
                    h * 1e3,
                    replace(base, delta_m=d, delta_h_m=h),
                    POINT_METHODS,
                )
            )
    for i, axis in enumerate(("theta_x", "theta_y", "theta_z")):
        for a in th:
            ang = [0.0, 0.0, 0.0]
            ang[i] = a
            methods = POINT_METHODS + (("stereo",) if axis == "theta_y" else ())
            cells.append(Cell(axis, a, replace(base, theta_deg=tuple(ang)), methods))
    for a in th:
        cells.append(Cell("theta_xyz", a, replace(base, theta_deg=(a, a, a)), POINT_METHODS))
    return cells


def _method_cfg(method: str) -> ReconstructionConfig:
    # plane_trim_k = 0: eq. 3.31's plain least-squares plane, as in the bound. The simulated
    # matches hold no mismatches, so the epipolar / reprojection filters are opened: a method
    # with a wrong pose then shows its error in ε instead of failing for lack of points.
    kw: dict[str, Any] = {"plane_trim_k": 0.0, "epi_inlier_px": 1e9, "max_reproj_px": 1e9}
    if method == "proposed_noiter":
        return ReconstructionConfig(method="proposed", f_iterations=0, **kw)
    return ReconstructionConfig(method=method, **kw)  # type: ignore[arg-type]


def run_cell(cell: Cell, n_trials: int, seed: int = 0) -> list[dict[str, Any]]:
    """Monte-Carlo trials of one cell -> one row per (trial, method)."""
    rows: list[dict[str, Any]] = []
    for trial in range(n_trials):
        rng_seed = seed * 1_000_003 + trial
        for scene_kind in ("mono", "stereo"):
            methods = [m for m in cell.methods if (m == "stereo") == (scene_kind == "stereo")]
            if not methods:
                continue
            scene = cell.scene
            if scene_kind == "stereo":  # rectified rig: baseline B along x, camera 2 perturbed
                scene = replace(scene, t_m=(_method_cfg("stereo").stereo_baseline_m, 0.0, 0.0))
            pp = simulate_points(scene, rng_seed)
            bound = epsilon_bound(
                pp.X_a_m,
                pp.d_true_m,
                pp.h_measured_m,
                pp.R_b_from_a,
                pp.t_b_from_a_m,
                pp.K,
                scene.sigma_px,
            )
            for m in methods:
                t0 = time.perf_counter()
                res = estimate_matches(pp.px_a, pp.px_b, pp.K, pp.h_measured_m, _method_cfg(m))
                rows.append(
                    {
                        "sweep": cell.sweep,
                        "x": cell.x,
                        "delta_mm": scene.delta_m * 1e3,
                        "sigma_px": scene.sigma_px,
                        "z_m_mm": scene.z_m * 1e3,
                        "theta_x_deg": scene.theta_deg[0],
                        "theta_y_deg": scene.theta_deg[1],
                        "theta_z_deg": scene.theta_deg[2],
                        "delta_h_mm": scene.delta_h_m * 1e3,
                        "trial": trial,
                        "method": m,
                        "status": res.status,
                        "eps_mm": epsilon(res, pp) * 1e3,
                        "bound_mm": bound * 1e3,
                        "config": res.config_name,
                        "time_ms": (time.perf_counter() - t0) * 1e3,
                    }
                )
    return rows


def _worker(args: tuple[Cell, int, int]) -> list[dict[str, Any]]:
    return run_cell(*args)


def aggregate(trials: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (sweep, x, method): median and p90 of ε (a failed trial counts as ∞), bound, ratios."""
    groups: dict[tuple[str, float, str], list[dict[str, Any]]] = {}
    for r in trials:
        groups.setdefault((r["sweep"], r["x"], r["method"]), []).append(r)
    out = []
    for (sweep, x, method), rs in groups.items():
        eps = np.nan_to_num(np.array([r["eps_mm"] for r in rs]), nan=np.inf)
        bnd = np.array([r["bound_mm"] for r in rs])
        ratio = eps / bnd
        configs = Counter(r["config"].split("=")[0] for r in rs if r["config"])
        out.append(
            {
                "sweep": sweep,
                "x": x,
                "method": method,
                "trials": len(rs),
                "success": float(np.mean([r["status"] == "ok" for r in rs])),
                "eps_median_mm": float(np.median(eps)),
                "eps_p90_mm": float(np.percentile(eps, 90)),
                "bound_median_mm": float(np.median(bnd)),
                "ratio_median": float(np.median(ratio)),
                "ratio_p90": float(np.percentile(ratio, 90)),
                "time_ms_median": float(np.median([r["time_ms"] for r in rs])),
                "config": ";".join(f"{k}:{v}" for k, v in configs.most_common())
                if method == "colmap"
                else "",
            }
        )
    out.sort(key=lambda r: (r["sweep"], r["x"], r["method"]))
    return out


def paired_vs_colmap(
    trials: list[dict[str, Any]], method: str = "rotation_aware"
) -> list[dict[str, Any]]:
    """Per cell, the paired per-trial comparison of `method` with colmap (same simulated pair).

    L_k = ln(ε_method / ε_colmap) for trial k; a trial where only `method` fails counts as
    worse, one where only colmap fails as better. Returns per cell the mean of L with its 95 %
    t interval, the one-sided p-value of "colmap is better" (mean L > 0), and the share of
    trials where `method` is at least as accurate. Medians of ε differ by ~1e-4 between two
    estimators at the first-order floor; this says whether such a gap is more than MC noise.
    """
    from scipy import stats

    eps: dict[tuple[str, float], dict[int, dict[str, float]]] = {}
    for r in trials:
        if r["method"] in (method, "colmap"):
            cell = eps.setdefault((r["sweep"], r["x"]), {})
            cell.setdefault(r["trial"], {})[r["method"]] = float(r["eps_mm"])
    out = []
    for (sweep, x), by_trial in sorted(eps.items()):
        pairs = [(v[method], v["colmap"]) for v in by_trial.values() if len(v) == 2]
        if not pairs:
            continue
        a, c = np.array(pairs).T
        a_ok, c_ok = np.isfinite(a), np.isfinite(c)
        both = a_ok & c_ok
        lr = np.log(a[both] / c[both])
        n_worse_fail = int(np.sum(~a_ok & c_ok))
        n = len(lr)
        mean = float(lr.mean()) if n else float("nan")
        if n >= 2 and lr.std(ddof=1) > 0:
            se = float(lr.std(ddof=1) / np.sqrt(n))
            half = float(stats.t.ppf(0.975, n - 1) * se)
            p_worse = float(stats.t.sf(mean / se, n - 1))
        else:
            half, p_worse = 0.0, 0.5 if n else float("nan")
        if n_worse_fail:  # failing where colmap succeeds is worse, whatever the ratios say
            p_worse = 0.0
        out.append(
            {
                "sweep": sweep,
                "x": x,
                "trials": len(pairs),
                "logratio_mean": mean,
                "logratio_ci_lo": mean - half,
                "logratio_ci_hi": mean + half,
                "p_colmap_better": p_worse,
                # a <= c with inf for a failure: a lone failure of `method` counts as worse
                "share_not_worse": float(
                    np.mean(np.nan_to_num(a, nan=np.inf) <= np.nan_to_num(c, nan=np.inf))
                ),
                "fails_only_method": n_worse_fail,
            }
        )
    return out


def run_study(
    out_dir: Path,
    *,
    quick: bool = False,
    trials: int | None = None,
    workers: int = 2,
    n_points: int | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """Run the sweeps; write study_cells.csv, study_trials.csv, the figure PNGs and summary.md."""
    out_dir = Path(out_dir)
    n_trials = trials or (6 if quick else 20)
    npts = n_points or (120 if quick else 200)
    cells = build_cells(quick, npts)
    t0 = time.perf_counter()
    jobs = [(c, n_trials, seed) for c in cells]
    rows: list[dict[str, Any]] = []
    if workers > 1:
        with ProcessPoolExecutor(max_workers=workers) as ex:
            for r in tqdm(ex.map(_worker, jobs), total=len(jobs), desc="study cells"):
                rows.extend(r)
    else:
        for j in tqdm(jobs, desc="study cells"):
            rows.extend(_worker(j))
    seconds = time.perf_counter() - t0
    agg = aggregate(rows)
    paired = paired_vs_colmap(rows)
    targets = evaluate_targets(agg, paired)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_rows_csv(out_dir / "study_cells.csv", agg)
    write_rows_csv(out_dir / "study_paired.csv", paired)
    _write_trials_gz(out_dir / "study_trials.csv.gz", rows)
    plots = make_plots(agg, out_dir)
    meta = {
        "command": "python -m benchmarks.reconstruction" + (" --quick" if quick else ""),
        "cells": len(cells),
        "trials": n_trials,
        "n_points": npts,
        "seconds": seconds,
        "machine": f"{os.cpu_count()}-CPU {platform.machine()} ({workers} workers)",
        "date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }
    md = summary_markdown(agg, targets, meta)
    write_text_atomic(out_dir / "summary.md", md)
    log.info("study: %d cells in %.0f s -> %s", len(cells), seconds, out_dir)
    return {
        "targets": targets,
        "cells": agg,
        "paired": paired,
        "plots": plots,
        "summary": md,
        "seconds": seconds,
    }


def _write_trials_gz(path: Path, rows: list[dict[str, Any]]) -> None:
    """Every trial, gzip-compressed CSV (the raw data behind study_cells.csv)."""
    import gzip

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0].keys()))
    w.writeheader()
    w.writerows(rows)
    with atomic_path(path) as tmp:
        tmp.write_bytes(gzip.compress(buf.getvalue().encode("utf-8"), mtime=0))


def write_rows_csv(path: Path, rows: list[dict[str, Any]]) -> Path:
    """Write dict rows (same keys) as CSV atomically; an empty list writes an empty file."""
    buf = io.StringIO()
    if rows:
        w = csv.DictWriter(buf, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)
    return write_text_atomic(path, buf.getvalue())
