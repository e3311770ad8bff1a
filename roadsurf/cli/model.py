"""Commands on the camera and the CNN: ``calibrate``, ``label`` and ``train``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from roadsurf.cli.app import Out, app


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
