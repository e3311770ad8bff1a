"""A small synthetic drive + run folder written with the project's own writers (seeded).

It follows the output contract of ``roadsurf run`` (docs: issue 4/5 tables): cloud.ply in UTM,
poses.npz/reference.json, defects.geojson, frames.csv, pairs/*.npz, mosaic.tif, surface.tif,
report.json, plus a refined mask for one frame. ``expected`` holds the counts the viewer must
reproduce.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from roadsurf.core.atomic import write_json_atomic
from roadsurf.core.geometry import (
    EnuReference,
    ExportFrame,
    enu_from_lla,
    lla_from_utm,
    world_from_cam,
)
from roadsurf.io.formats import (
    GridSpec,
    feature,
    polygon_geometry,
    write_csv,
    write_geojson,
    write_geotiff,
    write_ply,
)
from roadsurf.io.runfolder import pair_filename
from roadsurf.mapping.types import Trajectory, save_trajectory
from roadsurf.reconstruction.types import PairResult, save_pair

REF = EnuReference(45.0, 7.0, 200.0)
W, H = 160, 120
CAM_H = 0.5
STEP_M = 0.1


POTHOLE_C, POTHOLE_R = np.array([0.05, 0.35]), 0.08  # ENU centre (m), radius (m); 30 mm deep


def surface_model(xy: np.ndarray) -> np.ndarray:
    """Residual height (m) at ENU east/north: a 30 mm paraboloid pothole and a 12 mm crack."""
    d = np.linalg.norm(xy - POTHOLE_C, axis=1)
    resid = np.where(d < POTHOLE_R, -0.03 * (1 - (d / POTHOLE_R) ** 2), 0.0)
    crack = (np.abs(xy[:, 0] + 0.15) < 0.01) & (np.abs(xy[:, 1] - 0.5) < 0.1)
    return np.where(crack, -0.012, resid)


@dataclass
class SyntheticRun:
    run: Path
    drive: Path
    expected: dict[str, int] = field(default_factory=dict)
    defect_ids_by_severity: list[str] = field(default_factory=list)


def _write_drive(root: Path, n: int, rng: np.random.Generator, gps: bool) -> list[str]:
    (root / "frames").mkdir(parents=True, exist_ok=True)
    (root / "camera.yaml").write_text(
        f"model: pinhole\nwidth: {W}\nheight: {H}\nfx: 150.0\nfy: 150.0\ncx: 80.0\ncy: 60.0\n"
        f"height_m: {CAM_H}\nfps: 10.0\n"
    )
    names = []
    for i in range(n):
        img = cv2.GaussianBlur(rng.integers(0, 255, (H, W, 3), dtype=np.uint8), (5, 5), 0)
        name = f"f{i:04d}.png"
        cv2.imwrite(str(root / "frames" / name), img)
        names.append(name)
    write_csv(
        root / "frames.csv",
        ["filename", "timestamp_s"],
        [(nm, 0.1 * i) for i, nm in enumerate(names)],
    )
    if gps:
        ef = ExportFrame.for_reference(REF)
        rows = []
        for k in range(n // 2 + 1):  # 5 Hz fixes over the drive
            t = 0.2 * k
            enu = np.array([[0.0, t * STEP_M / 0.1, CAM_H]])
            from roadsurf.core.geometry import lla_from_enu

            lat, lon, alt = lla_from_enu(enu, REF)[0]
            rows.append((t, lat, lon, alt))
        write_csv(root / "gps.csv", ["timestamp_s", "lat", "lon", "alt_m"], rows)
        del ef
    return names


def make_synthetic_run(
    tmp: Path,
    *,
    n_frames: int = 8,
    gps: bool = True,
    defects: bool = True,
    seed: int = 0,
) -> SyntheticRun:
    rng = np.random.default_rng(seed)
    drive = tmp / "drive"
    run = tmp / "run"
    run.mkdir(parents=True, exist_ok=True)
    names = _write_drive(drive, n_frames, rng, gps)
    ref = REF if gps else None
    ef = ExportFrame.for_reference(REF) if gps else None

    # trajectory: heading north, camera 0.5 m above the road at z = 0
    poses = np.stack(
        [
            world_from_cam(0.0, position_enu_m=np.array([0.0, STEP_M * i, CAM_H]))
            for i in range(n_frames)
        ]
    )
    save_trajectory(
        run,
        Trajectory(
            names, np.arange(n_frames), 0.1 * np.arange(n_frames), poses, ["fused"] * n_frames, ref
        ),
    )

    # cloud: 1 cm grid over the corridor, a pothole (30 mm) and a crack (12 mm)
    xs = np.arange(-0.3, 0.3, 0.01)
    ys = np.arange(-0.1, STEP_M * n_frames + 0.1, 0.01)
    gx, gy = np.meshgrid(xs, ys)
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    resid = surface_model(xy) + rng.normal(0, 0.0005, len(xy))
    xyz = np.column_stack([xy, resid])
    rgb = np.full((len(xy), 3), 120, np.uint8)
    out_xyz = ef.utm_from_enu(xyz) if ef is not None else xyz
    write_ply(run / "cloud.ply", out_xyz, rgb, {"residual_m": resid.astype(np.float32)})

    # defects.geojson (lon/lat), medium pothole and low crack
    feats = []
    sev_order: list[str] = []
    if defects:
        ang = np.linspace(0, 2 * math.pi, 24, endpoint=False)
        ring_p = POTHOLE_C + POTHOLE_R * np.column_stack([np.cos(ang), np.sin(ang)])
        ring_c = np.array([[-0.16, 0.4], [-0.14, 0.4], [-0.14, 0.6], [-0.16, 0.6]])
        for did, typ, sev, ring, depth, area in (
            (2, "crack", "low", ring_c, 0.012, 0.004),
            (1, "pothole", "medium", ring_p, 0.03, math.pi * POTHOLE_R**2),
        ):
            if ef is not None:
                geom = polygon_geometry(ef.lonlat_from_enu(ring))
            else:  # no GPS: detection writes local coordinates (georeferenced: false)
                closed = np.vstack([ring, ring[:1]])
                geom = {"type": "Polygon", "coordinates": [closed.tolist()]}
            feats.append(
                feature(
                    geom,
                    {
                        "id": did,
                        "type": typ,
                        "severity": sev,
                        "max_depth_m": depth,
                        "mean_depth_m": depth / 2,
                        "area_m2": area,
                        "volume_m3": area * depth / 2,
                        "length_m": 0.2,
                        "width_m": 0.1,
                        "confidence": 0.9,
                        "frames": names[2:5],
                    },
                )
            )
        sev_order = ["1", "2"]  # medium before low
    if ef is not None:
        write_geojson(run / "defects.geojson", feats, {"georeferenced": True})
    else:
        import json

        (run / "defects.geojson").write_text(
            json.dumps(
                {
                    "type": "FeatureCollection",
                    "features": feats,
                    "properties": {"georeferenced": False},
                }
            )
        )
    write_csv(
        run / "frames.csv",
        ["filename", "defect", "p_defect", "source"],
        [
            (nm, int(2 <= i <= 4 and defects), 0.9 if 2 <= i <= 4 else 0.1, "3d")
            for i, nm in enumerate(names)
        ],
    )

    # pairs: 40 matches each (some deeper than 10 mm), 6 rejected; one failed pair
    (run / "pairs").mkdir(exist_ok=True)
    n_ok = 0
    for i in range(n_frames - 1):
        failed = i == n_frames - 2
        pr = PairResult(
            names[i],
            names[i + 1],
            i,
            i + 1,
            "proposed",
            "too_few_matches" if failed else "ok",
            "only 3 matches" if failed else "",
        )
        if not failed:
            m = 40
            pr.px_a = rng.uniform([0, 0], [W, H], (m, 2))
            pr.px_b = pr.px_a + [0.0, -30.0]
            pr.points_cam_a_m = rng.normal(0, 0.1, (m, 3))
            pr.plane_dist_m = np.where(np.arange(m) < 5, -0.02, 0.0)
            pr.rejected_px_a = rng.uniform([0, 0], [W, H], (6, 2))
            pr.rejected_px_b = rng.uniform([0, 0], [W, H], (6, 2))
            pr.n_matches, pr.n_inliers = 46, 40
            n_ok += 1
        save_pair(run / "pairs" / pair_filename(i, i + 1), pr)

    # rasters on a 5 mm UTM grid (or local grid without GPS)
    gsd = 0.005
    lo = np.array([-0.3, -0.1])
    if ef is not None:
        x0, y0 = ef.utm_from_enu(np.array([[lo[0], ys.max(), 0.0]]))[0, :2]
        crs = ef.crs
    else:
        x0, y0, crs = lo[0], ys.max(), "EPSG:32632"
    grid = GridSpec(crs, float(x0), float(y0), gsd, int(0.6 / gsd), int((ys.max() + 0.1) / gsd))
    write_geotiff(
        run / "mosaic.tif",
        rng.integers(60, 200, (grid.height, grid.width, 3), dtype=np.uint8),
        grid,
    )
    # the same surface model at the pixel centres (exact UTM -> ENU), plus noise
    rows, cols = np.mgrid[0 : grid.height, 0 : grid.width]
    pix = grid.xy_from_rowcol(rows.ravel(), cols.ravel())
    if ef is not None:
        latlon = lla_from_utm(pix[:, 0], pix[:, 1], ef.epsg)
        pix = enu_from_lla(latlon[:, 0], latlon[:, 1], 0.0, REF)[:, :2]
    surf = (surface_model(pix) + rng.normal(0, 0.0005, len(pix))).astype(np.float32)
    surf = surf.reshape(grid.height, grid.width)
    surf[:5] = -9999.0
    write_geotiff(run / "surface.tif", surf, grid, nodata=-9999.0)

    # refined 2D mask for frame 3
    (run / "masks").mkdir(exist_ok=True)
    mask = np.zeros((H, W), np.uint8)
    cv2.circle(mask, (80, 60), 20, 255, -1)
    cv2.imwrite(str(run / "masks" / (Path(names[3]).stem + ".png")), mask)

    write_json_atomic(
        run / "report.json",
        {
            "drive": str(drive.resolve()),
            "method": "proposed",
            "crs": ef.crs if ef else None,
            "reference": REF.to_dict() if gps else None,
            "counts": {
                "frames": n_frames,
                "gps_fixes": n_frames // 2 + 1 if gps else 0,
                "pairs": n_frames - 1,
                "pairs_ok": n_ok,
                "pairs_failed": 1,
                "posed_frames": n_frames,
            },
            "skipped_frames": [
                {"file": "frames/broken.jpg", "line": 9, "reason": "truncated JPEG"}
            ],
            "failed_pairs": [
                {
                    "frame_a": names[-2],
                    "frame_b": names[-1],
                    "status": "too_few_matches",
                    "reason": "only 3 matches",
                }
            ],
            "warnings": [],
            "timings_s": {
                "drive": 0.1,
                "reconstruction": 2.5,
                "poses": 0.3,
                "globalmap": 1.2,
                "detection": 0.8,
                "total": 4.9,
            },
            "versions": {"python": "3.11", "rerun-sdk": "0.41.0"},
        },
    )
    return SyntheticRun(
        run=run,
        drive=drive,
        expected={
            "frames": n_frames,
            "cloud_points": len(xy),
            "defects": len(feats),
            "gps_fixes": n_frames // 2 + 1 if gps else 0,
            "pairs_ok": n_ok,
            "matches_per_pair": 40,
            "rejected_per_pair": 6,
            "deep_points_per_pair": 5,
        },
        defect_ids_by_severity=sev_order,
    )
