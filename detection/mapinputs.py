"""What the map step of detection reads: the residual surface as a windowed source, the frames'
footprints, and each pair's points placed in the map's grid frame by the trajectory.

Points of a pair are in its camera-a frame; ``traj.world_from_cam`` of frame a takes them to
ENU and ``MapFrame.grid_from_enu`` to the grid frame (easting, northing in metres).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from roadsurf.detection.config import DetectionConfig
from roadsurf.detection.mapframe import MapFrame
from roadsurf.detection.mapseg import choose_gsd
from roadsurf.detection.pairs import PairDefects
from roadsurf.detection.windows import PointsSource, RasterSource, WindowSource
from roadsurf.io.drive import Drive
from roadsurf.io.runfolder import MAP_POINTS, SURFACE_TIF, SURFACE_VRT
from roadsurf.mapping.types import Trajectory
from roadsurf.reconstruction.types import PairResult

if TYPE_CHECKING:
    from shapely.geometry import Polygon
    from shapely.geometry.base import BaseGeometry


def evidence_points(
    pairs: list[PairResult],
    per_pair: dict[int, PairDefects],
    traj: Trajectory,
    pose_of: dict[str, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Defect points of all pairs in ENU (M, 3) and the pair id of each (M,): the refined
    points (2D + 3D) together with the plane fit's candidates, so that the 3D evidence of a
    defect that is not darker in the image still counts."""
    xyz, ids = [], []
    for k, pd in per_pair.items():
        i = pose_of.get(pd.frame_a)
        sel = pd.refined | pd.candidate
        if i is None or not sel.any():
            continue
        T = traj.world_from_cam[i]
        P = np.asarray(pairs[k].points_cam_a_m, float)[sel]
        xyz.append(P @ T[:3, :3].T + T[:3, 3])
        ids.append(np.full(len(P), k))
    if not xyz:
        return np.zeros((0, 3)), np.zeros(0, int)
    return np.vstack(xyz), np.concatenate(ids)


def depth_points(
    run_dir: Path,
    pairs: list[PairResult],
    per_pair: dict[int, PairDefects],
    traj: Trajectory,
    pose_of: dict[str, int],
    mframe: MapFrame,
) -> tuple[np.ndarray, np.ndarray, str] | None:
    """The 3D points with their residual (m, negative below) in the grid frame, and where they
    came from: the fused map points (RUN/map_points.npz) when mapping wrote them, else every
    pair's points ("pairs")."""
    mp = run_dir / MAP_POINTS
    if mp.exists():
        with np.load(mp, allow_pickle=False) as z:
            if len(z["xyz"]):
                xy = mframe.grid_from_enu(np.asarray(z["xyz"], float))
                return xy, np.asarray(z["residual_m"], float), MAP_POINTS
    xyz_l, res_l = [], []
    for k, pd in per_pair.items():
        i = pose_of.get(pd.frame_a)
        if i is None:
            continue
        T = traj.world_from_cam[i]
        xyz_l.append(np.asarray(pairs[k].points_cam_a_m, float) @ T[:3, :3].T + T[:3, 3])
        res_l.append(pd.dist_m)
    if not xyz_l:
        return None
    return mframe.grid_from_enu(np.vstack(xyz_l)), np.concatenate(res_l), "pairs"


def pair_keys(
    per_pair: dict[int, PairDefects], traj: Trajectory, pose_of: dict[str, int]
) -> list[int]:
    """The pair indices ``pair_points`` returns points for, in its order."""
    return [k for k, pd in per_pair.items() if pose_of.get(pd.frame_a) is not None]


def pair_points(
    pairs: list[PairResult],
    per_pair: dict[int, PairDefects],
    traj: Trajectory,
    pose_of: dict[str, int],
    mframe: MapFrame,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per ok pair: its points' grid xy (N, 2) via the trajectory (to select them only) and the
    same points in the pair's own camera-a frame (N, 3), where depths are measured."""
    out = []
    for k, pd in per_pair.items():
        i = pose_of.get(pd.frame_a)
        if i is None:
            continue
        T = traj.world_from_cam[i]
        P = np.asarray(pairs[k].points_cam_a_m, float)
        out.append((mframe.grid_from_enu(P @ T[:3, :3].T + T[:3, 3]), P))
    return out


def load_surface(
    cfg: DetectionConfig,
    run_dir: Path,
    pairs: list[PairResult],
    per_pair: dict[int, PairDefects],
    traj: Trajectory,
    pose_of: dict[str, int],
) -> tuple[WindowSource | None, MapFrame]:
    """The residual raster as a windowed source: RUN/surface.tif (or .vrt), else the map points
    or the pairs' points gridded per window. Nothing is read here."""
    for name in (SURFACE_TIF, SURFACE_VRT):
        path = run_dir / name
        if path.exists():
            src = RasterSource(path)
            mframe = MapFrame.create(traj.reference, src.grid.crs if traj.reference else None)
            return src, mframe
    mframe = MapFrame.create(traj.reference)
    pts = depth_points(run_dir, pairs, per_pair, traj, pose_of, mframe)
    if pts is None:
        return None, mframe
    xy, resid, name = pts
    gsd = choose_gsd(xy, cfg.map.fallback_gsd_m)
    return PointsSource(xy, resid, gsd, mframe.crs, name), mframe


def frame_footprints(drive: Drive, traj: Trajectory, mframe: MapFrame) -> dict[str, Polygon]:
    """filename -> shapely Polygon of the frame's footprint in the grid frame."""
    from shapely.geometry import Polygon

    out: dict[str, Polygon] = {}
    corners, names = [], []
    for fn, T in zip(traj.filenames, traj.world_from_cam, strict=True):
        fp = drive.camera.footprint_corners_enu(T)
        if fp is not None:
            corners.append(fp)
            names.append(fn)
    if not corners:
        return out
    xy = mframe.grid_from_enu(np.vstack(corners))
    for j, fn in enumerate(names):
        out[fn] = Polygon(xy[4 * j : 4 * j + 4])
    return out


def mapped_area(
    surface: WindowSource, pairs: list[PairResult], footprints: dict[str, Polygon]
) -> BaseGeometry | None:
    """Where the map's surface raster can hold data: the footprints of the frames of every pair
    (the map is made of the pairs' points), grown by 0.5 m for the raster's fill; None (all of
    it) for a source gridded from other points."""
    if not isinstance(surface, RasterSource):
        return None
    from shapely import unary_union

    frames = {fn for p in pairs for fn in (p.frame_a, p.frame_b)}
    return unary_union([fp for fn, fp in footprints.items() if fn in frames]).buffer(0.5)
