"""A drive whose frames carry a burned-in stamp and the bonnet (``roadsurf simulate
--set overlay_text=true --set hood_share=...``), end to end: without a camera.yaml mask the run
warns and writes a suggested mask that covers them; with the mask the mosaic no longer paints
them along the drive, and the map and defects are those of the same drive without overlays."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio

from roadsurf.evaluation.report import evaluate_run
from roadsurf.io import runfolder as rf
from roadsurf.pipeline.run import run_drive
from roadsurf.simulation.scenarios import simulate

SIM = {
    "n_frames": 10,
    "progress": False,
    "width": 320,
    "height": 240,
    "fx": 300.0,
    "n_potholes": 1,
    "n_cracks": 0,
    "n_ruts": 0,
    "n_shadows": 0,
    "n_oil_stains": 0,
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, dict]]:
    root = tmp_path_factory.mktemp("overlay")
    clean = simulate("potholes", root / "clean", **SIM)
    masked = simulate(
        "potholes", root / "masked", overlay_text=True, hood_share=0.15, write_mask=True, **SIM
    )
    bare = root / "bare"  # the same frames, camera.yaml without the mask
    shutil.copytree(masked, bare)
    text = (bare / "camera.yaml").read_text()
    (bare / "camera.yaml").write_text("".join(x for x in text.splitlines(True) if "mask" not in x))
    (bare / "mask.png").unlink()
    return {n: (d, run_drive(d, root / f"run_{n}")) for n, d in
            (("clean", clean), ("masked", masked), ("bare", bare))}  # fmt: skip


def _dark_share(run: Path) -> float:
    """Share of the mosaic's data pixels darker than 60 DN (the stamp's box, the bonnet at
    30-60 DN; the simulated road's darkest texture is a few percent of it)."""
    with rasterio.open(run / rf.MOSAIC_TIF) as ds:
        img = ds.read().astype(np.float32)
    data = img.any(axis=0)
    return float((img.mean(axis=0)[data] < 60).mean())


def test_without_a_mask_the_run_warns_and_suggests_one(runs) -> None:
    drive, rep = runs["bare"]
    run = drive.parent / "run_bare"
    warn = [w for w in rep["warnings"] if "the same in all" in w]
    assert len(warn) == 1 and rf.SUGGESTED_MASK_PNG in warn[0]
    suggested = cv2.imread(str(run / rf.SUGGESTED_MASK_PNG), cv2.IMREAD_GRAYSCALE)
    truth = cv2.imread(str(drive / "truth" / "mask.png"), cv2.IMREAD_GRAYSCALE)
    overlay = truth == 0
    assert (suggested[overlay] == 0).mean() > 0.97  # covers the stamp and the bonnet
    assert (suggested[~overlay] == 0).mean() < 0.02  # and little road
    # the clean drive and the masked one raise no such warning and leave no suggestion
    for name in ("clean", "masked"):
        d, r = runs[name]
        assert not [w for w in r["warnings"] if "the same in all" in w]
        assert not (d.parent / f"run_{name}" / rf.SUGGESTED_MASK_PNG).exists()


def test_with_the_mask_the_mosaic_and_map_match_the_clean_drive(runs) -> None:
    root = runs["clean"][0].parent
    dark = {n: _dark_share(root / f"run_{n}") for n in runs}
    # the bare run paints the stamp's box and the bonnet along the drive (measured: 4.1 % of
    # the clean mosaic darker than 60 DN, 8.2 % of the bare one, 4.1 % of the masked one)
    assert dark["bare"] > dark["clean"] + 0.02
    assert dark["masked"] < dark["clean"] + 0.005
    clean, masked = runs["clean"][1], runs["masked"][1]
    assert clean["camera_mask"] is None
    assert masked["camera_mask"]["file"].endswith("mask.png")
    assert 0.15 < masked["camera_mask"]["masked_share"] < 0.25  # the bonnet and the stamp
    assert masked["counts"]["pairs_ok"] == clean["counts"]["pairs_ok"]
    # the map against the truth: the bonnet hides part of each pair's overlap (fewer cells
    # seen twice), nothing more (measured flat / in-defect MAE: clean 1.17 / 2.73 mm, masked
    # 1.22 / 2.53 mm)
    ev = {
        n: evaluate_run(root / f"run_{n}", root / n / "truth")["surface"]["aligned"]
        for n in ("clean", "masked")
    }
    assert ev["masked"]["flat_mae_m"] < ev["clean"]["flat_mae_m"] + 0.0003
    assert ev["masked"]["defect_mae_m"] < ev["clean"]["defect_mae_m"] + 0.0005
