"""The imaged corridor of a drive's truth: each true frame's raw image border cast from its true
camera (each rolling-shutter row from its own pose) onto the true road (truth/height.tif), or a
flat road without it; the union of the footprints, or of consecutive frames' common parts (what
a two-view method can measure). Used by the surface figures (``evaluation.surface``)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from roadsurf.core.camera import RENDER_UNDISTORT_CRITERIA
from roadsurf.core.fits import fit_plane_z
from roadsurf.io import drivefolder as df
from roadsurf.io.drive.camera_yaml import load_camera

if TYPE_CHECKING:
    from shapely import Geometry

# number of rays cast along each image edge: the raw border's curve (lens distortion) and the
# road's relief between the corners (undulation) both bend the footprint's outline
_BORDER_RAYS_PER_EDGE = 8
# a border ray is cast on the truth heights within this height of the plane fitted under its
# footprint (m): the relief the plane leaves is the undulation over a footprint (~1 cm) and the
# defects (potholes at most 8 cm deep, SimConfig.pothole_depth_m)
_ROAD_RELIEF_M = 0.2
# truth heights sampled per footprint plane fit (a stride over the footprint's bounding box)
_PLANE_SAMPLES = 4000


def _border_rays_cam(cam: Any) -> tuple[np.ndarray, np.ndarray]:
    """(4n, 3) camera-frame rays (z = 1) through the raw image's border pixel centres, in order
    around the image from its top-left corner, undistorted as the simulator renders them, and
    their (4n,) raw rows v (px)."""
    w, h, n = float(cam.width) - 1.0, float(cam.height) - 1.0, _BORDER_RAYS_PER_EDGE
    t = np.linspace(0.0, 1.0, n + 1)[:-1]
    u = np.concatenate([t * w, np.full(n, w), (1 - t) * w, np.zeros(n)])
    v = np.concatenate([np.zeros(n), t * h, np.full(n, h), (1 - t) * h])
    und = cam.normalised_from_raw_px(np.column_stack([u, v]), criteria=RENDER_UNDISTORT_CRITERIA)
    return np.column_stack([und, np.ones(len(und))]), v


def _row_rays_world(
    rays_cam: np.ndarray,
    rows_px: np.ndarray,
    world_from_cam: np.ndarray,
    k: int,
    t_s: np.ndarray,
    readout_s: float,
    height_px: int,
) -> tuple[np.ndarray, np.ndarray]:
    """World (N, 3) centres and rays of frame ``k``'s camera rays (N, 3) at raw rows (N,) px:
    the frame's pose (N, 4, 4 for all frames) at its first row, each later row ``readout_s * v /
    height`` s later with the frame's motion from its neighbours (``core.rolling``'s convention;
    a global shutter: every ray from the frame's pose)."""
    from scipy.spatial.transform import Rotation

    from roadsurf.core.rolling import frame_motion

    R, C = world_from_cam[k, :3, :3], world_from_cam[k, :3, 3]
    rays_w = rays_cam @ R.T
    if readout_s <= 0 or not np.isfinite(t_s).all():
        return np.broadcast_to(C, rays_w.shape), rays_w
    vel, omega = frame_motion(world_from_cam, t_s, k)
    tau = readout_s * rows_px / float(height_px)
    turn = Rotation.from_rotvec(omega[None, :] * tau[:, None]).as_matrix()  # (N, 3, 3)
    return C + vel[None, :] * tau[:, None], np.einsum("nij,nj->ni", turn, rays_w)


def _truth_heights(truth_dir: Path) -> tuple[np.ndarray, Any] | None:
    """truth/height.tif as (rows, cols) float32 road heights (m, NaN off the road) and its
    affine transform, or None without the file."""
    path = truth_dir / df.TRUTH_HEIGHT_TIF
    if not path.is_file():
        return None
    import rasterio

    with rasterio.open(path) as src:
        z = src.read(1).astype(np.float32, copy=False)
        nd = src.nodata
        if nd is not None and not math.isnan(nd):
            z[z == nd] = np.nan
        return z, src.transform


