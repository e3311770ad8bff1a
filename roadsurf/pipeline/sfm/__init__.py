"""Baseline: pycolmap incremental SfM over a whole drive, scaled by camera height, aligned to GPS.

``roadsurf sfm-baseline DRIVE --out OUT`` (``run(cfg, drive_dir, out_dir)``):

1. COLMAP steps, all in ``OUT/colmap/`` and resumable (``colmap_run``): SIFT feature
   extraction on the drive's valid frames with the camera intrinsics of camera.yaml (PINHOLE,
   or OPENCV/FULL_OPENCV when ``dist`` is non-zero), sequential matching (``overlap``
   neighbours), incremental mapping with the intrinsics held fixed. Every model the mapper
   makes is kept in ``OUT/colmap/sparse/<k>/``.
2. Scale, per model, α = h / d_c (dissertation eq. 3.31-3.34), with inconsistent poses dropped
   (``georef``).
3. Georeferencing, per model: a robust 2D fit of the camera centres to GPS, the vertical from
   the GPS altitude; the largest model first, then smaller ones fill the frames it lacks.
   Without GPS: only the largest model, in a local metric frame, ``crs`` null and no lat/lon
   exports (``georef``). The ENU origin and the GPS at frame times are the mapping stage's
   (``mapping.pose_gps``).
4. Outputs in OUT, in the run-folder format of ``roadsurf run`` (``outputs``). residual_m is
   relative to the product's local road surface (``mapping.surface.LocalSurface``: robust
   planes on a 1 m node lattice, 2 m windows) fitted per model; surface.tif is the mean
   residual per cell on the tile lattice of ``roadsurf run`` (``surface``).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from roadsurf.core.atomic import write_json_atomic
from roadsurf.core.errors import RoadsurfError
from roadsurf.io.drive import load_drive
from roadsurf.io.runfolder import RunFolder
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.datum import vertical_datum
from roadsurf.pipeline.sfm.colmap_run import (
    COLMAP_DATABASE,
    COLMAP_DIR,
    not_registered_reasons,
    run_colmap,
)
from roadsurf.pipeline.sfm.config import SfmBaselineConfig, SfmBaselineResult, load_config
from roadsurf.pipeline.sfm.georef import drive_gps, place_models
from roadsurf.pipeline.sfm.outputs import build_report, write_products
from roadsurf.pipeline.sfm.surface import road_points

log = logging.getLogger(__name__)

__all__ = ["run", "run_from_paths"]


def run(
    cfg: SfmBaselineConfig, drive_dir: str | Path, out_dir: str | Path, *, overwrite: bool = False
) -> SfmBaselineResult:
    """Run the pycolmap baseline on a drive and write the run-folder outputs into ``out_dir``."""
    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    drive = load_drive(drive_dir)
    names = [f.filename for f in drive.frames]
    timings: dict[str, float] = {"load_s": time.perf_counter() - t_start}

    models, colmap_t = run_colmap(cfg, drive, out / COLMAP_DIR, overwrite)
    timings.update(colmap_t)
    t0 = time.perf_counter()
    sizes = {k: m.num_reg_images() for k, m in models.items()}
    ref, gps = drive_gps(drive)
    parts, notes, outlier_reasons, ref = place_models(models, sizes, drive, cfg, ref, gps)
    names_out = {f.filename for g2 in parts for f in g2.frames}
    missing = [n for n in names if n not in names_out]
    reasons = not_registered_reasons(
        out / COLMAP_DIR / COLMAP_DATABASE,
        [n for n in missing if n not in outlier_reasons],
        models,
        notes,
        cfg,
    )
    reasons.update({n: r for n, r in outlier_reasons.items() if n not in names_out})
    reasons = {n: reasons[n] for n in names if n in reasons}  # capture order
    if not parts:
        raise RoadsurfError(
            f"{drive.root}: pycolmap produced no usable model ({len(models)} models, sizes "
            f"{sizes}). Check the overlap between frames (speed vs fps) and the image texture. "
            + "; ".join(f"{n}: {r}" for n, r in list(reasons.items())[:5])
        )
    main = parts[0]

    # ---------------------------------------------------------------- merge the models
    frames_all = [f for g2 in parts for f in g2.frames]
    idx = np.argsort([f.index for f in frames_all], kind="stable")
    reg = [frames_all[i] for i in idx]
    R_wc = np.concatenate([g2.R_wc for g2 in parts])[idx]
    c_w = np.concatenate([g2.c_w for g2 in parts])[idx]

    p_w, rgb, residual = road_points(parts, cfg)
    timings["scale_align_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    datum = vertical_datum(MappingConfig(), drive, georeferenced=ref is not None)
    crs, raster, grid = write_products(
        out, cfg, reg, R_wc, c_w, ref, p_w, rgb, residual, datum=datum
    )
    timings["export_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start

    report = build_report(
        cfg=cfg,
        drive=drive,
        names=names,
        reg=reg,
        models=models,
        sizes=sizes,
        parts=parts,
        notes=notes,
        reasons=reasons,
        ref=ref,
        crs=crs,
        n_points=int(len(p_w)),
        raster=raster,
        grid=grid,
        timings=timings,
    )
    write_json_atomic(RunFolder(out).report, report)
    log.info(
        "sfm-baseline: %d/%d images in the outputs (models used %s of %d), α = %.4f m/unit, "
        "%d points, GPS fit rms %s m -> %s",
        len(reg),
        len(names),
        [g2.index for g2 in parts],
        len(models),
        main.scale["alpha_m_per_unit"],
        len(p_w),
        f"{main.align['rms_m']:.3f}" if "rms_m" in main.align else "n/a",
        out,
    )
    return SfmBaselineResult(
        out, len(names), len(reg), reasons, main.scale["alpha_m_per_unit"], crs, report
    )


def run_from_paths(
    drive_dir: str | Path,
    out_dir: str | Path,
    *,
    config_path: str | Path | None = None,
    overwrite: bool = False,
) -> SfmBaselineResult:
    """CLI entry: load the config (a YAML file with an ``sfm_baseline:`` section, or the keys of
    ``SfmBaselineConfig`` at top level; unknown keys are rejected) and ``run``."""
    return run(load_config(config_path), drive_dir, out_dir, overwrite=overwrite)
