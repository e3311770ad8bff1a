"""Score a run's detection outputs against the simulator's ground truth (DRIVE/truth/).

``evaluate_detection(run_dir, truth_dir) -> dict`` reports (dissertation Table 4.2, issue 5):
- per frame: TP, TN, FP, FN, accuracy, precision, recall (RUN/frames.csv vs frame_labels.csv);
- per defect: precision, recall, F1 by matching outlines one to one (shapely), and the recall on
  the target class (potholes >= 25 mm deep and >= 150 mm wide);
- depth MAE and relative depth error, median relative area error (matched defects);
- false alarms on distractors (reported defects overlapping a lane marking, shadow or oil stain
  and no true defect).

The run's map is first brought onto the truth's UTM grid by a 2D rigid fit of its trajectory
(RUN/poses.npz) to truth/poses.csv, which removes the absolute GPS offset (as the mapping
evaluation does). The fit is local: each defect is moved by the fit of the frames within 3 m of
it, since a map from consumer GPS is consistent only locally. The raw, unaligned matching is
reported too.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from roadsurf.core.errors import RoadsurfError
from roadsurf.core.fits import fit_rigid_2d
from roadsurf.core.geometry import ExportFrame
from roadsurf.io import drivefolder as df
from roadsurf.io import runfolder as rf
from roadsurf.io.formats import read_csv, read_geojson
from roadsurf.mapping.types import load_trajectory

if TYPE_CHECKING:
    from shapely import Geometry

    # a defect outline in metres and its GeoJSON properties
    Outline = tuple[Geometry, dict[str, Any]]

log = logging.getLogger(__name__)

MATCH_TOL_M = 0.05  # outlines closer than this count as overlapping (m)
LOCAL_RADIUS_M = 3.0  # defects are aligned by the trajectory within this distance (m)
TARGET_DEPTH_M = 0.025  # issue 5 target class: potholes at least this deep ...
TARGET_WIDTH_M = 0.150  # ... and this wide
CRACK_TARGET_M = 0.003  # issue 29 crack target: cracks at least this wide and this deep


def _safe_div(a: float, b: float) -> float:
    return float(a) / float(b) if b else float("nan")


def frame_metrics(pred: dict[str, int], truth: dict[str, int]) -> dict[str, Any]:
    """Confusion counts and rates over the frames present in both mappings."""
    common = sorted(set(pred) & set(truth))
    tp = sum(1 for f in common if pred[f] and truth[f])
    tn = sum(1 for f in common if not pred[f] and not truth[f])
    fp = sum(1 for f in common if pred[f] and not truth[f])
    fn = sum(1 for f in common if not pred[f] and truth[f])
    return {
        "n": len(common),
        "missing": len(set(truth) - set(pred)),
        "TP": tp,
        "TN": tn,
        "FP": fp,
        "FN": fn,
        "accuracy": _safe_div(tp + tn, len(common)),
        "precision": _safe_div(tp, tp + fp),
        "recall": _safe_div(tp, tp + fn),
    }


def _truth_crs(truth_dir: Path) -> str:
    sc = json.loads((truth_dir / df.TRUTH_SCENARIO_JSON).read_text())
    return str(sc["crs"])


def _project(geojson_fc: dict[str, Any], crs: str) -> list[Outline]:
    """Features -> (shapely geometry in ``crs`` metres, properties)."""
    import shapely.geometry
    from pyproj import Transformer
    from shapely.ops import transform

    tr = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    out = []
    for f in geojson_fc.get("features", []):
        g = shapely.geometry.shape(f["geometry"])
        out.append((transform(lambda x, y, z=None: tr.transform(x, y), g), f["properties"]))
    return out


def _run_geometries(run_dir: Path, crs: str) -> tuple[list[Outline], bool]:
    """The run's defects as (geometry in ``crs`` or local ENU metres, properties), georef flag."""
    import shapely.geometry

    fc = json.loads((run_dir / rf.DEFECTS_GEOJSON).read_text())
    georef = "coordinates" not in (fc.get("properties") or {})
    if georef:
        return _project(read_geojson(run_dir / rf.DEFECTS_GEOJSON), crs), True
    return [
        (shapely.geometry.shape(f["geometry"]), f["properties"]) for f in fc.get("features", [])
    ], False


