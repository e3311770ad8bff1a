"""Commands that inspect a finished run: ``view`` (Rerun) and ``report`` (HTML)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from roadsurf.cli.app import DriveOpt, RunDir, app


@app.command()
def view(
    run_dir: RunDir,
    save: Annotated[
        Path | None, typer.Option("--save", help="Write the recording to this .rrd (headless).")
    ] = None,
    serve: Annotated[
        bool, typer.Option("--serve", help="Serve the web viewer on 127.0.0.1.")
    ] = False,
    drive: DriveOpt = None,
    config: Annotated[Path | None, typer.Option(help="YAML with ViewerConfig keys.")] = None,
    web_port: Annotated[int, typer.Option(help="Web viewer port (--serve; 0 = any).")] = 9090,
    grpc_port: Annotated[int, typer.Option(help="gRPC data port (--serve; 0 = any).")] = 9876,
    screenshot: Annotated[
        Path | None,
        typer.Option(help="With --serve: headless-Chromium PNG of the web viewer, then stop."),
    ] = None,
    overwrite: Annotated[
        bool,
        typer.Option("--overwrite", help="With --serve: replace an existing recording."),
    ] = False,
) -> None:
    """Inspect a run in Rerun: native viewer (default), --save RUN.rrd, or --serve (web)."""
    from roadsurf.viewer.api import view as view_run

    res = view_run(
        run_dir,
        save=save,
        serve_web=serve,
        drive_dir=drive,
        config_path=config,
        web_port=web_port,
        grpc_port=grpc_port,
        screenshot_png=screenshot,
        on_ready=lambda url: typer.echo(f"Web viewer: {url}  (Ctrl-C to stop)"),
        overwrite=overwrite,
    )
    typer.echo(", ".join(f"{k}: {v}" for k, v in res.counts.items()))
    if res.rrd is not None:
        typer.echo(f"Recording: {res.rrd}")
    if screenshot is not None:
        typer.echo(f"Screenshot: {screenshot}")
    if res.missing:
        typer.echo("Not in the run folder: " + ", ".join(res.missing))


@app.command()
def report(
    run_dir: RunDir,
    html_out: Annotated[
        Path | None, typer.Option("--html", help="Output file (default RUN/report.html).")
    ] = None,
    drive: DriveOpt = None,
    screenshot: Annotated[
        Path | None, typer.Option(help="Also save a headless-Chromium PNG of the report.")
    ] = None,
) -> None:
    """Write the self-contained HTML run report (summary, defects, figures, timings)."""
    from roadsurf.viewer.report import report_command

    out, shot = report_command(run_dir, html_out, drive_dir=drive, screenshot_png=screenshot)
    typer.echo(f"Report: {out}")
    if shot is not None:
        typer.echo(f"Screenshot: {shot}")