def heights_from_xy(xy: np.ndarray, heights: np.ndarray, transform: Any) -> np.ndarray:
    """(N,) road heights (m) bilinear in the raster's cell centres at (N, 2) map points (m);
    NaN where one of the four cells is NaN or off the raster."""
    col, row = ~transform * (xy[:, 0], xy[:, 1])
    c, r = np.asarray(col) - 0.5, np.asarray(row) - 0.5
    c0, r0 = np.floor(c).astype(int), np.floor(r).astype(int)
    fc, fr = c - c0, r - r0
    ok = (r0 >= 0) & (c0 >= 0) & (r0 + 1 < heights.shape[0]) & (c0 + 1 < heights.shape[1])
    out = np.full(len(xy), np.nan)
    r0, c0, fr, fc = r0[ok], c0[ok], fr[ok], fc[ok]
    top = heights[r0, c0] * (1 - fc) + heights[r0, c0 + 1] * fc
    bot = heights[r0 + 1, c0] * (1 - fc) + heights[r0 + 1, c0 + 1] * fc
    out[ok] = top * (1 - fr) + bot * fr
    return out


def _plane_under(
    xy: np.ndarray, origin: np.ndarray, heights: np.ndarray, transform: Any
) -> np.ndarray | None:
    """(3,) plane z = a dx + b dy + c (dx, dy in m from ``origin``) fitted to the truth heights
    in the bounding box of the (N, 2) map points ``xy``; None with fewer than 3 heights."""
    (lo_x, lo_y), (hi_x, hi_y) = xy.min(0), xy.max(0)
    ca, ra = ~transform * (lo_x, hi_y)
    cb, rb = ~transform * (hi_x, lo_y)
    r0, r1 = max(int(min(ra, rb)), 0), min(int(max(ra, rb)) + 1, heights.shape[0])
    c0, c1 = max(int(min(ca, cb)), 0), min(int(max(ca, cb)) + 1, heights.shape[1])
    if r1 <= r0 or c1 <= c0:
        return None
    step = max(1, int(math.ceil(math.sqrt((r1 - r0) * (c1 - c0) / _PLANE_SAMPLES))))
    rr, cc = np.mgrid[r0:r1:step, c0:c1:step]
    z = heights[r0:r1:step, c0:c1:step]
    m = np.isfinite(z)
    if m.sum() < 3:
        return None
    x, y = transform * (cc[m] + 0.5, rr[m] + 0.5)
    dx, dy = np.asarray(x, float) - origin[0], np.asarray(y, float) - origin[1]
    return fit_plane_z(np.column_stack([dx, dy, z[m].astype(np.float64)]))


def road_xy_from_rays(
    centre: np.ndarray, rays: np.ndarray, height_m: float, heights: np.ndarray, transform: Any
) -> np.ndarray | None:
    """(N, 2) map points (m) where (N, 3) world rays from the camera centre (3,) or from one
    centre per ray (N, 3) (map x, y and the heights' z, m; a rolling shutter's rows) meet the
    truth road; None where a ray does not descend onto it.

    The rays meet a plane fitted to the heights under the flat-road footprint (``height_m``
    below the camera), then one fitted under that footprint (the footprint moves with the
    slope); each ray is then cast on the bilinear heights: its first crossing of them within
    ``_ROAD_RELIEF_M`` of that plane, the plane's point where the raster has none there (beyond
    the truth corridor). Without heights under the footprint: the flat-road footprint."""
    if np.any(rays[:, 2] >= -1e-6):
        return None
    C = np.broadcast_to(np.asarray(centre, float), rays.shape)
    c_xy, c_z = C[:, :2], C[:, 2]
    origin = c_xy.mean(axis=0)
    xy = c_xy + (-height_m / rays[:, 2])[:, None] * rays[:, :2]
    den = lam = None
    for _ in range(2):
        plane = _plane_under(xy, origin, heights, transform)
        if plane is None:
            break
        den = rays[:, 2] - plane[0] * rays[:, 0] - plane[1] * rays[:, 1]
        if np.any(den >= -1e-6):
            return None
        # the plane's height under each ray's own centre, minus that centre's height
        d_xy = c_xy - origin
        lam = (plane[0] * d_xy[:, 0] + plane[1] * d_xy[:, 1] + plane[2] - c_z) / den
        xy = c_xy + lam[:, None] * rays[:, :2]
    if den is None or lam is None:
        return xy
    # march each ray through the relief window, half a raster cell a step, to its first
    # crossing of the bilinear heights; the plane's point where it finds none (no heights)
    cell = 0.5 * min(abs(transform.a), abs(transform.e))
    reach = _ROAD_RELIEF_M / -den  # λ from the plane's point to ±_ROAD_RELIEF_M off the plane
    n = int(np.ceil(np.max(2 * reach * np.linalg.norm(rays[:, :2], axis=1)) / cell)) + 2
    ls = lam[:, None] + reach[:, None] * np.linspace(-1.0, 1.0, n)[None, :]  # (N, n)
    P = C[:, None, :] + ls[:, :, None] * rays[:, None, :]
    f = P[..., 2] - heights_from_xy(P[..., :2].reshape(-1, 2), heights, transform).reshape(ls.shape)
    cross = np.isfinite(f[:, :-1]) & np.isfinite(f[:, 1:]) & (f[:, :-1] > 0) & (f[:, 1:] <= 0)
    hit = cross.any(axis=1)
    i = np.argmax(cross, axis=1)[hit]
    rows = np.flatnonzero(hit)
    f0, f1 = f[rows, i], f[rows, i + 1]
    lam = lam.copy()
    lam[rows] = ls[rows, i] + f0 / (f0 - f1) * (ls[rows, i + 1] - ls[rows, i])
    return c_xy + lam[:, None] * rays[:, :2]


