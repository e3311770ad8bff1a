"""`roadsurf calibrate`: intrinsics and distortion from board photographs, camera height and
mount angles from a board on the road, written as the drive's ``camera.yaml`` plus a
``calibration.json`` report beside it."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from roadsurf.core.atomic import write_json_atomic, write_text_atomic
from roadsurf.io import drivefolder as df
from roadsurf.io.drive.frames import IMAGE_SUFFIXES
from roadsurf.reconstruction.calibration.board import BoardSpec, parse_board
from roadsurf.reconstruction.calibration.detect import read_gray
from roadsurf.reconstruction.calibration.errors import CalibrationError
from roadsurf.reconstruction.calibration.intrinsics import (
    CalibrationLimits,
    Intrinsics,
    calibrate_images,
)
from roadsurf.reconstruction.calibration.mount import Mount, mount_from_ground


@dataclass
class CalibrationResult:
    intrinsics: Intrinsics
    mount: Mount | None
    camera_yaml: Path
    report_json: Path
    lines: list[str]  # what the command prints


def expand_images(paths: Sequence[Path]) -> list[Path]:
    """Image files of ``paths``; a folder stands for its image files, sorted by name."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out += sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
        else:
            out.append(p)
    return out


# camera.yaml keys a calibration does not measure: with --overwrite they are carried over from
# the camera.yaml being replaced (a rolling shutter's readout time, the image mask, the GPS
# antenna's place on the vehicle)
CARRIED_KEYS = ("readout_s", "mask", "gps_antenna_m")


