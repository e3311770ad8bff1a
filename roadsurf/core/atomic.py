"""Atomic file writing and small JSON/npz helpers shared by all stages.

Every artifact is written to a temporary file in the same folder and then renamed, so a killed
run never leaves a half-written file that a resumed run would trust.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import shutil
import tempfile
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core.errors import OutputError

# temporary files of atomic_path: ".<stem>.<random>.tmp<suffix>" beside the final file
TEMP_GLOB = ".*.tmp*"


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def output_error(
    e: OSError, path: str | os.PathLike[str], needed_bytes: int | None = None
) -> OutputError:
    """A one-line, actionable error for a failed write of ``path`` (disk full, read-only,
    permission, not a folder)."""
    path = Path(path)
    folder = next((p for p in [path.parent, *path.parents] if p.exists()), Path("."))
    if e.errno == errno.ENOSPC:
        free = shutil.disk_usage(folder).free
        need = f", about {needed_bytes / 1e6:.1f} MB needed" if needed_bytes else ""
        return OutputError(
            f"{path}: disk full ({free / 1e6:.1f} MB free on {folder}{need}). Free some space "
            "or choose another --out, then run the same command again to resume."
        )
    if e.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        return OutputError(
            f"{path}: cannot write there ({os.strerror(e.errno or 0)}). Choose a writable --out."
        )
    if e.errno in (errno.ENOTDIR, errno.EEXIST):
        return OutputError(
            f"{path}: a file stands where a folder is needed ({folder}). Choose another --out."
        )
    return OutputError(f"{path}: cannot write ({e.strerror or e}). Check the output folder.")


def library_write_error(e: Exception, path: str | os.PathLike[str]) -> OutputError:
    """A one-line error for a write that failed inside a library (GDAL says only "Write
    failed"): disk full when the folder has almost no space left, else the library's words."""
    path = Path(path)
    folder = next((p for p in [path.parent, *path.parents] if p.exists()), Path("."))
    if shutil.disk_usage(folder).free < 64 * 2**20:
        return output_error(OSError(errno.ENOSPC, "No space left on device"), path)
    return OutputError(
        f"{path}: cannot write ({' '.join(str(e).split())}). Check the output folder."
    )


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str], *, allow_empty: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    The temporary name keeps the final suffix, so libraries that pick a format from the
    extension (rasterio, open3d, cv2) still work. The file is flushed to disk (fsync) before
    the rename, and an empty result is refused unless ``allow_empty``: some writers (cv2.imwrite
    on a full disk) report success after writing nothing. Write failures become one-line
    ``OutputError``s.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent
        )
        os.close(fd)
    except OSError as e:
        raise output_error(e, path) from e
    tmp_path = Path(tmp)
    try:
        try:
            yield tmp_path
            if not allow_empty and tmp_path.stat().st_size == 0:
                raise OSError(errno.ENOSPC, "nothing was written")
            _fsync(tmp_path)
            # mkstemp creates mode 0600; outputs are meant to be shared: apply the usual umask.
            os.chmod(tmp_path, 0o666 & ~_current_umask())
            os.replace(tmp_path, path)
        except OSError as e:
            raise output_error(e, path) from e
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def remove_stale_temporaries(root: str | os.PathLike[str]) -> list[Path]:
    """Delete the temporary files a killed run left below ``root`` (atomic_path's names);
    returns them."""
    root = Path(root)
    if not root.is_dir():
        return []
    gone = []
    for p in root.rglob(TEMP_GLOB):
        if p.is_file() and ".tmp" in p.name:
            p.unlink(missing_ok=True)
            gone.append(p)
    return gone


def write_text_atomic(path: str | os.PathLike[str], text: str) -> Path:
    with atomic_path(path, allow_empty=not text) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> Path:
    with atomic_path(path, allow_empty=not data) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def json_safe(obj: Any) -> Any:
    """``obj`` with what strict JSON cannot hold converted: NaN and ±inf -> None (``null``;
    a bare ``NaN`` token is not JSON and browsers, jq and GIS readers refuse the file), numpy
    arrays and scalars -> lists and Python numbers, paths -> str, tuples -> lists, keys -> str."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _json_default(obj: Any) -> Any:
    raise TypeError(f"cannot serialise {type(obj).__name__} to JSON")


def write_json_atomic(path: str | os.PathLike[str], obj: Any, indent: int = 2) -> Path:
    """Write ``obj`` as strict JSON (``json_safe``: NaN -> null) atomically."""
    text = json.dumps(json_safe(obj), indent=indent, default=_json_default, allow_nan=False)
    return write_text_atomic(path, text + "\n")


def read_json(path: str | os.PathLike[str]) -> Any:
    with open(path, encoding="utf-8") as f:
        return json.load(f)


# What reading a cached artifact back can raise when a kill, a full disk or a user truncated
# or overwrote it (np.load of a cut .npz: BadZipFile; of a damaged one: zlib.error; a JSON
# record that is not an object: TypeError / AttributeError on its fields): the stages then
# recompute it instead of stopping with a traceback.
UNREADABLE = (
    OSError,
    ValueError,
    KeyError,
    TypeError,
    AttributeError,
    EOFError,
    zipfile.BadZipFile,
    zlib.error,
)


def read_json_object(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A JSON file that must hold an object (a stage's record); ValueError when it does not."""
    d = read_json(path)
    if not isinstance(d, dict):
        raise ValueError(f"{path}: holds a JSON {type(d).__name__}, not an object")
    return d


def write_npz_atomic(
    path: str | os.PathLike[str], *, compressed: bool = True, **arrays: Any
) -> Path:
    """Write an .npz atomically (zlib-compressed unless ``compressed`` is False). Values are
    converted with ``np.asarray``."""
    save = np.savez_compressed if compressed else np.savez
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            save(f, **{k: np.asarray(v) for k, v in arrays.items()})  # type: ignore[arg-type]
    return Path(path)
