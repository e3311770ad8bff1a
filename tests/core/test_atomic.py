"""Atomic writes: a failed or empty write never leaves a file under its final name, errors are
one line that says what to do, and a killed run's temporaries are removed on the next start."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from roadsurf.core import atomic
from roadsurf.core.atomic import atomic_path, remove_stale_temporaries, write_text_atomic
from roadsurf.core.errors import OutputError


def test_write_and_rename(tmp_path: Path) -> None:
    p = write_text_atomic(tmp_path / "a" / "x.json", "{}\n")
    assert p.read_text() == "{}\n"
    assert [q.name for q in p.parent.iterdir()] == ["x.json"]


def test_an_empty_result_is_refused_and_leaves_nothing(tmp_path: Path) -> None:
    """cv2.imwrite returns True on a full disk after writing 0 bytes: that must not become a
    0-byte mask under its final name."""
    target = tmp_path / "masks" / "f.png"
    with pytest.raises(OutputError, match="disk full"):
        with atomic_path(target):
            pass  # the writer "succeeded" but wrote nothing
    assert not target.exists()
    assert list(target.parent.iterdir()) == []


def test_disk_full_is_one_line_with_free_space(tmp_path: Path, monkeypatch) -> None:
    def full(_fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", full)
    with pytest.raises(OutputError) as e:
        write_text_atomic(tmp_path / "report.json", "{}")
    msg = str(e.value)
    assert "disk full" in msg and "MB free" in msg and "resume" in msg and "\n" not in msg
    assert not (tmp_path / "report.json").exists()


def test_unwritable_folder_is_an_output_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OutputError, match="--out"):
        write_text_atomic(blocker / "report.json", "{}")


def test_stale_temporaries_are_removed(tmp_path: Path) -> None:
    (tmp_path / "tiles").mkdir()
    stale = [tmp_path / ".surface.abc123.tmp.tif", tmp_path / "tiles" / ".t_0001.x.tmp.tif"]
    for p in stale:
        p.write_bytes(b"half")
    keep = tmp_path / "surface.tif"
    keep.write_bytes(b"done")
    assert sorted(remove_stale_temporaries(tmp_path)) == sorted(stale)
    assert keep.exists() and not any(p.exists() for p in stale)


def test_json_is_strict_nan_becomes_null(tmp_path: Path) -> None:
    """A bare NaN token is not JSON (browsers, jq and GIS readers refuse the file): non-finite
    numbers, also inside numpy arrays and scalars, are written as null."""
    import json
    import math

    import numpy as np

    from roadsurf.core.atomic import write_json_atomic

    def strict(tok: str) -> float:
        raise ValueError(f"non-JSON token {tok}")

    obj = {
        "noise_m": math.nan,
        "inf": np.float32(np.inf),
        "arr": np.array([1.0, np.nan, -np.inf]),
        "nested": [(np.int64(3), Path("a/b"))],
        4: "key",
    }
    p = write_json_atomic(tmp_path / "x.json", obj)
    back = json.loads(p.read_text(), parse_constant=strict)
    assert back == {
        "noise_m": None,
        "inf": None,
        "arr": [1.0, None, None],
        "nested": [[3, "a/b"]],
        "4": "key",
    }
    with pytest.raises(TypeError, match="set"):
        write_json_atomic(tmp_path / "y.json", {"bad": {1, 2}})
