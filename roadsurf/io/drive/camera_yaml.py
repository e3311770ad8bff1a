"""camera.yaml of a drive: parse and validate it into a ``Camera``.

Errors name the file and the line of the offending key (from the YAML node marks)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import yaml

from roadsurf.core.camera import Camera
from roadsurf.core.errors import DriveFormatError
from roadsurf.io.drive.maskfile import load_mask
from roadsurf.io.drive.textfile import read_text
from roadsurf.io.drive.types import FORMAT_HINT

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
    "mount_pitch_deg": (float, False),
    "mount_roll_deg": (float, False),
    "mount_yaw_deg": (float, False),
    "readout_s": (float, False),
    "gps_antenna_m": (tuple, False),  # [forward, left, up] (m), mapping.antenna
    "mask": (Path, False),  # image of the pixels to ignore (io.drive.maskfile)
}
MAX_CAMERA_HEIGHT_M = 10.0  # above this, height_m is a unit mistake, not a vehicle mount
_MOUNT_KEYS = ("mount_pitch_deg", "mount_roll_deg", "mount_yaw_deg")
_MOUNT_LIMIT_DEG = {"mount_pitch_deg": 90.0, "mount_roll_deg": 45.0, "mount_yaw_deg": 45.0}
MAX_ANTENNA_M = 10.0  # a GPS antenna further than this from the camera is a unit mistake
MAX_READOUT_S = 0.2  # readout_s is in [0, this): rolling shutters read a frame in 5-50 ms


# field of view (deg) a camera.yaml focal length may give over its image side: beyond the
# widest rectilinear lenses (a fisheye needs another model), narrower than any road camera
MAX_FOV_DEG = 150.0
MIN_FOV_DEG = 2.0


def _yaml_key_lines(text: str) -> dict[str, int]:
    """1-based line number of each top-level key of a YAML mapping (for error messages)."""
    try:
        node = yaml.compose(text)
    except yaml.YAMLError:
        return {}
    if not isinstance(node, yaml.MappingNode):
        return {}
    return {str(k.value): k.start_mark.line + 1 for k, _ in node.value if hasattr(k, "value")}


def _is_finite_number(v: object) -> bool:
    """A YAML int or float that is finite as a float (a 400-digit integer is not)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return math.isfinite(float(v))
    except OverflowError:
        return False


