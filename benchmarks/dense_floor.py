"""Benchmark: how much of a labelled defect the dense matching measures, pair by pair, and which
check refuses the rest (``reconstruction.dense.checks`` REJECT_* flags). For real photographs with
2D labels (spd2: ``labels/<stem>.png``, 255 = pothole), on the pairs of a finished run.

Per ok pair of RUN/pairs, image a's labelled pixels on the dense work grid: the share with a
height (on the work grid, and filled from the coarser fallback grid), the share refused first by
each check (in the order outside, texture, ncc, step, exposure, lr, geometry: a pixel failing
several counts once), the labelled heights' 2nd / 10th percentiles, and the share of unlabelled
pixels with a height (``road_valid``; of the matched crop, whose margin image b does not see).
Medians over the pairs, for each ``--fallback-levels`` value. Only pixels inside the matched crop
count (REJECT_UNMATCHED excluded).

Reference (benchmarks/results/dense_floor.json, spd2, 26 ok pairs, medians): labelled pixels
with a height 36 % on the work grid alone, 67 % with one fallback level; refused first on the
work grid by ncc 33 %, lr 9 %, step 6 %, texture 2.5 %, exposure and geometry 0 % (before
DenseHeightConfig.step_max_sigma: 30 % and 62 %, step 13 %).
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

from benchmarks._result import ROOT, write_result

SPD2 = ROOT.parent / "shared" / "real" / "spd2"
ORDER = ("outside", "texture", "ncc", "step", "exposure", "lr", "geometry")


def pair_figures(dh: Any, label: np.ndarray) -> dict[str, Any] | None:
    """Figures of one pair's ``DenseHeight`` against image a's full-size label (bool)."""
    from roadsurf.reconstruction.dense.checks import REJECT_NAMES, REJECT_UNMATCHED

    h, w = dh.shape
    lab = cv2.resize(label.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
    matched = (dh.reject & REJECT_UNMATCHED) == 0
    m = lab & matched
    n = int(m.sum())
    if n == 0:
        return None
    level = dh.level if dh.level is not None else np.where(dh.valid, 0, -1)
    out: dict[str, Any] = {
        "labelled_px": n,
        "valid": float((dh.valid & m).sum() / n),
        "valid_work_grid": float(((level == 0) & m).sum() / n),
        "valid_filled": float(((level > 0) & m).sum() / n),
    }
    left = m & (level != 0)  # refused on the work grid
    bit_of = {v: k for k, v in REJECT_NAMES.items()}
    for name in ORDER:
        bad = left & ((dh.reject & bit_of[name]) != 0)
        out[f"first_{name}"] = float(bad.sum() / n)
        left &= ~bad
    road = matched & ~lab
    out["road_valid"] = float((dh.valid & road).sum() / max(int(road.sum()), 1))
    hv = dh.height_m[dh.valid & m]
    for q in (2, 10):
        out[f"height_p{q}_mm"] = float(np.percentile(hv, q) * 1e3) if len(hv) >= 20 else None
    return out


def medians(rows: list[dict[str, Any]]) -> dict[str, float]:
    keys = [k for k in rows[0] if k not in ("pair",)]
    out = {}
    for k in keys:
        x = [r[k] for r in rows if r.get(k) is not None]
        if x:
            out[k] = round(float(np.median(x)), 4)
    return out


def run(run_dir: Path, drive: Path, labels: Path, levels: int) -> dict[str, Any]:
    from roadsurf.io.drive import load_drive
    from roadsurf.io.drive.images import read_gray
    from roadsurf.mapping.config import MappingConfig
    from roadsurf.reconstruction.dense.parallax import dense_height
    from roadsurf.reconstruction.types import load_pair

    d = load_drive(drive)
    frames = {f.filename: f for f in d.frames}
    cfg = dataclasses.replace(MappingConfig().dense, device="cpu", fallback_levels=levels)
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for f in sorted((run_dir / "pairs").glob("*.npz")):
        p = load_pair(f)
        lab_path = labels / (Path(p.frame_a).stem + ".png")
        if not p.ok or not lab_path.exists():
            continue
        a, b = read_gray(frames[p.frame_a]), read_gray(frames[p.frame_b])
        lab = cv2.imread(str(lab_path), cv2.IMREAD_GRAYSCALE) > 127
        dh = dense_height(a, b, d.camera, p.R_b_from_a, p.t_b_from_a_m, p.plane, p.H, cfg)
        fig = pair_figures(dh, lab)
        if fig is None:
            continue
        rows.append({"pair": f.stem, **{k: _r(v) for k, v in fig.items()}})
        logging.info("%s: %s", f.stem, json.dumps(rows[-1]))
    return {
        "fallback_levels": levels,
        "pairs": len(rows),
        "match_s": round(time.perf_counter() - t0, 1),
        "median": medians(rows) if rows else {},
        "per_pair": rows,
    }


def _r(v: Any) -> Any:
    return round(v, 4) if isinstance(v, float) else v


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True, help="finished run (its pairs/)")
    ap.add_argument("--drive", type=Path, default=SPD2 / "drive", help="drive folder")
    ap.add_argument("--labels", type=Path, default=None, help="labels (default DRIVE/../labels)")
    ap.add_argument("--fallback-levels", default="0,1", help="values to compare, e.g. 0,1")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    labels = a.labels or a.drive.parent / "labels"
    res = {
        f"fallback_{k}": run(a.run, a.drive, labels, int(k)) for k in a.fallback_levels.split(",")
    }
    for k, v in res.items():
        print(k, json.dumps(v["median"]))
    write_result(a.json, "dense_floor", {"run": str(a.run), "drive": str(a.drive)} | res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
