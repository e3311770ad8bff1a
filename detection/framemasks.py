"""Frame views of the map's defects: each frame's 2D defect mask, its 3D frame label and the
frames each defect lists, all from one projection, so that RUN/frames.csv, RUN/masks/ and the
defects agree (issue 28).

A defect is a set of cells of the map's grid (``DefectCells``): the cells its mask shows (deeper
than the map's seed threshold T_d, the depth at which the map calls a cell a defect) and its
deep cells (deeper than the frame-label depth). A frame sees the cells through its own pose
(``traj.world_from_cam``) and the camera with its lens distortion, on the road plane the
frame's own pairs placed in the map (their road points in ENU), so each cell is drawn where
the frame's pixels saw it, whatever the camera's tilt. Each cell is drawn as the quadrilateral
of its four corners, so the ground size of a pixel never enters.

A frame's mask is the union of the cells of the defects visible in it, and a defect lists the
frames whose mask shows it. The frame label follows the simulator's rule: the deep area visible
in the image, A; p = A / (A + a_min), a defect frame when A >= a_min (``frame_min_area_m2``). So
a defect frame's mask always shows the defects that make it one, and they list it; a frame that
sees only a sliver of a defect, or a defect shallower than the frame-label depth (a crack),
shows it in its mask with p < 0.5.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from roadsurf.core.camera import Camera
from roadsurf.core.fits import robust_plane_z
from roadsurf.core.rolling import frame_motion, raw_px_from_world
from roadsurf.detection.mapframe import MapFrame
from roadsurf.mapping.types import Trajectory
from roadsurf.reconstruction.types import PairResult

if TYPE_CHECKING:
    from shapely.geometry import Polygon

    from roadsurf.detection.pairs import PairDefects

log = logging.getLogger(__name__)

MIN_PLANE_POINTS = 10  # road points a frame's own road plane needs (robust_plane_z's minimum)


@dataclass
class DefectCells:
    """The map cells of one defect (grid-frame centres, metres; cells ``gsd_m`` wide)."""

    mask_xy_m: np.ndarray  # (M, 2) cells the 2D masks show
    deep_xy_m: np.ndarray  # (K, 2) cells deeper than the frame-label depth (frame labels)
    gsd_m: float  # cell size (m)

    def bounds(self) -> tuple[float, float, float, float] | None:
        xy = np.vstack([self.mask_xy_m, self.deep_xy_m])
        if len(xy) == 0:
            return None
        lo, hi = xy.min(axis=0) - self.gsd_m, xy.max(axis=0) + self.gsd_m
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


@dataclass
class FrameView:
    """What one frame sees of the defects."""

    deep_area_m2: float  # deep cell area inside the image (m²)
    defects: list[int]  # indices of the defects with a cell inside the image


def outline_cells(outline_xy_m: np.ndarray, cell_m: float) -> np.ndarray:
    """(M, 2) centres of the ``cell_m`` lattice cells inside a polygon (K, 2), for defects
    measured along a line (cracks) that have an outline but no raster cells."""
    from shapely import contains_xy
    from shapely.geometry import Polygon

    ring = np.asarray(outline_xy_m, float)
    if len(ring) < 3:
        return np.zeros((0, 2))
    poly = Polygon(ring)
    x0, y0, x1, y1 = poly.bounds
    xs = np.arange(x0 + 0.5 * cell_m, x1, cell_m)
    ys = np.arange(y0 + 0.5 * cell_m, y1, cell_m)
    X, Y = np.meshgrid(xs, ys)
    inside = contains_xy(poly, X, Y)
    return np.c_[X[inside], Y[inside]]


def road_planes(
    pairs: list[PairResult],
    per_pair: dict[int, PairDefects],
    traj: Trajectory,
    pose_of: dict[str, int],
) -> dict[str, np.ndarray]:
    """Per frame: the road plane z = p0 x + p1 y + p2 (ENU, (3,)) through the road points of
    the ok pairs the frame belongs to (a or b), placed with the trajectory as the map placed
    them. Frames with fewer than ``MIN_PLANE_POINTS`` such points are left out."""
    pts: dict[str, list[np.ndarray]] = {}
    for k, pd in per_pair.items():
        i = pose_of.get(pd.frame_a)
        if i is None:
            continue
        road = ~pd.candidate & (np.abs(pd.dist_m) < pd.threshold_m)
        T = traj.world_from_cam[i]
        P = np.asarray(pairs[k].points_cam_a_m, float)[road] @ T[:3, :3].T + T[:3, 3]
        for fn in (pairs[k].frame_a, pairs[k].frame_b):
            pts.setdefault(fn, []).append(P)
    out: dict[str, np.ndarray] = {}
    for fn, lst in pts.items():
        P = np.vstack(lst)
        if len(P) < MIN_PLANE_POINTS:
            continue
        plane = robust_plane_z(P)
        if plane is not None and np.all(np.isfinite(plane)):
            out[fn] = plane
    return out


def motion_of(traj: Trajectory, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Frame i's linear (m/s) and angular (rad/s) velocity in ENU, for a rolling shutter."""
    return frame_motion(traj.world_from_cam, traj.timestamp_s, i, traj.segment)


