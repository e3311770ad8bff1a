"""The drive format (input contract) and its loader.

```
DRIVE/
  camera.yaml    # model: pinhole, width, height, fx, fy, cx, cy, dist: [k1,k2,p1,p2,k3] (optional),
                 # height_m (camera height above road, metres), fps
  frames/        # images (jpg/png); sorted name order = capture order
  frames.csv     # header: filename,timestamp_s
  gps.csv        # header: timestamp_s,lat,lon[,alt_m][,hdop][,sigma_m][,fix_quality]
                 # (or gps.gpx, or gps.nmea)
  obd.csv        # optional, header: timestamp_s,speed_mps
  truth/         # optional, written by the simulator only; ignored by the loader
```
See docs/formats.md. The loader validates everything; problems the run can live with (an
unreadable image, a bad GPS row) are skipped and recorded in ``Drive.skipped``; problems it
cannot live with raise ``DriveFormatError`` naming the file and line and saying what to do.

Modules, imported only downward: ``types``, ``textfile`` (UTF-8 reading) <- ``csvrows``,
``camera_yaml``, ``images``, ``checks`` (plausibility between inputs) <- ``frames``, ``gps`` (+
``gpx`` with gpxpy, ``nmea`` with pynmea2), ``obd`` <- ``loader``. They never import this facade.

Heights: ``GpsTrack.alt_m`` with its vertical datum in ``GpsTrack.alt_datum`` (docs/formats.md).
"""

from roadsurf.core.camera import Camera
from roadsurf.io.drive.images import GrayFrames, read_gray, read_image
from roadsurf.io.drive.loader import load_drive
from roadsurf.io.drive.types import Drive, Frame, GpsTrack, ObdLog, Skipped, along_track_m

__all__ = [
    "Camera",
    "Drive",
    "Frame",
    "GpsTrack",
    "GrayFrames",
    "ObdLog",
    "Skipped",
    "along_track_m",
    "load_drive",
    "read_gray",
    "read_image",
]
