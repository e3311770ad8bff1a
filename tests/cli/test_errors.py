"""The CLI's error contract: one line for user errors, the traceback only with --debug, and
a run never writes inside its drive folder."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "data_samples" / "drive"


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "roadsurf", *args], capture_output=True, text=True, cwd=REPO
    )


def test_out_inside_the_drive_is_refused_and_the_drive_is_untouched(tmp_path: Path) -> None:
    drive = tmp_path / "drive"
    shutil.copytree(SAMPLE, drive, ignore=shutil.ignore_patterns("truth"))
    before = (drive / "frames.csv").read_bytes()
    for out in (drive, drive / "run"):
        r = _cli("run", str(drive), "--out", str(out))
        assert r.returncode == 2, r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and "inside the drive folder" in lines[0], r.stderr
        assert "Traceback" not in r.stderr
    assert (drive / "frames.csv").read_bytes() == before
    assert not (drive / "run").exists()


def test_out_that_is_another_drive_or_holds_our_names_is_refused(tmp_path: Path) -> None:
    """--out pointing at another drive's folder (or a folder of the user's that holds a file
    the run writes) is refused before anything is written; other folders are fine."""
    victim = tmp_path / "victim"
    shutil.copytree(SAMPLE, victim, ignore=shutil.ignore_patterns("truth", "frames"))
    (victim / "frames").mkdir()
    before = (victim / "frames.csv").read_bytes()
    r = _cli("run", str(SAMPLE), "--out", str(victim))
    assert r.returncode == 2 and "holds a drive" in r.stderr and "camera.yaml" in r.stderr
    assert (victim / "frames.csv").read_bytes() == before and not (victim / "run.json").exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "report.html").write_text("my notes")
    r = _cli("run", str(SAMPLE), "--out", str(mine))
    assert r.returncode == 2 and "report.html" in r.stderr and "not a roadsurf run" in r.stderr
    assert (mine / "report.html").read_text() == "my notes"


def test_debug_shows_the_traceback(tmp_path: Path) -> None:
    r = _cli("--debug", "run", str(SAMPLE), "--out", str(SAMPLE))
    assert r.returncode != 0 and "Traceback" in r.stderr


def test_out_that_is_a_file_is_one_line(tmp_path: Path) -> None:
    f = tmp_path / "out"
    f.write_text("x")
    r = _cli("run", str(SAMPLE), "--out", str(f))
    assert r.returncode == 2 and "existing file" in r.stderr and "Traceback" not in r.stderr


def test_an_error_raised_while_a_signal_unwinds_counts_as_the_interruption() -> None:
    """SIGTERM inside np.savez: the zip file then refuses to close (ValueError) while the
    signal's exception unwinds; that is the stop, not a bug to show as a traceback."""
    from roadsurf.cli.main import _caused_by_interrupt, _Terminated

    try:
        try:
            raise _Terminated(15)
        except BaseException:
            raise ValueError("Can't close the ZIP file") from None
    except ValueError as e:
        assert _caused_by_interrupt(e)  # `from None` hides the cause, not the context
    assert not _caused_by_interrupt(ValueError("a real bug"))
    assert not _caused_by_interrupt(SystemExit(1))


def test_out_holding_only_the_live_stream_is_not_refused(tmp_path: Path) -> None:
    """`run --rerun` without a display opens OUT/live.rrd before the folder check: that folder
    is the run's own, not a user's."""
    from roadsurf.core.errors import ConfigError
    from roadsurf.pipeline.run_checks import check_out_folder

    out = tmp_path / "out"
    out.mkdir()
    (out / "live.rrd").write_bytes(b"stream")
    check_out_folder(SAMPLE, out)  # no error
    (out / "report.html").write_text("mine")
    try:
        check_out_folder(SAMPLE, out)
    except ConfigError as e:
        assert "report.html" in str(e) and "live.rrd" not in str(e)
    else:
        raise AssertionError("a user's report.html was not protected")
