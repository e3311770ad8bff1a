"""The `roadsurf` command line. It parses arguments and calls one function per command; the
logic lives in the stage packages. Output printed here is the CLI's own; stages log."""

from __future__ import annotations

import logging
import signal
import sys
from pathlib import Path
from typing import Annotated

import typer

from roadsurf.core.errors import RoadsurfError

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__)

Out = Annotated[Path, typer.Option("--out", "-o", help="Output folder.")]
_DEBUG = {"on": False}  # --debug: show tracebacks instead of one-line errors


@app.callback()
def _main(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Debug logging.")] = False,
    debug: Annotated[
        bool, typer.Option("--debug", help="Show the full traceback of an error.")
    ] = False,
) -> None:
    _DEBUG["on"] = debug
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )


@app.command()
def simulate(
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder.")] = None,
    scenario: Annotated[
        str, typer.Option(help="Named scenario (see `roadsurf simulate --list`).")
    ] = "potholes",
    seed: Annotated[
        int | None, typer.Option(help="Random seed (default: the scenario's own).")
    ] = None,
    frames: Annotated[int | None, typer.Option(help="Override the number of frames.")] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option(
            "--set",
            help="Override a simulator parameter, e.g. --set texture=brick --set greyscale=true "
            "(see docs/simulator.md; values are parsed as YAML).",
        ),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(help="YAML file of simulator parameters (docs/simulator.md); --set wins."),
    ] = None,
    mount_pitch: Annotated[
        float | None,
        typer.Option(
            "--mount-pitch", metavar="DEG", help="Camera tilted forward from nadir (deg, 0-60)."
        ),
    ] = None,
    mount_roll: Annotated[
        float | None,
        typer.Option("--mount-roll", metavar="DEG", help="Camera tilted to the right (deg, ±15)."),
    ] = None,
    mount_yaw: Annotated[
        float | None,
        typer.Option("--mount-yaw", metavar="DEG", help="Camera turned clockwise (deg, ±15)."),
    ] = None,
    write_mount: Annotated[
        bool,
        typer.Option(
            "--write-mount", help="Write the mount angles to camera.yaml (default: estimated)."
        ),
    ] = False,
    stereo_pair: Annotated[
        float | None,
        typer.Option(
            "--stereo-pair",
            metavar="BASELINE_M",
            help="Instead of a drive: a two-frame photo pair of a pothole, the second camera "
            "moved this far along its own x axis (m), no GPS (default pitch 45 deg, 0.5 m high).",
        ),
    ] = None,
    list_scenarios: Annotated[
        bool, typer.Option("--list", help="List scenarios and exit.")
    ] = False,
) -> None:
    """Render a photo-textured drive with ground truth in the drive format."""
    import yaml

    from roadsurf.simulation import scenarios

    if list_scenarios:
        for name, desc in scenarios.describe().items():
            typer.echo(f"{name:12s} {desc}")
        return
    if out is None:
        raise typer.BadParameter("--out is required (the folder to write the drive to)")
    overrides = {}
    for item in set_ or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise typer.BadParameter(f"--set expects key=value, got {item!r}")
        overrides[key.strip()] = yaml.safe_load(value)
    mount = {
        "mount_pitch_deg": mount_pitch,
        "mount_roll_deg": mount_roll,
        "mount_yaw_deg": mount_yaw,
        "write_mount": True if write_mount else None,
    }
    overrides |= {k: v for k, v in mount.items() if v is not None}  # given ones only
    if stereo_pair is not None:
        from roadsurf.simulation.stereo import DEFAULT_SEED, simulate_stereo_pair

        if scenario != "potholes" or config is not None or frames is not None:
            raise typer.BadParameter(
                "--stereo-pair renders its own two frames: drop --scenario, --config and --frames"
            )
        if "baseline_m" in overrides:
            raise typer.BadParameter("give the baseline as --stereo-pair BASELINE_M, not --set")

        res = simulate_stereo_pair(
            out, baseline_m=stereo_pair, seed=DEFAULT_SEED if seed is None else seed, **overrides
        )
        typer.echo(f"Wrote a stereo pair (baseline {stereo_pair} m) to {res}")
        return
    res = scenarios.simulate(scenario, out, seed=seed, n_frames=frames, config=config, **overrides)
    typer.echo(f"Wrote drive '{scenario}' to {res}")


