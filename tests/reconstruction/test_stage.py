"""Stage: consecutive pairs, cached features and pairs, resume, unreadable frames."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

import roadsurf.reconstruction.api as api
import roadsurf.reconstruction.stage as stage
from roadsurf.io.drive import Drive, Frame
from roadsurf.io.runfolder import RunFolder
from roadsurf.reconstruction.config import FeatureConfig, ReconstructionConfig
from tests.reconstruction.conftest import render_pair

CFG = ReconstructionConfig(features=FeatureConfig(max_features=500))


def _drive(root: Path, cam, n: int = 4, broken: int | None = None) -> Drive:
    (root / "frames").mkdir(parents=True)
    frames = []
    a, _ = render_pair(cam, seed=5)
    for i in range(n):
        # a strip of road seen by a camera moving 60 mm per frame along +x
        _, img = render_pair(cam, t_m=(0.06 * i, 0.0, 0.0), seed=5) if i else (None, a)
        p = root / "frames" / f"{i:03d}.png"
        if i == broken:
            p.write_bytes(b"\x89PNG not really")
        else:
            cv2.imwrite(str(p), img)
        frames.append(Frame(i, p.name, p, float(i)))
    return Drive(root, cam, frames, None, None)


def test_stage_runs_and_resumes(tmp_path, cam, monkeypatch) -> None:
    drive = _drive(tmp_path / "d", cam)
    run_dir = tmp_path / "run"
    res = stage.run(CFG, drive, run_dir)
    assert [(r.index_a, r.index_b) for r in res] == [(0, 1), (1, 2), (2, 3)]
    assert all(r.ok for r in res), [r.reason for r in res]
    assert all(RunFolder(run_dir).pair(i, i + 1).is_file() for i in range(3))
    assert len(list((run_dir / "features").glob("*.npz"))) == 4
    calls = []
    orig = api.reconstruct_features
    monkeypatch.setattr(
        stage, "reconstruct_features", lambda *a, **k: calls.append(1) or orig(*a, **k)
    )
    RunFolder(run_dir).pair(1, 2).unlink()
    res2 = stage.run(CFG, drive, run_dir)
    assert len(calls) == 1  # only the deleted pair is recomputed
    assert [r.status for r in res2] == ["ok"] * 3
    np.testing.assert_allclose(res2[0].points_cam_a_m, res[0].points_cam_a_m)
    only = stage.run(CFG, drive, run_dir, only_pairs={(2, 3)})
    assert [(r.index_a, r.index_b) for r in only] == [(2, 3)]


def test_unreadable_frame_is_a_status(tmp_path, cam) -> None:
    drive = _drive(tmp_path / "d", cam, n=3, broken=1)
    res = stage.run(CFG, drive, tmp_path / "run")
    assert [r.status for r in res] == ["unreadable_frame", "unreadable_frame"]
    assert all("001.png" in r.reason or r.reason for r in res)
