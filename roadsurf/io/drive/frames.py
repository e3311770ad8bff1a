"""frames.csv and frames/ of a drive: rows, timestamps, missing and unreadable images."""

from __future__ import annotations

import math
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.errors import DriveFormatError
from roadsurf.io import drivefolder as df
from roadsurf.io.drive.csvrows import check_increasing, csv_rows
from roadsurf.io.drive.images import check_image, image_size_from_header
from roadsurf.io.drive.types import FORMAT_HINT, Frame, Skipped

# what OpenCV decodes and survey cameras write (8 or 16 bit, grey or colour; 16 bit scaled)
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
_SUFFIXES_TEXT = "/".join(IMAGE_SUFFIXES)  # ".jpg/.jpeg/..." for messages


def _is_file(p: Path, exists: bool = False) -> bool:
    """``p.is_file()`` (or ``p.exists()``), False for a name the file system refuses."""
    try:
        return p.exists() if exists else p.is_file()
    except OSError:  # e.g. a name too long for the file system: there is no such image
        return False


def load_frames(
    root: Path, camera: Camera, check_images: bool, skipped: list[Skipped], warnings: list[str]
) -> list[Frame]:
    csv_path = root / df.FRAMES_CSV
    img_dir = root / df.FRAMES_DIR
    if not img_dir.is_dir():
        raise DriveFormatError(f"{img_dir}: the frames/ folder is missing. {FORMAT_HINT}")
    if not csv_path.is_file():
        by_name, t_by_name = _frames_by_name(root, img_dir, camera, warnings)
        return _present_frames(
            root, img_dir, csv_path, camera, check_images, skipped, warnings, by_name,
            t_by_name, None,
        )  # fmt: skip
    _, rows = csv_rows(csv_path, ("filename", "timestamp_s"))
    names: list[str] = []
    times: list[float] = []
    lines: list[int] = []
    seen: dict[str, int] = {}
    prefixed = False
    for line, row in rows:
        name = row["filename"].replace("\\", "/")
        if not name:
            raise DriveFormatError(f"{csv_path}:{line}: empty filename. Fill it in or delete it.")
        if name.startswith("frames/") and not _is_file(img_dir / name, exists=True):
            # Written relative to the drive instead of frames/: accept it, say so once.
            name = name[len("frames/") :]
            if not prefixed:
                warnings.append(
                    f"{csv_path}:{line}: filenames start with 'frames/'; they should be relative "
                    f"to frames/ (the prefix was removed)."
                )
                prefixed = True
        try:
            t = float(row["timestamp_s"])
        except ValueError:
            raise DriveFormatError(
                f"{csv_path}:{line}: timestamp_s {row['timestamp_s']!r} is not a number "
                f"(seconds). Fix the row."
            ) from None
        if not math.isfinite(t):
            raise DriveFormatError(
                f"{csv_path}:{line}: timestamp_s is {row['timestamp_s']!r}; it must be a finite "
                f"number of seconds. Fix the row."
            )
        if name in seen:
            raise DriveFormatError(
                f"{csv_path}:{line}: {name!r} is listed twice (also line {seen[name]}). "
                f"Remove the duplicate row."
            )
        seen[name] = line
        names.append(name)
        times.append(t)
        lines.append(line)
    if not names:
        raise DriveFormatError(
            f"{csv_path}: empty drive: frames.csv lists no images. Add one row per image in "
            f"frames/ (filename,timestamp_s)."
        )
    t_arr = np.asarray(times)
    check_increasing(t_arr, lines, csv_path, "frame")
    if names != sorted(names):
        warnings.append(
            f"{csv_path}: filenames are not in sorted order; capture order is taken from "
            f"frames.csv timestamps. Rename the files so sorted name order = capture order."
        )
    return _present_frames(
        root, img_dir, csv_path, camera, check_images, skipped, warnings, names, t_arr, lines
    )


def natural_key(name: str) -> list[Any]:
    """Sort key reading runs of digits as numbers: IMG_2 before IMG_10 (a camera's unpadded
    numbering), as a file manager orders them."""
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", name)]


def _is_image(p: Path) -> bool:
    """An image file of frames/ by its suffix, not hidden (macOS's ._ resource forks carry the
    image's suffix)."""
    return p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and _is_file(p)


