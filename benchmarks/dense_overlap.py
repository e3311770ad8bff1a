"""Benchmark: which part of a pair's overlap the dense matching leaves without a height, and
which check refuses it (issue 29, two-view coverage).

For each ok pair of a finished run (RUN/pairs) the pair is matched again (``dense_height``, the
run's dense config) and image a's work-grid pixels whose road point image b sees (the pair's own
road homography, inside both images) are counted, each weighted by its ground footprint
(h_a² / (f² (n·r)³), m²: a far-field pixel of a tilted camera covers 10x a near one), by

- whether it has a height (work grid, or filled from the coarse fallback grid);
- the check that refused it first (outside, texture, ncc, step, exposure, lr, geometry);
- its distance to the edge of the overlap (px of the work grid: 0-1, 2-3, 4-7, 8+), the edge
  being image a's border or the image of image b's border;
- its ground range from camera a (m), i.e. near and far field.

Shares are of the overlap's ground area, summed over the pairs.

    python -m benchmarks.dense_overlap --run RUN --drive DRIVE [--pairs 20] [--json OUT.json]

Diagnostic, not a reference result.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from benchmarks._result import write_result

ORDER = ("outside", "texture", "ncc", "step", "exposure", "lr", "geometry", "unmatched")
EDGE_BINS = ((0, 2), (2, 4), (4, 8), (8, 10**6))
RANGE_BINS = ((0.0, 1.5), (1.5, 2.0), (2.0, 2.5), (2.5, 100.0))


def overlap_mask(dh: Any, img_a: np.ndarray, img_b: np.ndarray, cam: Any) -> np.ndarray:
    """(h, w) bool: work pixels whose road point (height 0) lies inside image a and image b."""
    from roadsurf.reconstruction.dense.warp import resample_pair

    pp = dh.model
    # the model is on the work grid; resample_pair wants the full-size homography
    S = np.array(
        [[dh.scale, 0, 0.5 * dh.scale - 0.5], [0, dh.scale, 0.5 * dh.scale - 0.5], [0, 0, 1]]
    )
    H_full = np.linalg.inv(S) @ pp.H @ S
    _, _, mA, mB = resample_pair(img_a, img_b, cam, H_full / H_full[2, 2], dh.scale)
    return mA & mB


def pair_figures(dh: Any, ov: np.ndarray) -> dict[str, np.ndarray]:
    """Per-pixel arrays of one pair's overlap: area (m²), valid, level, first reject, edge
    distance (px), ground range (m)."""
    from roadsurf.reconstruction.dense.checks import REJECT_NAMES

    pp = dh.model
    u, v = dh.work_px()
    nr = pp.n_dot_ray(u, v)
    f = float(pp.K[0, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        area = pp.h_a**2 / (f * f * nr**3)
        Z = pp.h_a / nr
    Ki = np.linalg.inv(pp.K)
    X = np.stack([u, v, np.ones_like(u)], -1) @ Ki.T * Z[..., None]
    ground = np.linalg.norm(X - (X @ pp.n)[..., None] * pp.n, axis=-1)
    pad = np.pad(ov.astype(np.uint8), 1)
    edge = cv2.distanceTransform(pad, cv2.DIST_L2, 3)[1:-1, 1:-1] - 0.5
    level = dh.level if dh.level is not None else np.where(dh.valid, 0, -1)
    bit_of = {v: k for k, v in REJECT_NAMES.items()}
    first = np.full(dh.shape, -1, np.int8)  # -1: valid on the work grid
    left = level != 0
    for i, name in enumerate(ORDER):
        bad = left & ((dh.reject & bit_of[name]) != 0)
        first[bad] = i
        left &= ~bad
    m = ov & np.isfinite(area) & (area > 0)
    return {
        "area": area[m],
        "valid": dh.valid[m],
        "level": level[m],
        "first": first[m],
        "edge": edge[m],
        "range": ground[m],
    }


def summarise(parts: list[dict[str, np.ndarray]]) -> dict[str, Any]:
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    a = cat["area"]
    tot = float(a.sum())
    miss = ~cat["valid"]
    out: dict[str, Any] = {
        "overlap_area_m2": round(tot, 3),
        "valid_share": round(float(a[~miss].sum() / tot), 4),
        "valid_work_grid_share": round(float(a[cat["level"] == 0].sum() / tot), 4),
        "valid_filled_share": round(float(a[cat["level"] > 0].sum() / tot), 4),
        "missing_share": round(float(a[miss].sum() / tot), 4),
    }
    out["missing_by_first_check"] = {
        name: round(float(a[miss & (cat["first"] == i)].sum() / tot), 4)
        for i, name in enumerate(ORDER)
    }
    out["work_grid_refused_by_first_check"] = {
        name: round(float(a[cat["first"] == i].sum() / tot), 4) for i, name in enumerate(ORDER)
    }
    by_edge = {}
    for lo, hi in EDGE_BINS:
        sel = (cat["edge"] >= lo) & (cat["edge"] < hi)
        sa = float(a[sel].sum())
        by_edge[f"{lo}-{hi if hi < 10**6 else 'inf'}px"] = {
            "area_share": round(sa / tot, 4),
            "missing_share_of_overlap": round(float(a[sel & miss].sum() / tot), 4),
            "missing_within_bin": round(float(a[sel & miss].sum() / max(sa, 1e-12)), 4),
            "by_first_check": {
                name: round(float(a[sel & miss & (cat["first"] == i)].sum() / tot), 4)
                for i, name in enumerate(ORDER)
                if (sel & miss & (cat["first"] == i)).any()
            },
        }
    out["by_edge_distance"] = by_edge
    by_range = {}
    for lo_m, hi_m in RANGE_BINS:
        sel = (cat["range"] >= lo_m) & (cat["range"] < hi_m)
        sa = float(a[sel].sum())
        if sa <= 0:
            continue
        by_range[f"{lo_m}-{hi_m}m"] = {
            "area_share": round(sa / tot, 4),
            "missing_within_bin": round(float(a[sel & miss].sum() / sa), 4),
            "missing_interior_within_bin": round(
                float(a[sel & miss & (cat["edge"] >= 8)].sum() / sa), 4
            ),
        }
    out["by_ground_range"] = by_range
    return out


def run(run_dir: Path, drive: Path, max_pairs: int, overrides: dict[str, Any]) -> dict[str, Any]:
    from roadsurf.io.drive import load_drive
    from roadsurf.io.drive.images import read_gray
    from roadsurf.mapping.config import MappingConfig
    from roadsurf.reconstruction.dense.parallax import dense_height
    from roadsurf.reconstruction.types import load_pair

    d = load_drive(drive)
    frames = {f.filename: f for f in d.frames}
    cfg = dataclasses.replace(MappingConfig().dense, device="cpu", **overrides)
    files = sorted((run_dir / "pairs").glob("*.npz"))
    if max_pairs > 0 and len(files) > max_pairs:  # evenly along the drive
        files = [files[i] for i in np.linspace(0, len(files) - 1, max_pairs).round().astype(int)]
    parts = []
    t0 = time.perf_counter()
    for f in files:
        p = load_pair(f)
        if not p.ok:
            continue
        a, b = read_gray(frames[p.frame_a]), read_gray(frames[p.frame_b])
        dh = dense_height(a, b, d.camera, p.R_b_from_a, p.t_b_from_a_m, p.plane, p.H, cfg)
        parts.append(pair_figures(dh, overlap_mask(dh, a, b, d.camera)))
    res = summarise(parts)
    res["pairs"] = len(parts)
    res["match_s"] = round(time.perf_counter() - t0, 1)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True, help="finished run (its pairs/)")
    ap.add_argument("--drive", type=Path, required=True, help="drive folder")
    ap.add_argument("--pairs", type=int, default=0, help="at most this many pairs (0 = all)")
    ap.add_argument("--set", action="append", default=[], help="dense config KEY=VALUE (JSON)")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    overrides = {k: json.loads(v) for k, v in (s.split("=", 1) for s in a.set)}
    res = run(a.run, a.drive, a.pairs, overrides)
    print(json.dumps(res, indent=1))
    write_result(
        a.json, "dense_overlap", {"run": str(a.run), "drive": str(a.drive), "set": overrides} | res
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
