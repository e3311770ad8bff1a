"""Commands on drives: ``simulate``, ``run``, ``evaluate`` and ``sfm-baseline``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from roadsurf.cli.app import Out, app
from roadsurf.io import drivefolder as df


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
        typer.Option(
            help="Reconstruction method: rotation_aware (default), proposed, classic, colmap "
            "(pycolmap's two-view geometry) or stereo (a rectified rig; docs/reconstruction.md)."
        ),
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
    for name in sorted(p.name for p in Path(out).iterdir() if p.is_file() and p.name[0] != "."):
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
    detection); writes RUN/evaluation.json and .md and prints a markdown table. A photo pair's
    truth (simulate --stereo-pair) is scored by the pair figures, printed as JSON only."""
    from roadsurf.evaluation.report import evaluate_run, markdown_table

    if (truth / df.TRUTH_STEREO_PAIR_JSON).is_file():  # a photo pair (simulate --stereo-pair)
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
