"""Guards of ``roadsurf run`` around the stages: which drive a run folder belongs to, a run
in which no pair reconstructs (no 3D result: refused, never reported as "no defect"), and a
warning when many pairs fail (the map has gaps there).

``RUN/run.json`` records the drive a run folder was made from: its resolved path and a digest of
its small top-level files (camera.yaml, frames.csv, gps.*, obd.csv). A run of another drive into
that folder is refused unless ``--overwrite``; the same drive (same path, or a moved copy with
the same files) resumes, each stage deciding from its own fingerprints what to recompute.
"""

from __future__ import annotations

import hashlib
import logging
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any

from roadsurf.core.atomic import read_json, write_json_atomic
from roadsurf.core.errors import ConfigError, RoadsurfError
from roadsurf.io import drivefolder as df
from roadsurf.io import runfolder as rf
from roadsurf.reconstruction.types import STATUS_NO_MOTION

if TYPE_CHECKING:
    from roadsurf.io.drive import Drive
    from roadsurf.reconstruction.config import ReconstructionConfig
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)

RUN_JSON = rf.RUN_JSON
_HASH_MAX_BYTES = 16 * 1024 * 1024  # larger top-level files are identified by size and mtime


# a warning when more than this share of the pairs failed (−): an occasional failure (a stop,
# a blurred frame) leaves a gap GPS bridges; beyond a tenth the map and the defect list have
# holes the user must know of
FAILED_PAIRS_WARN_SHARE = 0.1


class NoReconstructionError(RoadsurfError):
    """Pairs were attempted and none reconstructed: the run has no 3D result to measure."""


# =========================================================================== drive identity


def drive_identity(drive_dir: str | Path) -> dict[str, Any]:
    """``{"drive": resolved path, "content": digest, "files": {name: digest}}`` over the drive's
    top-level files (camera.yaml, frames.csv, GPS and OBD logs: their bytes) and folders (the
    images: names and sizes; the reconstruction keys each pair by its image files itself)."""
    d = Path(drive_dir).resolve()
    files: dict[str, str] = {}
    for p in sorted(d.iterdir()) if d.is_dir() else []:
        if p.is_dir():  # image folders: names and sizes (a copied drive keeps them)
            sizes = sorted((f.name, f.stat().st_size) for f in p.iterdir() if f.is_file())
            files[p.name + "/"] = hashlib.sha256(repr(sizes).encode()).hexdigest()[:16]
            continue
        if not p.is_file():
            continue
        st = p.stat()
        if st.st_size <= _HASH_MAX_BYTES:
            files[p.name] = hashlib.sha256(p.read_bytes()).hexdigest()[:16]
        else:
            files[p.name] = f"size={st.st_size},mtime_ns={st.st_mtime_ns}"
    content = hashlib.sha256(repr(sorted(files.items())).encode()).hexdigest()[:16]
    return {"drive": str(d), "content": content, "files": files}


def check_out_folder(drive_dir: Path, out: Path) -> None:
    """The run never writes inside the drive (its frames.csv would be overwritten by the run's
    frame labels), into an existing file, into another drive's folder, nor into a folder that
    is not a run and holds a name the run writes (the user's file would be replaced)."""
    d, o = drive_dir.resolve(), out.resolve()
    if o == d or d in o.parents:
        raise ConfigError(
            f"--out {out} is inside the drive folder {drive_dir}: the run would overwrite the "
            "drive's own files (frames.csv). Choose an output folder outside the drive, e.g. "
            f"--out {d.parent / (d.name + '_run')}"
        )
    if o.exists() and not o.is_dir():
        raise ConfigError(f"--out {out} is an existing file, not a folder. Choose another --out.")
    if not o.is_dir() or rf.is_run_folder(o):
        return  # new, or a run folder (claim_run_folder checks whose)
    held = {p.name for p in o.iterdir()}
    drive_files = sorted(held & {df.CAMERA_YAML, df.FRAMES_DIR, *df.GPS_FILES})
    if drive_files:
        raise ConfigError(
            f"--out {out} holds a drive ({', '.join(drive_files)}), not a roadsurf run: the run "
            "would overwrite its frames.csv with the run's frame labels. Choose an empty or "
            f"new folder, e.g. --out {o.parent / (o.name + '_run')}"
        )
    # live.rrd: `run --rerun`'s own stream (a run refused here after its first stage may
    # have left one); the lock file: a run stopped before it wrote run.json
    clash = sorted(held & (rf.artifact_names() - {rf.LIVE_RRD, rf.RUN_LOCK}))
    if clash:
        raise ConfigError(
            f"--out {out} is not a roadsurf run folder (no {rf.RUN_JSON}) but holds "
            f"{', '.join(clash[:6])}{' ...' if len(clash) > 6 else ''}, which the run would "
            "overwrite. Move them, or choose an empty or new folder for --out."
        )