def _trajectory_alignment(run_dir: Path, truth_dir: Path, crs: str, georef: bool) -> dict[str, Any]:
    """Rigid 2D fit of the run's camera positions (in ``crs``) onto the true ones."""
    traj = load_trajectory(run_dir)
    truth = {r["filename"]: r for r in read_csv(truth_dir / df.TRUTH_POSES_CSV)}
    idx = [i for i, f in enumerate(traj.filenames) if f in truth]
    if len(idx) < 2:
        raise RoadsurfError(
            f"{run_dir}/{rf.POSES_NPZ} shares < 2 frames with {truth_dir}/poses.csv"
        )
    enu = traj.positions_enu_m[idx]
    if georef and traj.reference is not None:
        from pyproj import Transformer

        ef = ExportFrame.for_reference(traj.reference)
        src = ef.utm_from_enu(enu)[:, :2]
        if ef.crs != crs:
            src = np.column_stack(
                Transformer.from_crs(ef.crs, crs, always_xy=True).transform(src[:, 0], src[:, 1])
            )
    else:
        src = enu[:, :2]
    dst = np.array(
        [
            [
                float(truth[traj.filenames[i]]["easting_m"]),
                float(truth[traj.filenames[i]]["northing_m"]),
            ]
            for i in idx
        ]
    )
    fit = fit_rigid_2d(src, dst)
    R, t = fit.R, fit.t
    before = float(np.sqrt(np.mean(np.sum((src - dst) ** 2, axis=1))))
    after = float(np.sqrt(np.mean(np.sum((src @ R.T + t - dst) ** 2, axis=1))))
    return {
        "R": R,
        "t": t,
        "src": src,
        "dst": dst,
        "rmse_before_m": before,
        "rmse_after_m": after,
        "n": len(idx),
    }


def _local_transform(al: dict[str, Any], centre: np.ndarray) -> list[float]:
    """Affine parameters of the rigid fit of the trajectory within LOCAL_RADIUS_M of ``centre``
    (the map is only locally consistent under consumer GPS); the global fit when too few frames."""
    near = np.linalg.norm(al["src"] - centre, axis=1) <= LOCAL_RADIUS_M
    if near.sum() < 4:
        R, t = al["R"], al["t"]
    else:
        fit = fit_rigid_2d(al["src"][near], al["dst"][near])
        R, t = fit.R, fit.t
    return [R[0, 0], R[0, 1], R[1, 0], R[1, 1], t[0], t[1]]


def _match(preds: list[Outline], truths: list[Outline]) -> list[tuple[int, int]]:
    """One-to-one matches (pred index, truth index), greedy by overlap then centroid distance."""
    cands = []
    for i, (gp, _) in enumerate(preds):
        for j, (gt, _) in enumerate(truths):
            if gp.distance(gt) <= MATCH_TOL_M:
                inter = gp.intersection(gt).area
                iou = inter / max(gp.union(gt).area, 1e-12)
                cands.append((-iou, gp.centroid.distance(gt.centroid), i, j))
    cands.sort()
    used_p, used_t, out = set(), set(), []
    for _, _, i, j in cands:
        if i not in used_p and j not in used_t:
            used_p.add(i)
            used_t.add(j)
            out.append((i, j))
    return out


