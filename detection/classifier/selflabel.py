"""Self-labelling (dissertation eq. 5.8-5.9): a frame's label from its run folder's 3D evidence.

A frame's reconstructed points are normalised by the camera height, X̄ = X / h; the frame is a
*defect* when points lie deeper than α = Z^d / h below the fitted road plane over a sufficient
extent, and the physics pipeline's own frame label (RUN/frames.csv, detection stage) agrees.
Frames whose 3D evidence disagrees with the physics label are ambiguous and left out
(``drop_ambiguous``), so the CNN learns from clear cases only. The same rule decides growth and
overruling in a fused run (``guided``).
"""

from __future__ import annotations

import csv
import logging
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from roadsurf.core.errors import RoadsurfError
from roadsurf.detection.classifier.config import ClassifierConfig
from roadsurf.io.runfolder import RunFolder

if TYPE_CHECKING:
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)


# ---------------------------------------------------------------- depth / extent per frame
@dataclass
class FrameFigures:
    """3D evidence for one frame, from the reconstructed pairs it belongs to."""

    max_depth_m: float  # deepest point below the road plane (m, positive down); 0 if none
    extent_cm2: float  # footprint of the points deeper than Z^d (convex hull, cm²)
    n_deep: int  # points deeper than Z^d
    n_points: int  # all reconstructed points in the frame
    bbox_px: tuple[float, float, float, float] | None  # deep points' box in the frame (px)


def _hull_area_m2(xy: np.ndarray) -> float:
    if xy.shape[0] < 3:
        return 0.0
    hull = cv2.convexHull(xy.astype(np.float32))
    return float(cv2.contourArea(hull))


def frame_figures(
    run_dir: Path, filenames: list[str], camera_height_m: float, cfg: ClassifierConfig
) -> dict[str, FrameFigures]:
    """Depth and extent of each frame from RUN/pairs/*.npz (eq. 5.8-5.9); see
    ``figures_from_pairs``. ``filenames`` are the drive's valid frames in capture order."""
    from roadsurf.reconstruction.types import load_pair

    run = RunFolder(run_dir)
    pairs = []
    for i in range(len(filenames) - 1):
        p = run.pair(i, i + 1)
        if not p.is_file():
            continue
        try:
            res = load_pair(p)
        except Exception as e:  # noqa: BLE001 - a damaged cache file only loses this pair
            log.warning("%s: cannot read pair (%s); frames %d-%d get no 3D label", p, e, i, i + 1)
            continue
        # the run folder's file name decides which frames the pair belongs to
        res.frame_a, res.frame_b = filenames[i], filenames[i + 1]
        pairs.append(res)
    return figures_from_pairs(pairs, camera_height_m, cfg)


def figures_from_pairs(
    pairs: Iterable[PairResult], camera_height_m: float, cfg: ClassifierConfig
) -> dict[str, FrameFigures]:
    """Depth and extent of each frame seen by ``pairs`` (PairResults) -> {filename: figures}.

    Points are normalised by the camera height, X̄ = X / h; a point is deep when its signed
    plane distance satisfies d / h < -α with α = Z^d / h. Frame a of a pair collects its pixels
    ``px_a``, frame b its ``px_b``. Frames with no successful pair are absent.
    """
    h = float(camera_height_m)
    alpha = cfg.depth_threshold_m(h) / h
    per_frame: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    for res in pairs:
        if not res.ok or res.n_points == 0:
            continue
        d_bar = np.asarray(res.plane_dist_m, float) / h  # normalised depth, negative below road
        xy = np.asarray(res.points_cam_a_m, float)[:, :2]
        per_frame.setdefault(res.frame_a, []).append((d_bar, xy, np.asarray(res.px_a, float)))
        per_frame.setdefault(res.frame_b, []).append((d_bar, xy, np.asarray(res.px_b, float)))
    out: dict[str, FrameFigures] = {}
    for name, parts in per_frame.items():
        max_depth = 0.0
        extent = 0.0
        n_deep = 0
        n_pts = 0
        boxes = []
        for d_bar, xy, px in parts:
            n_pts += d_bar.size
            deep = d_bar < -alpha
            max_depth = max(max_depth, float(-d_bar.min() * h) if d_bar.size else 0.0)
            n_deep = max(n_deep, int(deep.sum()))
            extent = max(extent, _hull_area_m2(xy[deep]) * 1e4)
            if deep.any():
                q = px[deep]
                boxes.append((q[:, 0].min(), q[:, 1].min(), q[:, 0].max(), q[:, 1].max()))
        bbox = None
        if boxes:
            b = np.array(boxes)
            bbox = (
                float(b[:, 0].min()),
                float(b[:, 1].min()),
                float(b[:, 2].max()),
                float(b[:, 3].max()),
            )
        out[name] = FrameFigures(max(0.0, max_depth), extent, n_deep, n_pts, bbox)
    return out


