"""`roadsurf evaluate OUT --truth DRIVE/truth`: score a run folder against simulator truth.

Works on any run folder that follows the output contract (roadsurf or the SfM baseline):
``trajectory.geojson`` (Points with filename), ``surface.tif`` or ``surface.vrt``, and optionally
``map_points.npz`` (for the seam step) and ``defects.geojson`` (scored by
``detection.evaluate.evaluate_detection`` when that module exists).

Figures (targets of issue 4 are printed as met / not met):
- trajectory horizontal RMSE (m) against truth/poses.csv, raw and after a 2D rigid alignment;
- relative drift over 5 m windows (% of distance travelled);
- surface height MAE / RMSE (m) on flat road and inside defects, after removing the absolute
  GPS offset with the 2D rigid alignment of the trajectory (raw figures too);
- coverage of the imaged corridor (union of the true camera footprints on the road);
- the largest seam step between neighbouring pair patches (from map_points.npz).
"""

from __future__ import annotations

import importlib
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core.atomic import read_json, write_json_atomic, write_text_atomic
from roadsurf.core.errors import RoadsurfError
from roadsurf.io.formats import read_csv, read_geojson

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


def evaluate_run(run_dir: str | Path, truth_dir: str | Path) -> dict[str, Any]:
    """All mapping figures for one run folder; also writes RUN/evaluation.json and .md."""
    run_dir, truth_dir = Path(run_dir), Path(truth_dir)
    if not (truth_dir / "poses.csv").is_file():
        raise RoadsurfError(
            f"{truth_dir}: no poses.csv; pass the simulator's truth folder (DRIVE/truth)"
        )
    scen = read_json(truth_dir / "scenario.json") if (truth_dir / "scenario.json").is_file() else {}
    crs = scen.get("crs")
    out: dict[str, Any] = {"run": str(run_dir), "truth": str(truth_dir), "crs": crs}
    out["scenario"] = scen.get("scenario")
    truth = _truth_poses(truth_dir)
    est = _run_trajectory(run_dir, crs)
    if est is None:
        out["warnings"] = ["no georeferenced trajectory.geojson: trajectory figures skipped"]
        align = None
    else:
        tr = _trajectory_metrics(est, truth)
        out.update(tr["metrics"])
        align = tr["align"]
        gps_noise = _gps_noise_m(truth_dir, scen)
        if gps_noise:
            out["gps_sigma_m"] = gps_noise
        gps_rmse = _gps_rmse_m(truth_dir, crs)
        if gps_rmse:
            # the raw fixes' own error against the true camera centres (noise + bias + jumps)
            out["gps_rmse_m"] = gps_rmse
            out["trajectory_rmse_vs_gps_noise"] = out["trajectory_rmse_m"] / gps_rmse
    # the imaged corridor is that of the frames the run placed (all frames without a trajectory)
    seen = set(est["filename"]) if est is not None else set(truth["filename"])
    surf = _surface_metrics(run_dir, truth_dir, truth, align, crs, scen, seen)
    out["surface"] = surf.pop("metrics")
    out.update(surf)
    out["seam_step_max_m"], out["seam_step_p95_m"], out["seam_pairs"] = _seam_steps(run_dir)
    out["targets"] = _targets(out, scen)
    try:
        det = importlib.import_module("roadsurf.detection.evaluate")
    except ModuleNotFoundError:
        det = None
    if (
        det is not None
        and hasattr(det, "evaluate_detection")
        and (run_dir / "defects.geojson").is_file()
    ):
        try:
            out["detection"] = det.evaluate_detection(run_dir, truth_dir)
        except Exception as e:  # noqa: BLE001 - a detection scoring problem must not hide ours
            log.warning("detection evaluation failed: %s", e)
            out["detection_error"] = str(e)
    write_json_atomic(run_dir / "evaluation.json", out)
    write_text_atomic(run_dir / "evaluation.md", markdown_table([out]))
    return out


# --------------------------------------------------------------------------- trajectory


