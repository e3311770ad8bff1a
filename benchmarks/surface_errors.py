"""Benchmark: what a run's surface error and coverage are made of, against simulator truth
(issues 28 and 29). For a run folder and its simulated drive:

- the corridor (union of the true camera footprints) split into the part seen by one frame only
  (at the drive's ends, elsewhere: the sides of a tilted camera's trapezoids) and the part seen
  by two consecutive frames, and how much of each the run covers;
- the aligned flat MAE (as ``roadsurf evaluate``) against the MAE of a surface that is zero
  everywhere, and against the truth's own relief below a scale (truth smoothed by a Gaussian of
  σ 4 / 8 mm vs the truth): what no surface of that resolution can follow;
- the registration: the MAE after the best shift of each 0.4 m block against the truth
  (± 32 mm), the median shift, and the aligned camera centres' along-track error, which
  moves the whole map by as much;
- the in-defect MAE of measured cells and of filled ones (``surface_nobs`` 0).

    python -m benchmarks.surface_errors RUN DRIVE [--json OUT.json]

(RUN from ``make bench-surface``: WORK/run_TAG_dense, DRIVE: WORK/drive_TAG.) Prints one
JSON object; writes it with --json. Diagnostic, not a reference result.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np


def _truth(drive: Path) -> dict[str, Any]:
    import rasterio
    import shapely
    from pyproj import Transformer
    from rasterio.features import rasterize

    from roadsurf.core.atomic import read_json
    from roadsurf.io.formats import read_geojson

    td = drive / "truth"
    crs = read_json(td / "scenario.json")["crs"]
    with rasterio.open(td / "residual.tif") as t:
        tres, tT = t.read(1), t.transform
    trf = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    shapes = []
    for f in read_geojson(td / "defects.geojson")["features"]:
        ring = np.array(f["geometry"]["coordinates"][0], float)
        x, y = trf.transform(ring[:, 0], ring[:, 1])
        shapes.append(shapely.Polygon(np.column_stack([x, y])))
    dmask = (
        rasterize(shapes, out_shape=tres.shape, transform=tT, fill=0, default_value=1) > 0
        if shapes
        else np.zeros(tres.shape, bool)
    )
    return {"crs": crs, "res": tres, "T": tT, "defects": dmask}


def _views(drive: Path, truth: dict[str, Any], tr: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) int16: how many true camera footprints hold each truth cell; (H, W) bool: the
    cells in the first or the last frame's footprint."""
    import shapely
    from rasterio.features import rasterize
    from scipy.spatial.transform import Rotation

    from roadsurf.core.camera import RENDER_UNDISTORT_CRITERIA
    from roadsurf.io.drive.camera_yaml import load_camera

    cam = load_camera(drive / "camera.yaml")
    w, h = cam.width - 1.0, cam.height - 1.0
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
    und = cam.normalised_from_raw_px(corners, criteria=RENDER_UNDISTORT_CRITERIA)
    rays = np.column_stack([und, np.ones(4)])
    q = tr["q"]
    Rs = Rotation.from_quat(np.column_stack([q[:, 1], q[:, 2], q[:, 3], q[:, 0]])).as_matrix()
    cnt = np.zeros(truth["res"].shape, np.int16)
    ends = np.zeros(cnt.shape, bool)
    for k in range(len(q)):
        rw = rays @ Rs[k].T
        if np.any(rw[:, 2] >= -1e-6):
            continue
        xy = tr["xy"][k] + (-cam.height_m / rw[:, 2])[:, None] * rw[:, :2]
        m = rasterize([shapely.Polygon(xy)], out_shape=cnt.shape, transform=truth["T"], fill=0)
        cnt += m.astype(np.int16)
        if k in (0, len(q) - 1):
            ends |= m > 0
    return cnt, ends