def carried_over(yaml_path: Path) -> dict[str, object]:
    """The ``CARRIED_KEYS`` (and ``fps``) of an existing camera.yaml, as written there; {} when
    it does not exist or cannot be read as a mapping."""
    import yaml

    try:
        data = yaml.safe_load(yaml_path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return {}
    if not isinstance(data, dict):
        return {}
    return {k: data[k] for k in (*CARRIED_KEYS, "fps") if data.get(k) is not None}


def camera_yaml_text(
    intr: Intrinsics,
    mount: Mount | None,
    fps: float | None,
    height_m: float | None,
    note: str,
    extra: dict[str, object] | None = None,
) -> str:
    """camera.yaml in the drive format (docs/formats.md); mount_* keys only with a mount;
    ``extra`` keys (``CARRIED_KEYS``) appended as given."""
    K, d = intr.K, intr.dist
    lines = [
        f"# {note}",
        "model: pinhole",
        f"width: {intr.width}",
        f"height: {intr.height}",
        f"fx: {K[0, 0]:.6f}",
        f"fy: {K[1, 1]:.6f}",
        f"cx: {K[0, 2]:.6f}",
        f"cy: {K[1, 2]:.6f}",
        "dist: [" + ", ".join(f"{v:.9g}" for v in d) + "]  # k1, k2, p1, p2, k3",
    ]
    h = mount.height_m if mount is not None else height_m
    if h is None:
        lines.append("# height_m: MISSING: camera height above the road (m); use --ground")
    else:
        lines.append(f"height_m: {h:.5f}")
    if fps is None:
        lines.append("# fps: MISSING: frame rate (Hz); use --fps")
    else:
        lines.append(f"fps: {fps:g}")
    if mount is not None:
        lines += [
            f"mount_pitch_deg: {mount.pitch_deg:.4f}",
            f"mount_roll_deg: {mount.roll_deg:.4f}",
            f"mount_yaw_deg: {mount.yaw_deg:.4f}",
        ]
    for k, v in (extra or {}).items():
        lines.append(f"{k}: {v}  # carried over from the camera.yaml this one replaced")
    return "\n".join(lines) + "\n"


def _report(
    spec: BoardSpec,
    ground_spec: BoardSpec,
    intr: Intrinsics,
    mount: Mount | None,
    ground: Path | None,
    limits: CalibrationLimits,
) -> dict[str, Any]:
    out: dict[str, Any] = {
        "board": spec.text,
        "image_size": [intr.width, intr.height],
        "rms_reprojection_px": intr.rms_px,
        "limits": vars(limits),
        "images_used": len(intr.per_image_rms_px),
        "images_skipped": intr.skipped,
        "per_image": [
            {
                "image": n,
                "rms_px": e,
                "corners": intr.n_corners[n],
                "board_tilt_deg": intr.tilts_deg[n],
            }
            for n, e in intr.per_image_rms_px.items()
        ],
        "coverage": intr.coverage,
        "std_intrinsics": intr.std_intrinsics,
        "K": intr.K,
        "dist": intr.dist,
    }
    if mount is not None:
        out["ground"] = {"image": str(ground), "board": ground_spec.text, **vars(mount)}
    return out


def calibrate_command(
    images: Sequence[Path],
    board: str,
    out: Path,
    ground: Path | None = None,
    ground_board: str | None = None,
    board_thickness_m: float = 0.0,
    fps: float | None = None,
    height_m: float | None = None,
    max_rms_px: float = 1.0,
    min_images: int = 5,
    overwrite: bool = False,
) -> CalibrationResult:
    """Calibrate and write ``out/camera.yaml`` and ``out/calibration.json``.

    Raises CalibrationError / BoardSpecError (one line) on a bad board, too few or poor images,
    or an existing camera.yaml without ``overwrite``."""
    spec = parse_board(board)
    gspec = parse_board(ground_board) if ground_board else spec
    if ground is not None and height_m is not None:
        raise CalibrationError("give either --ground or --height-m, not both.")
    out = Path(out)
    yaml_path, json_path = out / df.CAMERA_YAML, out / "calibration.json"
    if yaml_path.exists() and not overwrite:
        raise CalibrationError(f"{yaml_path} exists. Pass --overwrite to replace it.")
    paths = expand_images(images)
    if not paths:
        raise CalibrationError("no images given. Pass board photographs (files or a folder).")
    limits = CalibrationLimits(min_images=min_images, max_rms_px=max_rms_px)
    intr = calibrate_images(paths, spec, limits)
    mount = None
    if ground is not None:
        gray = read_gray(Path(ground))
        if (gray.shape[1], gray.shape[0]) != (intr.width, intr.height):
            raise CalibrationError(
                f"{ground}: the --ground image is {gray.shape[1]}x{gray.shape[0]} px, the board "
                f"photographs {intr.width}x{intr.height}. Use the same camera and resolution."
            )
        mount = mount_from_ground(gray, gspec, intr.K, intr.dist, board_thickness_m)
    note = (
        f"roadsurf calibrate: {len(intr.per_image_rms_px)} images of {spec.text}, RMS "
        f"reprojection error {intr.rms_px:.3f} px (details in calibration.json)"
    )
    # what calibration does not measure stays as the replaced camera.yaml had it
    old = carried_over(yaml_path) if yaml_path.exists() else {}
    if fps is None and "fps" in old:
        fps = float(old["fps"])  # type: ignore[arg-type]
    extra = {k: old[k] for k in CARRIED_KEYS if k in old}
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(yaml_path, camera_yaml_text(intr, mount, fps, height_m, note, extra))
    write_json_atomic(json_path, _report(spec, gspec, intr, mount, ground, limits))
    K = intr.K
    lines = [
        f"Used {len(intr.per_image_rms_px)} of {len(paths)} images; RMS reprojection error "
        f"{intr.rms_px:.3f} px (limit {max_rms_px:g}); board coverage {intr.coverage:.0%}.",
        f"fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f} px; dist "
        + " ".join(f"{v:.5f}" for v in intr.dist),
    ]
    if intr.skipped:
        lines.append(f"Skipped {len(intr.skipped)}: " + ", ".join(
            f"{n} ({why})" for n, why in intr.skipped.items()))  # fmt: skip
    if mount is not None:
        lines.append(
            f"Mount: height {mount.height_m:.4f} m, pitch {mount.pitch_deg:.2f}°, roll "
            f"{mount.roll_deg:.2f}°, yaw {mount.yaw_deg:.2f}° (board fit {mount.rms_px:.2f} px)."
        )
    missing = [k for k, v in (("height_m", mount or height_m), ("fps", fps)) if v is None]
    if missing:
        lines.append(
            f"camera.yaml lacks {', '.join(missing)}: add them (or pass --ground / --fps) "
            "before using it for a drive."
        )
    if extra or "fps" in old:
        kept = [*extra, *(["fps"] if "fps" in old and fps == old.get("fps") else [])]
        lines.append(f"Kept {', '.join(kept)} from the camera.yaml replaced.")
    lines.append(f"Wrote {yaml_path} and {json_path}")
    return CalibrationResult(intr, mount, yaml_path, json_path, lines)