def _truth_poses(truth_dir: Path) -> dict[str, Any]:
    rows = read_csv(truth_dir / "poses.csv")
    return {
        "filename": [r["filename"] for r in rows],
        "xy": np.array([[float(r["easting_m"]), float(r["northing_m"])] for r in rows]),
        "up": np.array([float(r["up_m"]) for r in rows]),
        "q": np.array([[float(r[k]) for k in ("qw", "qx", "qy", "qz")] for r in rows]),
        "heading_deg": np.array([float(r["heading_deg"]) for r in rows]),
    }


def _run_trajectory(run_dir: Path, crs: str | None) -> dict[str, Any] | None:
    path = run_dir / "trajectory.geojson"
    if not path.is_file() or crs is None:
        return None
    from pyproj import Transformer

    fc = read_geojson(path)
    names, ll, hd = [], [], []
    for f in fc["features"]:
        if f["geometry"]["type"] == "Point" and "filename" in f["properties"]:
            names.append(f["properties"]["filename"])
            ll.append(f["geometry"]["coordinates"][:2])
            hd.append(float(f["properties"].get("heading_deg", float("nan"))))
    if not names:
        return None
    ll_a = np.array(ll, float)
    x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(ll_a[:, 0], ll_a[:, 1])
    return {"filename": names, "xy": np.column_stack([x, y]), "heading_deg": np.array(hd)}


