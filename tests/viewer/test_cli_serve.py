"""`roadsurf view --save`, `roadsurf report` and the `--serve` web viewer in headless Chromium."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from roadsurf.cli import app
from roadsurf.viewer.api import free_port, serve
from roadsurf.viewer.browser import is_blank, screenshot
from roadsurf.viewer.inspect import summarize_rrd
from tests.viewer.synthetic_run import SyntheticRun


def test_cli_view_save_and_report(synthetic_run: SyntheticRun, tmp_path: Path) -> None:
    runner = CliRunner()
    rrd = tmp_path / "cli.rrd"
    res = runner.invoke(app, ["view", str(synthetic_run.run), "--save", str(rrd)])
    assert res.exit_code == 0, res.output
    assert f"Recording: {rrd}" in res.output
    assert summarize_rrd(rrd).has("/world/cloud")
    html = tmp_path / "r.html"
    res = runner.invoke(app, ["report", str(synthetic_run.run), "--html", str(html)])
    assert res.exit_code == 0, res.output
    assert html.exists() and "<table id='defects'>" in html.read_text()


def test_cli_view_missing_run_folder_is_a_clear_error(tmp_path: Path) -> None:
    res = CliRunner().invoke(app, ["view", str(tmp_path / "nope"), "--save", "x.rrd"])
    assert res.exit_code != 0
    assert "run folder not found" in str(res.exception)


def _non_loopback_ip() -> str | None:
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("10.255.255.255", 1))  # no packet is sent for UDP connect
            ip = s.getsockname()[0]
    except OSError:
        return None
    return None if ip.startswith("127.") else ip


@pytest.mark.slow
def test_serve_loads_in_headless_chromium(
    synthetic_run: SyntheticRun, saved_rrd: Path, tmp_path: Path, chromium: str
) -> None:
    web_port = free_port()
    res = serve(
        synthetic_run.run,
        rrd=saved_rrd,
        record=False,
        web_port=web_port,
        grpc_port=free_port(),
    )
    try:
        assert res.url is not None and res.url.startswith("http://127.0.0.1:")
        ip = _non_loopback_ip()
        if ip is not None:  # bound to localhost only
            port = int(res.url.split(":")[2].split("/")[0])
            with socket.socket() as s:
                s.settimeout(1.0)
                assert s.connect_ex((ip, port)) != 0
        shot = screenshot(
            res.url,
            tmp_path / "web.png",
            size=(1200, 800),
            wait_s=90.0,
            wait_for="Wasm loaded",
            settle_s=1.0,
        )
        assert "Wasm loaded" in shot.console, shot.console[-2000:]
        if is_blank(shot.path):  # a loaded machine paints the first frame late: wait longer once
            shot = screenshot(
                res.url, tmp_path / "web2.png", size=(1200, 800), wait_s=90.0,
                wait_for="Wasm loaded", settle_s=8.0,
            )  # fmt: skip
        assert not is_blank(shot.path)
    finally:
        res.stop()
    assert res.server is not None and res.server.poll() is not None
    time.sleep(0.5)
    with socket.socket() as s:  # the viewer binary (a child process) is gone too
        assert s.connect_ex(("127.0.0.1", web_port)) != 0


def test_native_viewer_without_display_explains_alternatives(
    synthetic_run: SyntheticRun, monkeypatch: pytest.MonkeyPatch
) -> None:
    import sys

    for k in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    res = CliRunner().invoke(app, ["view", str(synthetic_run.run)])
    assert res.exit_code != 0
    msg = str(res.exception)
    assert "no display" in msg and "--save" in msg and "--serve" in msg
