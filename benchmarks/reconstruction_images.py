"""Reconstruction on rendered simulator drives, against the ground truth (part of
``python -m benchmarks.reconstruction``).

Per pair and method: the height error of every reconstructed point against truth/residual.tif
(height relative to the smooth road, negative below), split into flat road (true residual
above −3 mm) and potholes (true residual below −10 mm); the point count; the pair status.
Features and matches are computed once per frame/pair and shared by all methods, so the methods
differ only in the geometry.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from roadsurf.core.errors import FrameReadError
from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.io.drive import Drive, load_drive, read_gray
from roadsurf.io.formats import read_csv, read_geotiff
from roadsurf.reconstruction import features as feat
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.reconstruction.estimators import estimate_matches
from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)

IMAGE_METHODS = ("proposed", "rotation_aware", "classic", "colmap")
FLAT_MAX_M = -0.003  # truth residual above this: flat road (m)
POTHOLE_MAX_M = -0.010  # truth residual below this: inside a pothole (m)


def render_drive(work: Path, scenario: str, n_frames: int, overlap: float) -> Path:
    """Render (once, cached in ``work``) a simulator drive with the given frame overlap."""
    from roadsurf.simulation.scenarios import SCENARIOS, make_config, simulate

    out = work / f"{scenario}_{n_frames}f_ov{int(overlap * 100)}"
    if (out / "frames.csv").is_file():
        return out
    cfg = make_config(scenario)
    footprint_m = cfg.height * cfg.camera_height_m / cfg.fx  # along-track ground length
    speed = (1.0 - overlap) * cfg.fps * footprint_m
    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    simulate(scenario, tmp, seed=SCENARIOS[scenario].seed, n_frames=n_frames, speed_mps=speed)
    os.replace(tmp, out)
    return out


class Truth:
    """Ground truth of a simulator drive: camera poses (UTM) and the residual height raster."""

    def __init__(self, drive_dir: Path) -> None:
        tdir = drive_dir / "truth"
        self.poses: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for r in read_csv(tdir / "poses.csv"):
            q = [float(r["qx"]), float(r["qy"]), float(r["qz"]), float(r["qw"])]
            t = np.array([float(r["easting_m"]), float(r["northing_m"]), float(r["up_m"])])
            self.poses[r["filename"]] = (Rotation.from_quat(q).as_matrix(), t)
        self.residual, self.grid, nodata = read_geotiff(tdir / "residual.tif")
        self.residual = self.residual.astype(float)
        if nodata is not None:
            self.residual[self.residual == nodata] = np.nan

    def residual_at_cam_points(self, filename: str, X_cam: np.ndarray) -> np.ndarray:
        """True residual (m) under camera-frame points of frame ``filename`` (NaN off-road)."""
        R, t = self.poses[filename]
        w = X_cam @ R.T + t
        rc = np.rint(self.grid.rowcol_from_xy(w[:, :2])).astype(int)
        ok = (rc[:, 0] >= 0) & (rc[:, 0] < self.grid.height)
        ok &= (rc[:, 1] >= 0) & (rc[:, 1] < self.grid.width)
        out = np.full(len(w), np.nan)
        out[ok] = self.residual[rc[ok, 0], rc[ok, 1]]
        return out


def pair_errors(res: PairResult, truth: Truth) -> dict[str, float]:
    """Height RMSE (m) of one pair's points against the truth, flat road and in potholes.

    Our distances are to the pair's own fitted plane, the truth's to the smooth road: the two
    references differ by a plane over one footprint, so a robust plane fitted to the error on
    flat points is removed first (it carries no surface information).
    """
    nan = float("nan")
    if not res.ok or res.n_points == 0:
        return {"rmse_flat_m": nan, "rmse_pothole_m": nan, "n_pothole_pts": 0}
    true = truth.residual_at_cam_points(res.frame_a, res.points_cam_a_m)
    err = res.plane_dist_m - true
    flat = np.isfinite(true) & (true > FLAT_MAX_M)
    hole = np.isfinite(true) & (true < POTHOLE_MAX_M)
    if flat.sum() >= 10:
        X = res.points_cam_a_m
        A = np.column_stack([X[flat, 0], X[flat, 1], np.ones(int(flat.sum()))])
        c = np.linalg.lstsq(A, err[flat], rcond=None)[0]
        for _ in range(2):  # one robust re-fit without gross errors
            r = err[flat] - A @ c
            keep = np.abs(r) < 3 * MAD_TO_SIGMA * np.median(np.abs(r)) + 1e-9
            if keep.sum() >= 10:
                c = np.linalg.lstsq(A[keep], err[flat][keep], rcond=None)[0]
        err = err - (c[0] * X[:, 0] + c[1] * X[:, 1] + c[2])
    rm = lambda m: float(np.sqrt(np.mean(err[m] ** 2))) if m.sum() >= 5 else nan  # noqa: E731
    return {"rmse_flat_m": rm(flat), "rmse_pothole_m": rm(hole), "n_pothole_pts": int(hole.sum())}


def evaluate_drive(
    drive: Drive, methods: tuple[str, ...] = IMAGE_METHODS, cfg: ReconstructionConfig | None = None
) -> list[dict[str, Any]]:
    """Per pair and method: status, point count and height errors against the drive's truth."""
    cfg = cfg or ReconstructionConfig()
    truth = Truth(drive.root)
    cam = drive.camera
    rows: list[dict[str, Any]] = []
    prev = None
    for fr in tqdm(drive.frames, desc=f"pairs {drive.root.name}", leave=False):
        try:
            cur = (fr, feat.detect(read_gray(fr), cfg.features))
        except FrameReadError:
            cur = None
        if prev is not None and cur is not None:
            (fa_fr, fa), (fb_fr, fb) = prev, cur
            ia, ib = feat.match(fa, fb, cfg.features)
            pa = cam.undistort_px(fa.keypoints_px[ia])
            pb = cam.undistort_px(fb.keypoints_px[ib])
            for m in methods:
                res = estimate_matches(
                    pa,
                    pb,
                    cam.K,
                    cam.height_m,
                    replace(cfg, method=m),  # type: ignore[arg-type]
                    image_size=(cam.width, cam.height),
                )
                res.frame_a, res.frame_b = fa_fr.filename, fb_fr.filename
                rows.append(
                    {
                        "drive": drive.root.name,
                        "pair": f"{fa_fr.index}-{fb_fr.index}",
                        "method": m,
                        "status": res.status,
                        "n_points": res.n_points,
                        "config": res.config_name,
                        **pair_errors(res, truth),
                    }
                )
        prev = cur
    return rows


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    keys = sorted(
        {(r["drive"], r["method"]) for r in rows},
        key=lambda k: (k[0], IMAGE_METHODS.index(k[1]) if k[1] in IMAGE_METHODS else 9),
    )
    for d, m in keys:
        rs = [r for r in rows if r["drive"] == d and r["method"] == m]
        ok = [r for r in rs if r["status"] == "ok"]
        flat = [r["rmse_flat_m"] for r in ok if np.isfinite(r["rmse_flat_m"])]
        hole = [
            r["rmse_pothole_m"]
            for r in ok
            if np.isfinite(r["rmse_pothole_m"]) and r["n_pothole_pts"] >= 20
        ]
        out.append(
            {
                "drive": d,
                "method": m,
                "pairs": len(rs),
                "success": len(ok) / max(1, len(rs)),
                "points_median": float(np.median([r["n_points"] for r in ok])) if ok else 0.0,
                "rmse_flat_mm": 1e3 * float(np.median(flat)) if flat else float("nan"),
                "rmse_pothole_mm": 1e3 * float(np.median(hole)) if hole else float("nan"),
                "pothole_pairs": len(hole),
            }
        )
    return out


