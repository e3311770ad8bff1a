"""Keep apart what the images say is apart: segments that follow a ``no_overlap`` pair.

A segment (frames tied neither by a matched pair nor by GPS to the ones before it) is placed
by a constant-velocity guess. When the pair at its start failed because the two views share
no ground (status ``no_overlap``: too few matches, or matches covering too little of the
image), that guess contradicts the images whenever it lays the segment over ground already
mapped: the global map would then fuse different stretches of road as one (a 10x noisier
surface, a smeared mosaic). Such a segment is moved rigidly, along the direction of travel
before the break, until its road footprint clears every earlier segment's, and its road is
put at the level of the segment before it. Moving a whole untied segment rigidly changes
nothing inside it; where it lies was a guess before and is a guess after (the report says so).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from roadsurf.core.camera import Camera

log = logging.getLogger(__name__)

GAP_M = 0.5  # clearance left between separated segments' footprints (m)


def _footprint_xy(camera: Camera, W: np.ndarray) -> np.ndarray:
    """(M, 2) ENU x, y of the frames' road footprints (W (N, 4, 4)); the road is height_m
    below each camera (a level guess, good enough for keeping segments apart)."""
    pts = [camera.footprint_grid_enu(T, float(T[2, 3]) - camera.height_m) for T in W]
    pts = [p[:, :2] for p in pts if len(p)]
    if not pts:
        return W[:, :2, 3].copy()
    xy = np.vstack(pts)
    # rays near the horizon land far away: keep the footprint to what is imaged usefully
    c = np.median(W[:, :2, 3], axis=0)
    r = np.linalg.norm(xy - c, axis=1)
    return xy[r <= 10.0 * camera.height_m + float(np.ptp(W[:, :2, 3], axis=0).max())]


def _boxes_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Axis-aligned boxes [xmin, ymin, xmax, ymax] overlap (or touch within GAP_M)."""
    return bool(
        a[0] < b[2] + GAP_M and b[0] < a[2] + GAP_M and a[1] < b[3] + GAP_M and b[1] < a[3] + GAP_M
    )


def _box(xy: np.ndarray) -> np.ndarray:
    return np.array([xy[:, 0].min(), xy[:, 1].min(), xy[:, 0].max(), xy[:, 1].max()])


def separate_segments(
    world: np.ndarray, segment: np.ndarray, starts_apart: set[int], camera: Camera
) -> tuple[np.ndarray, list[int]]:
    """Move the segments whose first frame position is in ``starts_apart`` clear of the
    earlier segments' footprints. world (N, 4, 4) world_from_cam, segment (N,) ids. Returns
    (new world, ids of the segments moved)."""
    W = world.copy()
    moved: list[int] = []
    n_seg = int(segment.max()) + 1 if len(segment) else 0
    boxes: list[np.ndarray] = []
    for s in range(n_seg):
        fr = np.flatnonzero(segment == s)
        if s > 0 and int(fr[0]) in starts_apart:
            prev = np.flatnonzero(segment == s - 1)
            # the road of this segment at the level of the previous one (a level road guess)
            W[fr, 2, 3] += float(np.mean(W[prev, 2, 3]) - np.mean(W[fr, 2, 3]))
            box = _box(_footprint_xy(camera, W[fr]))
            if any(_boxes_overlap(box, b) for b in boxes):
                d = W[prev[-1], :2, 3] - W[prev[0], :2, 3]
                d = d / np.linalg.norm(d) if np.linalg.norm(d) > 1e-6 else np.array([1.0, 0.0])
                # smallest shift along d that clears every earlier box (boxes, so try the
                # clearance of each and keep the first that works)
                allb = np.array(boxes)
                span = float(np.hypot(*(allb[:, 2:].max(0) - allb[:, :2].min(0))))
                size = float(np.hypot(*(box[2:] - box[:2])))
                for step in np.linspace(0.0, span + size + 2 * GAP_M, 200):
                    shifted = box + np.tile(d * step, 2)
                    if not any(_boxes_overlap(shifted, b) for b in boxes):
                        break
                W[fr, :2, 3] += d * step
                box = shifted
                moved.append(s)
            boxes.append(box)
        else:
            boxes.append(_box(_footprint_xy(camera, W[fr])))
    return W, moved