@app.command()
def run(
    drive: Annotated[Path, typer.Argument(help="Drive folder (see docs/formats.md).")],
    out: Out,
    config: Annotated[
        Path | None, typer.Option(help="YAML config; top-level keys are stage names.")
    ] = None,
    method: Annotated[
        str | None,
        typer.Option(help="Reconstruction method: proposed, rotation_aware (default), classic."),
    ] = None,
    classifier: Annotated[
        Path | None, typer.Option(help="CNN model file: screen frames, reconstruct only unsure.")
    ] = None,
    rerun: Annotated[
        bool, typer.Option("--rerun", help="Stream live to the Rerun viewer.")
    ] = False,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Recompute finished artifacts (default: resume).")
    ] = False,
) -> None:
    """Run the whole pipeline on a drive: 3D map, mosaic, trajectory and defects."""
    from roadsurf.pipeline import run_drive

    observers = []
    if rerun:
        from roadsurf.viewer.live import make_observer

        observers.append(make_observer(out))
    report = run_drive(
        drive,
        out,
        config_path=config,
        method=method,
        classifier=classifier,
        overwrite=overwrite,
        observers=observers,
    )
    table = (report.get("detection") or {}).get("table")
    if table:
        typer.echo("Defects found:")
        typer.echo(table)
    this_run = report.get("timings_this_run_s", report["timings_s"])
    resumed = report.get("resumed_stages") or []
    note = f"; resumed: {', '.join(resumed)}" if resumed else ""
    typer.echo(f"Outputs in {out}/ ({this_run['total']:.1f} s{note}):")
    for name in sorted(p.name for p in Path(out).iterdir() if p.is_file()):
        typer.echo(f"  {name}")
    warnings = report.get("warnings") or []
    if warnings:
        typer.echo(f"Warnings ({len(warnings)}, also in {out}/report.json):")
        for w in warnings:
            typer.echo(f"  - {w}")


@app.command()
def evaluate(
    runs: Annotated[list[Path], typer.Argument(help="Run folder(s), side by side.")],
    truth: Annotated[Path, typer.Option(help="Simulator truth folder (DRIVE/truth).")],
) -> None:
    """Score run folders against simulator truth (trajectory, surface, coverage, seams,
    detection); writes RUN/evaluation.json and .md and prints a markdown table."""
    from roadsurf.evaluation.report import evaluate_run, markdown_table

    if (truth / "stereo_pair.json").is_file():  # a photo pair (simulate --stereo-pair)
        import json

        from roadsurf.evaluation.pair import score_pair

        for r in runs:
            typer.echo(f"{r}: {json.dumps(score_pair(r, truth.parent), indent=1)}")
        return
    results = [evaluate_run(r, truth) for r in runs]
    typer.echo(markdown_table(results, [str(r) for r in runs]))
    for r in runs:
        typer.echo(f"Wrote {r}/evaluation.json and {r}/evaluation.md")


@app.command("sfm-baseline")
def sfm_baseline(
    drive: Annotated[Path, typer.Argument(help="Drive folder (see docs/formats.md).")],
    out: Out,
    config: Annotated[
        Path | None, typer.Option(help="YAML config with an `sfm_baseline:` section.")
    ] = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Recompute COLMAP steps (default: resume).")
    ] = False,
) -> None:
    """Baseline: pycolmap incremental SfM, scaled by camera height, aligned to GPS; writes the
    same cloud.ply, surface.tif, trajectory.geojson and report.json as `roadsurf run`."""
    from roadsurf.pipeline.sfm import run_from_paths

    res = run_from_paths(drive, out, config_path=config, overwrite=overwrite)
    typer.echo(
        f"{res.n_registered}/{res.n_images} images registered; scale α = {res.alpha:.5g} m/unit; "
        f"CRS {res.crs or 'none (local frame)'}; outputs in {out}/"
    )
    for name, why in list(res.not_registered.items())[:20]:
        typer.echo(f"  not registered: {name}: {why}")
    if len(res.not_registered) > 20:
        typer.echo(f"  ... and {len(res.not_registered) - 20} more (see report.json)")


# --- CNN classifier (detection/classifier) -------------------------------------------------
@app.command()
def calibrate(
    images: Annotated[list[Path], typer.Argument(help="Board photographs (files or folders).")],
    board: Annotated[
        str,
        typer.Option(help="checkerboard:9x6:0.025 or charuco:7x5:0.04:0.03:DICT_5X5_100 (m)."),
    ],
    out: Out,
    ground: Annotated[
        Path | None, typer.Option(help="Photograph of a board flat on the road: height, mount.")
    ] = None,
    ground_board: Annotated[
        str | None, typer.Option(help="Board of --ground when it differs from --board.")
    ] = None,
    board_thickness: Annotated[float, typer.Option(help="Ground board thickness (m).")] = 0.0,
    fps: Annotated[float | None, typer.Option(help="Frame rate for camera.yaml (Hz).")] = None,
    height_m: Annotated[
        float | None, typer.Option(help="Camera height (m) when there is no --ground.")
    ] = None,
    max_rms: Annotated[float, typer.Option(help="Refuse above this RMS error (px).")] = 1.0,
    min_images: Annotated[int, typer.Option(help="Refuse with fewer usable images.")] = 5,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace camera.yaml.")] = False,
) -> None:
    """Calibrate a camera from board photographs and write camera.yaml (docs/reconstruction.md)."""
    from roadsurf.reconstruction.calibration.command import calibrate_command

    res = calibrate_command(
        images, board, out, ground=ground, ground_board=ground_board,
        board_thickness_m=board_thickness, fps=fps, height_m=height_m,
        max_rms_px=max_rms, min_images=min_images, overwrite=overwrite,
    )  # fmt: skip
    for line in res.lines:
        typer.echo(line)


