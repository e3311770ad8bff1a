"""SIGTERM stops `roadsurf run --classifier` cleanly (real processes): the CNN worker ends, its
temporary folder goes, one line says how to resume, and the same command then resumes."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.detection.test_classifier_signals import proc_gone, tiny_model, wait_until

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "data_samples" / "drive"

pytestmark = pytest.mark.skipif(
    not hasattr(signal, "SIGTERM") or not Path("/proc/self/stat").exists(),
    reason="needs SIGTERM and /proc",
)


def children(pid: int) -> list[int]:
    """Process ids whose parent is ``pid`` (from /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def small_drive(dst: Path, n_frames: int = 8) -> Path:
    """The first frames of the sample drive (a full run takes ~10 s on one core)."""
    (dst / "frames").mkdir(parents=True)
    for name in ("camera.yaml", "gps.csv", "obd.csv"):
        shutil.copy(SAMPLE / name, dst / name)
    rows = (SAMPLE / "frames.csv").read_text().splitlines()[: n_frames + 1]
    (dst / "frames.csv").write_text("\n".join(rows) + "\n")
    for row in rows[1:]:
        name = row.split(",")[0]
        shutil.copy(SAMPLE / "frames" / name, dst / "frames" / name)
    return dst


def test_sigterm_stops_a_fused_run_cleanly_and_it_resumes(tmp_path: Path) -> None:
    drive = small_drive(tmp_path / "drive")
    model = tiny_model(tmp_path / "model")
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "roadsurf", "run", str(drive), "--out", str(out)]
    cmd += ["--classifier", str(model)]
    env = {**os.environ, "TMPDIR": str(tmpdir)}
    proc = subprocess.Popen(
        cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:

        def worker() -> int | None:
            kids = [c for c in children(proc.pid) if "screen_job" in cmdline(c)]
            return kids[0] if kids and list(tmpdir.glob("roadsurf-screen-*")) else None

        assert wait_until(lambda: worker() is not None, 30.0), "no screening worker started"
        pid = worker()
        assert pid is not None
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode != 0
    assert "Traceback" not in stderr, stderr[-3000:]
    stopped = [ln for ln in stderr.splitlines() if ln.startswith("stopped:")]
    assert len(stopped) == 1 and "resume" in stopped[0], stderr[-3000:]
    assert wait_until(lambda: proc_gone(pid), 5.0), "the CNN worker outlived the run"
    assert not list(tmpdir.glob("roadsurf-screen-*"))

    again = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-3000:]
    assert (out / "report.json").is_file() and (out / "screening.json").is_file()
    assert not list(tmpdir.glob("roadsurf-screen-*"))
