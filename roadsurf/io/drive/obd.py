"""obd.csv: vehicle speed from OBD-II (optional)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from roadsurf.io.drive.csvrows import check_increasing, csv_float, csv_rows
from roadsurf.io.drive.types import Frame, ObdLog, Skipped, disjoint_text, log_overlap


def load_obd(path: Path, skipped: list[Skipped], warnings: list[str]) -> ObdLog | None:
    _, rows = csv_rows(path, ("timestamp_s", "speed_mps"))
    t: list[float] = []
    v: list[float] = []
    lines: list[int] = []
    n_total = 0
    for line, row in rows:
        n_total += 1
        try:
            ti, vi = float(row["timestamp_s"]), csv_float(row["speed_mps"])
        except ValueError:
            ti = vi = math.nan
        if not (math.isfinite(ti) and math.isfinite(vi)) or vi < 0:
            skipped.append(Skipped(path.name, line, "OBD row dropped: NaN or negative speed"))
            continue
        t.append(ti)
        v.append(vi)
        lines.append(line)
    if len(t) < n_total:
        warnings.append(f"{path}: dropped {n_total - len(t)} of {n_total} OBD rows.")
    if not t:
        warnings.append(f"{path}: no valid OBD row; OBD speed is not used.")
        return None
    ta = np.asarray(t)
    check_increasing(ta, lines, path, "OBD")
    return ObdLog(timestamp_s=ta, speed_mps=np.asarray(v))


def check_obd_overlap(
    path: Path, obd: ObdLog, frames: list[Frame], warnings: list[str]
) -> ObdLog | None:
    """The OBD log when its times overlap the frames' (None, with a warning, when they do not:
    a logger on another clock; a warning when it covers under 90 % of the frames' span)."""
    _, covered = log_overlap(obd.timestamp_s, frames)
    if covered is None:
        warnings.append(
            f"{path}: OBD {disjoint_text(obd.timestamp_s, frames)}, so OBD speed is not used. "
            "Write obd.csv times in the frames' clock."
        )
        return None
    if covered < 0.9:
        warnings.append(
            f"{path}: OBD covers only {100 * max(covered, 0.0):.0f}% of the frame time span."
        )
    return obd