class FrameProjector:
    """Projects grid-frame cells into one frame's raw image (see the module docstring)."""

    def __init__(
        self,
        camera: Camera,
        world_from_cam: np.ndarray,
        plane: np.ndarray | None,
        mframe: MapFrame,
        motion: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        self.camera = camera
        # rolling shutter: the frame's velocity (m/s) and angular velocity (rad/s) in ENU
        self.motion = motion if camera.readout_s > 0 else None
        T = np.asarray(world_from_cam, float)
        self.T = T
        self.R, self.C = T[:3, :3], T[:3, 3]
        # Without the frame's own road points: the road height_m below the camera centre (the
        # footprints' rule)
        self.plane = np.array([0.0, 0.0, self.C[2] - camera.height_m]) if plane is None else plane
        self.mframe = mframe
        # Ideal normalised coordinates a ray may have and still be in the image: the bounds of
        # the undistorted image border, with a margin (a distortion polynomial folds back into
        # the image beyond its valid field of view).
        w, h = camera.width, camera.height
        t = np.linspace(0.0, 1.0, 9)
        border = np.vstack([
            np.c_[t * (w - 1), np.zeros_like(t)], np.c_[t * (w - 1), np.full_like(t, h - 1)],
            np.c_[np.zeros_like(t), t * (h - 1)], np.c_[np.full_like(t, w - 1), t * (h - 1)],
        ])  # fmt: skip
        n = camera.normalised_from_raw_px(border)
        lo, hi = n.min(axis=0), n.max(axis=0)
        pad = 0.1 * (hi - lo)
        self._nlo, self._nhi = lo - pad, hi + pad

    def project(self, xy_grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) grid-frame points on the road -> raw pixels (N, 2) and (N,) bool valid (in
        front of the camera, within the lens's field of view)."""
        xy = _enu_from_grid(self.mframe, np.asarray(xy_grid, float).reshape(-1, 2))
        z = xy @ self.plane[:2] + self.plane[2]
        X = (np.c_[xy, z] - self.C) @ self.R  # camera frame: R^T (X - C)
        with np.errstate(divide="ignore", invalid="ignore"):
            nx, ny = X[:, 0] / X[:, 2], X[:, 1] / X[:, 2]
        ok = (X[:, 2] > 1e-6) & (nx >= self._nlo[0]) & (nx <= self._nhi[0])
        ok &= (ny >= self._nlo[1]) & (ny <= self._nhi[1])
        if self.motion is None:
            u, v = self.camera.project(X)
        else:  # each row has its own pose (the frame's is its first row's)
            u, v = raw_px_from_world(self.camera, np.c_[xy, z], self.T, *self.motion)
        uv = np.c_[u, v]
        ok &= np.isfinite(uv[:, 0]) & np.isfinite(uv[:, 1])
        return uv, ok

    def inside(self, xy_grid: np.ndarray) -> np.ndarray:
        """(N,) bool: the grid points are seen inside the image (pixel edges -0.5 .. w-0.5)."""
        if len(xy_grid) == 0:
            return np.zeros(0, bool)
        uv, ok = self.project(xy_grid)
        w, h = self.camera.width, self.camera.height
        ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < h - 0.5)
        return ok

    def draw(self, mask: np.ndarray, xy_grid: np.ndarray, gsd_m: float) -> None:
        """Draw the cells centred on ``xy_grid`` (N, 2), ``gsd_m`` wide, into ``mask`` (H, W)
        uint8 as the quadrilaterals of their projected corners."""
        if len(xy_grid) == 0:
            return
        h = 0.5 * gsd_m
        offs = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
        corners = (np.asarray(xy_grid, float)[:, None, :] + offs[None]).reshape(-1, 2)
        uv, ok = self.project(corners)
        uv, ok4 = uv.reshape(-1, 4, 2), ok.reshape(-1, 4)
        H, W = mask.shape
        # cells entirely off the image are skipped (cheap bounds test on the corners; the
        # four corners pairwise: numpy's reductions over an axis of 4 cost ~5x more)
        u, v = uv[:, :, 0], uv[:, :, 1]
        ok = (ok4[:, 0] & ok4[:, 1]) & (ok4[:, 2] & ok4[:, 3])
        ok &= np.maximum(np.maximum(u[:, 0], u[:, 1]), np.maximum(u[:, 2], u[:, 3])) >= -1
        ok &= np.minimum(np.minimum(u[:, 0], u[:, 1]), np.minimum(u[:, 2], u[:, 3])) <= W
        ok &= np.maximum(np.maximum(v[:, 0], v[:, 1]), np.maximum(v[:, 2], v[:, 3])) >= -1
        ok &= np.minimum(np.minimum(v[:, 0], v[:, 1]), np.minimum(v[:, 2], v[:, 3])) <= H
        quads = np.round(uv[ok] * 4.0).astype(np.int32)  # 2 fractional bits (shift=2)
        fill, line8 = cv2.fillConvexPoly, cv2.LINE_8  # ~2 us a cell: no keyword parsing
        for q in quads:
            fill(mask, q, 1, line8, 2)  # lineType, shift


def _enu_from_grid(mframe: MapFrame, xy: np.ndarray) -> np.ndarray:
    """``mframe.enu_from_grid`` of many points (N, 2): the exact transform at 3 x 3 points of
    their bounding box and the affine map fitted to them (the grid CRS is conformal and ENU
    tangent: over a few metres they differ from affine by far less than a micrometre; checked
    at four more points, exact otherwise). The exact transform per point cost a minute per
    drive on a 2 mm raster."""
    if len(xy) < 64:
        return mframe.enu_from_grid(xy)
    x, y = xy[:, 0], xy[:, 1]  # per column: numpy's reductions over an axis of 2 are slow
    lo, hi = np.array([x.min(), y.min()]), np.array([x.max(), y.max()])
    t = np.array([0.0, 0.5, 1.0])
    ctrl = np.array(
        [[lo[0] + a * (hi[0] - lo[0]), lo[1] + b * (hi[1] - lo[1])] for a in t for b in t]
    )
    chk = lo + np.array([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]]) * (hi - lo)
    exact = mframe.enu_from_grid(np.vstack([ctrl, chk]))
    M = np.column_stack([np.vstack([ctrl, chk]) - lo, np.ones(13)])
    A = np.linalg.lstsq(M[:9], exact[:9], rcond=None)[0]
    if np.abs(M[9:] @ A - exact[9:]).max() > 1e-6:
        return mframe.enu_from_grid(xy)
    dx, dy = xy[:, :1] - lo[0], xy[:, 1:2] - lo[1]
    return dx * A[0] + dy * A[1] + A[2]  # not (N, 2) @ (2, 2): numpy's small matmul is slow