def claim_run_folder(drive_dir: str | Path, out: Path, overwrite: bool) -> dict[str, Any]:
    """Refuse ``out`` when it holds the run of another drive (unless ``overwrite``), then record
    this drive in ``out/run.json``. Returns the recorded identity."""
    ident = drive_identity(drive_dir)
    recorded = _recorded_drive(out)
    if recorded is not None and not overwrite:
        same_path = recorded.get("drive") == ident["drive"]
        same_content = recorded.get("content") == ident["content"]
        if not same_path and not same_content:
            raise ConfigError(
                f"--out {out} holds the run of another drive ({recorded.get('drive')}); this "
                f"drive is {ident['drive']}. Its cached pairs, poses and map would be mixed "
                "with this drive's: use --overwrite to replace that run, or choose another --out."
            )
        if not same_path:
            log.info("run folder %s: drive moved from %s (same files)", out, recorded.get("drive"))
        elif not same_content:
            changed = sorted(
                k
                for k in set(ident["files"]) | set(recorded.get("files") or {})
                if ident["files"].get(k) != (recorded.get("files") or {}).get(k)
            )
            log.info("run folder %s: drive files changed since the last run: %s", out, changed)
    write_json_atomic(out / RUN_JSON, ident)
    return ident


def _recorded_drive(out: Path) -> dict[str, Any] | None:
    """The drive recorded in ``out`` (run.json; for an older run, report.json's drive path)."""
    for name, key in ((RUN_JSON, None), (rf.REPORT_JSON, "drive")):
        path = out / name
        if not path.is_file():
            continue
        try:
            data = read_json(path)
        except (OSError, ValueError):
            continue  # unreadable: the run rewrites it
        if not isinstance(data, dict):
            continue
        if key is None and isinstance(data.get("drive"), str):
            return data
        if key is not None and isinstance(data.get(key), str):
            return {"drive": data[key], "content": None}
    return None


# =========================================================================== no 3D result

# what to check for each failure status of a pair
_HINTS = {
    "unreadable_frame": "the image files (unreadable or truncated)",
    "too_few_features": "the images (exposure, blur) and reconstruction.features in --config",
    "too_few_matches": "reconstruction.min_matches in --config ({min_matches}) and the overlap "
    "between consecutive frames (frame rate, speed)",
    "no_overlap": "reconstruction.min_matches ({min_matches}) and min_overlap in --config, and "
    "the frame rate (consecutive frames must overlap)",
    "not_near_planar": "that the camera looks at the road, and the intrinsics in camera.yaml",
    "geometry_failed": "the intrinsics (fx, fy, cx, cy, dist) in camera.yaml",
    "scale_failed": "height_m in camera.yaml ({height_m} m; metres above the road, e.g. 1.1)",
    STATUS_NO_MOTION: "that the vehicle moved between the frames (these pairs show one view)",
}


# frames darker than this (median DN) are named as the likely cause when no pair reconstructs:
# an eighth of the range; the fault battery's drive failed at a mean of 12 DN and worked at 25
DARK_FRAMES_DN = 32


def _median_brightness(drive: Drive, n: int = 5) -> float | None:
    """Median grey level (DN) of up to ``n`` frames spread over the drive; None if unreadable."""
    import numpy as np

    from roadsurf.io.drive import read_gray

    frames = drive.frames
    if not frames:
        return None
    pick = sorted({round(k) for k in np.linspace(0, len(frames) - 1, min(n, len(frames)))})
    meds = []
    for k in pick:
        try:
            meds.append(float(np.median(read_gray(frames[k])[::4, ::4])))
        except (RoadsurfError, OSError, ValueError):
            continue
    return float(np.median(meds)) if meds else None


