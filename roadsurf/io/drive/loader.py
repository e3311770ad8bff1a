"""Implementation of ``roadsurf.io.drive.load_drive`` / ``read_image`` / ``read_gray``.

The rules (what is an error, what is skipped, how GPS times are matched to frame times) are
documented in docs/formats.md; keep the two in step.

Summary:
- Errors (``DriveFormatError``): missing folder / camera.yaml / frames.csv; camera.yaml with
  missing, unknown or ill-typed keys; a CSV without its required columns; timestamps that are not
  strictly increasing (frames, GPS, OBD); duplicate frame names; images whose size differs from
  camera.yaml; a drive with no usable frame.
- Skipped and recorded in ``Drive.skipped`` (the run goes on): frames.csv rows whose image is
  missing, unreadable or truncated images, GPS fixes with NaN / non-numeric / out-of-range
  lat/lon (or the 0,0 no-fix placeholder), NMEA sentences with a bad checksum or bad fields,
  OBD rows with NaN or negative speed.
- Warnings (``Drive.warnings``, also logged): no GPS log, a GPS log that does not overlap the
  frame times (then ``gps=None``: mapping runs in a local frame), partial overlap, images in
  frames/ that frames.csv does not list, several GPS logs present.
"""

from __future__ import annotations

import calendar
import csv
import logging
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from roadsurf.core.errors import DriveFormatError, FrameReadError
from roadsurf.io.drive import Camera, Drive, Frame, GpsTrack, ObdLog, Skipped

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
GPS_FILES = ("gps.csv", "gps.gpx", "gps.nmea")  # priority order when several are present
FORMAT_HINT = "See docs/formats.md for the drive format."

# camera.yaml: key -> (python type, required)
_CAMERA_KEYS: dict[str, tuple[type, bool]] = {
    "model": (str, False),
    "width": (int, True),
    "height": (int, True),
    "fx": (float, True),
    "fy": (float, True),
    "cx": (float, True),
    "cy": (float, True),
    "dist": (list, False),
    "height_m": (float, True),
    "fps": (float, True),
}


# =========================================================================== camera.yaml


def _yaml_key_lines(text: str) -> dict[str, int]:
    """1-based line number of each top-level key of a YAML mapping (for error messages)."""
    try:
        node = yaml.compose(text)
    except yaml.YAMLError:
        return {}
    if not isinstance(node, yaml.MappingNode):
        return {}
    return {str(k.value): k.start_mark.line + 1 for k, _ in node.value if hasattr(k, "value")}


