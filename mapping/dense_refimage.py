"""Which image of a pair the dense matching measures on (``MappingConfig.dense_match_image``).

The dense heights are measured on the pixel grid of one image (the reference): its windows set
the surface's resolution on the road. A camera tilted forward on a forward drive sees the
pair's common ground in the upper, far part of image a and in the lower, near part of image b,
whose pixels cover less road (at 45° and 0.4 m between shots about 20-40 % less along the
track). "nearer" matches on the image whose camera is nearer to the common ground; a nadir
camera is as near from both and keeps image a. Measured on the tilted drives: potholes read
0.3-1.3 mm less shallow at 45° (docs/mapping.md, *Reference image*).

Measured on image b, the sides of the drive's two-view part are image b's own first and last
columns (image a, further back, sees the road wider there), and its far corners lie next to
image a's top row. The left-right check keeps those columns since the sweep's pixels outside
the overlap start from their swept neighbours (``dense.parallax._init``): before, the reverse
match there started 2-13 px off and 2-4 columns a side were refused.

With a rolling shutter the pair measured on image b has b's timestamp first: its frame time
difference is negative, and ``dense.rolling`` places each row along the pair's motion from b
back to a.
"""

from __future__ import annotations

import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.fits import plane_b_from_plane_a
from roadsurf.reconstruction.types import PairResult

# image b is taken when its camera is nearer to the common ground by more than this share:
# a nadir pair (equal distances up to the vehicle's pitch) keeps image a
NEARER_MARGIN = 0.02


def reference_is_b(cam: Camera, world_from_cam_a: np.ndarray, world_from_cam_b: np.ndarray) -> bool:
    """True when camera b (pose (4, 4), m) sees the two frames' common road from nearer than
    camera a by more than ``NEARER_MARGIN``: the centroid of their footprints' intersection on
    the road ``height_m`` below each camera (ENU), distances from the camera centres. False
    without a common footprint."""
    import shapely

    hulls = []
    for W in (world_from_cam_a, world_from_cam_b):
        fp = cam.footprint_grid_enu(W, float(W[2, 3]) - cam.height_m)
        if len(fp) < 3:
            return False
        hulls.append(shapely.MultiPoint(fp[:, :2]).convex_hull)
    common = hulls[0].intersection(hulls[1])
    if common.is_empty or common.area <= 0:
        return False
    c = np.array(common.centroid.coords[0])
    z = 0.5 * (world_from_cam_a[2, 3] + world_from_cam_b[2, 3]) - cam.height_m
    g = np.array([c[0], c[1], z])
    da = float(np.linalg.norm(g - world_from_cam_a[:3, 3]))
    db = float(np.linalg.norm(g - world_from_cam_b[:3, 3]))
    return db < (1.0 - NEARER_MARGIN) * da


def reversed_pair(p: PairResult) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pair seen from image b: (R_a_from_b (3, 3), t_a_from_b_m (3,), the road plane in
    camera b (3,), z = p0 x + p1 y + p2)."""
    R = np.asarray(p.R_b_from_a, float)
    t = np.asarray(p.t_b_from_a_m, float)
    return R.T, -R.T @ t, plane_b_from_plane_a(np.asarray(p.plane, float), R, t)
