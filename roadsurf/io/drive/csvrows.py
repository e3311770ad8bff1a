"""CSV helpers of the drive loader: header check, numbered rows, numbers, increasing times."""

from __future__ import annotations

import csv
import io
import logging
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from roadsurf.core.errors import DriveFormatError
from roadsurf.io.drive.textfile import read_text
from roadsurf.io.drive.types import FORMAT_HINT

log = logging.getLogger(__name__)


def csv_rows(
    path: Path, required: tuple[str, ...], optional: tuple[str, ...] = ()
) -> tuple[list[str], Iterator[tuple[int, dict[str, str]]]]:
    """Read a CSV (UTF-8), check its header, and yield (line number, row dict) for non-empty
    rows. Raises ``DriveFormatError`` for bytes that are not UTF-8 and for CSV syntax errors."""
    f = io.StringIO(read_text(path), newline="")  # newline="": csv handles the line ends
    reader = csv.reader(f)
    try:
        header = next(reader)
    except StopIteration:
        raise DriveFormatError(
            f"{path}:1: file is empty; it needs the header {','.join(required)}. {FORMAT_HINT}"
        ) from None
    except csv.Error as e:
        raise _csv_error(path, reader.line_num, e) from None
    header = [h.strip() for h in header]
    missing = [c for c in required if c not in header]
    if missing:
        raise DriveFormatError(
            f"{path}:1: header {header} lacks column(s) {missing}; expected "
            f"{','.join(required)}{''.join(',' + o for o in optional)}. Fix the header line."
        )
    extra = [h for h in header if h not in required and h not in optional]
    if extra:
        log.warning("%s:1: ignoring unknown column(s) %s", path, extra)

    def gen() -> Iterator[tuple[int, dict[str, str]]]:
        while True:
            try:
                row = next(reader)
            except StopIteration:
                return
            except csv.Error as e:
                raise _csv_error(path, reader.line_num, e) from None
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) < len(header):
                row = row + [""] * (len(header) - len(row))
            yield reader.line_num, {h: c.strip() for h, c in zip(header, row, strict=False)}

    return header, gen()


def _csv_error(path: Path, line: int, e: csv.Error) -> DriveFormatError:
    return DriveFormatError(f"{path}:{max(line, 1)}: not valid CSV ({e}). Fix the line.")


def csv_float(s: str) -> float:
    """Parse a CSV number; empty -> NaN; raises ValueError for text."""
    return float(s) if s != "" else math.nan


def check_increasing(t: np.ndarray, lines: list[int], path: Path, what: str) -> None:
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0])
        same = ""
        if what == "frame" and t[i + 1] == t[i]:
            same = (
                " Two shots at once (a stereo rig's left and right images) are a pair in capture "
                "order: give the second a later time, or, without a GPS or OBD log, leave frames.csv "
                "out (the images are then taken in name order)."
            )
        elif t[i + 1] < t[i]:
            same = (
                " If the clock stepped back (the times fall by more than a row or two), sorting "
                "interleaves two stretches: cut the file at the step instead."
            )
        raise DriveFormatError(
            f"{path}:{lines[i + 1]}: {what} timestamp {float(t[i + 1])!r} is not after the previous one "
            f"({float(t[i])!r} on line {lines[i]}). Timestamps must strictly increase; sort the file "
            f"and remove duplicate rows.{same}"
        )