@app.command()
def label(
    drives: Annotated[list[Path], typer.Argument(help="Drive folders to label.")],
    out: Out,
    run_dirs: Annotated[
        list[Path] | None,
        typer.Option("--run", help="Finished run folder per drive (same order); else run them."),
    ] = None,
    runs_dir: Annotated[
        Path | None, typer.Option(help="Where to run the physics pipeline (default OUT/runs).")
    ] = None,
    config: Annotated[
        Path | None, typer.Option(help="YAML config; its `classifier:` section is used.")
    ] = None,
    augment: Annotated[
        bool | None, typer.Option("--augment/--no-augment", help="Augment defect images.")
    ] = None,
) -> None:
    """Self-label frames with the 3D physics pipeline into a CNN dataset (eq. 5.8-5.9)."""
    from roadsurf.pipeline.label import run_label

    bal = run_label(
        drives, out, runs=run_dirs, runs_dir=runs_dir, config_path=config, augment=augment
    )
    typer.echo(f"Dataset in {out}/: before augmentation {bal['before_augmentation']}, ")
    typer.echo(f"  after {bal['after_augmentation']}, dropped {bal['dropped_frames']}")


@app.command()
def train(
    dataset: Annotated[Path, typer.Argument(help="Dataset folder from `roadsurf label`.")],
    out: Out,
    config: Annotated[
        Path | None, typer.Option(help="YAML config; its `classifier:` section is used.")
    ] = None,
    epochs: Annotated[int | None, typer.Option(help="Override the number of epochs.")] = None,
    lr: Annotated[float | None, typer.Option(help="Override the learning rate.")] = None,
    input_size: Annotated[int | None, typer.Option(help="Network input side (px).")] = None,
    seed: Annotated[int | None, typer.Option(help="Random seed.")] = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Start again instead of resuming.")
    ] = False,
) -> None:
    """Train the defect CNN on a labelled dataset (resumes an interrupted training)."""
    from roadsurf.pipeline.train import run_train

    meta = run_train(
        dataset,
        out,
        config_path=config,
        epochs=epochs,
        learning_rate=lr,
        input_size_px=input_size,
        seed=seed,
        overwrite=overwrite,
    )
    m = meta.get("metrics", {})
    typer.echo(
        f"Model in {out}/model.safetensors (best epoch {meta.get('best_epoch')}): "
        f"val accuracy {m.get('val_accuracy')}, precision {m.get('val_precision')}, "
        f"recall {m.get('val_recall')}; {meta.get('train_time_s')} s"
    )


RunDir = Annotated[Path, typer.Argument(help="Run folder written by `roadsurf run --out`.")]
DriveOpt = Annotated[
    Path | None,
    typer.Option("--drive", help="Drive folder, when report.json's path no longer exists."),
]


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


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread so that every ``finally`` runs (the CNN worker and
    the Rerun server are stopped, temporary folders removed)."""


def _on_sigterm(signum: int, _frame: object) -> None:
    raise _Terminated(signum)


def _caused_by_interrupt(e: BaseException) -> bool:
    """An error raised while a signal unwound the stack (e.g. a half-written zip file that
    refuses to close) is part of the interruption, not a bug: its context chain holds it."""
    seen: set[int] = set()
    cur: BaseException | None = e
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, (KeyboardInterrupt, _Terminated)):
            return True
        seen.add(id(cur))
        cur = cur.__context__
    return False


def main() -> None:
    signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        app()
    except RoadsurfError as e:
        if _DEBUG["on"]:
            raise
        typer.echo(f"error: {e}", err=True)
        sys.exit(2)
    except BaseException as e:
        if _DEBUG["on"] or not _caused_by_interrupt(e):
            raise
        typer.echo(
            "stopped: interrupted. Finished work is kept; run the same command again to resume.",
            err=True,
        )
        sys.exit(130)


if __name__ == "__main__":
    main()
