"""The `roadsurf` Typer application, its global options and the option types the commands
share. The commands live in ``cli.drive``, ``cli.model`` and ``cli.outputs``; ``cli.main``
registers them and runs the app."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="The `roadsurf` command line. It parses arguments and calls one function per command; "
    "the logic lives in the stage packages. Output printed here is the CLI's own; stages log.",
)

Out = Annotated[Path, typer.Option("--out", "-o", help="Output folder.")]
RunDir = Annotated[Path, typer.Argument(help="Run folder written by `roadsurf run --out`.")]
DriveOpt = Annotated[
    Path | None,
    typer.Option("--drive", help="Drive folder, when report.json's path no longer exists."),
]
DEBUG = {"on": False}  # --debug: show tracebacks instead of one-line errors


@app.callback()
def _main(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Debug logging.")] = False,
    debug: Annotated[
        bool, typer.Option("--debug", help="Show the full traceback of an error.")
    ] = False,
) -> None:
    DEBUG["on"] = debug
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
