"""RunFolder names every artifact in one place."""

from __future__ import annotations

from pathlib import Path

from roadsurf.io import runfolder as rf


def test_paths() -> None:
    run = rf.RunFolder("/x/run")
    assert run.pair(3, 4) == Path("/x/run/pairs/000003_000004.npz")
    assert run.mask("sub/f_0001.jpg") == Path("/x/run/masks/f_0001.png")
    assert run.path(rf.DEFECTS_GEOJSON) == run.defects_geojson == Path("/x/run/defects.geojson")
    assert rf.tile_filename("surface", 1, 12) == "surface_0001_0012.tif"
    assert rf.SURFACE_TIF == "surface.tif" and rf.FRAME_LABELS_CSV == "frames.csv"
