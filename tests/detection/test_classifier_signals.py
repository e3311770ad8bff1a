"""The CNN screening worker never outlives its run: killed with its parent (``kill -9``), it
exits and removes its temporary folder; folders of dead parents go at the next start."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch

from roadsurf.detection.classifier import screen_job
from roadsurf.detection.classifier.modelfile import save_model
from roadsurf.detection.classifier.network import DefectNet

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(
    not hasattr(signal, "SIGKILL") or not Path("/proc/self/stat").exists(),
    reason="needs POSIX signals and /proc",
)


def proc_gone(pid: int) -> bool:
    """Whether ``pid`` has exited (a zombie nobody reaps counts as exited)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return True
    return stat.rsplit(")", 1)[1].split()[0] in ("Z", "X")


def wait_until(cond, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.05)
    return bool(cond())


def tiny_model(folder: Path) -> Path:
    torch.manual_seed(0)
    save_model(folder, DefectNet(48).eval(), {})
    return folder


def test_worker_exits_and_cleans_up_when_its_parent_is_killed(tmp_path: Path) -> None:
    """The parent holds a screening job (the worker waits for frames) and is killed with
    SIGKILL: no ``finally`` runs there, yet the worker exits and its folder goes."""
    model = tiny_model(tmp_path / "model")
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    parent_code = textwrap.dedent(
        f"""
        import sys, time
        from roadsurf.detection.classifier.screen_job import ScreeningJob
        job = ScreeningJob({str(model)!r}, progress=False)
        print(job.pid, flush=True)
        time.sleep(60)
        """
    )
    env = {**os.environ, "TMPDIR": str(tmpdir), "PYTHONPATH": str(REPO)}
    parent = subprocess.Popen(
        [sys.executable, "-c", parent_code], stdout=subprocess.PIPE, text=True, env=env
    )
    try:
        assert parent.stdout is not None
        worker = int(parent.stdout.readline())
        assert not proc_gone(worker)
        assert len(list(tmpdir.glob("roadsurf-screen-*"))) == 1
    finally:
        parent.kill()
        parent.wait()
    assert wait_until(lambda: proc_gone(worker), 10.0), "the worker outlived its parent"
    assert wait_until(lambda: not list(tmpdir.glob("roadsurf-screen-*")), 5.0)


def test_stale_folders_of_dead_parents_are_removed_at_the_next_start(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f"roadsurf-screen-{dead.pid}-abc"
    live = tmp_path / f"roadsurf-screen-{os.getpid()}-def"
    other = tmp_path / "roadsurf-screen-notapid"
    for d in (stale, live, other):
        d.mkdir()
        (d / "result.json").write_text("{}")
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))
    job = screen_job.ScreeningJob(tiny_model(tmp_path / "model"), progress=False)
    try:
        assert not stale.exists()
        assert live.is_dir() and other.is_dir()  # a running parent's, or not ours to judge
        own = [d for d in tmp_path.glob(f"roadsurf-screen-{os.getpid()}-*") if d != live]
        assert len(own) == 1
    finally:
        job.close()
    assert not own[0].exists()
