"""Reading the drive's text files as UTF-8 (a byte-order mark is allowed), with one-line errors
naming the file and line for unreadable files and non-UTF-8 bytes."""

from __future__ import annotations

from pathlib import Path

from roadsurf.core.errors import DriveFormatError

_BOM = b"\xef\xbb\xbf"


def read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as e:
        raise DriveFormatError(
            f"{path}: cannot read the file ({e.strerror or e}). Check that it is a readable file."
        ) from None


def line_col(data: bytes, offset: int) -> tuple[int, int]:
    """1-based (line, column) of a byte offset."""
    line = data.count(b"\n", 0, offset) + 1
    return line, offset - (data.rfind(b"\n", 0, offset) + 1) + 1


def read_text(path: Path) -> str:
    """The file decoded as UTF-8; ``DriveFormatError`` at the first byte that is not UTF-8."""
    data = read_bytes(path)
    body = data[len(_BOM) :] if data.startswith(_BOM) else data
    try:
        return body.decode("utf-8")
    except UnicodeDecodeError as e:
        line, col = line_col(body, e.start)
        raise DriveFormatError(
            f"{path}:{line}: byte 0x{body[e.start]:02X} (column {col}) is not UTF-8 text. "
            f"Save the file as UTF-8 and run again."
        ) from None