def read_defect_types(run_dir: Path) -> dict[str, set[str]]:
    """RUN/defects.geojson -> {filename: types of the physics defects seen in that frame}
    (the features' ``frames`` property); {} when the file does not exist."""
    from roadsurf.io.formats import read_geojson

    path = RunFolder(run_dir).defects_geojson
    if not path.is_file():
        return {}
    out: dict[str, set[str]] = {}
    for k, feat in enumerate(read_geojson(path).get("features") or []):
        props = feat.get("properties") or {}
        frames, kind = props.get("frames", []), props.get("type")
        if not isinstance(frames, list) or not isinstance(kind, str):
            raise RoadsurfError(
                f"{path}: feature {k} has a 'frames' that is not a list or no 'type'; re-run "
                "the detection stage (`roadsurf run DRIVE --out RUN --overwrite`) to rewrite it"
            )
        for fn in frames:
            out.setdefault(str(fn), set()).add(kind)
    return out


def skip_for_cnn(label: int | None, types: set[str] | None, cfg: ClassifierConfig) -> str | None:
    """The drop rule when a defect frame's physics defects are all of ``cnn_skip_types``."""
    skip = set(cfg.cnn_skip_types)
    if label != 1 or not skip or not types or not types <= skip:
        return None
    return f"left_to_3d({','.join(sorted(types))})"


def read_physics_labels(run_dir: Path) -> dict[str, tuple[bool, str]] | None:
    """RUN/frames.csv -> {filename: (defect, source)}; None when the file does not exist."""
    path = RunFolder(run_dir).frame_labels
    if not path.is_file():
        return None
    out: dict[str, tuple[bool, str]] = {}
    with open(path, newline="", encoding="utf-8") as f:
        for line, row in enumerate(csv.DictReader(f), start=2):
            if not str(row.get("defect", "x")).strip():
                continue  # not analysed: no physics label (detection.types.NOT_ANALYSED)
            try:
                out[row["filename"]] = (
                    str(row["defect"]).strip().lower() in ("1", "true", "yes"),
                    (row.get("source") or "3d").strip(),
                )
            except KeyError as e:
                raise RoadsurfError(
                    f"{path} line {line}: missing column {e}; expected filename,defect,..."
                ) from e
    return out


def label_frame(
    fig: FrameFigures | None, physics: tuple[bool, str] | None, cfg: ClassifierConfig
) -> tuple[int | None, str]:
    """One frame's label (1 defect, 0 non-defect, None = not used) and the rule that decided."""
    if physics is not None and physics[1] == "cnn":
        return None, "no_3d(cnn_screened)"
    if fig is None:
        return None, "no_3d(pair_failed)"
    deep_enough = fig.n_deep >= cfg.min_defect_points and fig.extent_cm2 >= cfg.min_defect_area_cm2
    clear_road = fig.n_deep <= 1 or fig.extent_cm2 < 0.25 * cfg.min_defect_area_cm2
    if physics is None:
        if deep_enough:
            return 1, "depth+extent"
        if clear_road:
            return 0, "depth+extent"
        return (None, "ambiguous(depth)") if cfg.drop_ambiguous else (0, "depth+extent")
    phys = physics[0]
    if phys and deep_enough:
        return 1, "physics+depth+extent"
    if not phys and not deep_enough:
        if clear_road or not cfg.drop_ambiguous:
            return 0, "physics+depth+extent"
        return None, "ambiguous(some_depth)"
    if cfg.drop_ambiguous:
        return None, "ambiguous(physics_vs_depth)"
    return int(phys), "physics"
