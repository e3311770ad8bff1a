"""The names of a drive folder's files and of its simulated truth (docs/formats.md, *Drive
folder*, and docs/simulator.md, *Ground truth*): the one place the loaders, the simulator and the
evaluation spell them. A run folder's names are ``roadsurf.io.runfolder``'s.

    DRIVE/
      camera.yaml  frames.csv  frames/  gps.csv | gps.gpx | gps.nmea  obd.csv  [mask.png]
      truth/  poses.csv  height.tif  residual.tif  defects.geojson  distractors.geojson
              frame_labels.csv  scenario.json  [stereo_pair.json]  [mask.png]
"""

from __future__ import annotations

CAMERA_YAML = "camera.yaml"  # intrinsics, distortion, height, mount, readout, mask
FRAMES_CSV = "frames.csv"  # filename,timestamp_s (the drive's frames; not RUN/frames.csv)
FRAMES_DIR = "frames"  # the images frames.csv names
GPS_CSV = "gps.csv"
GPS_GPX = "gps.gpx"
GPS_NMEA = "gps.nmea"
GPS_FILES = (GPS_CSV, GPS_GPX, GPS_NMEA)  # priority order when several are present
OBD_CSV = "obd.csv"  # optional vehicle speed
MASK_PNG = "mask.png"  # the simulator's image mask beside camera.yaml (and in truth/)

TRUTH_DIR = "truth"  # simulated drives only
TRUTH_POSES_CSV = "poses.csv"  # true camera poses per frame
TRUTH_HEIGHT_TIF = "height.tif"  # true surface height (m)
TRUTH_RESIDUAL_TIF = "residual.tif"  # true height minus the smooth road (m, negative below)
TRUTH_DEFECTS_GEOJSON = "defects.geojson"  # true defects (RFC 7946)
TRUTH_DISTRACTORS_GEOJSON = "distractors.geojson"  # markings, shadows, stains
TRUTH_FRAME_LABELS_CSV = "frame_labels.csv"  # true per-frame defect labels
TRUTH_SCENARIO_JSON = "scenario.json"  # scenario, seed, CRS, every simulator parameter
TRUTH_STEREO_PAIR_JSON = "stereo_pair.json"  # photo pairs (simulate --stereo-pair) only
