"""Benchmark: a rendered photo pair's dense heights, pixel by pixel, against a ray cast of the truth.

For a pair run of ``benchmarks.stereo_pair`` (RUN, and DRIVE with ``truth/stereo_pair.json``):
the pair is matched again with the run's R, t and plane and the mapping's dense settings
(``MappingConfig.dense``), and every work-grid pixel of image a is cast as a ray into the true
world (evaluated on a 1 mm grid, ``simulation.world``): its first crossing of the true surface
gives the height the pixel should read (the true residual there). Per pixel error = dense height
minus that, less a plane fitted to the flat pixels' errors (the pair's plane is its own estimate).

Figures split the pothole's pixels (true residual below -5 mm) by the grid that gave their
height (0 = work grid, 1 = the coarse-grid fallback, ``dense.pyramid``) and by the true slope
at the crossing: count, RMS, share of the pothole's squared error. A lead for where the surface's
error comes from, not the surface's figure (``evaluation.pair`` scores the fused cells).

    python -m benchmarks.dense_pair_truth --run RUN --drive DRIVE [--json OUT]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from benchmarks._result import write_result

POTHOLE_M = 0.005  # as evaluation.pair: true residual below -5 mm is inside the pothole (m)
TRUTH_GSD_M = 0.001  # the truth grid for the ray cast (m)
RAY_STEP_M = 0.0005  # ray march step (m, along the ray)


def truth_world(drive: Path) -> tuple[Any, dict[str, Any]]:
    from roadsurf.simulation.build import build_world
    from roadsurf.simulation.config import SimConfig
    from roadsurf.simulation.stereo import SEARCH_FRAMES

    meta = json.loads((drive / "truth" / "stereo_pair.json").read_text())
    p = meta["params"]
    fields = {f.name for f in dataclasses.fields(SimConfig)}
    cfg = SimConfig(
        **{k: (tuple(v) if isinstance(v, list) else v) for k, v in p.items() if k in fields}
    )
    return build_world(cfg, int(meta["seed"]), SEARCH_FRAMES), meta


def ray_cast(
    world: Any, T: np.ndarray, rays_cam: np.ndarray, above_m: float, below_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First crossing of rays (N, 3) (camera frame, any norm) from the pose T (world_from_cam,
    local m) with the world's surface, searched between above_m over and below_m under the road
    under the camera. Returns (N,) range along the unit ray (m, NaN: none), true residual (m)
    and slope (|∇height|, −) at the crossing."""
    d = rays_cam / np.linalg.norm(rays_cam, axis=1, keepdims=True)
    d = d @ T[:3, :3].T
    C = T[:3, 3]
    zr = float(
        world.evaluate(C[0] - 0.0005, C[1] + 0.0005, 0.001, 1, 1, appearance=False)["base"][0, 0]
    )
    down = np.maximum(-d[:, 2], 1e-3)
    t_near = (C[2] - zr - above_m) / down
    t_far = (C[2] - zr + below_m) / down
    # the truth on a grid over where the rays can land
    pts = np.stack([C + d * t_near[:, None], C + d * t_far[:, None]], 1)
    x0, x1 = pts[..., 0].min() - 0.01, pts[..., 0].max() + 0.01
    y0, y1 = pts[..., 1].min() - 0.01, pts[..., 1].max() + 0.01
    g = TRUTH_GSD_M
    cols, rows = int(np.ceil((x1 - x0) / g)), int(np.ceil((y1 - y0) / g))
    f = world.evaluate(x0, y1, g, rows, cols, appearance=False)
    hgt = f["height"].astype(np.float32)
    res = (f["height"] - f["base"]).astype(np.float32)
    gy, gx = np.gradient(hgt.astype(float), g)
    slope = np.hypot(gx, gy).astype(np.float32)

    def at(field: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        c = ((x - x0) / g - 0.5).astype(np.float32).reshape(-1)
        r = ((y1 - y) / g - 0.5).astype(np.float32).reshape(-1)
        k = len(c)
        pad = -k % 1024  # cv2.remap wants maps under 32767 rows
        c, r = (np.pad(q, (0, pad)).reshape(-1, 1024) for q in (c, r))
        out = cv2.remap(
            field, c, r, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan
        )
        return out.reshape(-1)[:k]

    n = len(d)
    rng = np.full(n, np.nan)
    prev_t = t_near.copy()
    prev_f = C[2] + d[:, 2] * prev_t - at(hgt, C[0] + d[:, 0] * prev_t, C[1] + d[:, 1] * prev_t)
    left = np.arange(n)
    k = 0
    while left.size and k < 100000:
        k += 1
        t = t_near[left] + k * RAY_STEP_M
        dl = d[left]
        fz = C[2] + dl[:, 2] * t - at(hgt, C[0] + dl[:, 0] * t, C[1] + dl[:, 1] * t)
        hit = (prev_f[left] > 0) & (fz <= 0)
        if hit.any():
            i = left[hit]
            a, b = prev_f[i], fz[hit]
            rng[i] = prev_t[i] + RAY_STEP_M * a / np.maximum(a - b, 1e-12)
        prev_f[left] = fz
        prev_t[left] = t
        left = left[~hit & ~np.isnan(fz) & (t < t_far[left])]
    P = C + d * rng[:, None]
    return rng, at(res, P[:, 0], P[:, 1]), at(slope, P[:, 0], P[:, 1])


def pair_truth(run: Path, drive: Path, cfg_over: dict[str, Any] | None = None) -> dict[str, Any]:
    from roadsurf.io.drive import load_drive
    from roadsurf.io.drive.images import read_gray
    from roadsurf.mapping.config import MappingConfig
    from roadsurf.reconstruction.dense.parallax import dense_height
    from roadsurf.reconstruction.types import load_pair

    d = load_drive(drive)
    frames = {f.filename: f for f in d.frames}
    p = load_pair(sorted((run / "pairs").glob("*.npz"))[0])
    cfg = dataclasses.replace(MappingConfig().dense, device="cpu", **(cfg_over or {}))
    a, b = read_gray(frames[p.frame_a]), read_gray(frames[p.frame_b])
    dh = dense_height(a, b, d.camera, p.R_b_from_a, p.t_b_from_a_m, p.plane, p.H, cfg)
    world, meta = truth_world(drive)
    T = np.asarray(meta["world_from_cam"][0], float)
    u, v = dh.ideal_px()
    m = dh.valid
    K = d.camera.K
    rays = np.column_stack(
        [(u[m] - K[0, 2]) / K[0, 0], (v[m] - K[1, 2]) / K[1, 1], np.ones(int(m.sum()))]
    )
    _, res_t, slope = ray_cast(world, T, rays, 0.07, 0.13)
    eta = dh.height_m[m].astype(float)
    err = eta - res_t
    ok = np.isfinite(err)
    flat = ok & (np.abs(res_t) < 0.002)
    A = np.column_stack([np.ones(m.sum()), u[m], v[m]])
    coef = np.zeros(3)
    keep = flat.copy()
    for _ in range(4):  # a robust plane of the flat pixels' errors
        coef = np.linalg.lstsq(A[keep], err[keep], rcond=None)[0]
        r = err - A @ coef
        mad = 1.4826 * np.median(np.abs(r[keep]))
        keep = flat & (np.abs(r) < max(4 * mad, 1e-4))
    err = err - A @ coef
    level = (dh.level if dh.level is not None else np.zeros(dh.shape, np.int8))[m]
    pit = ok & (res_t < -POTHOLE_M)
    tot = float(np.sum(err[pit] ** 2))
    out: dict[str, Any] = {
        "valid_px": int(m.sum()),
        "flat_mae_mm": float(np.mean(np.abs(err[ok & ~pit])) * 1e3),
        "pothole_px": int(pit.sum()),
        "pothole_rms_mm": float(np.sqrt(np.mean(err[pit] ** 2)) * 1e3),
        "pothole_bias_mm": float(np.mean(err[pit]) * 1e3),
    }

    def part(sel: np.ndarray) -> dict[str, Any]:
        s = sel & pit
        k = int(s.sum())
        if k == 0:
            return {"px": 0}
        e = err[s]
        return {
            "px": k,
            "share_px": round(k / max(int(pit.sum()), 1), 4),
            "rms_mm": round(float(np.sqrt(np.mean(e**2)) * 1e3), 3),
            "bias_mm": round(float(np.mean(e) * 1e3), 3),
            "share_sq_err": round(float(np.sum(e**2)) / max(tot, 1e-30), 4),
            "median_abs_over_sigma": round(
                float(np.median(np.abs(e) / np.sqrt(dh.var_m2[m][s]))), 3
            ),
        }

    out["by_level"] = {f"level{k}": part(level == k) for k in np.unique(level)}
    out["by_slope"] = {
        f"slope_{lo}_{hi}": part((slope >= lo) & (slope < hi))
        for lo, hi in ((0, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, 1e9))
    }
    out["by_level_slope"] = {
        f"level{k}_slope{'>=' if st else '<'}1": part((level == k) & ((slope >= 1.0) == st))
        for k in np.unique(level)
        for st in (False, True)
    }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True, help="the pair's run folder")
    ap.add_argument("--drive", type=Path, required=True, help="its drive (with truth/)")
    ap.add_argument("--set", default="", help="dense config overrides, e.g. fallback_levels=0")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    from roadsurf.reconstruction.dense.config import DenseHeightConfig

    over: dict[str, Any] = {}
    for kv in filter(None, a.set.split(",")):
        k, val = kv.split("=")
        kind = type(getattr(DenseHeightConfig(), k))
        over[k] = val.lower() in ("1", "true", "yes") if kind is bool else kind(val)
    res = pair_truth(a.run, a.drive, over)
    print(json.dumps(res, indent=1))
    write_result(a.json, "dense_pair_truth", {"run": str(a.run), "drive": str(a.drive), **res})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