def _count_types(props: Iterable[dict[str, Any]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for p in props:
        t = str(p.get("type", "?"))
        out[t] = out.get(t, 0) + 1
    return out


def _defect_metrics(
    preds: list[Outline], truths: list[Outline], distractors: list[Outline]
) -> dict[str, Any]:
    matches = _match(preds, truths)
    n_p, n_t, n_m = len(preds), len(truths), len(matches)
    precision, recall = _safe_div(n_m, n_p), _safe_div(n_m, n_t)
    f1 = (
        2 * precision * recall / (precision + recall)
        if n_m and precision + recall > 0
        else (float("nan") if not n_p and not n_t else 0.0)
    )
    matched_t = {j for _, j in matches}
    target = [
        j
        for j, (_, p) in enumerate(truths)
        if p.get("type") == "pothole"
        and float(p.get("max_depth_m", 0)) >= TARGET_DEPTH_M
        and float(p.get("width_m", 0)) >= TARGET_WIDTH_M
    ]
    depth_err, rel_depth, area_err, type_ok, details = [], [], [], [], []
    for i, j in matches:
        pp, tp = preds[i][1], truths[j][1]
        dt = float(tp["max_depth_m"])
        # a crack kept on the images has no measured depth (null): no depth error
        err = _num(pp.get("max_depth_m")) - dt
        if math.isfinite(err):
            depth_err.append(err)
            if dt > 0:
                rel_depth.append(abs(err) / dt)
        at = float(tp["area_m2"])
        if at > 0:
            area_err.append(abs(float(pp["area_m2"]) - at) / at)
        type_ok.append(pp.get("type") == tp.get("type"))
        details.append(
            {
                "truth_id": tp.get("id"),
                "pred_id": pp.get("id"),
                "truth_type": tp.get("type"),
                "pred_type": pp.get("type"),
                "truth_depth_m": dt,
                "depth_err_m": err,
                "area_rel_err": abs(float(pp["area_m2"]) - at) / at if at > 0 else float("nan"),
                # crack length and width (issue 29: length within 20 %)
                "length_rel_err": _rel(pp.get("length_m"), tp.get("length_m")),
                "width_err_m": _num(pp.get("width_m")) - _num(tp.get("width_m")),
            }
        )
    matched_p = {i for i, _ in matches}
    on_distractor = 0
    for i, (gp, _) in enumerate(preds):
        if i in matched_p:
            continue
        if any(gp.distance(gd) <= MATCH_TOL_M for gd, _ in distractors):
            on_distractor += 1
    return {
        "predicted": n_p,
        "truth": n_t,
        "matched": n_m,
        "precision": precision,
        "recall": recall,
        "f1": f1,
        "target_truth": len(target),
        "target_recall": _safe_div(sum(1 for j in target if j in matched_t), len(target)),
        "depth_mae_m": float(np.mean(np.abs(depth_err))) if depth_err else float("nan"),
        "depth_bias_m": float(np.mean(depth_err)) if depth_err else float("nan"),
        "depth_rel_err": float(np.mean(rel_depth)) if rel_depth else float("nan"),
        "area_median_rel_err": float(np.median(area_err)) if area_err else float("nan"),
        "type_accuracy": float(np.mean(type_ok)) if type_ok else float("nan"),
        "distractor_false_alarms": on_distractor,
        "distractors": len(distractors),
        "truth_by_type": _count_types(p for _, p in truths),
        "matched_by_type": _count_types(truths[j][1] for j in matched_t),
        "matches": details,
        "missed": [truths[j][1].get("id") for j in range(n_t) if j not in matched_t],
        "crack_target": _crack_target(preds, truths, matches),
    }


def _num(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _rel(pred: Any, truth: Any) -> float:
    """(pred - truth) / truth, NaN when either is missing or the truth is not positive."""
    t = _num(truth)
    return (_num(pred) - t) / t if t > 0 else float("nan")


def _crack_target(
    preds: list[Any], truths: list[Any], matches: list[tuple[int, int]]
) -> dict[str, int]:
    """Issue 29's crack target: true cracks at least 3 mm wide and 3 mm deep, how many were
    detected (matched), and how many of those with their length within 20 %."""
    target = {
        j
        for j, (_, p) in enumerate(truths)
        if p.get("type") == "crack"
        and _num(p.get("width_m")) >= CRACK_TARGET_M
        and _num(p.get("max_depth_m")) >= CRACK_TARGET_M
    }
    found = [(i, j) for i, j in matches if j in target]
    ok = [
        i
        for i, j in found
        if abs(_rel(preds[i][1].get("length_m"), truths[j][1].get("length_m"))) <= 0.2
    ]
    return {"truth": len(target), "detected": len(found), "length_within_20pct": len(ok)}


def evaluate_detection(run_dir: str | Path, truth_dir: str | Path) -> dict[str, Any]:
    """Frame- and defect-level scores of RUN's detection outputs against TRUTH (see module doc)."""
    from shapely import affinity

    run_dir, truth_dir = Path(run_dir), Path(truth_dir)
    for p in (
        run_dir / rf.FRAME_LABELS_CSV,
        run_dir / rf.DEFECTS_GEOJSON,
        truth_dir / df.TRUTH_FRAME_LABELS_CSV,
    ):
        if not p.exists():
            raise RoadsurfError(f"{p}: missing; run `roadsurf run` / `roadsurf simulate` first")
    rows = read_csv(run_dir / rf.FRAME_LABELS_CSV)
    # a frame the run did not analyse (empty defect) is scored as not flagged
    pred = {r["filename"]: int(r["defect"] or 0) for r in rows}
    truth = {
        r["filename"]: int(r["defect"]) for r in read_csv(truth_dir / df.TRUTH_FRAME_LABELS_CSV)
    }
    out: dict[str, Any] = {"frames": frame_metrics(pred, truth)}
    out["frames"]["not_analysed"] = sum(1 for r in rows if not str(r["defect"]).strip())

    crs = _truth_crs(truth_dir)
    preds, georef = _run_geometries(run_dir, crs)
    truths = _project(read_geojson(truth_dir / df.TRUTH_DEFECTS_GEOJSON), crs)
    dpath = truth_dir / df.TRUTH_DISTRACTORS_GEOJSON
    distractors = _project(read_geojson(dpath), crs) if dpath.exists() else []
    if georef:
        out["defects_raw"] = _defect_metrics(preds, truths, distractors)
    try:
        al = _trajectory_alignment(run_dir, truth_dir, crs, georef)
    except (OSError, KeyError, RoadsurfError) as e:
        log.warning("detection evaluation: no trajectory alignment (%s); using raw positions", e)
        al = None
    if al is not None:
        R, t = al["R"], al["t"]
        preds = [
            (affinity.affine_transform(g, _local_transform(al, np.array(g.centroid.coords[0]))), p)
            for g, p in preds
        ]
        out["alignment"] = {
            "rmse_before_m": al["rmse_before_m"],
            "rmse_after_m": al["rmse_after_m"],
            "rotation_deg": math.degrees(math.atan2(R[1, 0], R[0, 0])),
            "shift_m": [float(t[0]), float(t[1])] if not georef else None,
            "frames": al["n"],
        }
    out["defects"] = _defect_metrics(preds, truths, distractors)
    return out


def targets(res: dict[str, Any]) -> dict[str, tuple[float, str, bool]]:
    """Issue 5 targets: name -> (value, target text, met)."""
    f, d = res["frames"], res["defects"]

    def ge(v: float, x: float) -> bool:
        return bool(np.isfinite(v) and v >= x)

    def le(v: float, x: float) -> bool:
        return bool(np.isfinite(v) and v <= x)

    return {
        "frame accuracy": (f["accuracy"], ">= 0.99", ge(f["accuracy"], 0.99)),
        "frame precision": (f["precision"], ">= 0.97", ge(f["precision"], 0.97)),
        "frame recall": (f["recall"], ">= 0.97", ge(f["recall"], 0.97)),
        "pothole recall (>=25 mm, >=150 mm)": (
            d["target_recall"],
            ">= 0.95",
            ge(d["target_recall"], 0.95),
        ),
        "defect precision": (d["precision"], ">= 0.95", ge(d["precision"], 0.95)),
        "distractor false alarms": (
            d["distractor_false_alarms"],
            "== 0",
            d["distractor_false_alarms"] == 0,
        ),
        "depth MAE (m)": (d["depth_mae_m"], "<= 0.003", le(d["depth_mae_m"], 0.003)),
        "median area error": (
            d["area_median_rel_err"],
            "<= 0.15",
            le(d["area_median_rel_err"], 0.15),
        ),
    }
