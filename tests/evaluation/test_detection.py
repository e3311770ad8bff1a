"""evaluate_detection against a simulator-style truth folder."""

import dataclasses

import numpy as np
import pytest

from roadsurf.core.fits import fit_rigid_2d
from roadsurf.detection import stage
from roadsurf.detection.config import DetectionConfig
from roadsurf.evaluation.detection import evaluate_detection, frame_metrics, targets
from roadsurf.mapping.types import save_trajectory
from tests.detection.synthetic import Pothole, Scene, build, write_truth


def test_frame_metrics_counts():
    pred = {"a": 1, "b": 0, "c": 1, "d": 0, "e": 1}
    truth = {"a": 1, "b": 0, "c": 0, "d": 1, "e": 1, "f": 0}
    m = frame_metrics(pred, truth)
    assert (m["TP"], m["TN"], m["FP"], m["FN"], m["missing"]) == (2, 1, 1, 1, 1)
    assert m["accuracy"] == pytest.approx(3 / 5)
    assert m["precision"] == pytest.approx(2 / 3) and m["recall"] == pytest.approx(2 / 3)


def test_fit_rigid_2d_recovers_motion():
    # the evaluation aligns the run's trajectory with core's fit_rigid_2d (no local copy)
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 2))
    a = np.deg2rad(3.0)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    dst = src @ R.T + [5.0, -2.0]
    fit = fit_rigid_2d(src, dst)
    np.testing.assert_allclose(fit.R, R, atol=1e-12)
    np.testing.assert_allclose(fit.t, [5.0, -2.0], atol=1e-12)


@pytest.mark.parametrize("gps_offset_m", [0.0, 0.8])
def test_scores_a_synthetic_run(tmp_path, gps_offset_m):
    scene = Scene(
        potholes=[Pothole(0.1, 1.0, 0.15, 0.03), Pothole(-0.2, 1.9, 0.09, 0.026)],
        lane_x_m=-0.4,
        oil_xy_m=(0.25, 0.5),
    )
    drive, pairs, traj = build(scene, tmp_path / "drive")
    write_truth(scene, tmp_path / "truth", traj)
    # The run's map is shifted by a GPS offset; the evaluation's rigid fit removes it.
    wfc = traj.world_from_cam.copy()
    wfc[:, 0, 3] += gps_offset_m
    traj = dataclasses.replace(traj, world_from_cam=wfc)
    run_dir = tmp_path / "run"
    save_trajectory(run_dir, traj)
    stage.run(DetectionConfig(), drive, pairs, traj, run_dir)
    res = evaluate_detection(run_dir, tmp_path / "truth")
    f, d = res["frames"], res["defects"]
    assert f["accuracy"] == 1.0 and f["TP"] >= 2
    assert (d["predicted"], d["truth"], d["matched"]) == (2, 2, 2)
    assert d["precision"] == d["recall"] == d["f1"] == 1.0
    assert d["target_recall"] == 1.0 and d["target_truth"] == 2
    assert d["depth_mae_m"] < 0.003
    assert d["area_median_rel_err"] < 0.2
    assert d["distractor_false_alarms"] == 0
    assert res["alignment"]["rmse_after_m"] < 1e-3
    if gps_offset_m:
        assert res["defects_raw"]["matched"] == 0  # unaligned: shifted off the truth
    t = targets(res)
    assert t["frame accuracy"][2] and t["distractor false alarms"][2]


def test_false_alarm_on_a_distractor_is_counted(tmp_path):
    scene = Scene(potholes=[Pothole(0.1, 1.0, 0.15, 0.03)], lane_x_m=-0.4)
    drive, pairs, traj = build(scene, tmp_path / "drive")
    # Truth says there is no defect there, only a lane marking: the report is a false alarm.
    truth_scene = Scene(potholes=[], lane_x_m=0.1)
    write_truth(truth_scene, tmp_path / "truth", traj)
    run_dir = tmp_path / "run"
    save_trajectory(run_dir, traj)
    stage.run(DetectionConfig(), drive, pairs, traj, run_dir)
    d = evaluate_detection(run_dir, tmp_path / "truth")["defects"]
    assert d["predicted"] == 1 and d["matched"] == 0 and d["distractor_false_alarms"] == 1
