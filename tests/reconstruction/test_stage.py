"""Stage: consecutive pairs, cached features and pairs, resume, unreadable frames."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

import roadsurf.reconstruction.api as api
import roadsurf.reconstruction.features as features
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


def _count_calls(monkeypatch) -> tuple[list[tuple[int, int]], list[int]]:
    """Record the pairs the stage reconstructs and the frames whose features it detects."""
    pairs: list[tuple[int, int]] = []
    detected: list[int] = []
    orig_pair, orig_detect = stage._one_pair, features.detect

    def one_pair(cfg, drive, cache, a, b):
        pairs.append((a.index, b.index))
        return orig_pair(cfg, drive, cache, a, b)

    def detect(gray, cfg, mask=None):
        detected.append(1)
        return orig_detect(gray, cfg, mask)

    monkeypatch.setattr(stage, "_one_pair", one_pair)
    monkeypatch.setattr(features, "detect", detect)
    return pairs, detected


def test_pairs_are_reused_only_when_their_fingerprint_matches(tmp_path, cam, monkeypatch) -> None:
    drive = _drive(tmp_path / "d", cam)
    run_dir = tmp_path / "run"
    first = stage.run(CFG, drive, run_dir)
    fp_files = sorted(p.name for p in (run_dir / "pairs").glob("*.fingerprint"))
    assert fp_files == [f"00000{i}_00000{i + 1}.fingerprint" for i in range(3)]
    pairs, detected = _count_calls(monkeypatch)

    # nothing changed, or only settings that cannot change a pair: everything is reused
    again = stage.run(CFG, drive, run_dir)
    stage.run(replace(CFG, workers=1, save_features=False), drive, run_dir)
    assert pairs == [] and detected == []
    np.testing.assert_array_equal(again[1].points_cam_a_m, first[1].points_cam_a_m)

    # a setting that matters (a RANSAC threshold): every pair again, features from the cache
    cfg2 = replace(CFG, h_ransac_px=2.5)
    stage.run(cfg2, drive, run_dir)
    assert pairs == [(0, 1), (1, 2), (2, 3)] and detected == []
    pairs.clear()
    stage.run(cfg2, drive, run_dir)
    assert pairs == []

    # a replaced image (new mtime): its two pairs and its features only
    img = drive.frames[2].path
    st = img.stat()
    os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns + 2_000_000_000))
    stage.run(cfg2, drive, run_dir)
    assert pairs == [(1, 2), (2, 3)] and len(detected) == 1
    pairs.clear()

    # a pair file without a fingerprint (written by older code) is recomputed
    RunFolder(run_dir).pair(0, 1).with_suffix(".fingerprint").unlink()
    stage.run(cfg2, drive, run_dir)
    assert pairs == [(0, 1)]
    pairs.clear()

    # another camera (here its height, which sets the metric scale): every pair again
    drive2 = Drive(drive.root, replace(cam, height_m=1.2), drive.frames, None, None)
    res = stage.run(cfg2, drive2, run_dir)
    assert pairs == [(0, 1), (1, 2), (2, 3)]
    assert res[0].ok and abs(res[0].scale_alpha / first[0].scale_alpha - 1.2 / 1.1) < 0.05
    pairs.clear()

    # newer code (PAIR_VERSION bumped): every pair again, the features from their cache
    monkeypatch.setattr(stage, "PAIR_VERSION", stage.PAIR_VERSION + 1)
    stage.run(cfg2, drive2, run_dir)
    assert pairs == [(0, 1), (1, 2), (2, 3)] and len(detected) == 1


def test_feature_cache_name_follows_settings_and_image_file(tmp_path, cam) -> None:
    drive = _drive(tmp_path / "d", cam, n=2)
    f0 = drive.frames[0]
    name = stage._feature_path(tmp_path, f0, CFG).name
    assert name.startswith("000000_sift500_") and len(name) == len("000000_sift500_") + 8 + 4
    assert stage._feature_path(tmp_path, f0, CFG) == stage._feature_path(tmp_path, f0, CFG)
    other = replace(CFG, features=replace(CFG.features, contrast_threshold=0.02))
    assert stage._feature_path(tmp_path, f0, other) != stage._feature_path(tmp_path, f0, CFG)
    st = f0.path.stat()
    before = stage._feature_path(tmp_path, f0, CFG)
    os.utime(f0.path, ns=(st.st_atime_ns, st.st_mtime_ns + 1))
    assert stage._feature_path(tmp_path, f0, CFG) != before


def test_truncated_caches_are_recomputed_not_failed(tmp_path, cam) -> None:
    """A killed or damaged .npz (a cut zip: BadZipFile; damaged bytes: zlib.error) is
    recomputed: it stopped the run with a traceback (a pair file) or made the pair a
    permanent geometry_failed (a feature file)."""
    drive = _drive(tmp_path / "d", cam)
    run_dir = tmp_path / "run"
    first = stage.run(CFG, drive, run_dir)
    pair = RunFolder(run_dir).pair(1, 2)
    pair.write_bytes(pair.read_bytes()[: pair.stat().st_size // 2])
    feats = sorted((run_dir / "features").glob("*.npz"))
    feats[2].write_bytes(feats[2].read_bytes()[:1000])
    RunFolder(run_dir).pair(2, 3).unlink()  # needs frame 2's features again
    again = stage.run(CFG, drive, run_dir)
    assert [r.status for r in again] == ["ok"] * 3
    np.testing.assert_allclose(again[1].points_cam_a_m, first[1].points_cam_a_m)
