"""``load_drive``: load and validate a drive folder, one reader per file of the format.

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
- Warnings (``Drive.warnings``, also logged): no GPS log, no valid fix, or a GPS log that does
  not overlap the frame times (then ``gps=None``: mapping runs in a local frame; these say
  ``NO GEOREFERENCE``), partial overlap, images in frames/ that frames.csv does not list, several
  GPS logs present, binary data skipped in NMEA, heights that are not ellipsoidal, GPS fixes that
  jump impossibly far (rejected), a static receiver, OBD speed that disagrees with the GPS ground
  speed (km/h: converted; otherwise the OBD log is ignored). See ``checks``.
"""

from __future__ import annotations

import logging
from pathlib import Path

from roadsurf.core.errors import DriveFormatError
from roadsurf.io import drivefolder as df
from roadsurf.io.drive.camera_yaml import load_camera
from roadsurf.io.drive.checks import check_frame_rate, check_obd_vs_gps, check_static
from roadsurf.io.drive.frames import load_frames
from roadsurf.io.drive.gps import check_overlap, load_gps_csv
from roadsurf.io.drive.gpx import load_gps_gpx
from roadsurf.io.drive.maskfile import mask_warning
from roadsurf.io.drive.nmea import load_gps_nmea
from roadsurf.io.drive.obd import check_obd_overlap, load_obd
from roadsurf.io.drive.types import FORMAT_HINT, NO_GEOREF, Drive, GpsTrack, Skipped

log = logging.getLogger(__name__)

GPS_FILES = df.GPS_FILES  # priority order when several are present


def load_drive(root: str | Path, check_images: bool = True) -> Drive:
    """Load and validate a drive folder. See ``roadsurf.io.drive`` and docs/formats.md for the
    contract."""
    root = Path(root)
    if not root.is_dir():
        raise DriveFormatError(f"{root}: drive folder not found. {FORMAT_HINT}")
    skipped: list[Skipped] = []
    warnings: list[str] = []
    camera = load_camera(root / df.CAMERA_YAML)
    if camera.mask is not None and (w := mask_warning(camera.mask)):
        warnings.append(w)
    frames = load_frames(root, camera, check_images, skipped, warnings)
    check_frame_rate(root / df.FRAMES_CSV, frames, camera.fps, warnings)

    present = [name for name in GPS_FILES if (root / name).is_file()]
    gps: GpsTrack | None = None
    if not present:
        warnings.append(f"{root}: no GPS log (gps.csv, gps.gpx or gps.nmea); {NO_GEOREF}.")
    else:
        if len(present) > 1:
            warnings.append(f"{root}: several GPS logs {present}; using {present[0]}.")
        path = root / present[0]
        loader = {df.GPS_CSV: load_gps_csv, df.GPS_GPX: load_gps_gpx, df.GPS_NMEA: load_gps_nmea}
        gps = loader[present[0]](path, skipped, warnings)
        if gps is not None:
            gps = check_overlap(gps, frames, warnings)

    obd_path = root / df.OBD_CSV
    obd = load_obd(obd_path, skipped, warnings) if obd_path.is_file() else None
    if obd is not None:
        obd = check_obd_overlap(obd_path, obd, frames, warnings)
    # A static receiver says nothing about the speed: then OBD is not judged against it.
    if gps is not None and not check_static(gps, frames, warnings) and obd is not None:
        obd = check_obd_vs_gps(obd_path, obd, gps, warnings)

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