def load_camera(path: Path) -> Camera:
    """Parse and validate camera.yaml. Raises DriveFormatError naming the file and line."""
    if not path.is_file():
        raise DriveFormatError(
            f"{path}: camera.yaml not found. Every drive needs one with keys model, width, "
            f"height, fx, fy, cx, cy, height_m, fps (dist optional). {FORMAT_HINT}"
        )
    text = read_text(path)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        at = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        msg = " ".join(str(e).split())  # one line
        raise DriveFormatError(
            f"{at}: camera.yaml is not valid YAML ({msg}). Fix the syntax."
        ) from e
    except (ValueError, OverflowError, RecursionError) as e:
        # PyYAML builds some scalars itself: a date like 2024-13-45 raises ValueError, deep
        # nesting RecursionError. Neither is a camera.yaml value.
        raise DriveFormatError(
            f"{path}: camera.yaml has a value that cannot be read ({type(e).__name__}: {e}). "
            f"Fix the file; the values are plain numbers. {FORMAT_HINT}"
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
            if not _is_finite_number(v):
                raise DriveFormatError(
                    f"{where(key)}: camera.yaml '{key}' must be a number, got {v!r}."
                )
            v = float(v)
            if key in ("fx", "fy", "height_m", "fps") and v <= 0:
                raise DriveFormatError(f"{where(key)}: camera.yaml '{key}' must be > 0, got {v!r}.")
            if key == "height_m" and v > MAX_CAMERA_HEIGHT_M:
                raise DriveFormatError(
                    f"{where(key)}: camera.yaml 'height_m' = {v!r} m: a vehicle camera sits "
                    f"at most {MAX_CAMERA_HEIGHT_M:g} m above the road. It is in metres "
                    f"(cm typed for m? {v!r} cm = {v / 100:g} m)."
                )
            if key in _MOUNT_LIMIT_DEG and abs(v) > _MOUNT_LIMIT_DEG[key]:
                lim = _MOUNT_LIMIT_DEG[key]
                raise DriveFormatError(
                    f"{where(key)}: camera.yaml '{key}' = {v!r} is outside [-{lim:g}, {lim:g}] "
                    "degrees. Mount angles are in degrees (run `roadsurf calibrate --ground`)."
                )
            if key == "readout_s" and not 0.0 <= v < MAX_READOUT_S:
                raise DriveFormatError(
                    f"{where(key)}: camera.yaml 'readout_s' = {v!r} is outside "
                    f"[0, {MAX_READOUT_S:g}) s. It is the rolling shutter's readout time (first "
                    "to last row) in seconds, typically 0.005-0.05 (ms typed for s?); 0 or no "
                    "key = global shutter."
                )
        elif tp is Path:
            v = load_mask(v, path, where(key), vals["width"], vals["height"])
        elif tp is str:
            if not isinstance(v, str) or v.strip().lower() != "pinhole":
                raise DriveFormatError(
                    f"{where(key)}: camera.yaml 'model' must be 'pinhole' (with OpenCV 'dist' "
                    f"coefficients for lens distortion), got {v!r}."
                )
            v = "pinhole"
        elif key == "gps_antenna_m":
            if (
                not isinstance(v, (list, tuple))
                or len(v) != 3
                or not all(_is_finite_number(x) and abs(float(x)) <= MAX_ANTENNA_M for x in v)
            ):
                raise DriveFormatError(
                    f"{where(key)}: camera.yaml 'gps_antenna_m' must be 3 numbers [forward, "
                    "left, up]: the GPS antenna's position from the camera centre in metres, "
                    f"each within ±{MAX_ANTENNA_M:g} m (cm typed for m?), got {v!r}. Measure it "
                    "on the vehicle (tape, or the survey of the rig)."
                )
            v = tuple(float(x) for x in v)
        elif key == "dist":
            if v is None:
                v = []
            if (
                not isinstance(v, (list, tuple))
                or len(v) not in (0, 4, 5)
                or not all(_is_finite_number(x) for x in v)
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
        mount_deg=(
            tuple(float(vals.get(k, 0.0)) for k in _MOUNT_KEYS)  # type: ignore[arg-type]
            if any(k in vals for k in _MOUNT_KEYS)
            else None
        ),
        readout_s=float(vals.get("readout_s", 0.0)),
        mask=vals.get("mask"),
        gps_antenna_m=vals.get("gps_antenna_m"),
    )
    if cam.readout_s * cam.fps > 1.0 + 1e-9:
        raise DriveFormatError(
            f"{where('readout_s')}: camera.yaml 'readout_s' = {cam.readout_s!r} s is longer than "
            f"one frame period (1 / fps = {1.0 / cam.fps:.4g} s): a rolling-shutter sensor reads "
            "a frame before it starts the next. Check readout_s and fps."
        )
    if not (0 <= cam.cx <= cam.width and 0 <= cam.cy <= cam.height):
        raise DriveFormatError(
            f"{path}: principal point (cx, cy) = ({cam.cx}, {cam.cy}) lies outside the "
            f"{cam.width}x{cam.height} image. Check camera.yaml (pixels, origin top-left)."
        )
    for key, f, size in (("fx", cam.fx, cam.width), ("fy", cam.fy, cam.height)):
        fov = 2.0 * math.degrees(math.atan(0.5 * size / f))
        if not MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
            raise DriveFormatError(
                f"{where(key)}: camera.yaml '{key}' = {f:g} px gives a {fov:.1f}° field of view "
                f"over the image's {size} px; a pinhole camera with OpenCV distortion spans "
                f"{MIN_FOV_DEG:g}-{MAX_FOV_DEG:g}°. Focal lengths are in pixels (mm typed for "
                "px? f_px = f_mm / pixel pitch in mm); `roadsurf calibrate` measures them."
            )
    return cam