def _frames_by_name(
    root: Path, img_dir: Path, camera: Camera, warnings: list[str]
) -> tuple[list[str], np.ndarray]:
    """A drive without frames.csv: the images of ``img_dir`` in sorted name order, 1 / fps
    apart (s), numbers in names by value (``natural_key``), hidden files left out. Only a drive
    without a GPS or OBD log may leave the times out (a photo pair, a photo series): with one,
    the images cannot be placed on its clock."""
    csv_path = root / df.FRAMES_CSV
    logs = [n for n in (*df.GPS_FILES, df.OBD_CSV) if (root / n).is_file()]
    if logs:
        raise DriveFormatError(
            f"{csv_path}: frames.csv not found, and {logs[0]} needs the frames' times to be "
            f"matched to it. Write frames.csv with the header filename,timestamp_s and one row "
            f"per image in frames/, on the same clock as {logs[0]}. {FORMAT_HINT}"
        )
    names = sorted((p.name for p in img_dir.iterdir() if _is_image(p)), key=natural_key)
    if not names:
        raise DriveFormatError(
            f"{img_dir}: empty drive: no {_SUFFIXES_TEXT} images, and no frames.csv. {FORMAT_HINT}"
        )
    warnings.append(
        f"{csv_path}: not found; the {len(names)} images of frames/ are taken in name order "
        f"(numbers by value: {names[0]}, {names[1] if len(names) > 1 else '...'}, ...), 1 / fps = {1.0 / camera.fps:.4g} s apart (camera.yaml fps). Without a GPS log "
        f"only their order is used. Write frames.csv (filename,timestamp_s) to give the "
        f"capture times."
    )
    return names, np.arange(len(names), dtype=float) / camera.fps


def _present_frames(
    root: Path,
    img_dir: Path,
    csv_path: Path,
    camera: Camera,
    check_images: bool,
    skipped: list[Skipped],
    warnings: list[str],
    names: list[str],
    t_arr: np.ndarray,
    lines: list[int] | None,
) -> list[Frame]:
    """The listed images that exist and decode, as Frames (``lines``: their frames.csv line
    numbers; None when they were read from the folder)."""
    n_skip0 = len(skipped)
    present: list[int] = []
    for k, name in enumerate(names):
        p = img_dir / name
        line = lines[k] if lines is not None else None
        if not _is_file(p):
            skipped.append(
                Skipped(df.FRAMES_CSV, line, f"image frames/{name} does not exist; row skipped")
            )
        elif p.suffix.lower() not in IMAGE_SUFFIXES:
            skipped.append(
                Skipped(
                    df.FRAMES_CSV,
                    line,
                    f"frames/{name} is not a {_SUFFIXES_TEXT} image; row skipped",
                )
            )
        else:
            present.append(k)
    n_missing = len(names) - len(present)
    if n_missing:
        warnings.append(
            f"{csv_path}: {n_missing} of {len(names)} rows point to missing or non-image files "
            f"and were skipped (see report skipped list)."
        )
    listed = set(names)
    unlisted = [p.name for p in img_dir.iterdir() if _is_image(p) and p.name not in listed]
    if unlisted:
        warnings.append(
            f"{img_dir}: {len(unlisted)} image(s) are not listed in frames.csv and are ignored "
            f"(e.g. {sorted(unlisted)[0]}). Add rows for them if they belong to the drive."
        )

    # Decode/validate the images (threads: cv2 releases the GIL while decoding).
    paths = [img_dir / names[k] for k in present]
    if check_images:
        with ThreadPoolExecutor(max_workers=4) as ex:
            results = list(ex.map(lambda p: check_image(p, True), paths))
    else:
        # Only the first present image's header, to catch a wrong camera.yaml early.
        results = [(None, None)] * len(paths)
        if paths:
            try:
                results[0] = (image_size_from_header(paths[0].read_bytes()), None)
            except OSError:
                pass
    frames: list[Frame] = []
    for k, p, (size, why) in zip(present, paths, results, strict=True):
        if why is not None:
            skipped.append(Skipped(f"frames/{names[k]}", None, f"unreadable image: {why}"))
            continue
        if size is not None and size != (camera.width, camera.height):
            where = f" (frames.csv line {lines[k]})" if lines is not None else ""
            raise DriveFormatError(
                f"{p}: image is {size[0]}x{size[1]} px but camera.yaml says "
                f"{camera.width}x{camera.height}{where}. All frames must "
                f"have the calibrated size: fix camera.yaml or re-export the images."
            )
        frames.append(Frame(len(frames), names[k], p, float(t_arr[k])))
    n_bad = len(present) - len(frames)
    if n_bad:
        warnings.append(f"{img_dir}: {n_bad} unreadable or truncated image(s) skipped.")
    if not frames:
        why = ""
        if len(skipped) > n_skip0:  # the first row's reason, usually every row's
            first = skipped[n_skip0]
            where = f"{first.file}:{first.line}" if first.line is not None else first.file
            why = f" E.g. {where}: {first.reason}."
        if lines is None:
            raise DriveFormatError(
                f"{img_dir}: empty drive: none of its {len(names)} images is readable.{why} "
                f"Check the files ({_SUFFIXES_TEXT})."
            )
        raise DriveFormatError(
            f"{root}: empty drive: none of the {len(names)} rows of frames.csv has a readable "
            f"image in frames/.{why} Check the folder and the filenames in frames.csv (names "
            f"relative to frames/, {_SUFFIXES_TEXT})."
        )
    return frames
