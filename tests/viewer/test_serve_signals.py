"""`roadsurf view --serve`: SIGTERM ends the Rerun server and its viewer process group (real
processes), and a recording it was given is never replaced without --overwrite."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from roadsurf.core.errors import OutputError
from roadsurf.viewer.api import serve
from tests.cli.test_signals import children, cmdline
from tests.detection.test_classifier_signals import wait_until

REPO = Path(__file__).resolve().parents[2]


def group_members(pgid: int) -> list[int]:
    """Live (not zombie) processes of process group ``pgid``, from /proc."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] not in ("Z", "X"):
            out.append(int(stat.parent.name))
    return out


def start_serving(run: Path, stderr: int = subprocess.PIPE) -> tuple[subprocess.Popen[str], int]:
    """`roadsurf view RUN --serve` in a child; returns it and its Rerun server's process group once
    the web viewer is up (the server runs in its own group)."""
    cmd = [sys.executable, "-m", "roadsurf", "view", str(run), "--serve"]
    cmd += ["--web-port", "0", "--grpc-port", "0", "--overwrite"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=stderr, text=True)
    ready = threading.Event()

    def read_stdout() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.startswith("Web viewer:"):
                ready.set()

    threading.Thread(target=read_stdout, daemon=True).start()
    try:
        assert wait_until(ready.is_set, 60.0), "the web viewer did not start"
        servers = [c for c in children(proc.pid) if "rerun" in cmdline(c)]
        assert len(servers) == 1
        return proc, os.getpgid(servers[0])
    except BaseException:
        proc.kill()
        proc.wait()
        raise


def stop_all(proc: subprocess.Popen[str], pgid: int | None) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.wait()
    if pgid is not None and group_members(pgid):
        os.killpg(pgid, signal.SIGKILL)


@pytest.fixture()
def bare_run(tmp_path: Path) -> Path:
    """A run folder with only its report (everything else is optional to the viewer)."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "report.json").write_text("{}\n")
    return run


def refusal(run: Path, **kw: object) -> str:
    """The error of ``serve`` (a regression that serves instead is stopped, then fails)."""
    try:
        res = serve(run, web_port=0, grpc_port=0, **kw)  # type: ignore[arg-type]
    except OutputError as e:
        return str(e)
    res.stop()
    pytest.fail("serve replaced an existing recording")


def test_serve_never_overwrites_a_recording_it_was_given(bare_run: Path) -> None:
    other = bare_run / "other.rrd"
    other.write_bytes(b"kept")
    assert "other.rrd" in refusal(bare_run, rrd=other)
    assert other.read_bytes() == b"kept"
    # the CLI: one line, nothing replaced
    r = subprocess.run(
        [
            sys.executable, "-m", "roadsurf", "view", str(bare_run), "--serve", "--save",
            str(other), "--web-port", "0",
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=60,
    )  # fmt: skip
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "--overwrite" in errors[0], r.stderr[-2000:]
    assert other.read_bytes() == b"kept"


def test_the_runs_own_recording_is_served_until_a_run_finishes_after_it(bare_run: Path) -> None:
    """RUN/run.rrd (as `make demo` writes it) is the run's own: served as it is while current,
    recorded again once a run has finished after it (it refused before, so `roadsurf view OUT
    --serve` failed right after `make demo`)."""
    from roadsurf.viewer.api import recording_is_stale

    rrd = bare_run / "run.rrd"
    rrd.write_bytes(b"a recording")
    report = bare_run / "report.json"
    os.utime(report, (1_000_000, 1_000_000))
    assert not recording_is_stale(bare_run, rrd)
    os.utime(report, None)
    os.utime(rrd, (1_000_000, 1_000_000))
    assert recording_is_stale(bare_run, rrd)


@pytest.mark.skipif(
    not hasattr(signal, "SIGTERM") or not Path("/proc/self/stat").exists(),
    reason="needs SIGTERM and /proc",
)
def test_sigterm_ends_the_rerun_server_and_its_process_group(bare_run: Path) -> None:
    proc, pgid = start_serving(bare_run)
    try:
        assert pgid != os.getpgid(proc.pid) and group_members(pgid)
        proc.send_signal(signal.SIGTERM)
        assert proc.stderr is not None
        stderr = proc.stderr.read()
        proc.wait(timeout=30)
    finally:
        stop_all(proc, pgid)
    assert proc.returncode != 0
    assert "Traceback" not in stderr, stderr[-3000:]
    assert len([ln for ln in stderr.splitlines() if ln.startswith("stopped:")]) == 1, stderr
    assert wait_until(lambda: not group_members(pgid), 10.0), "the Rerun server outlived view"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_kill_9_of_view_ends_the_rerun_server(bare_run: Path) -> None:
    """No handler runs on SIGKILL; the kernel must end the server (it holds the ports)."""
    proc, pgid = start_serving(bare_run, stderr=subprocess.DEVNULL)
    try:
        proc.kill()
        proc.wait(timeout=30)
        assert wait_until(lambda: not group_members(pgid), 15.0), "the server outlived kill -9"
    finally:
        stop_all(proc, pgid)