def true_footprints(
    truth_dir: Path, truth: dict[str, Any], seen: set[str], road: bool = True
) -> list[Geometry | None] | None:
    """Each true frame's footprint (truth CRS; None for a frame not in ``seen`` or whose border
    does not meet the road), or None without camera.yaml.

    The footprint is the raw image's border cast from the true camera onto the true road
    (truth/height.tif, ``road_xy_from_rays``) when the truth has heights and camera heights
    (``truth["up"]``) and ``road`` is on; else onto a flat road ``height_m`` below the camera."""
    import shapely

    from roadsurf.evaluation.trajectory import truth_rotations

    cam_yaml = truth_dir.parent / df.CAMERA_YAML
    if not cam_yaml.is_file():
        return None
    cam = load_camera(cam_yaml)
    rays, rows = _border_rays_cam(cam)
    hmap = _truth_heights(truth_dir) if road and "up" in truth else None
    q = truth["q"]
    W = np.tile(np.eye(4), (len(q), 1, 1))
    W[:, :3, :3] = truth_rotations(truth)
    W[:, :2, 3] = truth["xy"]
    W[:, 2, 3] = truth["up"] if "up" in truth else 0.0
    t_s = truth.get("t", np.full(len(q), np.nan))
    polys: list[Geometry | None] = []
    for k in range(len(q)):
        if truth["filename"][k] not in seen:
            polys.append(None)
            continue
        # a rolling shutter's rows each from their own pose (the bottom rows are exposed up to
        # readout_s later: on the drive's border that is the vehicle's travel over it)
        cw, rw = _row_rays_world(rays, rows, W, k, t_s, cam.readout_s, cam.height)
        xy: np.ndarray | None
        if hmap is not None:
            xy = road_xy_from_rays(cw, rw, cam.height_m, *hmap)
        elif np.all(rw[:, 2] < -1e-6):
            xy = cw[:, :2] + (-cam.height_m / rw[:, 2])[:, None] * rw[:, :2]
        else:
            xy = None
        # a frame without a footprint keeps its place, so the stereo pairs stay consecutive
        polys.append(None if xy is None else shapely.make_valid(shapely.Polygon(xy)))
    return polys


def corridor_from_footprints(
    footprints: list[Geometry | None] | None, stereo: bool = False
) -> Geometry | None:
    """Union of the frames' footprints (``true_footprints``), or with ``stereo`` of each two
    consecutive frames' common part (what a two-view method can measure); None when empty."""
    import shapely

    if footprints is None:
        return None
    polys = footprints
    if stereo:
        polys = [
            a.intersection(b)
            for a, b in zip(footprints[:-1], footprints[1:], strict=True)
            if a is not None and b is not None
        ]
    polys = [p for p in polys if p is not None and not p.is_empty]
    return shapely.union_all(polys) if polys else None


def _corridor_polygon(
    truth_dir: Path, truth: dict[str, Any], seen: set[str], stereo: bool = False, road: bool = True
) -> Geometry | None:
    """Union of the true camera footprints on the road (truth CRS), or None."""
    return corridor_from_footprints(true_footprints(truth_dir, truth, seen, road), stereo)
