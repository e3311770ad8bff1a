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


def test_the_lock_never_stops_a_run_it_cannot_take(tmp_path, monkeypatch, caplog) -> None:
    """A lock file only readable (another user's, in a shared folder) is locked read-only; a
    file system without locks, or a folder that cannot hold the file, runs unlocked with a
    warning (each was a traceback); the lock is re-entrant within a process."""
    import errno
    import fcntl
    import os

    from roadsurf.io.runfolder import RUN_LOCK, run_folder_lock

    (tmp_path / RUN_LOCK).write_text("pid 1")
    real_open = os.open

    def no_write(path, flags, *a):
        if flags & (os.O_RDWR | os.O_WRONLY):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_open(path, flags, *a)

    monkeypatch.setattr(os, "open", no_write)
    with run_folder_lock(tmp_path):
        with run_folder_lock(tmp_path):  # re-entrant: the CLI and the pipeline both take it
            pass
    monkeypatch.setattr(os, "open", real_open)

    def no_locks(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with run_folder_lock(tmp_path):
        pass
    assert "has no locks" in caplog.text
    monkeypatch.undo()
    (tmp_path / RUN_LOCK).unlink()
    monkeypatch.setattr(os, "open", lambda *a: (_ for _ in ()).throw(PermissionError("ro")))
    with run_folder_lock(tmp_path):
        pass
    assert "running without the one-run lock" in caplog.text
