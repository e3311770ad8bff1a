"""Keep apart what the images say is apart: segments placed by a guess over ground already
mapped.

A segment (frames tied neither by a matched pair nor by GPS to the ones before it) is placed
by a constant-velocity guess. When the pair at its start failed because the two views share
no ground (status ``no_overlap``: too few matches, or matches covering too little of the
image), that guess contradicts the images whenever it lays the segment over ground already
mapped: the global map would then fuse different stretches of road as one (a 10x noisier
surface, a smeared mosaic). Such a segment is moved rigidly, along the direction of travel
before the break, until its road footprint clears every earlier segment's, and its road is
put at the level of the segment before it.

A segment after any other break (a blurred frame, a failed geometry) is expected to continue
its predecessor's ground, so it may overlap the segment just before it; when the guess lays it
over ground mapped by an older segment, it is moved clear of those in the same way, with a
warning naming the frames. Every move is carried to the later guessed segments (their guess
was made relative to the moved one). Segments with GPS fixes are placed by GPS and never moved.
Moving a whole untied segment rigidly changes nothing inside it; where it lies was a guess
before and is a guess after (the report says so).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from roadsurf.core.camera import Camera
    from roadsurf.reconstruction.types import PairResult

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


def segment_has_gps(segment: np.ndarray, t_s: np.ndarray, gps_t_s: np.ndarray | None) -> np.ndarray:
    """(n_seg,) bool: a GPS fix lies within the segment's frame times (± half a frame
    interval). segment (N,) ids, t_s (N,) frame times (s), gps_t_s (M,) fix times or None."""
    n_seg = int(segment.max()) + 1 if len(segment) else 0
    out = np.zeros(n_seg, bool)
    if gps_t_s is None or len(gps_t_s) == 0 or n_seg == 0:
        return out
    dt = float(np.median(np.diff(t_s))) if len(t_s) > 1 else 0.0
    for s in range(n_seg):
        fr = np.flatnonzero(segment == s)
        lo, hi = t_s[fr[0]] - 0.5 * dt, t_s[fr[-1]] + 0.5 * dt
        out[s] = bool(np.any((gps_t_s >= lo) & (gps_t_s <= hi)))
    return out


def keep_apart(
    world: np.ndarray,
    segment: np.ndarray,
    pairs: list[PairResult],
    pos_of: dict[int, int],
    camera: Camera,
    filenames: list[str],
    *,
    has_gps: np.ndarray | None = None,
) -> tuple[np.ndarray, list[str]]:
    """The poses stage's step: world (N, 4, 4) world_from_cam with segments (N,) ids, the
    drive's pairs (their statuses at the breaks), pos_of (frame index -> position),
    filenames (N,), has_gps (n_seg,) from ``segment_has_gps`` (None: no GPS). Returns (new
    world, warnings naming the moved frames)."""
    n_seg = int(segment.max()) + 1 if len(segment) else 0
    if n_seg < 2:
        return world, []
    status_at = {
        pos_of[p.index_b]: p.status for p in pairs if p.index_a in pos_of and p.index_b in pos_of
    }
    starts = {int(np.flatnonzero(segment == s)[0]) for s in range(1, n_seg)}
    no_overlap = {i for i in starts if status_at.get(i) == "no_overlap"}
    W, moved = separate_segments(
        world, segment, no_overlap, camera, any_break=True, has_gps=has_gps
    )
    groups: dict[bool, list[str]] = {True: [], False: []}
    for s, over in moved:
        fr = np.flatnonzero(segment == s)
        what = status_at.get(int(fr[0]), "no pair")
        olds = ", ".join(_span(filenames, np.flatnonzero(segment == o)) for o in over)
        tag = "" if what == "no_overlap" else f" (after a {what} pair)"
        groups[what == "no_overlap"].append(f"{_span(filenames, fr)}{tag} over {olds}")
    warns: list[str] = []
    if groups[True]:
        warns.append(
            f"{len(groups[True])} segment(s) start where the images share no ground "
            "(no_overlap) and were laid over ground already mapped; moved apart so the map does "
            "not fuse different stretches (their placement is a guess): " + "; ".join(groups[True])
        )
    if groups[False]:
        warns.append(
            f"{len(groups[False])} segment(s) after a break that neither a pair nor GPS ties "
            "were laid by the constant-velocity guess over ground mapped by older segments; "
            "moved apart (their placement is a guess): " + "; ".join(groups[False])
        )
    for w in warns:
        log.warning("separate: %s", w)
    return W, warns


def separate_segments(
    world: np.ndarray,
    segment: np.ndarray,
    starts_apart: set[int],
    camera: Camera,
    *,
    any_break: bool = False,
    has_gps: np.ndarray | None = None,
) -> tuple[np.ndarray, list[tuple[int, list[int]]]]:
    """Move the segments whose first frame position is in ``starts_apart`` clear of the
    earlier segments' footprints; with ``any_break`` also the other segments, clear of the
    segments before their predecessor. world (N, 4, 4) world_from_cam, segment (N,) ids,
    has_gps (n_seg,) segments placed by GPS (never moved; None = none). Each move is carried
    to the later segments without GPS. Returns (new world, [(segment moved, ids of the
    segments it overlapped)])."""
    W = world.copy()
    moved: list[tuple[int, list[int]]] = []
    n_seg = int(segment.max()) + 1 if len(segment) else 0
    gps = np.zeros(n_seg, bool) if has_gps is None else np.asarray(has_gps, bool)
    boxes: list[np.ndarray] = []
    carry = np.zeros(3)  # moves of earlier guessed segments, carried to the later guesses
    for s in range(n_seg):
        fr = np.flatnonzero(segment == s)
        apart = s > 0 and int(fr[0]) in starts_apart
        if s == 0 or gps[s] or not (apart or any_break):
            carry = np.zeros(3) if (s == 0 or gps[s]) else carry
            W[fr, :3, 3] += carry
            boxes.append(_box(_footprint_xy(camera, W[fr])))
            continue
        W[fr, :3, 3] += carry
        prev = np.flatnonzero(segment == s - 1)
        if apart:
            # the road of this segment at the level of the previous one (a level road guess)
            dz = float(np.mean(W[prev, 2, 3]) - np.mean(W[fr, 2, 3]))
            W[fr, 2, 3] += dz
            carry[2] += dz
        # a segment after another break continues its predecessor's ground: only the older
        # segments count as ground already mapped
        check = list(range(s)) if apart else list(range(s - 1))
        box = _box(_footprint_xy(camera, W[fr]))
        over = [o for o in check if _boxes_overlap(box, boxes[o])]
        if over:
            d = W[prev[-1], :2, 3] - W[prev[0], :2, 3]
            d = d / np.linalg.norm(d) if np.linalg.norm(d) > 1e-6 else np.array([1.0, 0.0])
            # smallest shift along d that clears every checked box (boxes, so try the
            # clearance of each and keep the first that works)
            allb = np.array([boxes[o] for o in check])
            span = float(np.hypot(*(allb[:, 2:].max(0) - allb[:, :2].min(0))))
            size = float(np.hypot(*(box[2:] - box[:2])))
            step = 0.0
            shifted = box
            for step in np.linspace(0.0, span + size + 2 * GAP_M, 200):
                shifted = box + np.tile(d * step, 2)
                if not any(_boxes_overlap(shifted, boxes[o]) for o in check):
                    break
            W[fr, :2, 3] += d * step
            carry[:2] += d * step
            box = shifted
            moved.append((s, over))
        boxes.append(box)
    return W, moved


def _span(filenames: list[str], fr: np.ndarray) -> str:
    """'first-last' frame names of positions fr (one name for one frame)."""
    a, b = filenames[int(fr[0])], filenames[int(fr[-1])]
    return a if a == b else f"{a}-{b}"
