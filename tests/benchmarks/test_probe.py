"""benchmarks.probe: the audit probe against full pairs on a rendered strip of road."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from benchmarks.probe import bench_probe, report
from roadsurf.reconstruction.config import FeatureConfig, ReconstructionConfig
from tests.reconstruction.conftest import texture
from tests.reconstruction.test_probe import _rut, render_surface


def _along(depth_m: float):
    """A rut along the direction of travel (y), at x = 0.1 m: seen by every pair."""
    across = _rut(depth_m, 0.1, 0.1)
    return lambda x, y: across(y, x)


def _write_drive(root: Path, depth_m: float) -> Path:
    (root / "frames").mkdir(parents=True)
    w, h, f, cam_h = 512, 384, 480.0, 1.1
    (root / "camera.yaml").write_text(
        f"model: pinhole\nwidth: {w}\nheight: {h}\nfx: {f}\nfy: {f}\ncx: {w / 2}\ncy: {h / 2}\n"
        f"height_m: {cam_h}\nfps: 10.0\n"
    )
    from roadsurf.io.drive import Camera

    cam = Camera(w, h, f, f, w / 2, h / 2, cam_h, 10.0)
    tex = texture((1600, 1600), 11)
    rows = ["filename,timestamp_s"]
    for i in range(3):
        img = render_surface(cam, tex, cam_h / f, _along(depth_m), t_m=np.array([0, -0.2 * i, 0]))
        cv2.imwrite(str(root / "frames" / f"{i:03d}.png"), img)
        rows.append(f"{i:03d}.png,{0.1 * i:.3f}")
    (root / "frames.csv").write_text("\n".join(rows) + "\n")
    return root


def test_bench_probe_counts_escalations_and_misses(tmp_path: Path) -> None:
    rec = ReconstructionConfig(features=FeatureConfig(max_features=1500))
    deep = _write_drive(tmp_path / "rut", 0.025)
    flat = _write_drive(tmp_path / "flat", 0.0)
    rows = bench_probe([deep, flat], rec_cfg=rec, progress=False)
    r, f = rows
    assert (r.drive, r.pairs, f.pairs) == ("rut", 2, 2)
    # a 25 mm rut: every full pair sees it and every probe escalates; flat road: neither
    assert r.full_not_clear == r.escalated == 2 and r.missed == 0
    assert f.full_not_clear == f.escalated == f.missed == 0
    assert 0 < r.probe_s < r.full_s
    table = report(rows)
    assert table.splitlines()[2].startswith("| rut | 2 | 0 | 2 | 2 | 0 | 0 |")
