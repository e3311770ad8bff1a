"""Benchmark: real photographs with 2D pothole labels (issue 28). Runs ``roadsurf run`` on a photo
drive (default the development set ``../shared/real/spd2``: 40 photographs, 45° off nadir, no
GPS, one label PNG per frame) and scores what a user sees against the labels:

- frame recall (and precision where labels have negatives) on the frames of reconstructed (ok)
  pairs: frames.csv against "the label has pothole pixels";
- 2D mask IoU per frame (RUN/masks/<stem>.png against labels/<stem>.png), median and mean over
  all labelled frames (a missing mask counts as empty) and over the frames of ok pairs;
- potholes found: per segment of frames chained by ok pairs (one pothole each in spd2), whether
  a defect's mask overlaps a label in it; frames whose label a mask overlaps;
- defects (type, depth, area, frames) and their depths against an expected range if given;
- map noise and T_d (report.json), and whether frames.csv, the masks and the defects agree.

    python -m benchmarks.real_photos [--drive DIR] [--labels DIR] [--work DIR] [--no-run]
    python -m benchmarks.real_photos --drive SIMDRIVE --truth-labels   # simulated drive: labels
                                                                       # from DRIVE/truth
    make bench-real_photos ARGS="--depth-range-mm 24,39"

Writes benchmarks/results/real_photos.json (figures + command, commit, machine, date).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from benchmarks._result import ROOT, write_result

SPD2 = ROOT.parent / "shared" / "real" / "spd2"
TARGETS = {"frame_recall_ok_pairs": (">=", 0.8), "mask_iou_median": (">=", 0.5)}


def truth_labels(drive: Path, out: Path, types: tuple[str, ...] = ("pothole",)) -> Path:
    """Label PNGs for a simulated drive: its truth defects of ``types`` (DRIVE/truth/
    defects.geojson) at the road's height (truth/height.tif) projected through the true poses
    (truth/poses.csv) with the drive's camera. Returns ``out``."""
    import rasterio
    from pyproj import Transformer
    from scipy.spatial.transform import Rotation

    from roadsurf.io.drive import load_drive

    cam = load_drive(drive).camera
    truth = drive / "truth"
    crs = json.loads((truth / "scenario.json").read_text())["crs"]
    to_grid = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    rings = []
    with rasterio.open(truth / "height.tif") as hs:
        height = hs.read(1)
        for f in json.loads((truth / "defects.geojson").read_text())["features"]:
            if f["properties"].get("type") not in types:
                continue
            ll = np.asarray(f["geometry"]["coordinates"][0], float)
            e, n = to_grid.transform(ll[:, 0], ll[:, 1])
            xy = np.c_[e, n]
            # densified (5 mm): a straight edge on the road is not straight through a lens
            seg = []
            for a, b in zip(xy, np.roll(xy, -1, axis=0), strict=True):
                k = max(1, int(np.linalg.norm(b - a) / 0.005))
                seg.append(a + np.outer(np.arange(k) / k, b - a))
            xy = np.vstack(seg)
            r, c = rasterio.transform.rowcol(hs.transform, xy[:, 0], xy[:, 1])
            r = np.clip(np.asarray(r), 0, height.shape[0] - 1)
            c = np.clip(np.asarray(c), 0, height.shape[1] - 1)
            z = height[r, c]
            if not np.isfinite(z).any():
                continue
            rings.append(np.c_[xy, np.where(np.isfinite(z), z, np.nanmedian(z))])
    out.mkdir(parents=True, exist_ok=True)
    with open(truth / "poses.csv", newline="") as fh:
        for row in csv.DictReader(fh):
            C = np.array([float(row[k]) for k in ("easting_m", "northing_m", "up_m")])
            q = [float(row[k]) for k in ("qx", "qy", "qz", "qw")]
            R = Rotation.from_quat(q).as_matrix()  # world_from_cam
            mask = np.zeros((cam.height, cam.width), np.uint8)
            for P in rings:
                X = (P - C) @ R
                if (X[:, 2] <= 0.05).any():
                    continue
                u, v = cam.project(X)
                pts = np.round(np.c_[u, v] * 4).astype(np.int32)
                cv2.fillPoly(mask, [pts], 255, lineType=cv2.LINE_8, shift=2)
            cv2.imwrite(str(out / f"{Path(row['filename']).stem}.png"), mask)
    return out