def images_markdown(summary: list[dict[str, Any]], overlap: float) -> str:
    lines = [
        f"Rendered drives at {overlap:.0%} overlap (simulator scenarios, 640x480, f = 600 px). "
        "Median over pairs of the per-pair height RMSE against truth/residual.tif (mm), flat road "
        f"(true residual > {FLAT_MAX_M * 1e3:g} mm) and in potholes (< {POTHOLE_MAX_M * 1e3:g} mm, "
        "pairs with ≥ 20 such points); median points per pair; pair success rate.",
        "",
        "| drive | method | pairs | success | points | RMSE flat (mm) | RMSE pothole (mm) "
        "| pothole pairs |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in summary:
        lines.append(
            f"| {s['drive']} | {s['method']} | {s['pairs']} | {s['success']:.1%} | "
            f"{s['points_median']:.0f} | {s['rmse_flat_mm']:.2f} | {s['rmse_pothole_mm']:.2f} | "
            f"{s['pothole_pairs']} |"
        )
    return "\n".join(lines) + "\n"


def bench_images(
    work: Path,
    *,
    scenarios: tuple[str, ...] = ("flat", "potholes", "vibration"),
    n_frames: int = 30,
    overlap: float = 0.5,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], str]:
    """Render (cached) and evaluate the drives. Returns (rows, summary, markdown)."""
    rows: list[dict[str, Any]] = []
    for sc in scenarios:
        path = render_drive(Path(work), sc, n_frames, overlap)
        rows += evaluate_drive(load_drive(path))
    summary = summarise(rows)
    return rows, summary, images_markdown(summary, overlap)
