"""Entry points of the viewer: record a run folder to .rrd, spawn the native viewer, or serve
the web viewer on localhost. The CLI (`roadsurf view`, `roadsurf report`) calls these."""

from __future__ import annotations

import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Literal
from urllib.parse import quote

import rerun as rr
import rerun.blueprint as rrb

from roadsurf.core.atomic import output_error
from roadsurf.core.errors import OutputError, RoadsurfError
from roadsurf.io.runfolder import RECORDING_RRD, REPORT_JSON
from roadsurf.viewer.blueprint import layout_for
from roadsurf.viewer.config import ViewerConfig
from roadsurf.viewer.recording import APP_ID, log_run
from roadsurf.viewer.rundata import RunData
from roadsurf.viewer.runfolder import load_run

log = logging.getLogger(__name__)

Mode = Literal["spawn", "save", "serve"]


@dataclass
class ViewResult:
    """What ``view`` did: the recording file (save/serve), counts logged, and the web URL."""

    mode: Mode
    rrd: Path | None
    counts: dict[str, int]
    url: str | None = None
    missing: list[str] = field(default_factory=list)
    server: subprocess.Popen[bytes] | None = None

    def stop(self) -> None:
        """Stop the web viewer server of ``serve`` (no-op otherwise)."""
        if self.server is not None:
            stop_server(self.server)