def check_reconstruction(
    pairs: list[PairResult], drive: Drive, rec_cfg: ReconstructionConfig, out: Path
) -> None:
    """Raise NoReconstructionError when pairs were attempted and none is ok, with the failure
    counts per reason and what to check. A camera height implausible for a vehicle (above
    10 m, e.g. cm typed for m) is named whatever the reasons."""
    if not pairs or any(p.ok for p in pairs):
        return
    counts = Counter(p.status for p in pairs)
    fmt = {
        "min_matches": getattr(rec_cfg, "min_matches", "?"),
        "height_m": drive.camera.height_m,
    }
    reasons = ", ".join(f"{s}: {n}" for s, n in counts.most_common())
    checks = [_HINTS.get(s, f"the cause of '{s}'").format(**fmt) for s, _ in counts.most_common()]
    h = float(drive.camera.height_m)
    if not 0.1 <= h <= 10.0:
        checks.insert(
            0,
            f"height_m in camera.yaml ({h:g} m is no vehicle camera height: metres expected, "
            "e.g. 1.1)",
        )
    ro = float(drive.camera.readout_s)
    if ro > 0:  # a frame's rows are read while the vehicle moves: less road in common
        checks.append(
            f"the rolling shutter (camera.yaml readout_s {1000 * ro:.0f} ms): a frame's rows "
            f"are read over readout_s x speed of travel ({15 * ro:.2f} m at 15 m/s), which "
            "shrinks the road two frames share; a higher frame rate or a lower speed leaves more"
        )
    dark = _median_brightness(drive)
    if dark is not None and dark < DARK_FRAMES_DN:
        checks.insert(
            0,
            f"the exposure: the frames are very dark (median {dark:.0f} DN of 255), too dark for "
            "the road's texture to give features; brighten them (exposure, gain) or drop the "
            "night frames",
        )
    checks = list(dict.fromkeys(checks))
    first = next((p for p in pairs if p.status == counts.most_common(1)[0][0]), pairs[0])
    example = f"{first.frame_a} -> {first.frame_b}: {first.reason}" if first.reason else ""
    raise NoReconstructionError(
        f"no pair reconstructed: 0 of {len(pairs)} pairs ok ({reasons}); the run has no 3D "
        f"result. Check {'; '.join(checks)}."
        + (f" E.g. {example}." if example else "")
        + f" Details per pair: {out / rf.PAIRS_DIR}"
    )


def pair_failures_warning(pairs: list[PairResult], out: Path) -> str | None:
    """A warning when more than ``FAILED_PAIRS_WARN_SHARE`` of the pairs failed: how many, per
    reason, the frames of the longest run of failures and one reason in full; else None."""
    still = [p for p in pairs if p.status == STATUS_NO_MOTION]
    if still:  # not a failure: the frames of a stop are held together, the road is mapped
        log.info(
            "%d pair(s) where the vehicle stood still (%s -> %s, ...): no depth there, the "
            "frames are held in place", len(still), still[0].frame_a, still[0].frame_b,
        )  # fmt: skip
    failed = [i for i, p in enumerate(pairs) if not p.ok and p.status != STATUS_NO_MOTION]
    if not pairs or len(failed) <= FAILED_PAIRS_WARN_SHARE * len(pairs):
        return None
    counts = Counter(pairs[i].status for i in failed)
    # the longest run of consecutive failed pairs: where the map's largest hole is
    best, start = (0, 0), failed[0]
    for prev, i in zip([failed[0] - 1, *failed[:-1]], failed, strict=True):
        if i != prev + 1:
            start = i
        if i + 1 - start > best[1] - best[0]:
            best = (start, i + 1)
    a, b = pairs[best[0]], pairs[best[1] - 1]
    first = pairs[failed[0]]
    msg = (
        f"{len(failed)} of {len(pairs)} pairs failed "
        f"({', '.join(f'{s}: {n}' for s, n in counts.most_common())}); their frames have no 3D "
        f"surface and no defect can be found there. Longest run: {best[1] - best[0]} pairs, "
        f"{a.frame_a} -> {b.frame_b}. E.g. {first.frame_a} -> {first.frame_b}: {first.reason}. "
        f"Details per pair: {out / rf.PAIRS_DIR}"
    )
    log.warning(msg)
    return msg


def static_pixels(drive: Drive, out: Path) -> str | None:
    """A warning (added to ``drive.warnings``, logged, returned) and RUN/suggested_mask.png
    when the frames hold pixels that never change (``io.drive.staticpx``) that camera.yaml's
    mask does not already name; else None (and an old suggestion in ``out`` is removed).

    A black border in every frame joins the camera's mask on the way
    (``staticpx.static_pixels_of_drive``)."""
    import cv2

    from roadsurf.core.atomic import atomic_path
    from roadsurf.io.drive.staticpx import static_pixels_of_drive as find_static

    path = Path(out) / rf.SUGGESTED_MASK_PNG
    own_mask = drive.camera.mask is not None  # camera.yaml's, before a black border joins it
    sp = find_static(drive)
    cam = drive.camera
    if sp is not None and cam.mask is not None:  # what the mask leaves, off its edge's blur
        sp = sp.outside(cam.mask.eroded(sp.grow_px))
    if sp is None or not sp.static.any():
        path.unlink(missing_ok=True)
        return None
    suggestion = sp.suggested_mask()
    if cam.mask is not None:  # the suggestion extends the user's own mask
        suggestion[~cam.mask.usable] = 0
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), suggestion):
            log.warning("%s: could not be written", path)
    msg = sp.warning(str(path), outside_mask=own_mask)
    log.warning(msg)
    drive.warnings.append(msg)
    return msg