def analyse(run: Path, drive: Path) -> dict[str, Any]:
    import rasterio

    from roadsurf.evaluation.trajectory import run_trajectory, trajectory_metrics, truth_poses

    truth = _truth(drive)
    tr = truth_poses(drive / "truth")
    est = run_trajectory(run, truth["crs"])
    if est is None:
        raise SystemExit(f"{run}: no georeferenced trajectory.geojson")
    A, b = trajectory_metrics(est, tr)["align"]
    tres, tT = truth["res"], truth["T"]
    out: dict[str, Any] = {"run": str(run), "drive": str(drive)}
    # the run's cells on the truth grid (the cell holding each truth cell's centre, aligned)
    views, ends = _views(drive, truth, tr)
    rr, cc = np.nonzero(views > 0)
    x, y = tT.c + (cc + 0.5) * tT.a, tT.f + (rr + 0.5) * tT.e
    P = (np.column_stack([x, y]) - b) @ np.linalg.inv(A).T
    with rasterio.open(run / "surface.tif") as s:
        our, sT = s.read(1), s.transform
    nobs_path = run / "surface_nobs.tif"
    nob = rasterio.open(nobs_path).read(1) if nobs_path.is_file() else np.ones_like(our, np.uint8)
    col, row = ~sT * (P[:, 0], P[:, 1])
    col, row = np.floor(col).astype(int), np.floor(row).astype(int)
    ok = (row >= 0) & (row < our.shape[0]) & (col >= 0) & (col < our.shape[1])
    ov = np.full(len(rr), np.nan, np.float32)
    no = np.zeros(len(rr), np.int32)
    ov[ok], no[ok] = our[row[ok], col[ok]], nob[row[ok], col[ok]]
    have = np.isfinite(ov)
    v = views[rr, cc]
    n_frames = len(est["filename"])
    single = v == 1
    out["corridor_single_view_share"] = float(single.mean())
    # single-view cells at the drive's ends (in the first / last frame's footprint); the rest
    # are the sides of a tilted camera's trapezoids, wider than the next frame's view there
    out["corridor_single_view_ends_share"] = float((single & ends[rr, cc]).mean())
    out["coverage"] = float(have.mean())
    out["coverage_two_view"] = float(have[~single].mean())
    out["coverage_single_view"] = float(have[single].mean()) if single.any() else None
    out["n_frames"] = n_frames
    # flat error
    tv = tres[rr, cc]
    isdef = truth["defects"][rr, cc]
    fl = have & np.isfinite(tv) & ~isdef
    d = ov[fl] - tv[fl]
    out["flat_mae_m"] = float(np.mean(np.abs(d)))
    out["flat_mae_zero_surface_m"] = float(np.mean(np.abs(tv[fl])))
    Tz = np.where(np.isfinite(tres), tres, 0).astype(np.float32)
    Wt = np.isfinite(tres).astype(np.float32)
    below = {}
    for sg_mm in (4, 8):
        sg = sg_mm * 1e-3 / abs(tT.a)
        sm = cv2.GaussianBlur(Tz, (0, 0), sg) / np.maximum(cv2.GaussianBlur(Wt, (0, 0), sg), 1e-6)
        below[f"{sg_mm}mm"] = float(np.mean(np.abs(tv[fl] - sm[rr, cc][fl])))
    out["truth_relief_below_sigma_mae_m"] = below
    # registration: per 0.4 m block, the whole-cell shift (± 8 truth cells) that fits the run
    # best. Whole cells only: a fractional shift samples the truth bilinearly, which smooths
    # it towards the run's own smoothing and lowers the MAE of a perfectly registered surface
    # (truth blurred by 6 mm + noise: 0.94 -> 0.67 mm; whole cells: unchanged, shift 0)
    H, W = tres.shape
    fr, fc, fo = rr[fl], cc[fl], ov[fl]
    B = max(1, int(round(0.4 / abs(tT.a))))
    blk = (fr // B) * 1_000_000 + (fc // B)
    rows = []
    for key in np.unique(blk):
        m = blk == key
        if m.sum() < 0.3 * B * B:
            continue
        best = (np.inf, 0, 0)
        for i in range(-8, 9):
            for j in range(-8, 9):
                t = Tz[np.clip(fr[m] + i, 0, H - 1), np.clip(fc[m] + j, 0, W - 1)]
                e = float(np.mean(np.abs(fo[m] - t)))
                if e < best[0]:
                    best = (e, i, j)
        rows.append((m.sum(), float(np.mean(np.abs(d[m]))), *best))
    if rows:
        g = np.array(rows, float)
        wts = g[:, 0] / g[:, 0].sum()
        mm = abs(tT.a) * 1e3
        out["flat_mae_blocks_m"] = float((wts * g[:, 1]).sum())
        out["flat_mae_after_block_shift_m"] = float((wts * g[:, 2]).sum())
        out["block_shift_median_mm"] = [
            float(np.median(g[:, 3]) * mm),
            float(np.median(g[:, 4]) * mm),
        ]
        out["block_shift_std_mm"] = [float(g[:, 3].std() * mm), float(g[:, 4].std() * mm)]
        out["n_blocks"] = len(g)
    # the aligned camera centres' along-track / lateral error
    idx = {f: i for i, f in enumerate(tr["filename"])}
    k = [idx[f] for f in est["filename"]]
    Pc = np.asarray(est["xy"]) @ A.T + b
    Tc = tr["xy"][k]
    fw = np.gradient(Tc, axis=0)
    fw /= np.maximum(np.linalg.norm(fw, axis=1), 1e-9)[:, None]
    dc = Pc - Tc
    out["camera_along_track_error_std_m"] = float(((dc * fw).sum(1)).std())
    out["camera_lateral_error_std_m"] = float((dc[:, 0] * -fw[:, 1] + dc[:, 1] * fw[:, 0]).std())
    # in-defect: measured vs filled cells
    dd = have & np.isfinite(tv) & isdef
    for name, m in (("measured", no > 0), ("filled", no == 0)):
        mm = dd & m
        out[f"defect_mae_{name}_m"] = float(np.mean(np.abs(ov[mm] - tv[mm]))) if mm.any() else None
        out[f"defect_cells_{name}"] = int(mm.sum())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="run folder (surface.tif, trajectory)")
    ap.add_argument("drive", type=Path, help="simulated drive (camera.yaml, truth/)")
    ap.add_argument("--json", type=Path, default=None, help="write the figures here")
    a = ap.parse_args(argv)
    res = analyse(a.run, a.drive)
    txt = json.dumps(res, indent=2)
    print(txt)
    if a.json:
        a.json.write_text(txt + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
