"""The `roadsurf` command line. It parses arguments and calls one function per command; the
logic lives in the stage packages. Output printed here is the CLI's own; stages log.

This module registers the commands (``cli.drive``, ``cli.model``, ``cli.outputs``) on the app
(``cli.app``) and turns errors and signals into exit codes."""

from __future__ import annotations

import signal
import sys

import typer

# Importing the command modules registers their commands on the app (in this order in --help).
import roadsurf.cli.drive  # noqa: F401
import roadsurf.cli.model  # noqa: F401
import roadsurf.cli.outputs  # noqa: F401
from roadsurf.cli.app import DEBUG, app
from roadsurf.core.errors import RoadsurfError


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
        if DEBUG["on"]:
            raise
        typer.echo(f"error: {e}", err=True)
        sys.exit(2)
    except BaseException as e:
        if DEBUG["on"] or not _caused_by_interrupt(e):
            raise
        typer.echo(
            "stopped: interrupted. Finished work is kept; run the same command again to resume.",
            err=True,
        )
        sys.exit(130)


if __name__ == "__main__":
    main()
