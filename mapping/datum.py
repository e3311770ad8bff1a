"""The vertical datum of the heights the mapping stage exports (cloud.ply z, trajectory heights,
report.json): named in every output that carries heights.

With GPS altitude the map's heights follow the GPS heights (the loader names their datum in
``GpsTrack.alt_datum``; gps.csv altitudes are WGS84 ellipsoidal heights). Without GPS altitude
the pose graph pins the first frame's camera centre at height 0 (local heights)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from roadsurf.mapping.config import MappingConfig

if TYPE_CHECKING:
    from roadsurf.io.drive import Drive

GPS_DATUM_DEFAULT = "WGS84 ellipsoidal height"  # gps.csv alt_m (and the loaders' output)
LOCAL_DATUM = "local: metres above the first frame's camera centre (no GPS altitude)"
# surface.tif and residual_m: heights relative to the road, whatever the absolute datum
RESIDUAL_DATUM = "relative: metres above the locally fitted road surface (negative below)"


def vertical_datum(cfg: MappingConfig, drive: Drive, georeferenced: bool = True) -> str:
    """Datum of the exported absolute heights for this drive and config; ``georeferenced``
    False (no GPS reference, e.g. GPS outside the frame times) gives the local datum."""
    g = drive.gps
    if not georeferenced or g is None or len(g) == 0:
        return LOCAL_DATUM
    if not bool(np.isfinite(np.asarray(g.alt_m, float)).any()):
        return LOCAL_DATUM
    datum = str(getattr(g, "alt_datum", None) or GPS_DATUM_DEFAULT)
    if not cfg.use_gps_altitude:
        # the ENU origin takes the altitude of the fix nearest the middle frame
        # (pose_gps.enu_reference); the first camera sits at its height
        return f"local: the first frame's camera centre at the reference fix's altitude ({datum})"
    return datum
