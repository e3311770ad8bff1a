"""Benchmark: the global map's voxel fusion, numpy hash (``mapping.cloud.voxel_fuse``) against
open3d's ``voxel_down_sample_and_trace`` (issue 27: use open3d where it is the right tool).

    python -m benchmarks.voxel_fuse RUN [RUN ...] [--scale 20] [--repeats 5]

(``make bench-voxel_fuse ARGS="..."``). Each RUN is a folder written by ``roadsurf run`` (its
pairs and poses are read; the drive comes from RUN/report.json or ``--drive``). The fusion's
input is rebuilt exactly as the global map builds it (points posed and coloured, patch seams
removed), then both implementations run alternately on it, ``--repeats`` times each, and the
medians are reported with a check that both give the same arrays. ``--scale K`` adds a row with
the largest cloud repeated K times side by side (a long drive's point count). The cold import
of open3d is timed in a fresh process, since production would pay it once per run.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.mapping.cloud import voxel_fuse

Fused = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def voxel_fuse_open3d(
    xyz: np.ndarray, rgb: np.ndarray, frame_idx: np.ndarray, voxel_m: float
) -> Fused:
    """The candidate: ``voxel_fuse``'s outputs from open3d's voxel_down_sample_and_trace.

    Same voxels (open3d indexes floor((p - min_bound) / voxel), min_bound = the cloud's
    minimum, as the numpy hash does), mean xyz and colour from open3d, observation count and
    first frame index from the trace, then sorted by voxel like the numpy hash's output."""
    import open3d as o3d

    if len(xyz) == 0 or voxel_m <= 0:
        return xyz, rgb, frame_idx, np.ones(len(xyz), np.int64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    pcd.colors = o3d.utility.Vector3dVector(rgb.astype(float))  # 0..255: open3d only averages
    lo = xyz.min(0)
    down, _, trace = pcd.voxel_down_sample_and_trace(voxel_m, lo, xyz.max(0), False)
    cnt = np.fromiter(map(len, trace), np.int64, len(trace))
    idx = np.concatenate([np.asarray(t) for t in trace])
    starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    first = np.minimum.reduceat(frame_idx[idx], starts)
    q = np.floor((xyz[idx[starts]] - lo) / voxel_m).astype(np.int64)
    o = np.lexsort((q[:, 2], q[:, 1], q[:, 0]))
    col = np.clip(np.round(np.asarray(down.colors)[o]), 0, 255).astype(np.uint8)
    return np.asarray(down.points)[o], col, first[o], cnt[o]


def fuse_input(run_dir: Path, drive_dir: Path | None = None) -> dict[str, Any]:
    """The points, colours and frame indices that the global map of RUN fuses."""
    from roadsurf.io.drive import load_drive
    from roadsurf.io.runfolder import REPORT_JSON, RunFolder
    from roadsurf.mapping.cloud import align_patches, collect_points
    from roadsurf.mapping.config import MappingConfig
    from roadsurf.mapping.types import load_trajectory
    from roadsurf.reconstruction.types import load_pair

    run = RunFolder(run_dir)
    if drive_dir is None:
        drive_dir = Path(json.loads(run.path(REPORT_JSON).read_text())["drive"])
    drive = load_drive(drive_dir)
    pairs = [load_pair(p) for p in sorted(run.pairs_dir.glob("*.npz"))]
    traj = load_trajectory(run.root)
    cfg = MappingConfig()
    frames_by_index = {f.index: f for f in drive.frames}
    pose_of = {fn: i for i, fn in enumerate(traj.filenames)}
    xyz, rgb, fidx, _ = collect_points(cfg, drive, pairs, traj, frames_by_index, pose_of)
    if cfg.align_patches and len(xyz):
        xyz, _ = align_patches(cfg, xyz, fidx)
    return {"xyz": xyz, "rgb": rgb, "frame_idx": fidx, "voxel_m": cfg.voxel_m}


def repeated(inp: dict[str, Any], k: int) -> dict[str, Any]:
    """``inp``'s cloud k times side by side along y (no voxel shared between copies)."""
    xyz = inp["xyz"]
    step = float(np.ptp(xyz[:, 1])) + 1.0
    return {
        "xyz": np.concatenate([xyz + [0.0, step * i, 0.0] for i in range(k)]),
        "rgb": np.tile(inp["rgb"], (k, 1)),
        "frame_idx": np.tile(inp["frame_idx"], k),
        "voxel_m": inp["voxel_m"],
    }


def time_both(inp: dict[str, Any], repeats: int = 5) -> dict[str, Any]:
    """Median wall time (s) of each implementation, run alternately; and whether they agree."""
    args = (inp["xyz"], inp["rgb"], inp["frame_idx"], float(inp["voxel_m"]))
    a, b = voxel_fuse(*args), voxel_fuse_open3d(*args)  # warm: the import is timed apart
    t_np, t_o3d = [], []
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        a = voxel_fuse(*args)
        t_np.append(time.perf_counter() - t)
        t = time.perf_counter()
        b = voxel_fuse_open3d(*args)
        t_o3d.append(time.perf_counter() - t)
    return {
        "points": len(args[0]),
        "voxels": len(a[0]),
        "numpy_s": statistics.median(t_np),
        "open3d_s": statistics.median(t_o3d),
        "identical": all(np.array_equal(x, y) for x, y in zip(a, b, strict=True)),
    }


def open3d_import_s() -> float:
    """Seconds a fresh Python process takes to import open3d."""
    code = "import time; t = time.perf_counter(); import open3d; print(time.perf_counter() - t)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def table(rows: list[dict[str, Any]], import_s: float) -> str:
    lines = [
        "| cloud | points | voxels | numpy | open3d | open3d / numpy | same output |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['name']} | {r['points']} | {r['voxels']} | {1000 * r['numpy_s']:.1f} ms | "
            f"{1000 * r['open3d_s']:.1f} ms | {r['open3d_s'] / r['numpy_s']:.1f}x | "
            f"{'yes' if r['identical'] else 'NO'} |"
        )
    lines.append(f"\nopen3d's import in a fresh process: {import_s:.2f} s (once per run).")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.voxel_fuse RUN [RUN ...]`` (``make bench-voxel_fuse``)."""
    import argparse

    from benchmarks._result import write_result

    ap = argparse.ArgumentParser(description="Voxel fusion: numpy hash vs open3d, same inputs.")
    ap.add_argument("runs", nargs="+", type=Path, help="run folders of `roadsurf run`")
    ap.add_argument("--drive", type=Path, default=None, help="the drive (default: report.json)")
    ap.add_argument("--repeats", type=int, default=5, help="timed calls of each (median)")
    ap.add_argument("--scale", type=int, default=0, help="add the largest cloud repeated K times")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    inputs = {r.name: fuse_input(r, a.drive) for r in a.runs}
    rows = [{"name": n, **time_both(inp, a.repeats)} for n, inp in inputs.items()]
    if a.scale > 1:
        name, big = max(inputs.items(), key=lambda kv: len(kv[1]["xyz"]))
        rows.append({"name": f"{name} x{a.scale}", **time_both(repeated(big, a.scale), a.repeats)})
    md = table(rows, open3d_import_s())
    print(md)
    write_result(a.json, "voxel_fuse", {"rows": rows, "markdown": md})
    return 0 if all(r["identical"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
