"""A defect cut at the antimeridian (RFC 7946 §3.1.9) is one outline again in the viewer."""

import numpy as np
import shapely

from roadsurf.core.geometry import EnuReference
from roadsurf.io.formats import feature, polygon_geometry, split_at_antimeridian
from roadsurf.viewer.runfolder import _joined_enu, _ring_enu


def test_defect_cut_at_the_antimeridian_joins_in_enu() -> None:
    d = 1e-5  # about 1 m
    ring = np.array(
        [[180 - d, -16.8], [-180 + d, -16.8], [-180 + d, -16.8 + d], [180 - d, -16.8 + d]]
    )
    g = split_at_antimeridian(feature(polygon_geometry(ring), {})["geometry"])
    assert g["type"] == "MultiPolygon"
    ref = EnuReference(-16.8, 180.0, 10.0)
    enu = _joined_enu([p[0] for p in g["coordinates"]], True, ref)
    whole = shapely.Polygon(_ring_enu(np.vstack([ring, ring[:1]]), True, ref))
    joined = shapely.Polygon(enu)
    assert joined.is_valid and abs(joined.area / whole.area - 1) < 0.01
    assert joined.symmetric_difference(whole).area < 0.01 * whole.area