def rigid_2d(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares 2D rotation R (2, 2) and translation t (2,) with dst ≈ src @ R.T + t."""
    ms, md = src.mean(0), dst.mean(0)
    S = (src - ms).T @ (dst - md)
    yaw = math.atan2(S[0, 1] - S[1, 0], S[0, 0] + S[1, 1])
    R = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    return R, md - ms @ R.T


def _trajectory_metrics(est: dict[str, Any], truth: dict[str, Any]) -> dict[str, Any]:
    idx = {n: i for i, n in enumerate(truth["filename"])}
    pairs = [(i, idx[n]) for i, n in enumerate(est["filename"]) if n in idx]
    e = est["xy"][[a for a, _ in pairs]]
    t = truth["xy"][[b for _, b in pairs]]
    err = np.linalg.norm(e - t, axis=1)
    R, tr = rigid_2d(e, t)
    ea = e @ R.T + tr
    err_a = np.linalg.norm(ea - t, axis=1)
    # relative drift (relative pose error): the displacement over windows of 5 m of true travel,
    # each expressed in its own vehicle frame (heading), so a global heading offset does not
    # count; UTM grid north vs true north is the same for both and cancels too.
    he = np.radians(est["heading_deg"][[a for a, _ in pairs]])
    ht = np.radians(truth["heading_deg"][[b for _, b in pairs]])
    if not np.all(np.isfinite(he)):
        he = ht  # a producer without headings: world-frame displacements
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(t, axis=0), axis=1))])
    drift = []
    for i in range(len(s)):
        j = int(np.searchsorted(s, s[i] + 5.0))
        if j >= len(s):
            break
        d_true = _body(t[j] - t[i], ht[i])
        d_est = _body(e[j] - e[i], he[i])
        drift.append(np.linalg.norm(d_est - d_true) / max(s[j] - s[i], 1e-9) * 100.0)
    drift_a = np.array(drift)
    if not drift:
        log.info("drive shorter than 5 m: no relative drift figure")
    dstat = (
        (float(np.median(drift_a)), float(np.percentile(drift_a, 95)), float(np.max(drift_a)))
        if drift
        else (float("nan"),) * 3
    )
    metrics = {
        "n_frames_matched": len(pairs),
        "trajectory_rmse_m": float(np.sqrt(np.mean(err**2))),
        "trajectory_max_m": float(err.max()),
        "trajectory_rmse_aligned_m": float(np.sqrt(np.mean(err_a**2))),
        "alignment_offset_m": float(np.linalg.norm(tr + (R - np.eye(2)) @ e.mean(0))),
        "alignment_rotation_deg": float(math.degrees(math.atan2(R[1, 0], R[0, 0]))),
        "drift_5m_median_pct": dstat[0],
        "drift_5m_p95_pct": dstat[1],
        "drift_5m_max_pct": dstat[2],
        "distance_m": float(s[-1]),
    }
    return {"metrics": metrics, "align": (R, tr)}


def _body(d: np.ndarray, heading_rad: float) -> np.ndarray:
    """World (E, N) displacement -> vehicle frame (right, forward) for a compass heading."""
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    return np.array([d[0] * c - d[1] * s, d[0] * s + d[1] * c])


def _gps_rmse_m(truth_dir: Path, crs: str | None) -> float | None:
    """RMSE of the drive's GPS fixes against the true path interpolated at the fix times."""
    gps = truth_dir.parent / "gps.csv"
    if crs is None or not gps.is_file():
        return None
    from pyproj import Transformer

    rows = read_csv(truth_dir / "poses.csv")
    tt = np.array([float(r["timestamp_s"]) for r in rows])
    txy = np.array([[float(r["easting_m"]), float(r["northing_m"])] for r in rows])
    g = read_csv(gps)
    try:
        t = np.array([float(r["timestamp_s"]) for r in g])
        lat = np.array([float(r["lat"]) for r in g])
        lon = np.array([float(r["lon"]) for r in g])
    except (KeyError, ValueError):
        return None
    inside = (t >= tt[0]) & (t <= tt[-1])
    if not inside.any():
        return None
    x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(
        lon[inside], lat[inside]
    )
    ex = np.interp(t[inside], tt, txy[:, 0])
    ey = np.interp(t[inside], tt, txy[:, 1])
    return float(np.sqrt(np.mean((np.asarray(x) - ex) ** 2 + (np.asarray(y) - ey) ** 2)))


def _gps_noise_m(truth_dir: Path, scen: dict[str, Any]) -> float | None:
    g = scen.get("derived", {}).get("gps", {})
    if isinstance(g, dict) and g.get("sigma_m"):
        return float(g["sigma_m"])
    p = scen.get("params", {})
    for k in ("gps_sigma_m", "gps_noise_m", "gps_sigma"):
        if k in p and p[k]:
            return float(p[k])
    return None


# --------------------------------------------------------------------------- surface


def _open_surface(run_dir: Path) -> Path | None:
    for name in ("surface.tif", "surface.vrt"):
        if (run_dir / name).exists():
            return run_dir / name
    return None


def _corridor_polygon(
    truth_dir: Path, truth: dict[str, Any], seen: set[str], stereo: bool = False
) -> Any:
    """Union of the true camera footprints on the road (truth CRS), or None."""
    import shapely
    import yaml

    cam_yaml = truth_dir.parent / "camera.yaml"
    if not cam_yaml.is_file():
        return None
    cam = yaml.safe_load(cam_yaml.read_text())
    from scipy.spatial.transform import Rotation

    w, h = float(cam["width"]), float(cam["height"])
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
    rays = np.column_stack(
        [
            (corners[:, 0] - cam["cx"]) / cam["fx"],
            (corners[:, 1] - cam["cy"]) / cam["fy"],
            np.ones(4),
        ]
    )
    q = truth["q"]
    Rs = Rotation.from_quat(np.column_stack([q[:, 1], q[:, 2], q[:, 3], q[:, 0]])).as_matrix()
    polys = []
    for k in range(len(q)):
        if truth["filename"][k] not in seen:
            polys.append(None)
            continue
        rw = rays @ Rs[k].T
        if np.any(rw[:, 2] >= -1e-6):
            continue
        lam = -float(cam["height_m"]) / rw[:, 2]
        xy = truth["xy"][k] + lam[:, None] * rw[:, :2]
        polys.append(shapely.Polygon(xy))
    if stereo:  # seen by two consecutive frames: what a two-view method can measure
        polys = [
            a.intersection(b)
            for a, b in zip(polys[:-1], polys[1:], strict=True)
            if a is not None and b is not None
        ]
    polys = [p for p in polys if p is not None and not p.is_empty]
    return shapely.union_all(polys) if polys else None


def _surface_metrics(
    run_dir: Path,
    truth_dir: Path,
    truth: dict[str, Any],
    align: tuple[np.ndarray, np.ndarray] | None,
    crs: str | None,
    scen: dict[str, Any],
    seen: set[str],
) -> dict[str, Any]:
    import rasterio
    import shapely
    from rasterio.features import rasterize
    from rasterio.windows import Window

    res: dict[str, Any] = {"metrics": {}}
    path = _open_surface(run_dir)
    tpath = truth_dir / "residual.tif"
    if path is None or not tpath.is_file():
        res["metrics"]["note"] = "no surface raster or no truth residual"
        return res
    with rasterio.open(tpath) as t:
        tres = t.read(1).astype(np.float32)
        tnd = t.nodata
        tT = t.transform
        tshape = (t.height, t.width)
    if tnd is not None and not math.isnan(tnd):
        tres[tres == tnd] = np.nan
    defects_path = truth_dir / "defects.geojson"
    dmask = np.zeros(tshape, bool)
    if defects_path.is_file() and crs:
        from pyproj import Transformer

        trf = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
        shapes = []
        for f in read_geojson(defects_path)["features"]:
            ring = np.array(f["geometry"]["coordinates"][0], float)
            x, y = trf.transform(ring[:, 0], ring[:, 1])
            shapes.append(shapely.Polygon(np.column_stack([x, y])))
        if shapes:
            dmask = rasterize(
                shapes, out_shape=tshape, transform=tT, fill=0, default_value=1
            ).astype(bool)

    def burn(poly: Any) -> np.ndarray | None:
        if poly is None:
            return None
        return rasterize([poly], out_shape=tshape, transform=tT, fill=0, default_value=1) > 0

    cmask = burn(_corridor_polygon(truth_dir, truth, seen))
    smask = burn(_corridor_polygon(truth_dir, truth, seen, stereo=True))
    n_in_stereo = 0
    inv_t = ~tT

    acc = {k: [] for k in ("raw_flat", "raw_def", "al_flat", "al_def")}
    n_in_corridor = 0
    our_px_area = 0.0
    with rasterio.open(path) as src:
        nd = src.nodata
        W, H = src.width, src.height
        bs = 1024
        for r0 in range(0, H, bs):
            for c0 in range(0, W, bs):
                win = Window(c0, r0, min(bs, W - c0), min(bs, H - r0))
                a = src.read(1, window=win).astype(np.float32)
                if nd is not None and not math.isnan(nd):
                    a[a == nd] = np.nan
                rr, cc = np.nonzero(np.isfinite(a))
                if len(rr) == 0:
                    continue
                T = src.window_transform(win)
                x = T.c + (cc + 0.5) * T.a
                y = T.f + (rr + 0.5) * T.e
                v = a[rr, cc]
                xy = np.column_stack([x, y])
                for tag, pts in (
                    ("raw", xy),
                    ("al", xy @ align[0].T + align[1] if align else None),
                ):
                    if pts is None:
                        continue
                    col, row = inv_t * (pts[:, 0], pts[:, 1])
                    col, row = np.floor(col).astype(int), np.floor(row).astype(int)
                    ok = (row >= 0) & (row < tshape[0]) & (col >= 0) & (col < tshape[1])
                    tv = np.full(len(v), np.nan, np.float32)
                    tv[ok] = tres[row[ok], col[ok]]
                    isdef = np.zeros(len(v), bool)
                    isdef[ok] = dmask[row[ok], col[ok]]
                    good = np.isfinite(tv)
                    d = (v - tv)[good]
                    acc[f"{tag}_flat"].append(d[~isdef[good]])
                    acc[f"{tag}_def"].append(d[isdef[good]])
                    if tag == ("al" if align else "raw") and cmask is not None:
                        n_in_corridor += int(cmask[row[ok], col[ok]].sum())
                        our_px_area = abs(T.a * T.e)
                        if smask is not None:
                            n_in_stereo += int(smask[row[ok], col[ok]].sum())

    def stats(lst: list[np.ndarray]) -> dict[str, float]:
        d = np.concatenate(lst) if lst else np.zeros(0)
        if len(d) == 0:
            return {"n": 0, "mae_m": float("nan"), "rmse_m": float("nan"), "bias_m": float("nan")}
        return {
            "n": int(len(d)),
            "mae_m": float(np.mean(np.abs(d))),
            "rmse_m": float(np.sqrt(np.mean(d**2))),
            "bias_m": float(np.median(d)),
        }

    m = res["metrics"]
    for tag, name in (("raw", "raw"), ("al", "aligned")):
        f, dd = stats(acc[f"{tag}_flat"]), stats(acc[f"{tag}_def"])
        m[name] = {
            "flat_mae_m": f["mae_m"],
            "flat_rmse_m": f["rmse_m"],
            "flat_bias_m": f["bias_m"],
            "flat_n": f["n"],
            "defect_mae_m": dd["mae_m"],
            "defect_rmse_m": dd["rmse_m"],
            "defect_bias_m": dd["bias_m"],
            "defect_n": dd["n"],
        }
    if cmask is not None and cmask.any():
        # our pixels (their own area) inside the true corridor, over the corridor's area
        area = float(cmask.sum() * abs(tT.a * tT.e))
        res["coverage"] = float(min(1.0, n_in_corridor * our_px_area / area))
        res["corridor_area_m2"] = area
    if smask is not None and smask.any():
        sarea = float(smask.sum() * abs(tT.a * tT.e))
        res["coverage_two_view"] = float(min(1.0, n_in_stereo * our_px_area / sarea))
        if cmask is not None and cmask.any():
            # the ceiling of a two-view method: the drive's ends are seen by one frame only
            res["coverage_two_view_share"] = float(min(1.0, sarea / area))
    return res


# --------------------------------------------------------------------------- seams


def _seam_steps(run_dir: Path) -> tuple[float, float, int]:
    """Height disagreement between neighbouring patches: for patches k and the next one, the
    median residual difference of nearby points (within 1.5 cm) on flat road (|r| < 1 cm)."""
    path = run_dir / "map_points.npz"
    if not path.is_file():
        return float("nan"), float("nan"), 0
    from scipy.spatial import cKDTree

    with np.load(path, allow_pickle=False) as z:
        xyz, r, fr = z["xyz"], z["residual_m"].astype(float), z["frame_index"]
    flat = np.abs(r) < 0.01
    xyz, r, fr = xyz[flat], r[flat], fr[flat]
    ids = np.unique(fr)
    steps = []
    for a, b in zip(ids[:-1], ids[1:], strict=True):
        A, B = fr == a, fr == b
        if A.sum() < 20 or B.sum() < 20:
            continue
        tree = cKDTree(xyz[A, :2])
        d, j = tree.query(xyz[B, :2], distance_upper_bound=0.015)
        ok = np.isfinite(d)
        if ok.sum() < 20:
            continue
        diff = r[B][ok] - r[A][j[ok]]
        steps.append(abs(float(np.median(diff))))
    if not steps:
        return float("nan"), float("nan"), 0
    s = np.array(steps)
    return float(s.max()), float(np.percentile(s, 95)), len(s)


# --------------------------------------------------------------------------- targets / report


def _get(d: dict[str, Any], key: str) -> Any:
    for k in key.split("."):
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _targets(out: dict[str, Any], scen: dict[str, Any]) -> list[dict[str, Any]]:
    sig = out.get("gps_sigma_m")
    rtk = sig is not None and sig <= 0.05
    targets = TARGETS_RTK if rtk else TARGETS_CONSUMER + TARGETS_RTK[2:]
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
    if key.startswith("coverage") or key.endswith(("accuracy", "precision", "recall")):
        return f"{v * 100:.1f} %"
    return f"{v:.3g}" if isinstance(v, float) else str(v)


ROWS = [
    ("gps_rmse_m", "GPS fixes' own RMSE (for reference)"),
    ("trajectory_rmse_m", "trajectory RMSE (raw)"),
    ("trajectory_rmse_aligned_m", "trajectory RMSE (after 2D rigid alignment)"),
    ("drift_5m_median_pct", "relative drift over 5 m, median"),
    ("drift_5m_p95_pct", "relative drift over 5 m, 95th pct"),
    ("surface.aligned.flat_mae_m", "flat-road height MAE (aligned)"),
    ("surface.aligned.flat_rmse_m", "flat-road height RMSE (aligned)"),
    ("surface.aligned.defect_mae_m", "in-defect height MAE (aligned)"),
    ("surface.aligned.defect_rmse_m", "in-defect height RMSE (aligned)"),
    ("surface.raw.flat_mae_m", "flat-road height MAE (raw)"),
    ("surface.raw.defect_mae_m", "in-defect height MAE (raw)"),
    ("coverage", "coverage of the imaged corridor"),
    ("coverage_two_view", "coverage of the part seen by two consecutive frames"),
    ("coverage_two_view_share", "share of the corridor seen by two consecutive frames"),
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
