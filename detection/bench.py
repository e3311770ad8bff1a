"""`roadsurf bench detection`: the dissertation's Table 4.2 on simulator drives.

The same detector runs on the reconstructions of the ``proposed`` method and the ``classic``
and ``colmap`` baselines, over a fixed set of simulated drives (several seeds; flat, potholes,
rough-GPS, highway). Per method it pools the frame confusion counts, defect matches, depth and
area errors and false alarms on distractors over all drives, prints the table with the issue 5
targets as met / not met, and writes it into docs/benchmarks.md (section ``## detection``).

Beyond the dissertation, it also shows the effect of the adaptive T_b on the dissertation's
per-pair frame decision (2D + 3D refinement alone, no map), against the fixed T_b, on the
proposed reconstructions (detection re-run only; pairs and maps are reused).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import logging
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core.atomic import read_json, write_json_atomic

log = logging.getLogger(__name__)

# (scenario, seed, frames): fixed so that the table is reproducible.
DRIVES: tuple[tuple[str, int, int], ...] = (
    ("flat", 101, 30),
    ("potholes", 202, 40),
    ("potholes", 212, 40),
    ("rough-gps", 404, 50),
    ("highway", 505, 40),
)
QUICK_DRIVES: tuple[tuple[str, int, int], ...] = (("flat", 101, 12), ("potholes", 202, 20))
# The product's method first (rotation-aware variant of the proposed method), then baselines.
METHODS: tuple[str, ...] = ("rotation_aware", "proposed", "classic", "colmap")
DOC_BEGIN = "<!-- detection-bench:begin -->"
DOC_END = "<!-- detection-bench:end -->"


def _drive(out: Path, scenario: str, seed: int, n: int) -> Path:
    from roadsurf.simulation.scenarios import simulate

    d = out / "drives" / f"{scenario}_s{seed}_n{n}"
    if not (d / "truth" / "frame_labels.csv").exists():
        log.info("bench detection: simulating %s seed %d (%d frames)", scenario, seed, n)
        simulate(scenario, d, seed=seed, n_frames=n)
    return d


def _variant(run_dir: Path, drive_dir: Path, name: str, **cfg_changes: Any) -> Path:
    """Re-run detection only, with changed config, into RUN/../<run>_<name> (maps reused)."""
    from roadsurf.detection import stage
    from roadsurf.detection.config import DetectionConfig, RefineConfig
    from roadsurf.io.drive import load_drive
    from roadsurf.mapping.types import load_trajectory
    from roadsurf.reconstruction.types import load_pair

    out = run_dir.parent / f"{run_dir.name}_{name}"
    out.mkdir(parents=True, exist_ok=True)
    for f in ("surface.tif", "surface.vrt", "map_points.npz", "poses.npz", "reference.json"):
        src = run_dir / f
        if src.exists() and not (out / f).exists():
            os.symlink(src.resolve(), out / f)
    # surface.vrt points at tiles relative to the run folder; link those too.
    for tiles in run_dir.glob("tiles*"):
        if not (out / tiles.name).exists():
            os.symlink(tiles.resolve(), out / tiles.name)
    refine = cfg_changes.pop("refine", RefineConfig())
    cfg = dataclasses.replace(DetectionConfig(), refine=refine, **cfg_changes)
    drive = load_drive(drive_dir)
    pairs = [load_pair(p) for p in sorted((run_dir / "pairs").glob("*.npz"))]
    stage.run(cfg, drive, pairs, load_trajectory(run_dir), out)
    return out


def redetect(run_dir: Path, drive_dir: Path) -> Path:
    """Re-run the detection stage alone, in place, on a finished run (its pairs, poses and map
    are reused; the defaults of ``DetectionConfig``, as ``roadsurf run`` uses them)."""
    from roadsurf.core.errors import RoadsurfError
    from roadsurf.detection import stage
    from roadsurf.detection.config import DetectionConfig
    from roadsurf.io.drive import load_drive
    from roadsurf.mapping.types import load_trajectory
    from roadsurf.reconstruction.types import load_pair

    if not (run_dir / "poses.npz").exists():
        raise RoadsurfError(
            f"{run_dir}: no poses.npz; run `roadsurf bench detection` once without "
            "--detection-only to make the runs"
        )
    drive = load_drive(drive_dir)
    pairs = [load_pair(p) for p in sorted((run_dir / "pairs").glob("*.npz"))]
    stage.run(DetectionConfig(overwrite=True), drive, pairs, load_trajectory(run_dir), run_dir)
    return run_dir


def binarisation_stats(run_dir: Path, drive_dir: Path, mode: str) -> dict[str, int]:
    """How T_b splits the 3D classes: dark pixels at 3D road points (false dark: shadows,
    exposure) and at 3D defect points deeper than 2 T_d (hits), summed over a run's pairs."""
    from roadsurf.detection.config import DetectionConfig, RefineConfig
    from roadsurf.detection.planefit import recursive_plane_fit
    from roadsurf.detection.refine import binarise
    from roadsurf.io.drive import load_drive, read_gray
    from roadsurf.reconstruction.types import load_pair

    cfg = DetectionConfig()
    rcfg = RefineConfig(binarise=mode)  # type: ignore[arg-type]
    drive = load_drive(drive_dir)
    frames = {f.filename: f for f in drive.frames}
    out = {"road": 0, "road_dark": 0, "defect": 0, "defect_dark": 0}
    for path in sorted((run_dir / "pairs").glob("*.npz")):
        p = load_pair(path)
        if not p.ok or p.n_points < cfg.plane.min_points or p.frame_a not in frames:
            continue
        fit = recursive_plane_fit(np.asarray(p.points_cam_a_m, float), cfg.plane)
        if not np.isfinite(fit.threshold_m):
            continue
        road = ~fit.candidate & (np.abs(fit.dist_m) < fit.threshold_m)
        deep = fit.dist_m <= -2 * fit.threshold_m
        dark = binarise(read_gray(frames[p.frame_a]), rcfg, road_px=np.asarray(p.px_a)[road])
        h, w = dark.shape
        uv = np.round(np.asarray(p.px_a, float)).astype(int)
        uv[:, 0] = np.clip(uv[:, 0], 0, w - 1)
        uv[:, 1] = np.clip(uv[:, 1], 0, h - 1)
        at = dark[uv[:, 1], uv[:, 0]]
        out["road"] += int(road.sum())
        out["road_dark"] += int((at & road).sum())
        out["defect"] += int(deep.sum())
        out["defect_dark"] += int((at & deep).sum())
    return out