def load_camera(path: Path) -> Camera:
    """Parse and validate camera.yaml. Raises DriveFormatError naming the file and line."""
    if not path.is_file():
        raise DriveFormatError(
            f"{path}: camera.yaml not found. Every drive needs one with keys model, width, "
            f"height, fx, fy, cx, cy, height_m, fps (dist optional). {FORMAT_HINT}"
        )
    text = path.read_text(encoding="utf-8-sig")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        raise DriveFormatError(
            f"{where}: camera.yaml is not valid YAML ({e}). Fix the syntax."
        ) from e
    if not isinstance(data, dict):
        raise DriveFormatError(
            f"{path}: camera.yaml must be a mapping of keys to values (got "
            f"{type(data).__name__}). {FORMAT_HINT}"
        )
    lines = _yaml_key_lines(text)

    def where(key: str) -> str:
        return f"{path}:{lines[key]}" if key in lines else str(path)

    unknown = sorted(str(k) for k in data if k not in _CAMERA_KEYS)
    if unknown:
        raise DriveFormatError(
            f"{where(unknown[0])}: unknown key(s) {unknown} in camera.yaml. Valid keys are "
            f"{sorted(_CAMERA_KEYS)}. Fix the spelling or remove them."
        )
    missing = [k for k, (_, req) in _CAMERA_KEYS.items() if req and k not in data]
    if missing:
        raise DriveFormatError(
            f"{path}: camera.yaml is missing required key(s) {missing}. Add them "
            f"(pixels for width/height/fx/fy/cx/cy, metres for height_m, Hz for fps). {FORMAT_HINT}"
        )
    vals: dict[str, Any] = {}
    for key, (tp, _) in _CAMERA_KEYS.items():
        if key not in data:
            continue
        v = data[key]
        if tp is int:
            if isinstance(v, float) and v.is_integer():  # "640.0" from some writers
                v = int(v)
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise DriveFormatError(
                    f"{where(key)}: camera.yaml '{key}' must be a positive integer (pixels), "
                    f"got {v!r}."
                )
        elif tp is float:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise DriveFormatError(
                    f"{where(key)}: camera.yaml '{key}' must be a number, got {v!r}."
                )
            v = float(v)
            if key in ("fx", "fy", "height_m", "fps") and v <= 0:
                raise DriveFormatError(f"{where(key)}: camera.yaml '{key}' must be > 0, got {v!r}.")
        elif tp is str:
            if not isinstance(v, str) or v.strip().lower() != "pinhole":
                raise DriveFormatError(
                    f"{where(key)}: camera.yaml 'model' must be 'pinhole' (with OpenCV 'dist' "
                    f"coefficients for lens distortion), got {v!r}."
                )
            v = "pinhole"
        elif key == "dist":
            if v is None:
                v = []
            if (
                not isinstance(v, (list, tuple))
                or len(v) not in (0, 4, 5)
                or any(
                    isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x)
                    for x in v
                )
            ):
                raise DriveFormatError(
                    f"{where(key)}: camera.yaml 'dist' must be a list of 5 numbers "
                    f"[k1, k2, p1, p2, k3] in OpenCV order (4 are accepted, k3 = 0), got {v!r}."
                )
            v = tuple(float(x) for x in v) + (0.0,) * (5 - len(v))
        vals[key] = v
    cam = Camera(
        width=vals["width"],
        height=vals["height"],
        fx=vals["fx"],
        fy=vals["fy"],
        cx=vals["cx"],
        cy=vals["cy"],
        height_m=vals["height_m"],
        fps=vals["fps"],
        dist=vals.get("dist", (0.0,) * 5),
        model=vals.get("model", "pinhole"),
    )
    if not (0 <= cam.cx <= cam.width and 0 <= cam.cy <= cam.height):
        raise DriveFormatError(
            f"{path}: principal point (cx, cy) = ({cam.cx}, {cam.cy}) lies outside the "
            f"{cam.width}x{cam.height} image. Check camera.yaml (pixels, origin top-left)."
        )
    return cam


# =========================================================================== CSV helpers


def _csv_rows(
    path: Path, required: tuple[str, ...], optional: tuple[str, ...] = ()
) -> tuple[list[str], Iterator[tuple[int, dict[str, str]]]]:
    """Open a CSV, check its header, and yield (line number, row dict) for non-empty rows."""
    f = open(path, encoding="utf-8-sig", newline="")  # noqa: SIM115 - closed by the generator
    reader = csv.reader(f)
    try:
        header = next(reader)
    except StopIteration:
        f.close()
        raise DriveFormatError(
            f"{path}:1: file is empty; it needs the header {','.join(required)}. {FORMAT_HINT}"
        ) from None
    header = [h.strip() for h in header]
    missing = [c for c in required if c not in header]
    if missing:
        f.close()
        raise DriveFormatError(
            f"{path}:1: header {header} lacks column(s) {missing}; expected "
            f"{','.join(required)}{''.join(',' + o for o in optional)}. Fix the header line."
        )
    extra = [h for h in header if h not in required and h not in optional]
    if extra:
        log.warning("%s:1: ignoring unknown column(s) %s", path, extra)

    def gen() -> Iterator[tuple[int, dict[str, str]]]:
        with f:
            for row in reader:
                if not row or all(not c.strip() for c in row):
                    continue
                if len(row) < len(header):
                    row = row + [""] * (len(header) - len(row))
                yield reader.line_num, {h: c.strip() for h, c in zip(header, row, strict=False)}

    return header, gen()


