"""RunFolder names every artifact in one place."""

from __future__ import annotations

from pathlib import Path

import pytest

from roadsurf.io import runfolder as rf


def test_paths() -> None:
    run = rf.RunFolder("/x/run")
    assert run.pair(3, 4) == Path("/x/run/pairs/000003_000004.npz")
    assert run.mask("sub/f_0001.jpg") == Path("/x/run/masks/f_0001.png")
    assert run.path(rf.DEFECTS_GEOJSON) == run.defects_geojson == Path("/x/run/defects.geojson")
    assert rf.tile_filename("surface", 1, 12) == "surface_0001_0012.tif"
    assert rf.SURFACE_TIF == "surface.tif" and rf.FRAME_LABELS_CSV == "frames.csv"


def test_one_run_at_a_time_holds_the_folder(tmp_path) -> None:
    """A second run in a folder another process works in is refused, naming it; the lock goes
    with its holder (a killed run's lock file is no obstacle)."""
    import subprocess
    import sys

    from roadsurf.core.errors import RunFolderBusyError
    from roadsurf.io.runfolder import RUN_LOCK, run_folder_lock

    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from roadsurf.io.runfolder import run_folder_lock\n"
            f"with run_folder_lock({str(tmp_path)!r}):\n"
            "    print('held', flush=True); time.sleep(30)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with pytest.raises(RunFolderBusyError, match=f"pid {holder.pid}.*another --out"):
            with run_folder_lock(tmp_path):
                pass
    finally:
        holder.kill()
        holder.wait()
    assert (tmp_path / RUN_LOCK).exists()
    with run_folder_lock(tmp_path):  # the killed holder's lock went with it
        pass