def frame_views(
    camera: Camera,
    traj: Trajectory,
    mframe: MapFrame,
    frames: list[str],
    footprints: dict[str, Polygon],
    cells: list[DefectCells],
    planes: dict[str, np.ndarray],
) -> dict[str, FrameView]:
    """For each frame of ``frames`` with a pose: the deep area of the defects inside its image
    and which defects it sees. ``footprints`` (grid frame) only narrow the defects to test."""
    idx = {fn: i for i, fn in enumerate(traj.filenames)}
    boxes = [c.bounds() for c in cells]
    out: dict[str, FrameView] = {}
    for fn in frames:
        i = idx.get(fn)
        if i is None:
            continue
        fp = footprints.get(fn)
        near = _near(boxes, None if fp is None else fp.buffer(0.5).bounds)
        area, seen = 0.0, []
        if near:
            proj = FrameProjector(
                camera, traj.world_from_cam[i], planes.get(fn), mframe, motion_of(traj, i)
            )
            for j in near:
                c = cells[j]
                n_deep = int(proj.inside(c.deep_xy_m).sum())
                area += n_deep * c.gsd_m**2
                if n_deep or proj.inside(c.mask_xy_m).any():
                    seen.append(j)
        out[fn] = FrameView(area, seen)
    return out


def _near(
    boxes: list[tuple[float, float, float, float] | None],
    fp: tuple[float, float, float, float] | None,
) -> list[int]:
    """Defects whose box meets the footprint box (all of them without a footprint)."""
    out = []
    for j, b in enumerate(boxes):
        if b is None:
            continue
        if fp is not None and (b[2] < fp[0] or b[0] > fp[2] or b[3] < fp[1] or b[1] > fp[3]):
            continue
        out.append(j)
    return out


