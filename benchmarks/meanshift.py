"""Benchmark: should scikit-learn do the map segmentation's mean shift (eq. 5.11-5.12)?

``roadsurf.detection.meanshift.mean_shift_flat`` is hand-written: a square w x w window
(Chebyshev ball), depth-weighted window means, one seed per occupied w-cell, modes merged by
single linkage. ``sklearn.cluster.MeanShift`` has a flat kernel over a Euclidean disk and no
sample weights. This benchmark measures the difference on real inputs:

1. record: the detection stage re-runs on a copy of each finished run folder (reconstruction
   and mapping resume) with ``mapseg.mean_shift_flat`` wrapped to save every call's inputs;
2. compare: on the recorded calls, ours against MeanShift variants (bandwidth w/2 or
   w/sqrt(pi), the disk of equal area; bin seeding or our seeds): adjusted Rand index against
   ours, cluster counts and time (median of ``--repeat`` alternating calls); and the mode
   merging (scipy linkage/fcluster) against ``sklearn.cluster.AgglomerativeClustering``;
3. end to end: detection precision, recall and depth MAE with ours and with the best variant
   substituted for ``mean_shift_flat``.

    python -m benchmarks.meanshift --runs /tmp/bc/old/runs --drives /tmp/bc/old/drives
    make bench-meanshift ARGS="--runs RUNS --drives DRIVES [--names potholes,flat]"

RUNS/NAME is a finished run folder of the drive DRIVES/NAME (``sample`` is data_samples/drive);
the run folders are copied, never written. Writes benchmarks/results/meanshift.json.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import statistics
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from sklearn.cluster import AgglomerativeClustering, MeanShift
from sklearn.metrics import adjusted_rand_score

from roadsurf.detection import mapseg
from roadsurf.detection.meanshift import grid_seeds, mean_shift_flat, merge_modes, shift_windows

Call = dict[str, Any]  # one recorded call: xy (N, 2), window (m), weights (N,), kwargs
Clusterer = Callable[..., tuple[np.ndarray, np.ndarray]]

# name -> (bandwidth as a share of w, seeds): "bin" = sklearn's bin seeding, "grid" = ours.
VARIANTS: dict[str, tuple[float, str]] = {
    "sk_half_bin": (0.5, "bin"),
    "sk_area_bin": (1 / np.sqrt(np.pi), "bin"),
    "sk_half_grid": (0.5, "grid"),
    "sk_area_grid": (1 / np.sqrt(np.pi), "grid"),
}
SAMPLE_DRIVE = Path("data_samples/drive")


def sklearn_mean_shift(
    xy_m: np.ndarray,
    window_m: float,
    *,
    variant: str = "sk_half_grid",
    weights: np.ndarray | None = None,
    max_iter: int = 50,
    tol_m: float = 1e-3,
    merge_m: float | None = None,
    min_points: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """``mean_shift_flat``'s signature on ``sklearn.cluster.MeanShift`` (weights, tol_m and
    merge_m have no counterpart there: MeanShift ignores them)."""
    del weights, tol_m, merge_m
    xy = np.asarray(xy_m, float)
    if len(xy) == 0:
        return np.zeros(0, int), np.zeros((0, 2))
    share, seeding = VARIANTS[variant]
    seeds = grid_seeds(xy, window_m, min_points) if seeding == "grid" else None
    ms = MeanShift(
        bandwidth=share * window_m,
        seeds=seeds,
        bin_seeding=seeding == "bin",
        min_bin_freq=min_points,
        cluster_all=True,
        max_iter=max_iter,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            ms.fit(xy)
        except ValueError:  # no seed has a point within the bandwidth: one cluster
            return np.zeros(len(xy), int), xy.mean(axis=0, keepdims=True)
    return ms.labels_.astype(int), ms.cluster_centers_


def _variant(name: str) -> Clusterer:
    def f(xy_m: np.ndarray, window_m: float, **kw: Any) -> tuple[np.ndarray, np.ndarray]:
        return sklearn_mean_shift(xy_m, window_m, variant=name, **kw)

    return f


def sklearn_merge(modes_m: np.ndarray, merge_m: float) -> np.ndarray:
    """``merge_modes`` on ``AgglomerativeClustering`` (single linkage, Chebyshev, same cut)."""
    if len(modes_m) <= 1:
        return np.zeros(len(modes_m), int)
    ac = AgglomerativeClustering(
        n_clusters=None, linkage="single", metric="chebyshev", distance_threshold=merge_m * 1.0001
    )
    return ac.fit_predict(modes_m)


def run_detection(
    run: Path, drive: Path, work: Path, clusterer: Clusterer | None = None
) -> tuple[list[Call], dict[str, Any]]:
    """Re-run detection on a copy of ``run`` with ``clusterer`` as mapseg's mean shift (None:
    ours); returns the recorded calls and the detection evaluation against DRIVE/truth."""
    from roadsurf.evaluation.detection import evaluate_detection
    from roadsurf.pipeline import run_drive

    copy = work / run.name
    if copy.exists():
        shutil.rmtree(copy)
    shutil.copytree(run, copy)
    cfg = work / "detection_overwrite.yaml"
    cfg.write_text("detection:\n  overwrite: true\n")
    calls: list[Call] = []
    impl = clusterer or mean_shift_flat

    def recording(xy_m: np.ndarray, window_m: float, **kw: Any) -> tuple[np.ndarray, np.ndarray]:
        w = kw.get("weights")
        calls.append(
            {
                "xy": np.array(xy_m, float),
                "window": float(window_m),
                "weights": None if w is None else np.array(w, float),
                "kwargs": {k: v for k, v in kw.items() if k != "weights"},
            }
        )
        return impl(xy_m, window_m, **kw)

    saved = mapseg.mean_shift_flat
    mapseg.mean_shift_flat = recording
    try:
        run_drive(drive, copy, config_path=cfg)
    finally:
        mapseg.mean_shift_flat = saved
    ev = evaluate_detection(copy, drive / "truth")
    shutil.rmtree(copy)
    return calls, ev


def _timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    t = time.perf_counter()
    out = fn()
    return time.perf_counter() - t, out


def compare_calls(calls: Sequence[Call], repeat: int = 5) -> dict[str, Any]:
    """Ours vs every sklearn variant on ``calls``: ARI (point-weighted mean and minimum),
    cluster counts, summed median times; and the merge step, scipy vs sklearn."""
    methods: dict[str, Clusterer] = {"ours": mean_shift_flat}
    methods.update({name: _variant(name) for name in VARIANTS})
    times: dict[str, float] = dict.fromkeys(methods, 0.0)
    clusters: dict[str, int] = dict.fromkeys(methods, 0)
    ari_sum: dict[str, float] = dict.fromkeys(VARIANTS, 0.0)
    ari_min: dict[str, float] = dict.fromkeys(VARIANTS, 1.0)
    merge_t = {"scipy": 0.0, "sklearn": 0.0}
    merge_same = 0
    n_pts = 0
    for c in calls:
        kw = dict(c["kwargs"], weights=c["weights"])
        per: dict[str, list[float]] = {m: [] for m in methods}
        labels: dict[str, np.ndarray] = {}
        for _ in range(repeat):  # alternate methods so that load drifts hit all alike
            for m, fn in methods.items():
                dt, (lab, _) = _timed(lambda fn=fn, c=c, kw=kw: fn(c["xy"], c["window"], **kw))
                per[m].append(dt)
                labels[m] = lab
        n = len(c["xy"])
        n_pts += n
        for m in methods:
            times[m] += statistics.median(per[m])
            clusters[m] += int(labels[m].max()) + 1 if n else 0
        for v in VARIANTS:
            a = float(adjusted_rand_score(labels["ours"], labels[v])) if n else 1.0
            ari_sum[v] += a * n
            ari_min[v] = min(ari_min[v], a)
        # Merge step on our converged windows: same cut, same partition?
        xy = c["xy"]
        if n == 0:
            continue
        wts = np.ones(n) if c["weights"] is None else c["weights"]
        modes = shift_windows(
            xy, grid_seeds(xy, c["window"], c["kwargs"].get("min_points", 1)), c["window"], wts,
            max_iter=c["kwargs"].get("max_iter", 50), tol_m=c["kwargs"].get("tol_m", 1e-3),
            tree=cKDTree(xy),
        )  # fmt: skip
        merge = c["kwargs"].get("merge_m") or c["window"]
        mt: dict[str, list[float]] = {"scipy": [], "sklearn": []}
        for _ in range(repeat):
            dt, g_sp = _timed(lambda m=modes, d=merge: merge_modes(m, d))
            mt["scipy"].append(dt)
            dt, g_sk = _timed(lambda m=modes, d=merge: sklearn_merge(m, d))
            mt["sklearn"].append(dt)
        for k in mt:
            merge_t[k] += statistics.median(mt[k])
        merge_same += int(adjusted_rand_score(g_sp, g_sk) == 1.0)
    return {
        "calls": len(calls),
        "points": n_pts,
        "time_s": times,
        "clusters": clusters,
        "ari_mean": {v: (ari_sum[v] / n_pts if n_pts else 1.0) for v in VARIANTS},
        "ari_min": ari_min,
        "merge_time_s": merge_t,
        "merge_same_partition": merge_same,
    }


def _detection_figures(ev: dict[str, Any]) -> dict[str, float]:
    d = ev["defects"]
    return {k: float(d[k]) for k in ("predicted", "matched", "precision", "recall", "depth_mae_m")}


def bench(
    runs: Path, drives: Path, names: Sequence[str], work: Path, repeat: int = 5
) -> dict[str, Any]:
    """Record, compare and evaluate end to end on every drive in ``names``."""
    out: dict[str, Any] = {"drives": {}}
    recorded: dict[str, tuple[list[Call], dict[str, Any]]] = {}
    for name in names:
        drive = SAMPLE_DRIVE if name == "sample" else drives / name
        calls, ev = run_detection(runs / name, drive, work)
        recorded[name] = (calls, ev)
        out["drives"][name] = {"compare": compare_calls(calls, repeat), "end_to_end": {}}
        out["drives"][name]["end_to_end"]["ours"] = _detection_figures(ev)
        logging.getLogger(__name__).warning("%s: %s", name, out["drives"][name]["compare"])
    # The best variant: highest point-weighted ARI over all drives.
    tot = {
        v: sum(d["compare"]["ari_mean"][v] * d["compare"]["points"] for d in out["drives"].values())
        for v in VARIANTS
    }
    best = max(tot, key=lambda v: tot[v])
    out["best_variant"] = best
    for name in names:
        drive = SAMPLE_DRIVE if name == "sample" else drives / name
        _, ev = run_detection(runs / name, drive, work, _variant(best))
        out["drives"][name]["end_to_end"][best] = _detection_figures(ev)
    return out


def table_markdown(res: dict[str, Any]) -> str:
    """The comparison and end-to-end tables (docs/detection.md, "Libraries")."""
    best = res["best_variant"]
    lines = [
        "| drive | calls | points | method | ARI vs ours (mean / min) | clusters | time |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, d in res["drives"].items():
        c = d["compare"]
        for m in ["ours", *VARIANTS]:
            ari = "-" if m == "ours" else f"{c['ari_mean'][m]:.3f} / {c['ari_min'][m]:.3f}"
            lines.append(
                f"| {name} | {c['calls']} | {c['points']} | {m} | {ari} | {c['clusters'][m]} "
                f"| {1000 * c['time_s'][m]:.1f} ms |"
            )
    lines += [
        "",
        "| drive | merge: same partition | scipy linkage+fcluster | sklearn Agglomerative |",
        "|---|---|---|---|",
    ]
    for name, d in res["drives"].items():
        c = d["compare"]
        lines.append(
            f"| {name} | {c['merge_same_partition']}/{c['calls']} "
            f"| {1000 * c['merge_time_s']['scipy']:.2f} ms "
            f"| {1000 * c['merge_time_s']['sklearn']:.2f} ms |"
        )
    lines += [
        "",
        "| drive | clusterer | defects predicted / matched | precision | recall | depth MAE |",
        "|---|---|---|---|---|---|",
    ]
    for name, d in res["drives"].items():
        for m in ("ours", best):
            e = d["end_to_end"][m]
            lines.append(
                f"| {name} | {m} | {e['predicted']:.0f} / {e['matched']:.0f} "
                f"| {e['precision']:.3f} | {e['recall']:.3f} | {1000 * e['depth_mae_m']:.2f} mm |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.meanshift --runs RUNS --drives DRIVES`` (make bench-meanshift)."""
    from benchmarks._result import write_result

    ap = argparse.ArgumentParser(description="Hand-written mean shift vs scikit-learn's.")
    ap.add_argument("--runs", type=Path, required=True, help="finished run folders RUNS/NAME")
    ap.add_argument("--drives", type=Path, required=True, help="their drives DRIVES/NAME")
    ap.add_argument("--names", default="potholes,flat,varied,vibration,sample")
    ap.add_argument("--repeat", type=int, default=5, help="timed calls per method (median)")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    with tempfile.TemporaryDirectory(prefix="roadsurf_bench_meanshift_") as tmp:
        res = bench(a.runs, a.drives, a.names.split(","), Path(tmp), a.repeat)
    table = table_markdown(res)
    print(table)
    write_result(a.json, "meanshift", {**res, "markdown": table})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
