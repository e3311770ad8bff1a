"""The SfM baseline's outputs, in the run-folder format of ``roadsurf run`` (docs/formats.md).

cloud.ply, surface.tif, trajectory.geojson and report.json, plus poses.npz/reference.json (the
mapping ``Trajectory`` artifact) so the evaluation tools read both runs the same way.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from roadsurf.core.config import to_dict
from roadsurf.core.geometry import EnuReference
from roadsurf.io.drive import Drive, Frame
from roadsurf.io.formats import GridSpec, write_geotiff
from roadsurf.io.runfolder import TRAJECTORY_GEOJSON, RunFolder
from roadsurf.mapping.datum import RESIDUAL_DATUM
from roadsurf.mapping.export import export_xyz, write_cloud_ply, write_trajectory_geojson
from roadsurf.mapping.rasterise import NODATA_SURFACE
from roadsurf.mapping.types import Trajectory, save_trajectory
from roadsurf.pipeline.sfm.colmap_run import colmap_camera, software_versions
from roadsurf.pipeline.sfm.config import SfmBaselineConfig
from roadsurf.pipeline.sfm.georef import ModelGeo
from roadsurf.pipeline.sfm.surface import surface_raster

if TYPE_CHECKING:
    import pycolmap


def write_products(
    out: Path,
    cfg: SfmBaselineConfig,
    reg: list[Frame],
    R_wc: np.ndarray,
    c_w: np.ndarray,
    ref: EnuReference | None,
    p_w: np.ndarray,
    rgb: np.ndarray,
    residual: np.ndarray,
    *,
    datum: str | None = None,
) -> tuple[str | None, np.ndarray, GridSpec]:
    """Write poses.npz/reference.json, cloud.ply, surface.tif and trajectory.geojson.

    reg: the frames in the outputs (capture order) with their world_from_cam rotations R_wc
    (M, 3, 3) and centres c_w (M, 3) m; p_w (K, 3) m points with rgb (K, 3) and residual_m (K,).
    Returns (crs or None in a local frame, the surface raster (H, W), its grid)."""
    times = np.array([f.timestamp_s for f in reg])
    world_from_cam = np.tile(np.eye(4), (len(reg), 1, 1))
    world_from_cam[:, :3, :3] = R_wc
    world_from_cam[:, :3, 3] = c_w
    traj = Trajectory(
        filenames=[f.filename for f in reg],
        frame_indices=np.array([f.index for f in reg], dtype=np.int64),
        timestamp_s=times,
        world_from_cam=world_from_cam,
        source=["visual"] * len(reg),
        reference=ref,
    )
    save_trajectory(out, traj)
    ef = traj.export_frame
    crs = ef.crs if ef is not None else None
    run = RunFolder(out)
    write_cloud_ply(run.cloud_ply, p_w, rgb, residual, ef, vertical_datum=datum)
    xy_out = export_xyz(p_w, ef)[:, :2]
    raster, grid = surface_raster(xy_out, residual, cfg, crs)
    write_geotiff(
        run.surface_tif,
        raster,
        grid,
        nodata=NODATA_SURFACE,
        tags={"source": "roadsurf sfm-baseline", "units": "m, negative below the road"},
        vertical_datum=RESIDUAL_DATUM,
    )
    write_trajectory_geojson(
        run.path(TRAJECTORY_GEOJSON),
        traj,
        extra={"producer": "sfm-baseline"},
        vertical_datum=datum,
    )
    return crs, raster, grid


def build_report(
    *,
    cfg: SfmBaselineConfig,
    drive: Drive,
    names: list[str],
    reg: list[Frame],
    models: dict[int, pycolmap.Reconstruction],
    sizes: dict[int, int],
    parts: list[ModelGeo],
    notes: dict[int, str],
    reasons: dict[str, str],
    ref: EnuReference | None,
    crs: str | None,
    n_points: int,
    raster: np.ndarray,
    grid: GridSpec,
    timings: dict[str, float],
) -> dict[str, Any]:
    """report.json: counts, why frames are missing, scale and GPS fit per model, settings,
    timings (s) and software versions."""
    main = parts[0]
    report: dict[str, Any] = {
        "producer": "roadsurf sfm-baseline",
        "drive": str(drive.root),
        "crs": crs,
        "reference": {**ref.to_dict(), "crs": crs} if ref is not None else None,
        "frame": "UTM (crs) for cloud.ply/surface.tif"
        if crs
        else "local metric frame (no GPS): x right of the first frame, y its forward, z up",
        "counts": {
            "frames": len(drive.frames),
            "n_images": len(names),
            "registered": len(reg),
            "models": {str(k): v for k, v in sorted(sizes.items())},
            "model_used": main.index,
            "models_used": [g2.index for g2 in parts],
            "points": n_points,
            "surface_px_observed": int(np.isfinite(raster).sum()),
        },
        "registered": len(reg),
        "n_images": len(names),
        "not_registered_reason": reasons,
        "skipped": [{"file": s.file, "line": s.line, "reason": s.reason} for s in drive.skipped],
        "warnings": list(drive.warnings),
        "scale": main.scale,
        "gps_alignment": main.align,
        "models": [
            {
                "index": g2.index,
                "registered": int(sizes[g2.index]),
                "used_frames": len(g2.frames),
                "scale": g2.scale,
                "gps_alignment": g2.align,
            }
            for g2 in parts
        ],
        "models_not_used": {str(k): v for k, v in notes.items()},
        "surface": {"gsd_m": grid.gsd_m, "width": grid.width, "height": grid.height},
        "colmap": {
            "mean_reprojection_error_px": float(
                models[main.index].compute_mean_reprojection_error()
            ),
            "mean_track_length": float(models[main.index].compute_mean_track_length()),
            "camera_model": colmap_camera(drive.camera)[0],
        },
        "config": to_dict(cfg),
        "timings_s": timings,
        "versions": software_versions(),
    }
    return report