def frame_mask(
    camera: Camera,
    world_from_cam: np.ndarray,
    plane: np.ndarray | None,
    mframe: MapFrame,
    cells: list[DefectCells],
    motion: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """(H, W) bool mask of the given defects' cells seen by one frame (``motion``: its
    velocity and angular velocity for a rolling shutter, ``motion_of``)."""
    mask = np.zeros((camera.height, camera.width), np.uint8)
    proj = FrameProjector(camera, world_from_cam, plane, mframe, motion)
    for c in cells:
        proj.draw(mask, _distinct_rows(np.vstack([c.mask_xy_m, c.deep_xy_m])), c.gsd_m)
    return mask.astype(bool)


def _distinct_rows(xy: np.ndarray) -> np.ndarray:
    """(N, 2) -> its distinct rows, in their first order. A defect's deep cells are mostly
    also mask cells (the same lattice centres, bit for bit): drawing a cell twice changes no
    pixel, but costs a fillConvexPoly call."""
    if len(xy) < 2:
        return xy
    # each row as one complex number: a plain sort, ~10x faster than np.unique(axis=0)'s rows
    z = np.ascontiguousarray(xy, dtype=np.float64).view(np.complex128).ravel()
    _, first = np.unique(z, return_index=True)
    return xy if len(first) == len(xy) else xy[np.sort(first)]


def write_frame_masks(
    masks_dir: Path,
    camera: Camera,
    traj: Trajectory,
    mframe: MapFrame,
    views: dict[str, FrameView],
    cells: list[DefectCells],
    planes: dict[str, np.ndarray],
) -> dict[int, list[str]]:
    """Write RUN/masks/<stem>.png for every viewed frame: the cells of the defects it sees
    (empty when it sees none). Returns defect index -> the frames whose mask shows it."""
    from roadsurf.detection.pairs import write_mask

    idx = {fn: i for i, fn in enumerate(traj.filenames)}
    shown: dict[int, list[str]] = {}
    empty = np.zeros((camera.height, camera.width), bool)
    for fn, view in views.items():
        mask = empty
        if view.defects:
            mask = frame_mask(
                camera, traj.world_from_cam[idx[fn]], planes.get(fn), mframe,
                [cells[j] for j in view.defects], motion_of(traj, idx[fn]),
            )  # fmt: skip
            for j in view.defects:
                shown.setdefault(j, []).append(fn)
        write_mask(Path(masks_dir) / f"{Path(fn).stem}.png", mask)
    return shown
