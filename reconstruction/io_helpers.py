"""Small file helpers for the benchmarks."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

from roadsurf.core.atomic import write_text_atomic


def write_rows_csv(path: Path, rows: list[dict[str, Any]]) -> Path:
    """Write dict rows (same keys) as CSV atomically; an empty list writes an empty file."""
    buf = io.StringIO()
    if rows:
        w = csv.DictWriter(buf, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)
    return write_text_atomic(path, buf.getvalue())
