"""`roadsurf run --rerun`: the observer streams each stage's artifacts as they appear."""

from __future__ import annotations

import shutil
from pathlib import Path

from roadsurf.io.drive import load_drive
from roadsurf.mapping.types import load_trajectory
from roadsurf.viewer.inspect import summarize_rrd
from roadsurf.viewer.live import LiveObserver
from tests.viewer.synthetic_run import SyntheticRun


def test_live_observer_streams_stage_by_stage(synthetic_run: SyntheticRun, tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    src = synthetic_run.run
    obs = LiveObserver(run, spawn=False)  # no display in CI: the stream goes to RUN/live.rrd
    # nothing opened before the run's first stage (a run refused at the folder's lock must
    # not truncate the live.rrd of the run holding it)
    assert obs.rrd is None and not (run / "live.rrd").exists()

    # replay a pipeline: copy each stage's files into the run folder, then notify
    obs("drive", load_drive(synthetic_run.drive))
    assert obs.rrd == run / "live.rrd"
    shutil.copytree(src / "pairs", run / "pairs")
    obs("reconstruction", [])
    for f in ("poses.npz", "reference.json"):
        shutil.copy(src / f, run / f)
    obs("poses", load_trajectory(run))
    for f in ("cloud.ply", "mosaic.tif", "surface.tif"):
        shutil.copy(src / f, run / f)
    obs("globalmap", None)
    for f in ("defects.geojson", "frames.csv"):
        shutil.copy(src / f, run / f)
    obs("detection", None)
    shutil.copy(src / "report.json", run / "report.json")
    obs("report", {})

    exp = synthetic_run.expected
    s = summarize_rrd(run / "live.rrd")
    assert s.rows("/world/camera/image", "EncodedImage:blob") == exp["frames"]
    assert s.rows("/world/camera", "Transform3D:translation") == exp["frames"]
    assert s.instances("/world/cloud", "Points3D:positions") == exp["cloud_points"]
    assert s.instances("/world/defects", "LineStrips3D:strips") == exp["defects"]
    assert s.instances("/map/trajectory", "GeoLineStrings:line_strings") == 1
    assert s.has("/summary")
    assert obs.counts["defects"] == exp["defects"]
