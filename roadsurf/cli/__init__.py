"""The `roadsurf` command line (top layer): parses arguments and calls the pipeline."""

from roadsurf.cli.main import app, main

__all__ = ["app", "main"]