def _float(s: str) -> float:
    """Parse a CSV number; empty -> NaN; raises ValueError for text."""
    return float(s) if s != "" else math.nan


def _check_increasing(t: np.ndarray, lines: list[int], path: Path, what: str) -> None:
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0])
        raise DriveFormatError(
            f"{path}:{lines[i + 1]}: {what} timestamp {float(t[i + 1])!r} is not after the previous one "
            f"({float(t[i])!r} on line {lines[i]}). Timestamps must strictly increase; sort the file "
            f"and remove duplicate rows."
        )


# =========================================================================== images


def _image_size_from_header(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG IHDR or JPEG SOF header, or None if not found."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:2] == b"\xff\xd8":
        i, n = 2, len(data)
        while i + 9 < n:
            if data[i] != 0xFF:
                i += 1
                continue
            m = data[i + 1]
            if m in (0xD8, 0x01) or 0xD0 <= m <= 0xD7 or m == 0xFF:
                i += 1 if m == 0xFF else 2
                continue
            seglen = int.from_bytes(data[i + 2 : i + 4], "big")
            if 0xC0 <= m <= 0xCF and m not in (0xC4, 0xC8, 0xCC):
                h = int.from_bytes(data[i + 5 : i + 7], "big")
                w = int.from_bytes(data[i + 7 : i + 9], "big")
                return w, h
            if m == 0xDA:  # start of scan before any SOF: malformed
                return None
            i += 2 + seglen
    return None


def _truncation_reason(data: bytes, name: str) -> str | None:
    """Why the encoded image is incomplete (missing end marker), or None if it looks whole."""
    if not data:
        return "empty file"
    if data[:2] == b"\xff\xd8":
        # Some cameras pad after EOI with zeros or append a few bytes; look near the end only.
        tail = data.rstrip(b"\x00")[-1024:]
        if b"\xff\xd9" not in tail:
            return "truncated JPEG (no end-of-image marker FFD9)"
    elif data[:8] == b"\x89PNG\r\n\x1a\n":
        if b"IEND" not in data[-64:]:
            return "truncated PNG (no IEND chunk)"
    elif Path(name).suffix.lower() in (".jpg", ".jpeg", ".png"):
        return "not a JPEG/PNG file (bad signature bytes)"
    return None


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as e:
        raise FrameReadError(f"{path}: cannot read image ({e}). Check the file.") from e


def _decode(path: Path, flags: int) -> np.ndarray:
    data = _read_bytes(path)
    why = _truncation_reason(data, path.name)
    if why is not None:
        raise FrameReadError(f"{path}: {why}. Re-export or remove the frame.")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if img is None or img.size == 0:
        raise FrameReadError(f"{path}: image cannot be decoded. Re-export or remove the frame.")
    if img.dtype != np.uint8:  # 16-bit PNG: scale to 8 bit
        img = (img / 257.0).round().astype(np.uint8) if img.dtype == np.uint16 else None
        if img is None:
            raise FrameReadError(f"{path}: unsupported pixel type; use 8-bit JPEG/PNG.")
    return img


def read_image(frame: Frame) -> np.ndarray:
    """RGB uint8 (H, W, 3); greyscale files are replicated to 3 channels."""
    # EXIF orientation is ignored: pixels must stay in the calibrated sensor frame.
    img = _decode(Path(frame.path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    return cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2RGB)


def read_gray(frame: Frame) -> np.ndarray:
    """Greyscale uint8 (H, W)."""
    img = _decode(Path(frame.path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


def _check_image(path: Path, full: bool) -> tuple[tuple[int, int] | None, str | None]:
    """Cheap validity check: (width, height) from the header and a failure reason (or None).

    ``full`` also decodes the image (at 1/8 scale for JPEG, which is fast)."""
    try:
        data = path.read_bytes()
    except OSError as e:
        return None, f"cannot read file ({e.strerror or e})"
    why = _truncation_reason(data, path.name)
    if why is not None:
        return None, why
    size = _image_size_from_header(data)
    if full:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_REDUCED_GRAYSCALE_8)
        if img is None or img.size == 0:
            return size, "image cannot be decoded (corrupt data)"
        if size is None:  # a format without a parsed header: decode fully for the size
            full_img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
            if full_img is None:
                return None, "image cannot be decoded (corrupt data)"
            size = (int(full_img.shape[1]), int(full_img.shape[0]))
    return size, None


# =========================================================================== frames


def _load_frames(
    root: Path, camera: Camera, check_images: bool, skipped: list[Skipped], warnings: list[str]
) -> list[Frame]:
    csv_path = root / "frames.csv"
    img_dir = root / "frames"
    if not csv_path.is_file():
        raise DriveFormatError(
            f"{csv_path}: frames.csv not found. Write it with the header filename,timestamp_s "
            f"and one row per image in frames/. {FORMAT_HINT}"
        )
    if not img_dir.is_dir():
        raise DriveFormatError(f"{img_dir}: the frames/ folder is missing. {FORMAT_HINT}")
    _, rows = _csv_rows(csv_path, ("filename", "timestamp_s"))
    names: list[str] = []
    times: list[float] = []
    lines: list[int] = []
    seen: dict[str, int] = {}
    prefixed = False
    for line, row in rows:
        name = row["filename"].replace("\\", "/")
        if not name:
            raise DriveFormatError(f"{csv_path}:{line}: empty filename. Fill it in or delete it.")
        if name.startswith("frames/") and not (img_dir / name).exists():
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
    _check_increasing(t_arr, lines, csv_path, "frame")
    if names != sorted(names):
        warnings.append(
            f"{csv_path}: filenames are not in sorted order; capture order is taken from "
            f"frames.csv timestamps. Rename the files so sorted name order = capture order."
        )

    # Which rows have an image at all.
    present: list[int] = []
    for k, name in enumerate(names):
        p = img_dir / name
        if not p.is_file():
            skipped.append(
                Skipped("frames.csv", lines[k], f"image frames/{name} does not exist; row skipped")
            )
        elif p.suffix.lower() not in IMAGE_SUFFIXES:
            skipped.append(
                Skipped(
                    "frames.csv",
                    lines[k],
                    f"frames/{name} is not a .jpg/.jpeg/.png image; row skipped",
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
    unlisted = [
        p.name
        for p in img_dir.iterdir()
        if p.suffix.lower() in IMAGE_SUFFIXES and p.name not in listed
    ]
    if unlisted:
        warnings.append(
            f"{img_dir}: {len(unlisted)} image(s) are not listed in frames.csv and are ignored "
            f"(e.g. {sorted(unlisted)[0]}). Add rows for them if they belong to the drive."
        )

    # Decode/validate the images (threads: cv2 releases the GIL while decoding).
    paths = [img_dir / names[k] for k in present]
    if check_images:
        with ThreadPoolExecutor(max_workers=4) as ex:
            results = list(ex.map(lambda p: _check_image(p, True), paths))
    else:
        # Only the first present image's header, to catch a wrong camera.yaml early.
        results = [(None, None)] * len(paths)
        if paths:
            try:
                results[0] = (_image_size_from_header(paths[0].read_bytes()), None)
            except OSError:
                pass
    frames: list[Frame] = []
    for k, p, (size, why) in zip(present, paths, results, strict=True):
        if why is not None:
            skipped.append(Skipped(f"frames/{names[k]}", None, f"unreadable image: {why}"))
            continue
        if size is not None and size != (camera.width, camera.height):
            raise DriveFormatError(
                f"{p}: image is {size[0]}x{size[1]} px but camera.yaml says "
                f"{camera.width}x{camera.height} (frames.csv line {lines[k]}). All frames must "
                f"have the calibrated size: fix camera.yaml or re-export the images."
            )
        frames.append(Frame(len(frames), names[k], p, float(t_arr[k])))
    n_bad = len(present) - len(frames)
    if n_bad:
        warnings.append(f"{img_dir}: {n_bad} unreadable or truncated image(s) skipped.")
    if not frames:
        raise DriveFormatError(
            f"{root}: empty drive: none of the {len(names)} rows of frames.csv has a readable "
            f"image in frames/. Check the folder and the filenames in frames.csv."
        )
    return frames


# =========================================================================== GPS


def _valid_latlon(lat: float, lon: float) -> str | None:
    if not (math.isfinite(lat) and math.isfinite(lon)):
        return "lat/lon is NaN or missing"
    if abs(lat) > 90 or abs(lon) > 180:
        return f"lat/lon ({lat}, {lon}) out of range"
    if lat == 0.0 and lon == 0.0:
        return "lat/lon is (0, 0), a receiver's no-fix placeholder"
    return None


def _gps_from_lists(
    path: Path,
    rows: list[tuple[int | None, float, float, float, float, float]],
    skipped: list[Skipped],
    n_bad: int,
    n_total: int,
    warnings: list[str],
) -> GpsTrack | None:
    """rows: (line, t, lat, lon, alt, hdop) of fixes that passed validation."""
    # A row repeated verbatim (same time and position; some loggers write a fix twice) carries
    # no information: drop it. Any other non-increasing time is an error below.
    dedup: list[tuple[int | None, float, float, float, float, float]] = []
    for r in rows:
        if dedup and r[1] == dedup[-1][1] and r[2:4] == dedup[-1][2:4]:
            where = f"line {r[0]}" if r[0] is not None else f"time {r[1]}"
            skipped.append(Skipped(path.name, r[0], f"duplicate GPS fix ({where}) dropped"))
            n_bad += 1
            continue
        dedup.append(r)
    rows = dedup
    if n_bad:
        warnings.append(
            f"{path}: dropped {n_bad} of {n_total} GPS record(s) (bad or out-of-range values; "
            f"see report skipped list)."
        )
    if not rows:
        warnings.append(f"{path}: no valid GPS fix; running without GPS (local frame).")
        return None
    arr = np.array([r[1:] for r in rows], dtype=float)
    lines = [r[0] or 0 for r in rows]
    if any(r[0] is None for r in rows):
        bad = np.flatnonzero(np.diff(arr[:, 0]) <= 0)
        if bad.size:
            i = int(bad[0])
            raise DriveFormatError(
                f"{path}: GPS fix #{i + 2} (time {float(arr[i + 1, 0])!r} s) is not after fix #{i + 1} "
                f"({float(arr[i, 0])!r} s). GPS times must strictly increase; fix the log."
            )
    else:
        _check_increasing(arr[:, 0], lines, path, "GPS")
    return GpsTrack(
        timestamp_s=arr[:, 0],
        lat_deg=arr[:, 1],
        lon_deg=arr[:, 2],
        alt_m=arr[:, 3],
        hdop=arr[:, 4],
        source=path.name,
    )


def _load_gps_csv(path: Path, skipped: list[Skipped], warnings: list[str]) -> GpsTrack | None:
    _, rows = _csv_rows(path, ("timestamp_s", "lat", "lon"), ("alt_m", "hdop"))
    good: list[tuple[int | None, float, float, float, float, float]] = []
    n_total = n_bad = 0
    for line, row in rows:
        n_total += 1
        try:
            t = float(row["timestamp_s"])
        except ValueError:
            t = math.nan
        if not math.isfinite(t):
            n_bad += 1
            skipped.append(Skipped(path.name, line, "GPS row without a numeric timestamp_s"))
            continue
        try:
            lat, lon = _float(row["lat"]), _float(row["lon"])
        except ValueError:
            lat = lon = math.nan
        why = _valid_latlon(lat, lon)
        if why is not None:
            n_bad += 1
            skipped.append(Skipped(path.name, line, f"GPS row dropped: {why}"))
            continue
        try:
            alt = _float(row.get("alt_m", ""))
        except ValueError:
            alt = math.nan
        try:
            hdop = _float(row.get("hdop", ""))
        except ValueError:
            hdop = math.nan
        if math.isfinite(hdop) and hdop <= 0:
            hdop = math.nan
        good.append((line, t, lat, lon, alt, hdop))
    return _gps_from_lists(path, good, skipped, n_bad, n_total, warnings)


def _parse_iso_time(s: str) -> float:
    """ISO 8601 time -> UNIX seconds (UTC when no offset is given)."""
    s = s.strip()
    if s.endswith(("Z", "z")):
        s = s[:-1] + "+00:00"
    dt = datetime.fromisoformat(s)
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    return dt.timestamp()


def _num(d: dict[str, str], key: str) -> float:
    try:
        return float(d[key]) if d.get(key) else math.nan
    except ValueError:
        return math.nan


def _load_gps_gpx(path: Path, skipped: list[Skipped], warnings: list[str]) -> GpsTrack | None:
    try:
        tree = ET.parse(path)
    except ET.ParseError as e:
        line = e.position[0] if getattr(e, "position", None) else None
        raise DriveFormatError(
            f"{path}:{line}: not valid XML ({e}). Fix or re-export the GPX file."
        ) from e

    def local(tag: str) -> str:
        return tag.rsplit("}", 1)[-1]

    pts = [el for el in tree.iter() if local(el.tag) == "trkpt"]
    if not pts:
        raise DriveFormatError(
            f"{path}: GPX has no <trkpt> track points. Export the track (not waypoints/routes)."
        )
    good: list[tuple[int | None, float, float, float, float, float]] = []
    n_bad = 0
    for k, el in enumerate(pts, start=1):
        child = {local(c.tag): (c.text or "").strip() for c in el}
        tag = f"trkpt #{k}"
        try:
            lat, lon = float(el.get("lat", "nan")), float(el.get("lon", "nan"))
        except ValueError:
            lat = lon = math.nan
        why = _valid_latlon(lat, lon)
        if why is None and not child.get("time"):
            why = "no <time>"
        t = math.nan
        if why is None:
            try:
                t = _parse_iso_time(child["time"])
            except ValueError:
                why = f"<time> {child['time']!r} is not ISO 8601"
        if why is not None:
            n_bad += 1
            skipped.append(Skipped(path.name, None, f"GPX {tag} dropped: {why}"))
            continue

        good.append((None, t, lat, lon, _num(child, "ele"), _num(child, "hdop")))
    return _gps_from_lists(path, good, skipped, n_bad, len(pts), warnings)


_NMEA_RE = re.compile(r"^\$([A-Z]{2})(RMC|GGA),(.*)\*([0-9A-Fa-f]{2})\s*$")


def _nmea_deg(value: str, hemi: str) -> float:
    """ddmm.mmmm / dddmm.mmmm + N/S/E/W -> signed degrees."""
    if not value or hemi not in ("N", "S", "E", "W"):
        return math.nan
    v = float(value)
    deg = math.floor(v / 100.0)
    d = deg + (v - deg * 100.0) / 60.0
    return -d if hemi in ("S", "W") else d


def _nmea_tod(hhmmss: str) -> float:
    """hhmmss.ss -> seconds of the day."""
    if len(hhmmss) < 6:
        raise ValueError("bad time")
    return int(hhmmss[0:2]) * 3600 + int(hhmmss[2:4]) * 60 + float(hhmmss[4:])


def _load_gps_nmea(path: Path, skipped: list[Skipped], warnings: list[str]) -> GpsTrack | None:
    """$xxRMC gives date/time/position; $xxGGA gives time/position/HDOP/altitude. Sentences of
    the same second are merged into one fix. Times become UNIX seconds (UTC) using the RMC date."""
    fixes: dict[float, dict[str, Any]] = {}  # key: seconds of day (+ day offset)
    n_bad = n_sent = 0
    day0: float | None = None  # UNIX seconds at 00:00 UTC of the current date
    first_day0: float | None = None
    last_tod: float | None = None
    pending_gga: list[tuple[int, float, dict[str, Any]]] = []  # GGA seen before any RMC date
    with open(path, encoding="ascii", errors="replace") as f:
        for line_no, raw in enumerate(f, start=1):
            s = raw.strip()
            if not s.startswith("$"):
                continue
            m = _NMEA_RE.match(s)
            if m is None:
                if s[3:6] in ("RMC", "GGA"):
                    n_sent += 1
                    n_bad += 1
                    skipped.append(Skipped(path.name, line_no, "malformed NMEA sentence"))
                continue  # other sentence types are ignored
            n_sent += 1
            body = s[1 : s.rindex("*")]
            chk = 0
            for ch in body:
                chk ^= ord(ch)
            if chk != int(m.group(4), 16):
                n_bad += 1
                skipped.append(Skipped(path.name, line_no, "NMEA checksum mismatch"))
                continue
            kind, fields = m.group(2), m.group(3).split(",")
            try:
                if kind == "RMC":
                    # time,status,lat,N,lon,E,speed_kn,course,date(ddmmyy),...
                    if len(fields) < 9:
                        raise ValueError("too few fields")
                    tod = _nmea_tod(fields[0])
                    if fields[1] != "A":
                        raise ValueError("status V (no fix)")
                    lat, lon = _nmea_deg(fields[2], fields[3]), _nmea_deg(fields[4], fields[5])
                    d = fields[8]
                    if len(d) != 6:
                        raise ValueError("bad date")
                    yy = int(d[4:6])
                    day0 = float(
                        calendar.timegm(
                            (2000 + yy if yy < 80 else 1900 + yy, int(d[2:4]), int(d[0:2]), 0, 0, 0)
                        )
                    )
                    if first_day0 is None:
                        first_day0 = day0
                    rec: dict[str, Any] = {"lat": lat, "lon": lon}
                else:
                    # time,lat,N,lon,E,quality,nsat,hdop,alt,M,...
                    if len(fields) < 9:
                        raise ValueError("too few fields")
                    tod = _nmea_tod(fields[0])
                    if fields[5] in ("", "0"):
                        raise ValueError("fix quality 0 (no fix)")
                    lat, lon = _nmea_deg(fields[1], fields[2]), _nmea_deg(fields[3], fields[4])
                    rec = {
                        "lat": lat,
                        "lon": lon,
                        "hdop": float(fields[7]) if fields[7] else math.nan,
                        "alt": float(fields[8]) if fields[8] else math.nan,
                    }
            except ValueError as e:
                n_bad += 1
                skipped.append(Skipped(path.name, line_no, f"NMEA {kind} dropped: {e}"))
                continue
            why = _valid_latlon(rec["lat"], rec["lon"])
            if why is not None:
                n_bad += 1
                skipped.append(Skipped(path.name, line_no, f"NMEA {kind} dropped: {why}"))
                continue
            if day0 is None:
                pending_gga.append((line_no, tod, rec))
                continue
            if last_tod is not None and tod < last_tod - 43200 and kind == "GGA":
                day0 += 86400.0  # midnight rollover between RMC sentences
            last_tod = tod
            t = round(day0 + tod, 3)
            fx = fixes.setdefault(t, {"line": line_no})
            for k2, v2 in rec.items():
                if k2 in ("lat", "lon") and k2 in fx:
                    continue  # first sentence of the epoch wins for position
                fx[k2] = v2
    if pending_gga:
        if first_day0 is None:
            raise DriveFormatError(
                f"{path}: NMEA log has $GPGGA but no valid $GPRMC sentence, so the date is "
                f"unknown and GPS times cannot be matched to frames.csv. Log RMC sentences too."
            )
        # GGA sentences before the first RMC: use the first RMC's date.
        d0 = first_day0
        for line_no, tod, rec in pending_gga:
            fx = fixes.setdefault(round(d0 + tod, 3), {"line": line_no})
            for k2, v2 in rec.items():
                fx.setdefault(k2, v2)
    if n_sent == 0:
        raise DriveFormatError(
            f"{path}: no $GPRMC/$GPGGA sentences found. Record RMC and GGA sentences."
        )
    good = [
        (
            fx["line"],
            t,
            fx["lat"],
            fx["lon"],
            fx.get("alt", math.nan),
            fx.get("hdop", math.nan),
        )
        for t, fx in sorted(fixes.items())
    ]
    if n_bad:
        log.info("%s: %d of %d RMC/GGA sentences skipped", path, n_bad, n_sent)
    return _gps_from_lists(path, good, skipped, n_bad, n_sent, warnings)


def _check_overlap(gps: GpsTrack, frames: list[Frame], warnings: list[str]) -> GpsTrack | None:
    t0, t1 = frames[0].timestamp_s, frames[-1].timestamp_s
    g0, g1 = float(gps.timestamp_s[0]), float(gps.timestamp_s[-1])
    # A fix slightly outside the frame span still helps; allow one GPS interval of slack.
    slack = float(np.median(np.diff(gps.timestamp_s))) if len(gps) > 1 else 1.0
    if g1 < t0 - slack or g0 > t1 + slack:
        warnings.append(
            f"{gps.source}: GPS times [{g0:.3f}, {g1:.3f}] s do not overlap the frame times "
            f"[{t0:.3f}, {t1:.3f}] s (offset about {g0 - t0:+.1f} s), so the GPS is ignored and "
            f"the map is built in a local frame without lat/lon. Write frames.csv times in the "
            f"same clock as the GPS (UNIX seconds, UTC, for GPX/NMEA logs)."
        )
        return None
    span = max(t1 - t0, 1e-9)
    covered = (min(t1, g1) - max(t0, g0)) / span if t1 > t0 else 1.0
    if covered < 0.9:
        warnings.append(
            f"{gps.source}: GPS covers only {100 * max(covered, 0):.0f}% of the frame time span; "
            f"frames outside it are placed by visual chaining."
        )
    return gps


# =========================================================================== OBD


def _load_obd(path: Path, skipped: list[Skipped], warnings: list[str]) -> ObdLog | None:
    _, rows = _csv_rows(path, ("timestamp_s", "speed_mps"))
    t: list[float] = []
    v: list[float] = []
    lines: list[int] = []
    n_total = 0
    for line, row in rows:
        n_total += 1
        try:
            ti, vi = float(row["timestamp_s"]), _float(row["speed_mps"])
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
    _check_increasing(ta, lines, path, "OBD")
    return ObdLog(timestamp_s=ta, speed_mps=np.asarray(v))


# =========================================================================== entry point


def load_drive(root: str | Path, check_images: bool = True) -> Drive:
    """Load and validate a drive folder (see docs/formats.md)."""
    root = Path(root)
    if not root.is_dir():
        raise DriveFormatError(f"{root}: drive folder not found. {FORMAT_HINT}")
    skipped: list[Skipped] = []
    warnings: list[str] = []
    camera = load_camera(root / "camera.yaml")
    frames = _load_frames(root, camera, check_images, skipped, warnings)

    present = [name for name in GPS_FILES if (root / name).is_file()]
    gps: GpsTrack | None = None
    if not present:
        warnings.append(
            f"{root}: no GPS log (gps.csv, gps.gpx or gps.nmea); the map is built in a local "
            f"frame without lat/lon."
        )
    else:
        if len(present) > 1:
            warnings.append(f"{root}: several GPS logs {present}; using {present[0]}.")
        path = root / present[0]
        loader = {"gps.csv": _load_gps_csv, "gps.gpx": _load_gps_gpx, "gps.nmea": _load_gps_nmea}
        gps = loader[present[0]](path, skipped, warnings)
        if gps is not None:
            gps = _check_overlap(gps, frames, warnings)

    obd_path = root / "obd.csv"
    obd = _load_obd(obd_path, skipped, warnings) if obd_path.is_file() else None

    for w in warnings:
        log.warning("%s", w)
    log.info(
        "loaded drive %s: %d frames, %s, %d skipped item(s)",
        root,
        len(frames),
        f"{len(gps)} GPS fixes from {gps.source}" if gps is not None else "no GPS",
        len(skipped),
    )
    return Drive(
        root=root,
        camera=camera,
        frames=frames,
        gps=gps,
        obd=obd,
        skipped=skipped,
        warnings=warnings,
    )