def _pool(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Pool per-drive evaluations: sums of counts, errors over all matched defects."""
    tp = sum(r["frames"]["TP"] for r in results)
    tn = sum(r["frames"]["TN"] for r in results)
    fp = sum(r["frames"]["FP"] for r in results)
    fn = sum(r["frames"]["FN"] for r in results)
    d = [r["defects"] for r in results]
    pred = sum(x["predicted"] for x in d)
    truth = sum(x["truth"] for x in d)
    matched = sum(x["matched"] for x in d)
    tgt = sum(x["target_truth"] for x in d)
    tgt_hit = sum(round(x["target_recall"] * x["target_truth"]) for x in d if x["target_truth"])
    m = [mm for x in d for mm in x["matches"]]
    derr = np.array([mm["depth_err_m"] for mm in m])
    rel = np.array(
        [abs(mm["depth_err_m"]) / mm["truth_depth_m"] for mm in m if mm["truth_depth_m"] > 0]
    )
    aerr = np.array([mm["area_rel_err"] for mm in m if np.isfinite(mm["area_rel_err"])])

    by_type_t: dict[str, int] = {}
    by_type_m: dict[str, int] = {}
    for x in d:
        for k, v in x.get("truth_by_type", {}).items():
            by_type_t[k] = by_type_t.get(k, 0) + v
        for k, v in x.get("matched_by_type", {}).items():
            by_type_m[k] = by_type_m.get(k, 0) + v

    def div(a: float, b: float) -> float:
        return a / b if b else float("nan")

    p, rcl = div(matched, pred), div(matched, truth)
    return {
        "frames": tp + tn + fp + fn,
        "TP": tp,
        "TN": tn,
        "FP": fp,
        "FN": fn,
        "accuracy": div(tp + tn, tp + tn + fp + fn),
        "precision": div(tp, tp + fp),
        "recall": div(tp, tp + fn),
        "defects_pred": pred,
        "defects_truth": truth,
        "defects_matched": matched,
        "defect_precision": p,
        "defect_recall": rcl,
        "defect_f1": div(2 * p * rcl, p + rcl) if matched else 0.0,
        "target_recall": div(tgt_hit, tgt),
        "target_truth": tgt,
        "depth_mae_m": float(np.mean(np.abs(derr))) if len(derr) else float("nan"),
        "depth_bias_m": float(np.mean(derr)) if len(derr) else float("nan"),
        "depth_rel_err": float(np.mean(rel)) if len(rel) else float("nan"),
        "area_median_rel_err": float(np.median(aerr)) if len(aerr) else float("nan"),
        "recall_by_type": {k: f"{by_type_m.get(k, 0)}/{v}" for k, v in sorted(by_type_t.items())},
        "distractor_false_alarms": sum(x["distractor_false_alarms"] for x in d),
        "distractors": sum(x["distractors"] for x in d),
    }


def _fmt(v: Any, pct: bool = False, mm: bool = False) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "n/a"
    if pct:
        return f"{100 * v:.1f}%"
    if mm:
        return f"{1000 * v:.2f}"
    return str(v)


TARGETS: tuple[tuple[str, str, str, Any], ...] = (
    # (pooled key, text, kind, threshold)
    ("accuracy", "frame accuracy >= 99%", "ge", 0.99),
    ("precision", "frame precision >= 97%", "ge", 0.97),
    ("recall", "frame recall >= 97%", "ge", 0.97),
    ("target_recall", "pothole (>= 25 mm, >= 150 mm) recall >= 95%", "ge", 0.95),
    ("defect_precision", "defect precision >= 95%", "ge", 0.95),
    ("distractor_false_alarms", "no defects on distractors", "le", 0),
    ("depth_mae_m", "depth MAE <= 3 mm", "le", 0.003),
    ("area_median_rel_err", "median area error <= 15%", "le", 0.15),
)


def _met(v: Any, kind: str, thr: Any) -> bool:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return False
    return v >= thr if kind == "ge" else v <= thr


def table_markdown(
    pooled: dict[str, dict[str, Any]],
    tb: dict[str, dict[str, Any]],
    bstats: dict[str, dict[str, int]] | None = None,
) -> str:
    """The Table 4.2-style comparison, the T_b comparison and the targets, as markdown."""
    methods = list(pooled)
    rows = [
        ("frames (TP/TN/FP/FN)", lambda p: f"{p['TP']}/{p['TN']}/{p['FP']}/{p['FN']}"),
        ("frame accuracy", lambda p: _fmt(p["accuracy"], pct=True)),
        ("frame precision", lambda p: _fmt(p["precision"], pct=True)),
        ("frame recall", lambda p: _fmt(p["recall"], pct=True)),
        (
            "defects found / true / matched",
            lambda p: f"{p['defects_pred']}/{p['defects_truth']}/{p['defects_matched']}",
        ),
        ("defect precision", lambda p: _fmt(p["defect_precision"], pct=True)),
        ("defect recall (all types)", lambda p: _fmt(p["defect_recall"], pct=True)),
        (
            "found per type",
            lambda p: ", ".join(f"{k} {v}" for k, v in p.get("recall_by_type", {}).items()),
        ),
        ("defect F1", lambda p: _fmt(p["defect_f1"], pct=True)),
        ("pothole recall (>= 25 mm, >= 150 mm)", lambda p: _fmt(p["target_recall"], pct=True)),
        ("depth MAE (mm)", lambda p: _fmt(p["depth_mae_m"], mm=True)),
        ("depth bias (mm)", lambda p: _fmt(p["depth_bias_m"], mm=True)),
        ("relative depth error", lambda p: _fmt(p["depth_rel_err"], pct=True)),
        ("median area error", lambda p: _fmt(p["area_median_rel_err"], pct=True)),
        (
            "false alarms on distractors",
            lambda p: f"{p['distractor_false_alarms']} (of {p['distractors']})",
        ),
    ]
    out = ["| | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for name, fn in rows:
        out.append(f"| {name} | " + " | ".join(fn(pooled[m]) for m in methods) + " |")
    if tb:
        out += [
            "",
            "Effect of T_b on the dissertation's per-pair frame decision (refined points only, "
            f"`frame_label: pair`), {methods[0]} reconstructions; the product's map-based label "
            "for reference:",
            "",
            "| frame label | TP/TN/FP/FN | accuracy | precision | recall |",
            "|---|---|---|---|---|",
        ]
        for name, p in tb.items():
            out.append(
                f"| {name} | {p['TP']}/{p['TN']}/{p['FP']}/{p['FN']} | "
                f"{_fmt(p['accuracy'], pct=True)} | {_fmt(p['precision'], pct=True)} | "
                f"{_fmt(p['recall'], pct=True)} |"
            )
    if bstats:
        out += [
            "",
            "Binarisation alone (pixels of the 3D classes that T_b calls dark; ideal: 0% of road, "
            "100% of defects deeper than 2 T_d):",
            "",
            "| T_b | road points dark (false) | defect points dark (hits) |",
            "|---|---|---|",
        ]
        for mode, st in bstats.items():
            fr = st["road_dark"] / st["road"] if st["road"] else float("nan")
            hr = st["defect_dark"] / st["defect"] if st["defect"] else float("nan")
            out.append(
                f"| {mode} | {_fmt(fr, pct=True)} of {st['road']} | "
                f"{_fmt(hr, pct=True)} of {st['defect']} |"
            )
    if methods:
        p = pooled[methods[0]]
        out += ["", f"Issue 5 targets ({methods[0]}, the product's default):", ""]
        for key, text, kind, thr in TARGETS:
            v = p[key]
            shown = (
                _fmt(v, mm=True) + " mm"
                if key == "depth_mae_m"
                else str(v)
                if key == "distractor_false_alarms"
                else _fmt(v, pct=True)
            )
            out.append(f"- {text}: {shown} — **{'met' if _met(v, kind, thr) else 'not met'}**")
    return "\n".join(out)


READING = (
    "Reading: detection is decided by 3D, with thresholds relative to the measured noise of "
    "each map, so a bad reconstruction produces no defects rather than false ones: `classic` "
    "(8-point F on a near-planar scene) fails most pairs and leaves a map with decimetre noise, "
    "T_d rises with it and nothing is reported (the dissertation's SfM column instead had many "
    "false positives, precision 34%). Lane markings, shadows and oil stains are never reported: "
    "they have no depth. The simulator's cracks (2-6 mm wide, 4-6 mm deep) are below T_d and the "
    "5 mm raster, hence the all-type recall (the 2D detector finds 4 of 7 on textured "
    "roads). Depths, areas and volumes of potholes come from dense Lucas-Kanade tracks inside "
    "each defect, per pair (detection/dense.py): the sparse points rarely sample a pothole's "
    "deepest spot, the raster interpolated between them shaves it; the remaining ~2 mm bias is "
    "the millimetre bottom roughness the 13 mm tracking window smooths (the truth is the "
    "maximum on a 1 mm grid). T_b: the adaptive threshold calls far fewer flat-road pixels "
    "dark and more "
    "defect pixels dark than the fixed one; on these drives this does not change any frame "
    "decision, because 3D evidence already separates the classes."
)


def update_docs(
    doc: Path,
    body: str,
    command: str,
    wall_s: float,
    drives: tuple[tuple[str, int, int], ...],
    detection_only_s: float | None = None,
) -> None:
    """Replace (or append) the detection section of docs/benchmarks.md between markers."""
    now = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    redo = (
        f" This table: detection stage re-run alone on the cached runs (`--detection-only`, "
        f"{detection_only_s / 60:.1f} min wall; pairs, poses and maps as made by the last full "
        "run)."
        if detection_only_s is not None
        else ""
    )
    section = (
        f"{DOC_BEGIN}\n## detection\n\n"
        f"Command: `{command}` — {now}, load average {load}, 2-core x86-64 VM, 24 GB, no GPU, "
        f"shared with other jobs; wall {wall_s / 60:.0f} min for a cold run (simulation, "
        "reconstruction, mapping and detection of every drive and method; a re-run in the same "
        f"work folder reuses them and only redoes what changed).{redo} Drives: "
        + ", ".join(f"{s} seed {sd} ({n} frames)" for s, sd, n in drives)
        + ". Each column is a full `roadsurf run --method M` of every drive, scored by "
        "`detection.evaluate.evaluate_detection`; counts are pooled over all drives. Defects are "
        "matched one to one by outline overlap (5 cm tolerance) after a local rigid 2D fit of "
        "the run's trajectory to the true one (frames within 3 m), which removes the absolute "
        "GPS offset. Dissertation (real roads, Table 4.2): accuracy 98.95%, precision 94.33%, "
        "recall 95.76%; its SfM column: precision 34%.\n\n"
        f"{body}\n\n{READING}\n{DOC_END}\n"
    )
    text = doc.read_text(encoding="utf-8") if doc.exists() else "# Benchmarks\n"
    if DOC_BEGIN in text and DOC_END in text:
        a = text.index(DOC_BEGIN)
        b = text.index(DOC_END) + len(DOC_END)
        text = text[:a] + section.rstrip("\n") + text[b:]
    else:
        text = text.rstrip("\n") + "\n\n" + section
    from roadsurf.core.atomic import write_text_atomic

    write_text_atomic(doc, text)


def run_benchmark(
    out: str | Path,
    *,
    quick: bool = False,
    methods: tuple[str, ...] = METHODS,
    drives: tuple[tuple[str, int, int], ...] | None = None,
    docs: Path | None = None,
    command: str = "roadsurf bench detection",
    detection_only: bool = False,
) -> dict[str, Any]:
    """Run (or resume) the benchmark into ``out``; returns pooled results per method.

    Each drive is simulated once; each (drive, method) is a full `roadsurf run` into
    OUT/runs/<drive>_<method>, which resumes from its cached pairs when re-run. With
    ``detection_only`` the runs must exist: only their detection stage is re-run (minutes
    instead of the cold run's half hour), e.g. after a change to ``detection/``.
    """
    from roadsurf.detection.config import RefineConfig
    from roadsurf.detection.evaluate import evaluate_detection
    from roadsurf.pipeline import run_drive

    t0 = time.perf_counter()
    out = Path(out)
    drives = drives or (QUICK_DRIVES if quick else DRIVES)
    per: dict[str, list[dict[str, Any]]] = {m: [] for m in methods}
    tb: dict[str, list[dict[str, Any]]] = {
        "map (product)": [],
        "pair, adaptive T_b": [],
        "pair, fixed T_b": [],
    }
    failures: list[str] = []
    bstats: dict[str, dict[str, int]] = {}
    for scenario, seed, n in drives:
        drive_dir = _drive(out, scenario, seed, n)
        for m in methods:
            run_dir = out / "runs" / f"{drive_dir.name}_{m}"
            try:
                if detection_only:
                    redetect(run_dir, drive_dir)
                else:
                    run_drive(drive_dir, run_dir, method=m)
                res = evaluate_detection(run_dir, drive_dir / "truth")
            except Exception as e:  # noqa: BLE001 - a failing baseline is reported, not fatal
                log.error("bench detection: %s on %s failed: %s", m, drive_dir.name, e)
                failures.append(f"{m} on {drive_dir.name}: {e}")
                continue
            write_json_atomic(run_dir / "detection_eval.json", res)
            per[m].append(res)
            if m == methods[0]:
                tb["map (product)"].append(res)
                for name, mode in (
                    ("pair, adaptive T_b", "adaptive"),
                    ("pair, fixed T_b", "fixed"),
                ):
                    v = _variant(
                        run_dir, drive_dir, f"pair_{mode}", frame_label="pair",
                        refine=RefineConfig(binarise=mode),
                    )  # fmt: skip
                    tb[name].append(evaluate_detection(v, drive_dir / "truth"))
                for mode in ("adaptive", "fixed"):
                    st = binarisation_stats(run_dir, drive_dir, mode)
                    acc = bstats.setdefault(mode, dict.fromkeys(st, 0))
                    for k, v in st.items():
                        acc[k] += v
    pooled = {m: _pool(r) for m, r in per.items() if r}
    tb_pooled = {k: _pool(v) for k, v in tb.items() if v}
    body = table_markdown(pooled, tb_pooled, bstats)
    if failures:
        body += "\n\nFailed runs: " + "; ".join(failures)
    wall = time.perf_counter() - t0
    # The docs quote the cold-run time: keep the longest wall seen in this work folder.
    prev = out / "bench_detection.json"
    cold = max(wall, float(read_json(prev).get("cold_wall_s", 0.0))) if prev.exists() else wall
    summary = {
        "pooled": pooled,
        "t_b": tb_pooled,
        "binarisation": bstats,
        "failures": failures,
        "drives": [list(d) for d in drives],
        "machine": platform.platform(),
        "wall_s": wall,
        "cold_wall_s": cold,
        "markdown": body,
    }
    write_json_atomic(out / "bench_detection.json", summary)
    if docs is not None and not quick:
        update_docs(docs, body, command, cold, drives, wall if detection_only else None)
    return summary


def load_summary(out: str | Path) -> dict[str, Any]:
    return read_json(Path(out) / "bench_detection.json")
