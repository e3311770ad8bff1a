"""Benchmark: the two-view coverage by measured cells (``roadsurf evaluate``'s
``coverage_two_view_measured``) against two truth corridors: the evaluation's, whose camera
footprints lie on a flat road ``height_m`` below each true camera
(``roadsurf.evaluation.surface._corridor_polygon``), and one whose footprints are cast on the
true road: a plane fitted to ``truth/height.tif`` around each footprint (the simulated road's
grade and cross slope; the plane is extrapolated where the truth raster ends).

Why: a forward-tilted camera sees its far corners at a grazing angle (45° pitch: ~23° below the
horizon), where a road 5 cm higher than the flat one (2 % cross slope over 1.2 m plus a 1 %
grade over 2.6 m) moves the corner ~12 cm; the flat corridor then holds cells the cameras never
saw and misses some they did (tilted drive, seed 202: the far-left corners of the run's
footprints sit 3.7 cm (25°) and 14 cm (45°) from the flat-road ones, and 4 mm from the ones cast
on the truth road at 25°).

    python -m benchmarks.two_view_corridor RUN DRIVE [--json OUT.json]

Diagnostic, not a reference result.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path
from typing import Any

import numpy as np


def road_corridor(drive: Path, truth: dict[str, Any]) -> Any:
    """Union of consecutive true footprints' intersections, each footprint cast on a plane fitted
    to the truth heights within 0.3 m of its flat-road footprint (shapely geometry)."""
    import rasterio
    import shapely
    from scipy.spatial.transform import Rotation

    from roadsurf.core.camera import RENDER_UNDISTORT_CRITERIA
    from roadsurf.io.drive.camera_yaml import load_camera

    td = drive / "truth"
    with rasterio.open(td / "height.tif") as H:
        hz, hT = H.read(1).astype(float), H.transform
    cam = load_camera(drive / "camera.yaml")
    w, h = float(cam.width), float(cam.height)
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
    und = cam.normalised_from_raw_px(corners, criteria=RENDER_UNDISTORT_CRITERIA)
    rays = np.column_stack([und, np.ones(4)])
    q = truth["q"]
    Rs = Rotation.from_quat(np.column_stack([q[:, 1], q[:, 2], q[:, 3], q[:, 0]])).as_matrix()
    with open(td / "poses.csv", newline="") as f:
        up = {r["filename"]: float(r["up_m"]) for r in csv.DictReader(f)}
    polys: list[Any] = []
    for k in range(len(q)):
        rw = rays @ Rs[k].T
        xy0 = truth["xy"][k]
        if np.any(rw[:, 2] >= -1e-6):
            polys.append(None)
            continue
        flat = xy0 + (-cam.height_m / rw[:, 2])[:, None] * rw[:, :2]
        lo, hi = flat.min(0) - 0.3, flat.max(0) + 0.3
        c0, r1 = ~hT * (lo[0], lo[1])
        c1, r0 = ~hT * (hi[0], hi[1])
        r0, r1 = max(int(r0), 0), min(int(r1) + 1, hz.shape[0])
        c0, c1 = max(int(c0), 0), min(int(c1) + 1, hz.shape[1])
        rr, cc = np.mgrid[r0:r1:4, c0:c1:4]
        z = hz[r0:r1:4, c0:c1:4]
        m = np.isfinite(z)
        if m.sum() < 3:
            polys.append(None)
            continue
        x, y = hT * (cc[m] + 0.5, rr[m] + 0.5)
        A = np.column_stack([x - xy0[0], y - xy0[1], np.ones(int(m.sum()))])
        a, b, c = np.linalg.lstsq(A, z[m], rcond=None)[0]
        # the ray C + λ r meets z = a dx + b dy + c
        lam = (c - up[truth["filename"][k]]) / (rw[:, 2] - a * rw[:, 0] - b * rw[:, 1])
        polys.append(shapely.Polygon(xy0 + lam[:, None] * rw[:, :2]))
    pairs = [
        p.intersection(n)
        for p, n in zip(polys[:-1], polys[1:], strict=True)
        if p is not None and n is not None
    ]
    return shapely.union_all([p for p in pairs if not p.is_empty])


def analyse(run: Path, drive: Path) -> dict[str, Any]:
    import rasterio
    from rasterio.features import rasterize

    from roadsurf.core.atomic import read_json
    from roadsurf.evaluation.surface import _corridor_polygon
    from roadsurf.evaluation.trajectory import run_trajectory, trajectory_metrics, truth_poses

    td = drive / "truth"
    crs = read_json(td / "scenario.json")["crs"]
    truth = truth_poses(td)
    with rasterio.open(td / "residual.tif") as t:
        shape, tT = t.shape, t.transform
    est = run_trajectory(run, crs)
    if est is None:
        raise SystemExit(f"{run}: no georeferenced trajectory.geojson")
    A, b = trajectory_metrics(est, truth)["align"]
    with rasterio.open(run / "surface_nobs.tif") as s:
        nob, sT = s.read(1), s.transform

    def measured_share(poly: Any) -> tuple[float, int]:
        mask = rasterize([poly], out_shape=shape, transform=tT, fill=0) > 0
        rr, cc = np.nonzero(mask)
        x, y = tT.c + (cc + 0.5) * tT.a, tT.f + (rr + 0.5) * tT.e
        P = (np.column_stack([x, y]) - b) @ np.linalg.inv(A).T
        col, row = ~sT * (P[:, 0], P[:, 1])
        col, row = np.floor(col).astype(int), np.floor(row).astype(int)
        ok = (row >= 0) & (row < nob.shape[0]) & (col >= 0) & (col < nob.shape[1])
        n = np.zeros(len(rr), np.int64)
        n[ok] = nob[row[ok], col[ok]]
        return float((n > 0).mean()), int(len(rr))

    flat, n_flat = measured_share(_corridor_polygon(td, truth, set(truth["filename"]), True))
    road, n_road = measured_share(road_corridor(drive, truth))
    return {
        "run": str(run),
        "drive": str(drive),
        "two_view_measured_flat_corridor": round(flat, 4),
        "two_view_measured_road_corridor": round(road, 4),
        "cells_flat_corridor": n_flat,
        "cells_road_corridor": n_road,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("drive", type=Path)
    ap.add_argument("--json", type=Path, default=None, help="write the figures here")
    a = ap.parse_args(argv)
    res = analyse(a.run, a.drive)
    print(json.dumps(res))
    if a.json is not None:
        from benchmarks._result import write_result

        write_result(a.json, "two_view_corridor", res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