def stop_server(proc: subprocess.Popen[bytes]) -> None:
    """Terminate a server started by ``serve`` and its children (its process group)."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def record(rec: rr.RecordingStream, data: RunData, cfg: ViewerConfig) -> dict[str, int]:
    """Log a loaded run into an open recording stream (any sink)."""
    counts = log_run(rec, data, cfg)
    rec.flush()
    return counts


def save_rrd(
    run_dir: str | Path,
    out: str | Path | None = None,
    *,
    drive_dir: str | Path | None = None,
    cfg: ViewerConfig | None = None,
) -> ViewResult:
    """Write the run's recording (with its default blueprint) to ``out`` (default RUN/run.rrd).

    The file is written beside its final name and renamed, so a viewer never opens half a file;
    an interrupted or failed recording leaves no temporary file."""
    cfg = cfg or ViewerConfig()
    data = load_run(run_dir, drive_dir, max_raster_side_px=cfg.max_mosaic_side_px)
    out = Path(out) if out is not None else Path(run_dir) / RECORDING_RRD
    if out.is_dir():
        raise OutputError(f"{out}: is a folder; give a file name such as {out / RECORDING_RRD}")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise output_error(e, out) from e
    tmp = out.with_name(f".{out.stem}.tmp.rrd")
    try:
        rec = rr.RecordingStream(APP_ID)
        rec.save(tmp, default_blueprint=layout_for(data))
        counts = record(rec, data, cfg)
        rec.disconnect()  # closes and finishes the file sink
        if not tmp.is_file():  # the file sink reports failures only in its log
            raise OSError(f"the recording was not written to {tmp}")
        tmp.replace(out)
    except OSError as e:
        raise output_error(e, out) from e
    finally:
        tmp.unlink(missing_ok=True)
    log.info("wrote %s (%s)", out, ", ".join(f"{k} {v}" for k, v in counts.items()))
    return ViewResult("save", out, counts, missing=data.missing)


def spawn_viewer(
    run_dir: str | Path,
    *,
    drive_dir: str | Path | None = None,
    cfg: ViewerConfig | None = None,
) -> ViewResult:
    """Start the native Rerun viewer (needs a display) and stream the run into it."""
    cfg = cfg or ViewerConfig()
    require_display(f"roadsurf view {run_dir}")
    data = load_run(run_dir, drive_dir, max_raster_side_px=cfg.max_mosaic_side_px)
    rec = rr.RecordingStream(APP_ID)
    spawn_native(rec, layout_for(data), hint=f"roadsurf view {run_dir}")
    counts = record(rec, data, cfg)
    return ViewResult("spawn", None, counts, missing=data.missing)


def has_display() -> bool:
    """Whether a native window can open (always assumed on macOS/Windows)."""
    if not sys.platform.startswith("linux"):
        return True
    return any(os.environ.get(k) for k in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"))


def rerun_executable() -> str | None:
    """The `rerun` viewer shipped with rerun-sdk in this environment (even if not on PATH)."""
    exe = Path(sys.executable).parent / ("rerun.exe" if os.name == "nt" else "rerun")
    return str(exe) if exe.exists() else shutil.which("rerun")


def spawn_native(
    rec: rr.RecordingStream, bp: rrb.Blueprint, hint: str = "roadsurf view RUN"
) -> None:
    """Spawn the native viewer and connect ``rec`` to it; RoadsurfError when impossible."""
    require_display(hint)
    try:
        rr.spawn(recording=rec, default_blueprint=bp, executable_path=rerun_executable())
    except RuntimeError as e:
        raise RoadsurfError(
            f"could not start the native Rerun viewer ({str(e).splitlines()[0]}). "
            f"Use `{hint} --save RUN.rrd` or `--serve`."
        ) from e


def require_display(hint: str = "roadsurf view RUN") -> None:
    if not has_display():
        raise RoadsurfError(
            "no display (DISPLAY/WAYLAND_DISPLAY unset), so the native Rerun viewer cannot open. "
            f"Use `{hint} --save RUN.rrd` and open the file elsewhere, or `{hint} --serve` and "
            "open the printed URL in a browser."
        )


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def viewer_url(web_port: int, grpc_port: int) -> str:
    """The web viewer URL that opens the gRPC proxy of ``serve``."""
    proxy = f"rerun+http://127.0.0.1:{grpc_port}/proxy"
    return f"http://127.0.0.1:{web_port}/?url={quote(proxy, safe='')}"


def recording_is_stale(run_dir: str | Path, rrd: Path) -> bool:
    """True when a run finished in ``run_dir`` after ``rrd`` was written (its report.json is
    newer), or the run has no report: the recording no longer shows the run."""
    report = Path(run_dir) / REPORT_JSON
    return not report.exists() or report.stat().st_mtime > rrd.stat().st_mtime


def serve(
    run_dir: str | Path,
    *,
    rrd: str | Path | None = None,
    drive_dir: str | Path | None = None,
    web_port: int = 9090,
    grpc_port: int = 9876,
    cfg: ViewerConfig | None = None,
    wait_ready_s: float = 30.0,
    record: bool = True,
    overwrite: bool = False,
) -> ViewResult:
    """Record the run to ``rrd`` (default RUN/run.rrd) and serve it with the Rerun web viewer
    bound to 127.0.0.1 only. Returns with the server running (``result.server``); the caller
    stops it (``terminate()``). ``record=False`` serves an existing ``rrd`` unchanged. An
    existing recording named by ``rrd`` is never replaced unless ``overwrite`` (OutputError);
    the run's own RUN/run.rrd (``rrd`` None, as ``make demo`` writes it) is served as it is
    while no run has finished since it was written, else recorded again."""
    target = Path(rrd) if rrd is not None else Path(run_dir) / RECORDING_RRD
    if record and target.exists() and not overwrite:
        if rrd is not None:
            raise OutputError(
                f"{target}: a recording already exists; add --overwrite to record the run "
                "again into it, or --save OTHER.rrd to record elsewhere"
            )
        record = recording_is_stale(run_dir, target)
        log.info(
            "%s: %s", target, "older than the run: recorded again" if record else "served as it is"
        )
    if record or not target.exists():
        res = save_rrd(run_dir, target, drive_dir=drive_dir, cfg=cfg)
    else:  # serve an existing recording as it is
        res = ViewResult("serve", target, {})
    web_port = web_port or free_port()
    grpc_port = grpc_port or free_port()
    cmd = [
        *_server_command(),
        "--serve-web",
        "--bind",
        "127.0.0.1",
        "--web-viewer-port",
        str(web_port),
        "--port",
        str(grpc_port),
        str(res.rrd),
    ]
    errlog = tempfile.TemporaryFile()  # a pipe nobody reads would block the server
    # own process group: `python -m rerun` runs the viewer binary as a child, and stopping
    # must reach that child too
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.DEVNULL,
        stderr=errlog,
        start_new_session=True,
        preexec_fn=_end_with_parent(),  # noqa: PLW1509 (no lock is taken: prctl only)
    )
    try:
        _wait_ready(proc, errlog, web_port, grpc_port, wait_ready_s)
    except BaseException:  # also Ctrl-C / SIGTERM while it starts: never leave it running
        stop_server(proc)
        raise
    url = viewer_url(web_port, grpc_port)
    log.info("web viewer at %s", url)
    return ViewResult("serve", res.rrd, res.counts, url=url, missing=res.missing, server=proc)


def _server_command() -> list[str]:
    """The Rerun server binary itself where rerun-sdk ships it (so the kernel can end it with
    this process, ``_end_with_parent``), else ``python -m rerun`` (a wrapper that runs it)."""
    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).parent / ("rerun.exe" if os.name == "nt" else "rerun")
        if exe.is_file() and os.access(exe, os.X_OK):
            return [str(exe)]
    except ImportError:
        pass
    return [sys.executable, "-m", "rerun"]


def _end_with_parent() -> Callable[[], None] | None:
    """A pre-exec hook that asks Linux to send the server SIGTERM when this process dies, even
    by SIGKILL (no handler runs then, and a server in its own session would outlive it, holding
    its ports). None where prctl is missing."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        prctl = libc.prctl
    except (OSError, AttributeError):
        return None
    parent = os.getpid()
    pr_set_pdeathsig = 1

    def hook() -> None:
        prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)
        if os.getppid() != parent:  # the parent died before the request took effect
            os._exit(1)

    return hook


