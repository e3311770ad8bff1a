"""End to end: `roadsurf run` (roadsurf.pipeline.run_drive) on the first frames of the committed
sample drive, outputs read back with real readers and scored against the simulator's truth."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import rasterio
from plyfile import PlyData

from roadsurf.core.errors import ModelFileError
from roadsurf.io.formats import read_csv, read_geojson

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "drive"
N_FRAMES = 10


@pytest.fixture(scope="module")
def sample_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict]:
    if not (SAMPLE / "frames.csv").is_file():
        pytest.skip(f"{SAMPLE} is missing (regenerate it with `make sample`)")
    root = tmp_path_factory.mktemp("e2e")
    drive = root / "drive"
    (drive / "frames").mkdir(parents=True)
    lines = (SAMPLE / "frames.csv").read_text().splitlines()
    (drive / "frames.csv").write_text("\n".join(lines[: N_FRAMES + 1]) + "\n")
    for line in lines[1 : N_FRAMES + 1]:
        name = line.split(",")[0]
        shutil.copy(SAMPLE / "frames" / name, drive / "frames" / name)
    for name in ("camera.yaml", "gps.csv", "obd.csv"):
        if (SAMPLE / name).is_file():
            shutil.copy(SAMPLE / name, drive / name)
    shutil.copytree(SAMPLE / "truth", drive / "truth")
    from roadsurf.pipeline import run_drive

    out = root / "out"
    report = run_drive(drive, out)
    return drive, out, report


@pytest.mark.slow
def test_run_writes_the_output_contract(sample_run) -> None:
    drive, out, report = sample_run
    for name in (
        "cloud.ply",
        "surface.tif",
        "mosaic.tif",
        "trajectory.geojson",
        "report.json",
        "mosaic_preview.png",
        "surface_preview.png",
        "map_points.npz",
    ):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    rep = json.loads((out / "report.json").read_text())
    truth_crs = json.loads((drive / "truth" / "scenario.json").read_text())["crs"]
    assert rep["crs"] == truth_crs and rep["coordinates"].startswith(f"georeferenced: {truth_crs}")
    assert rep["counts"]["frames"] == N_FRAMES
    assert rep["counts"]["pairs_ok"] >= N_FRAMES - 2
    assert {"drive", "reconstruction", "poses", "globalmap", "total"} <= set(rep["timings_s"])
    assert "numpy" in rep["versions"] and rep["reference"]["lat_deg"] > 0
    assert isinstance(rep["skipped_frames"], list) and isinstance(rep["failed_pairs"], list)


@pytest.mark.slow
def test_outputs_are_georeferenced_against_truth(sample_run) -> None:
    drive, out, _ = sample_run
    truth = read_csv(drive / "truth" / "poses.csv")[:N_FRAMES]
    txy = np.array([[float(r["easting_m"]), float(r["northing_m"])] for r in truth])
    # trajectory: RFC 7946 points per frame, close to the true camera centres
    from pyproj import Transformer

    fc = read_geojson(out / "trajectory.geojson")
    pts = [f for f in fc["features"] if f["geometry"]["type"] == "Point"]
    assert [p["properties"]["filename"] for p in pts] == [r["filename"] for r in truth]
    ll = np.array([p["geometry"]["coordinates"] for p in pts])
    x, y = Transformer.from_crs("EPSG:4326", "EPSG:32617", always_xy=True).transform(
        ll[:, 0], ll[:, 1]
    )
    err = np.linalg.norm(np.column_stack([x, y]) - txy, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.1
    # cloud: UTM doubles under the driven path, residuals in a sane range
    v = PlyData.read(str(out / "cloud.ply"))["vertex"].data
    xy = np.column_stack([v["x"], v["y"]])
    d = np.min(np.linalg.norm(xy[:, None] - txy[None], axis=2), axis=1)
    assert np.percentile(d, 99) < 1.0
    r = np.asarray(v["residual_m"], float)
    assert -0.15 < np.percentile(r, 0.5) and np.percentile(r, 99.5) < 0.05
    assert np.median(np.abs(r)) < 0.003
    # surface and mosaic on one grid in the truth CRS, overlapping the truth raster
    with rasterio.open(out / "surface.tif") as s, rasterio.open(out / "mosaic.tif") as m:
        assert s.crs == m.crs and s.crs.to_string() == "EPSG:32617"
        assert s.transform == m.transform
        sb = s.bounds
        res = s.read(1)
    with rasterio.open(drive / "truth" / "residual.tif") as t:
        tb = t.bounds
    assert sb.left < tb.right and sb.right > tb.left and sb.bottom < tb.top and sb.top > tb.bottom
    fin = np.isfinite(res)
    assert fin.sum() > 10000 and np.nanmedian(np.abs(res)) < 0.003
    # each defect's figures agree with each other and with the outline a GIS shows
    from shapely.geometry import shape
    from shapely.ops import transform

    to_utm = Transformer.from_crs("EPSG:4326", "EPSG:32617", always_xy=True)
    for f in read_geojson(out / "defects.geojson")["features"]:
        p = f["properties"]
        poly = transform(lambda x, y, z=None: to_utm.transform(x, y), shape(f["geometry"]))
        assert 0 < p["area_m2"] <= poly.area * 1.001, (p["id"], p["area_m2"], poly.area)
        if p["mean_depth_m"] is not None:
            assert p["mean_depth_m"] <= p["max_depth_m"], p


@pytest.mark.slow
def test_evaluate_scores_the_run(sample_run) -> None:
    drive, out, _ = sample_run
    from roadsurf.evaluation.report import evaluate_run

    ev = evaluate_run(out, drive / "truth")
    assert ev["trajectory_rmse_m"] < 0.1
    assert ev["surface"]["aligned"]["flat_mae_m"] < 0.004
    assert 0.3 < ev["coverage"] <= 1.0
    # the measured cells (count > 0) are a part of it; the rest is filled or the road model
    assert 0.3 < ev["coverage_measured"] <= ev["coverage"]
    assert 0 < ev["measured_area_m2"] <= ev["observed_area_m2"]
    assert (out / "evaluation.json").is_file() and (out / "evaluation.md").is_file()


@pytest.mark.slow
def test_rerun_resumes_without_recomputing(sample_run) -> None:
    drive, out, _ = sample_run
    from roadsurf.pipeline import run_drive

    first = json.loads((out / "report.json").read_text())
    m0 = (out / "surface.tif").stat().st_mtime_ns
    rep = run_drive(drive, out)
    assert (out / "surface.tif").stat().st_mtime_ns == m0
    assert rep["timings_this_run_s"]["globalmap"] < 5.0
    # the resumed stages keep the times of the run that computed them, and say so
    assert {"reconstruction", "poses", "globalmap"} <= set(rep["resumed_stages"])
    for name in ("reconstruction", "poses", "globalmap"):
        st = rep["stages"][name]
        assert st["resumed"] == "all"
        assert st["computed_s"] == first["timings_s"][name]
        assert rep["timings_s"][name] == first["timings_s"][name]
    assert first["stages"]["globalmap"]["resumed"] == "no"


@pytest.mark.slow
def test_run_with_classifier_screens_audits_and_fuses(sample_run, tmp_path: Path) -> None:
    """`roadsurf run --classifier`: a CNN sure that every frame is clear road leaves only the
    sparse 3D audit (and growth along what it finds) to the physics pipeline; frames.csv says
    which source decided each frame, screening.json why each frame got 3D."""
    import torch

    from roadsurf.detection.classifier.modelfile import save_model
    from roadsurf.detection.classifier.network import DefectNet
    from roadsurf.pipeline import run_drive

    drive, _, _ = sample_run
    net = DefectNet(48).eval()
    with torch.no_grad():  # a constant "non-defect" network: p_defect ~ 1e-9 on every frame
        net.fc8.weight.zero_()
        net.fc8.bias.copy_(torch.tensor([10.0, -10.0]))
    save_model(tmp_path / "model", net, {"architecture": {"dropout": 0.5, "width": 1}})
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("classifier:\n  audit_every_m: 1.5\n  grow_along_defects: false\n")
    # by default each audit pair is probed first: frames 3 and 7 are clear road, so the
    # probes settle them and no full pair runs
    probed = tmp_path / "probed"
    rep = run_drive(drive, probed, classifier=tmp_path / "model", config_path=cfg)
    scr = json.loads((probed / "screening.json").read_text())
    names = [f["filename"] for f in scr["frames"]]
    assert scr["audit_probes"] == scr["audit_probes_clear"] == 2
    assert [f["filename"] for f in scr["frames"] if f["audit_probe"]] == [names[3], names[7]]
    assert all(scr["frames"][i]["audit_probe"]["status"] == "ok" for i in (3, 7))
    assert all(scr["frames"][i]["audit_probe"]["points"] > 100 for i in (3, 7))
    assert len(list((probed / "probes").glob("000003_000004_*.npz"))) == 1
    assert rep["counts"]["pairs"] == scr["pairs_reconstructed"] == 0
    assert {r["source"] for r in read_csv(probed / "frames.csv")} == {"cnn"}
    # without the probe the audit pairs are full pairs
    cfg.write_text(
        "classifier:\n  audit_every_m: 1.5\n  grow_along_defects: false\n  audit_probe: false\n"
    )
    out = tmp_path / "fused"
    rep = run_drive(drive, out, classifier=tmp_path / "model", config_path=cfg)
    scr = json.loads((out / "screening.json").read_text())
    # the audit is spaced in metres (GPS/OBD): frames ~0.39 m apart, so a pair every 4 frames
    # of the 10: frames 3 and 7 -> pairs (3, 4) and (7, 8) only
    audited = [f["filename"] for f in scr["frames"] if f["3d_reason"] == "audit"]
    assert audited == [names[3], names[7]] and scr["audit_every_m"] == 1.5
    assert scr["frames_with_3d_by_reason"] == {"audit": 2} and scr["audit_probes"] == 0
    assert rep["counts"]["pairs"] == scr["pairs_reconstructed"] == 2
    assert rep["screening"]["frames_with_3d_by_reason"] == {"audit": 2}
    rows = {r["filename"]: r for r in read_csv(out / "frames.csv")}
    overrules = {f["filename"]: f["3d_overrules_cnn"] for f in scr["frames"]}
    assert len(rows) == N_FRAMES
    for fn, r in rows.items():
        # 3D decides only audited frames where it sees a defect; the sure CNN keeps the rest
        assert r["source"] == ("3d" if overrules[fn] else "cnn"), fn
        if r["source"] == "cnn":
            assert r["defect"] == "0" and float(r["p_defect"]) < 1e-3
        else:
            assert r["defect"] == "1"
    # screening in the pipeline's own process instead of its worker: the same probabilities
    cfg.write_text(cfg.read_text() + "  screen_in_subprocess: false\n")
    run_drive(drive, out, classifier=tmp_path / "model", config_path=cfg)
    scr2 = json.loads((out / "screening.json").read_text())
    assert [f["p_defect"] for f in scr2["frames"]] == [f["p_defect"] for f in scr["frames"]]
    # a corrupt model stops a fused run with the worker's ModelFileError, naming the file
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"\x00garbage" * 8)
    with pytest.raises(ModelFileError, match="bad.safetensors"):
        run_drive(drive, tmp_path / "bad", classifier=bad)
