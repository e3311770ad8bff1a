"""Benchmark: rolling shutter (issue 28). Rendered drives with and without a rolling-shutter
readout (``SimConfig.readout_s``); per pair the pose and scale error against the truth poses and
the height errors against truth/residual.tif, with the correction (``rolling_shutter=True``)
and without it.

    python -m benchmarks.rolling_shutter [--frames 20] [--sets highway_gs,highway_rs10ms]
    make bench-rolling_shutter ARGS="--frames 12"

Writes benchmarks/results/rolling_shutter.json (figures + command, commit, machine, date).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from benchmarks._result import write_result
from benchmarks.reconstruction_images import Truth, pair_errors
from roadsurf.io.drive import load_drive, read_gray
from roadsurf.reconstruction import features as feat
from roadsurf.reconstruction.api import reconstruct_features, retry_stretched
from roadsurf.reconstruction.config import ReconstructionConfig
from roadsurf.simulation.scenarios import simulate

SETS = {
    "highway_gs": dict(readout_s=0.0),
    "highway_rs5ms": dict(readout_s=0.005),
    "highway_rs10ms": dict(readout_s=0.01),
    "highway_rs16ms": dict(readout_s=1 / 60),
    "tilt40_50fps_gs": dict(readout_s=0.0, fps=50.0, mount_pitch_deg=40.0),
    "tilt40_50fps_rs20ms": dict(readout_s=0.02, fps=50.0, mount_pitch_deg=40.0),
    "potholes_gs": dict(scenario="potholes", readout_s=0.0),
    "potholes_rs30ms": dict(scenario="potholes", readout_s=0.03),
    "potholes_rs60ms": dict(scenario="potholes", readout_s=0.06),
    "potholes_rs30ms_still": dict(
        scenario="potholes",
        readout_s=0.03,
        vibration_deg=0.0,
        yaw_noise_deg=0.0,
        height_noise_m=0.0,
    ),
}


def rot_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20, help="frames per drive")
    ap.add_argument("--sets", default=",".join(SETS), help="comma-separated drive sets")
    ap.add_argument("--work", type=Path, default=Path("out/bench_rolling_shutter"))
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    WORK, N, only = a.work, a.frames, a.sets.split(",")
    out = {}
    for name in only:
        kw = dict(SETS[name])
        scenario = kw.pop("scenario", "highway")
        d = WORK / name
        if not (d / "frames.csv").is_file():
            t0 = time.perf_counter()
            simulate(scenario, d, n_frames=N, progress=False, **kw)
            print(name, f"rendered {N} frames in {time.perf_counter() - t0:.1f} s", flush=True)
        drive = load_drive(d)
        truth = Truth(d)
        feats = [feat.detect(read_gray(f), ReconstructionConfig().features) for f in drive.frames]
        for corr in (False, True) if kw["readout_s"] > 0 else (True,):
            cfg = ReconstructionConfig(rolling_shutter=corr)
            rows = []
            for i in range(len(drive.frames) - 1):
                fa, fb = drive.frames[i], drive.frames[i + 1]
                t0 = time.perf_counter()
                res = reconstruct_features(
                    feats[i],
                    feats[i + 1],
                    drive.camera,
                    cfg,
                    frame_dt_s=fb.timestamp_s - fa.timestamp_s,
                )
                # as the stage does: a pair short of matches is tried on stretched views of b
                res = retry_stretched(
                    res,
                    feats[i],
                    read_gray(fb),
                    drive.camera,
                    cfg,
                    frame_dt_s=fb.timestamp_s - fa.timestamp_s,
                )
                el = time.perf_counter() - t0
                res.frame_a, res.frame_b = fa.filename, fb.filename
                Ra, Ca = truth.poses[fa.filename]
                Rb, Cb = truth.poses[fb.filename]
                R_true = Rb.T @ Ra
                t_true = Rb.T @ (Ca - Cb)
                row = dict(
                    pair=i,
                    status=res.status,
                    n=res.n_points,
                    s=el,
                    cfg=res.config_name,
                    stretch_b=res.stretch_b,
                )
                if res.ok:
                    row["rot_deg"] = rot_deg(res.R_b_from_a.T @ R_true)
                    c = (
                        res.t_b_from_a_m
                        @ t_true
                        / np.linalg.norm(res.t_b_from_a_m)
                        / np.linalg.norm(t_true)
                    )
                    row["t_deg"] = float(np.degrees(np.arccos(np.clip(c, -1, 1))))
                    row["scale"] = float(
                        np.linalg.norm(res.t_b_from_a_m) / np.linalg.norm(t_true) - 1
                    )
                    e = pair_errors(res, truth)
                    row.update(
                        flat_mm=1e3 * e["rmse_flat_m"],
                        hole_mm=1e3 * e["rmse_pothole_m"],
                        n_hole=e["n_pothole_pts"],
                    )
                    true = truth.residual_at_cam_points(fa.filename, res.points_cam_a_m)
                    deep = np.isfinite(true) & (true < -0.02)
                    row["deep_ratio"] = (
                        float(np.median(res.plane_dist_m[deep] / true[deep]))
                        if deep.sum() >= 10
                        else float("nan")
                    )
                rows.append(row)
            ok = [r for r in rows if r["status"] == "ok"]

            def med(k: str, ok: list = ok) -> float:
                if not ok:
                    return float("nan")
                return float(np.nanmedian([abs(r[k]) if k == "scale" else r[k] for r in ok]))

            summ = dict(
                pairs=len(rows),
                ok=len(ok),
                points=med("n"),
                rot_deg=med("rot_deg"),
                t_deg=med("t_deg"),
                abs_scale_pct=100 * med("scale"),
                mean_scale_pct=100 * float(np.mean([r["scale"] for r in ok]))
                if ok
                else float("nan"),
                flat_mm=med("flat_mm"),
                hole_mm=float(
                    np.nanmedian([r["hole_mm"] for r in ok if r["n_hole"] >= 20] or [np.nan])
                ),
                deep_ratio=float(np.nanmedian([r["deep_ratio"] for r in ok] or [np.nan])),
                s_per_pair=med("s"),
                statuses=sorted({r["status"] for r in rows}),
                stretched=sum(1 for r in ok if r["stretch_b"] < 1),  # ok only after the retry
                rounds=sorted(
                    {r["cfg"].split("rs_iterations=")[-1] for r in ok if "rs_iter" in r["cfg"]}
                ),
            )
            key = f"{name}{'' if kw['readout_s'] == 0 else ('_corrected' if corr else '_uncorrected')}"
            out[key] = summ
            print(
                key,
                json.dumps(
                    {k: (round(v, 4) if isinstance(v, float) else v) for k, v in summ.items()}
                ),
                flush=True,
            )

    path = write_result(a.json, "rolling_shutter", {"frames": N, "sets": out})
    print(f"Wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