def _wait_ready(
    proc: subprocess.Popen[bytes],
    errlog: IO[bytes],
    web_port: int,
    grpc_port: int,
    wait_ready_s: float,
) -> None:
    deadline = time.monotonic() + wait_ready_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            errlog.seek(0)
            err = " ".join(errlog.read().decode(errors="replace").split())  # one line
            raise RoadsurfError(
                f"the Rerun web viewer server exited (code {proc.returncode}); ports "
                f"{web_port}/{grpc_port} may be taken (use --web-port/--grpc-port). {err[-500:]}"
            )
        if _port_open(web_port) and _port_open(grpc_port):
            return
        time.sleep(0.2)
    raise RoadsurfError(f"the Rerun web viewer did not start within {wait_ready_s:.0f} s")


def _port_open(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def load_viewer_config(path: str | Path | None) -> ViewerConfig:
    """ViewerConfig from a YAML file (keys of ViewerConfig; unknown keys are rejected)."""
    if path is None:
        return ViewerConfig()
    from roadsurf.core.config import load_yaml_config

    return load_yaml_config(ViewerConfig, path)


def view(
    run_dir: str | Path,
    *,
    save: str | Path | None = None,
    serve_web: bool = False,
    drive_dir: str | Path | None = None,
    config_path: str | Path | None = None,
    web_port: int = 9090,
    grpc_port: int = 9876,
    screenshot_png: str | Path | None = None,
    screenshot_wait_s: float = 45.0,  # after the app started, for data to stream in
    on_ready: Callable[[str], None] | None = None,
    overwrite: bool = False,
) -> ViewResult:
    """`roadsurf view`: ``save`` writes an .rrd (headless); ``serve_web`` serves the web viewer on
    127.0.0.1 until interrupted (or, with ``screenshot_png``, takes a headless-Chromium
    screenshot of it and stops); neither spawns the native viewer. ``serve_web`` refuses to
    replace an existing recording unless ``overwrite``. The server (and its viewer process
    group) is stopped however this returns or raises (Ctrl-C, SIGTERM turned into an
    exception by the CLI)."""
    cfg = load_viewer_config(config_path)
    if not serve_web:
        if screenshot_png is not None:
            raise RoadsurfError("--screenshot needs --serve (it photographs the web viewer)")
        if save is not None:
            return save_rrd(run_dir, save, drive_dir=drive_dir, cfg=cfg)
        return spawn_viewer(run_dir, drive_dir=drive_dir, cfg=cfg)
    res = serve(
        run_dir,
        rrd=save,
        drive_dir=drive_dir,
        web_port=web_port,
        grpc_port=grpc_port,
        cfg=cfg,
        overwrite=overwrite,
    )
    if res.server is None or res.url is None:  # serve() always sets both
        raise RoadsurfError("internal: the web viewer server did not report its URL")
    try:
        if on_ready is not None:
            on_ready(res.url)
        if screenshot_png is not None:
            from roadsurf.viewer.browser import is_blank, screenshot

            shot = screenshot(
                res.url,
                screenshot_png,
                size=(1600, 1000),
                wait_s=screenshot_wait_s + 120.0,
                wait_for="Wasm loaded",
                settle_s=screenshot_wait_s,
            )
            if "Wasm loaded" not in shot.console or is_blank(shot.path):
                log.warning("the web viewer may not have rendered in %s", shot.path)
        else:
            res.server.wait()
    except KeyboardInterrupt:
        pass
    finally:
        res.stop()
    return res
