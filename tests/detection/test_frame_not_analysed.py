"""A frame nothing measured (no ok pair, no place on the map, no CNN) is "not analysed" in
frames.csv, never "no defect"; evaluation and classifier training treat it so."""

from __future__ import annotations

from pathlib import Path

from roadsurf.core.camera import Camera
from roadsurf.detection.config import DetectionConfig
from roadsurf.detection.framelabels import frame_labels, fuse_labels
from roadsurf.detection.mapframe import MapFrame
from roadsurf.detection.output import load_result, write_outputs
from roadsurf.detection.types import NOT_ANALYSED, DetectionResult
from roadsurf.io.drive import Drive, Frame
from roadsurf.io.formats import read_csv


def _drive(root: Path) -> Drive:
    cam = Camera(640, 480, 600.0, 600.0, 319.5, 239.5, 1.1, 15.0)
    frames = [Frame(i, f"{i:03d}.png", root / f"{i:03d}.png", float(i)) for i in range(3)]
    return Drive(root, cam, frames, None, None)


def test_unmeasured_frame_is_not_analysed(tmp_path: Path) -> None:
    from roadsurf.detection.classifier.selflabel import read_physics_labels

    cfg = DetectionConfig()
    drive = _drive(tmp_path)
    labels = frame_labels(cfg, drive, {}, {"000.png": 0.9, "001.png": 0.1})
    assert [(f.defect, f.source) for f in labels] == [(1, "3d"), (0, "3d"), (None, NOT_ANALYSED)]
    # the CNN decides a frame 3D did not measure; a frame it did not screen stays not analysed
    fused = fuse_labels(cfg, labels, {"000.png": 0.5, "001.png": 0.5, "002.png": 0.999}, [])
    assert fused[2].defect == 1 and fused[2].source == "cnn"
    fused = fuse_labels(cfg, labels, {"000.png": 0.5, "001.png": 0.5}, [])
    assert fused[2].defect is None and fused[2].source == NOT_ANALYSED
    # an ok pair covers it but gave no 3D label: a confident CNN decides, as without the pair
    from types import SimpleNamespace

    cover = [SimpleNamespace(ok=True, frame_a="001.png", frame_b="002.png")]
    fused = fuse_labels(cfg, labels, {"000.png": 0.5, "001.png": 0.5, "002.png": 0.999}, cover)  # type: ignore[arg-type]
    assert fused[2].defect == 1 and fused[2].source == "cnn"
    fused = fuse_labels(cfg, labels, {"000.png": 0.5, "001.png": 0.5}, [])
    assert fused[2].defect is None and fused[2].source == NOT_ANALYSED

    run = tmp_path / "run"
    res = DetectionResult(defects=[], frames=labels, run_dir=run)
    write_outputs(res, MapFrame.create(None), "sig", {})
    rows = read_csv(run / "frames.csv")
    assert [(r["defect"], r["p_defect"], r["source"]) for r in rows][2] == ("", "", "none")
    back = load_result(run, "sig")
    assert back is not None and back.frames[2].defect is None
    assert res.to_report()["frames_not_analysed"] == 1
    physics = read_physics_labels(run)
    assert physics is not None and set(physics) == {"000.png", "001.png"}
