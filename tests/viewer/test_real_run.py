"""End to end: a tiny simulated drive through the real pipeline, then `view --save` + report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from roadsurf.io.formats import read_geojson
from roadsurf.viewer.api import save_rrd
from roadsurf.viewer.inspect import summarize_rrd
from roadsurf.viewer.report import write_report


@pytest.mark.slow
def test_viewer_reads_a_real_pipeline_run(tmp_path: Path) -> None:
    from roadsurf.pipeline import run_drive
    from roadsurf.simulation.scenarios import simulate

    drive = simulate("potholes", tmp_path / "drive", n_frames=6)
    run = tmp_path / "run"
    report = run_drive(drive, run)
    res = save_rrd(run)
    s = summarize_rrd(res.rrd)

    with np.load(run / "map_points.npz") as z:
        n_points = len(z["xyz"])
    n_defects = len(read_geojson(run / "defects.geojson")["features"])
    assert s.instances("/world/cloud", "Points3D:positions") == n_points > 0
    assert s.rows("/world/camera/image", "EncodedImage:blob") == report["counts"]["frames"]
    assert s.rows("/world/camera", "Transform3D:translation") == (report["counts"]["posed_frames"])
    assert s.instances("/map/trajectory", "GeoLineStrings:line_strings") == 1
    assert s.instances("/map/gps_fixes", "GeoPoints:positions") == report["counts"]["gps_fixes"]
    assert s.instances("/world/defects", "LineStrips3D:strips") == n_defects
    assert s.rows("/mosaic/image", "Image:buffer") == 1
    html = write_report(run).read_text()
    assert "Drive summary" in html and "data:image/png;base64," in html