def _read_mask(path: Path, shape: tuple[int, int]) -> np.ndarray:
    m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
    if m is None:
        return np.zeros(shape, bool)
    if m.shape != shape:
        m = cv2.resize(m, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
    return m > 0


def _segments(ok_pairs: list[tuple[str, str]], frames: list[str]) -> list[list[str]]:
    """Frames chained by ok pairs (consecutive frames a-b), in drive order."""
    nxt = dict(ok_pairs)
    linked_to = {b for _, b in ok_pairs}
    out = []
    for f in frames:
        if f in nxt and f not in linked_to:
            seg = [f]
            while seg[-1] in nxt:
                seg.append(nxt[seg[-1]])
            out.append(seg)
    return out


def score(run: Path, labels: Path, depth_range_mm: tuple[float, float] | None = None) -> dict:
    """The figures of one finished run against a folder of label PNGs (see the module doc)."""
    from roadsurf.reconstruction.types import load_pair

    with open(run / "frames.csv", newline="") as fh:
        frames = {r["filename"]: r for r in csv.DictReader(fh)}
    names = list(frames)
    pairs = [load_pair(p) for p in sorted((run / "pairs").glob("*.npz"))]
    ok_pairs = [(p.frame_a, p.frame_b) for p in pairs if p.ok]
    in_ok = {f for ab in ok_pairs for f in ab}
    defects = json.loads((run / "defects.geojson").read_text())["features"]
    report = json.loads((run / "report.json").read_text())
    per_frame: dict[str, dict[str, Any]] = {}
    for fn in names:
        lab_path = labels / f"{Path(fn).stem}.png"
        if not lab_path.is_file():
            continue
        L = cv2.imread(str(lab_path), cv2.IMREAD_GRAYSCALE) > 127
        M = _read_mask(run / "masks" / f"{Path(fn).stem}.png", L.shape)
        inter, union = int((M & L).sum()), int((M | L).sum())
        per_frame[fn] = {
            "iou": inter / union if union else 1.0,
            "label_px": int(L.sum()),
            "mask_px": int(M.sum()),
            "overlap": inter > 0,
            "flagged": frames[fn]["defect"] == "1",
            "ok_pair": fn in in_ok,
            "has_mask": (run / "masks" / f"{Path(fn).stem}.png").is_file(),
        }
    pos = [f for f, r in per_frame.items() if r["ok_pair"] and r["label_px"] > 0]
    neg = [f for f, r in per_frame.items() if r["ok_pair"] and r["label_px"] == 0]
    tp = sum(per_frame[f]["flagged"] for f in pos)
    fp = sum(per_frame[f]["flagged"] for f in neg)
    # IoU over frames that show a pothole or have a mask (two empty masks agree, uninformative)
    shown = [f for f, r in per_frame.items() if r["label_px"] > 0 or r["mask_px"] > 0]
    ious_all = [per_frame[f]["iou"] for f in shown]
    ious_ok = [per_frame[f]["iou"] for f in shown if per_frame[f]["ok_pair"]]
    segs = _segments(ok_pairs, names)
    seg_found = [any(per_frame.get(f, {}).get("overlap") for f in s) for s in segs]
    # agreement of frames.csv, masks and defects
    listed = {f for d in defects for f in d["properties"]["frames"]}
    masked = {f for f, r in per_frame.items() if r["mask_px"] > 0}
    masked |= {
        fn for fn in names if fn not in per_frame
        and _read_mask(run / "masks" / f"{Path(fn).stem}.png", (1, 1)).any()
    }  # fmt: skip
    flagged = {f for f, r in frames.items() if r["defect"] == "1"}
    depths = [1000 * float(d["properties"]["max_depth_m"]) for d in defects]
    det = report.get("detection") or {}
    fig = {
        "run": str(run),
        "labels": str(labels),
        "frames": len(names),
        "frames_ok_pairs": len(in_ok),
        "pairs_ok": len(ok_pairs),
        "pairs": len(pairs),
        "frame_recall_ok_pairs": tp / len(pos) if pos else None,
        "frame_precision_ok_pairs": tp / (tp + fp) if (tp + fp) else None,
        "frames_flagged": len(flagged),
        "mask_iou_median": float(np.median(ious_all)) if ious_all else None,
        "mask_iou_mean": float(np.mean(ious_all)) if ious_all else None,
        "mask_iou_median_ok_pairs": float(np.median(ious_ok)) if ious_ok else None,
        "mask_iou_mean_ok_pairs": float(np.mean(ious_ok)) if ious_ok else None,
        "mask_iou_frames": len(ious_all),
        "masks_written": sum(r["has_mask"] for r in per_frame.values()),
        "label_frames_overlapped": sum(r["overlap"] for r in per_frame.values()),
        "label_frames": sum(r["label_px"] > 0 for r in per_frame.values()),
        "segments": len(segs),
        "segments_with_pothole_found": int(sum(seg_found)),
        "defects": len(defects),
        "defect_list": [
            {
                "id": d["properties"]["id"],
                "type": d["properties"]["type"],
                "max_depth_mm": round(1000 * float(d["properties"]["max_depth_m"]), 1),
                "area_m2": d["properties"]["area_m2"],
                "frames": d["properties"]["frames"],
            }
            for d in defects
        ],
        "depths_mm": [round(x, 1) for x in depths],
        "map_noise_mm": None if det.get("noise_m") is None else 1000 * det["noise_m"],
        "agree": {
            "flagged_without_mask": sorted(flagged - masked),
            "masked_not_listed": sorted(masked - listed),
            "listed_without_mask": sorted(listed - masked),
        },
        "per_frame": {
            f: {k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()}
            for f, r in per_frame.items()
        },  # fmt: skip
    }
    if depth_range_mm is not None:
        lo, hi = depth_range_mm
        fig["depth_range_mm"] = [lo, hi]
        fig["depths_in_range"] = int(sum(lo <= x <= hi for x in depths))
    return fig


def _met(name: str, v: float | None) -> str:
    if name not in TARGETS or v is None:
        return ""
    op, lim = TARGETS[name]
    return "met" if (v >= lim if op == ">=" else v <= lim) else "NOT met"


def table(fig: dict) -> str:
    rows = [
        ("frame_recall_ok_pairs", "frame recall, frames of ok pairs"),
        ("frame_precision_ok_pairs", "frame precision, frames of ok pairs"),
        ("mask_iou_median", "mask IoU, median (labelled frames)"),
        ("mask_iou_mean", "mask IoU, mean"),
        ("mask_iou_median_ok_pairs", "mask IoU, median (frames of ok pairs)"),
        ("segments_with_pothole_found", "segments whose pothole a mask overlaps"),
        ("defects", "defects"),
        ("map_noise_mm", "map noise σ (mm)"),
    ]
    out = ["| figure | value | target |", "|---|---|---|"]
    for k, name in rows:
        v = fig.get(k)
        s = f"{v:.3f}" if isinstance(v, float) else str(v)
        if k == "segments_with_pothole_found":
            s += f" / {fig['segments']}"
        out.append(f"| {name} | {s} | {_met(k, v)} |")
    out.append(f"| depths (mm) | {', '.join(f'{x:.1f}' for x in fig['depths_mm'])} | |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drive", type=Path, default=SPD2 / "drive", help="drive folder")
    ap.add_argument(
        "--labels", type=Path, default=None, help="label PNGs (default DRIVE/../labels)"
    )
    ap.add_argument("--truth-labels", action="store_true",
                    help="simulated drive: make the labels from DRIVE/truth (potholes)")  # fmt: skip
    ap.add_argument("--work", type=Path, default=Path("out/bench_real_photos"), help="work folder")
    ap.add_argument("--no-run", action="store_true", help="score WORK/run as it is")
    ap.add_argument("--depth-range-mm", default=None, help="expected depths, e.g. 24,39")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    run = a.work / "run"
    labels = a.labels or a.drive.parent / "labels"
    if a.truth_labels:
        labels = truth_labels(a.drive, a.work / "labels")
    t0 = time.perf_counter()
    if not a.no_run:
        cmd = [sys.executable, "-m", "roadsurf.cli.main", "run", str(a.drive), "--out", str(run),
               "--overwrite"]  # fmt: skip
        with open(a.work / "run.log", "w") as log:
            rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, check=False).returncode
        if rc != 0:
            raise SystemExit(f"{' '.join(cmd)} exited {rc}; see {a.work / 'run.log'}")
    run_s = time.perf_counter() - t0
    rng = None
    if a.depth_range_mm:
        lo, hi = (float(x) for x in a.depth_range_mm.split(","))
        rng = (lo, hi)
    fig = score(run, labels, rng) | {"run_s": round(run_s, 1), "drive": str(a.drive)}
    md = table(fig)
    print(md)
    print("per frame IoU:", " ".join(f"{r['iou']:.2f}" for r in fig["per_frame"].values()))
    print("agreement:", json.dumps(fig["agree"]))
    write_result(a.json, "real_photos", fig | {"table_markdown": md})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
