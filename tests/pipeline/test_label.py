"""`roadsurf label`: the physics pipeline labels a rendered drive (eq. 5.8-5.9) into a dataset."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest

from roadsurf.detection.classifier.config import ClassifierConfig
from roadsurf.io.formats import read_geojson, write_geojson
from roadsurf.pipeline.label import label_drives


def _read_labels(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_labelling_a_rendered_drive_agrees_with_truth_on_clear_cases(tmp_path: Path) -> None:
    """Simulate a tiny drive, let `label` run the physics pipeline, compare with truth."""
    scenarios = pytest.importorskip("roadsurf.simulation.scenarios")
    drive = scenarios.simulate(
        "potholes",
        tmp_path / "drive",
        seed=5,
        n_frames=12,
        width=320,
        height=240,
        fx=300.0,
        progress=False,
    )
    bal = label_drives(
        [drive], tmp_path / "ds", ClassifierConfig(store_size_px=64, augment_target_ratio=4.0)
    )
    truth = {r["filename"]: r for r in _read_labels(drive / "truth" / "frame_labels.csv")}
    rows = _read_labels(tmp_path / "ds" / "labels.csv")
    orig = [r for r in rows if not r["augmentation"]]
    assert len(orig) >= 6  # most frames get a confident label
    agree = 0
    clear = {0: 0, 1: 0}
    for r in orig:
        t = truth[r["frame"]]
        area, depth = float(t["defect_area_cm2"]), float(t["max_depth_m"])
        # clear cases: a sizeable deep defect, or nothing deeper than the 10 mm truth threshold
        want = 1 if area >= 100 and depth >= 0.015 else 0 if area == 0 else None
        if want is not None:
            clear[want] += 1
            agree += int(r["label"]) == want
        assert r["rule"] == "physics+depth+extent" and Path(r["run"]).is_dir()
    # the labels can be no better than the 3D teacher; it may miss a frame, not most of them
    n_clear = clear[0] + clear[1]
    assert clear[0] >= 1 and clear[1] >= 1 and n_clear >= 5, clear
    assert agree >= 0.8 * n_clear, (agree, clear)
    assert (
        bal["before_augmentation"]["defect"] >= 1 and bal["before_augmentation"]["non-defect"] >= 1
    )
    # augmentation copies point back to their source image and exist on disk
    aug = [r for r in rows if r["augmentation"]]
    assert aug and all((tmp_path / "ds" / r["image"]).is_file() for r in aug)
    assert all(r["source_image"] in {o["image"] for o in orig} for r in aug)
    assert bal["after_augmentation"]["defect"] == bal["before_augmentation"]["defect"] + len(aug)
    img = cv2.imread(str(tmp_path / "ds" / orig[0]["image"]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (64, 64) and img.dtype == np.uint8

    # cnn_skip_types: a defect frame whose physics defects are all ruts is left to 3D. Relabel
    # the same run with its defects retyped as ruts (real files, real readers)
    run = Path(orig[0]["run"])
    gj = read_geojson(run / "defects.geojson")
    seen = {fn for f in gj["features"] for fn in f["properties"]["frames"]}
    for f in gj["features"]:
        f["properties"]["type"] = "rut"
    write_geojson(run / "defects.geojson", gj["features"])
    cfg = ClassifierConfig(store_size_px=64, augment=False)
    bal2 = label_drives([drive], tmp_path / "ds2", cfg, runs=[run])
    defect_frames = {r["frame"] for r in orig if r["label"] == "1"}
    skipped = defect_frames & seen
    assert skipped, "the physics defects list their frames"
    assert bal2["dropped_frames"].get("left_to_3d(rut)") == len(skipped)
    assert bal2["before_augmentation"]["defect"] == len(defect_frames - seen)
    assert bal2["before_augmentation"]["non-defect"] == bal["before_augmentation"]["non-defect"]
    bal3 = label_drives(
        [drive], tmp_path / "ds3", ClassifierConfig(store_size_px=64, augment=False, cnn_skip_types=()),
        runs=[run],
    )  # fmt: skip
    assert bal3["before_augmentation"] == bal["before_augmentation"]
