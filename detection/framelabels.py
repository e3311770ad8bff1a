"""Frame labels: is there a defect in this frame?

With a map, a frame's score is the deep defect area its image sees (the simulator's rule: cells
deeper than ``frame_depth_m``, projected through the frame's pose by ``framemasks``),
p = A / (A + ``frame_min_area_m2``); without one, the
dissertation's per-pair decision from the refined points alone. CNN probabilities, when given,
are fused with these 3D labels (Fig. 5.6, ``classifier.fusion``).
"""

from __future__ import annotations

import math

import numpy as np

from roadsurf.detection.classifier.fusion import FusionRule, fuse_frames
from roadsurf.detection.config import DetectionConfig
from roadsurf.detection.framemasks import FrameView
from roadsurf.detection.gsd import NadirView
from roadsurf.detection.pairs import PairDefects
from roadsurf.detection.types import NOT_ANALYSED, FrameLabel
from roadsurf.io.drive import Drive
from roadsurf.reconstruction.types import PairResult


def frame_labels(
    cfg: DetectionConfig,
    drive: Drive,
    views: dict[str, FrameView],
    pair_score: dict[str, float],
) -> list[FrameLabel]:
    """Deep defect area the frame's image sees of the map's defects (``views``, see
    ``framemasks``), or the pairs' estimate for a frame without a view; a frame with neither
    (no ok pair, no place on the map) is not analysed (``NOT_ANALYSED``, defect None)."""
    a_min = cfg.map.frame_min_area_m2
    out: list[FrameLabel] = []
    for f in drive.frames:
        view = views.get(f.filename)
        if view is not None:
            area = view.deep_area_m2
            p = area / (area + a_min) if area > 0 else 0.0
        elif f.filename in pair_score:
            p = pair_score[f.filename]
        else:
            out.append(FrameLabel(f.filename, None, None, NOT_ANALYSED))
            continue
        out.append(FrameLabel(f.filename, int(p >= 0.5), float(p), "3d"))
    return out


def pair_frame_scores(
    cfg: DetectionConfig,
    drive: Drive,
    pairs: list[PairResult],
    per_pair: dict[int, PairDefects],
) -> dict[str, float]:
    """The dissertation's per-frame decision from refined points alone.

    Frame k is seen by pair (k-1, k) (its pixels px_b) and pair (k, k+1) (px_a), which together
    cover its whole image. The deep refined points of both are binned on a grid of the frame's
    nadir view (``gsd.NadirView``: the image itself for a nadir camera, where the road has one
    scale) whose cells are one point spacing wide, and the occupied cells give the deep area.
    """
    view = NadirView(drive.camera)
    m_per_px = view.m_per_px
    items: dict[str, list[tuple[np.ndarray, float]]] = {}
    for k, pd in per_pair.items():
        p = pairs[k]
        deep = pd.refined & (-pd.dist_m >= cfg.map.frame_depth_m)
        for fn, px in ((p.frame_a, p.px_a), (p.frame_b, p.px_b)):
            lst = items.setdefault(fn, [])
            if deep.any():
                q = view.px(np.asarray(px, float)[deep])
                lst.append((q[np.all(np.isfinite(q), axis=1)], pd.area_per_point_m2))
    a_min = cfg.map.frame_min_area_m2
    scores: dict[str, float] = {}
    for fn, lst in items.items():
        n = sum(len(px) for px, _ in lst)
        if n < 3:
            scores[fn] = 0.0
            continue
        app = float(np.median([a for _, a in lst]))
        s_px = max(1.0, math.sqrt(app) / m_per_px)
        cells = np.unique(np.floor(np.vstack([px for px, _ in lst]) / s_px).astype(int), axis=0)
        area = len(cells) * (s_px * m_per_px) ** 2
        scores[fn] = area / (area + a_min)
    return scores


def fuse_labels(
    cfg: DetectionConfig,
    frames: list[FrameLabel],
    frame_probs: dict[str, float] | None,
    pairs: list[PairResult],
    rule: FusionRule | None = None,
) -> list[FrameLabel]:
    """Fig. 5.6: a confident CNN decides, otherwise 3D (frames no ok pair covers have no 3D)."""
    if not frame_probs:
        return frames
    if rule is None:
        rule = FusionRule(threshold=cfg.fusion_threshold)
    covered = {p.frame_a for p in pairs if p.ok} | {p.frame_b for p in pairs if p.ok}
    labels_3d = {
        f.filename: bool(f.defect)
        for f in frames
        if f.filename in covered and f.defect is not None  # not analysed: no 3D label
    }
    fused = fuse_frames(
        frame_probs,
        labels_3d,
        [f.filename for f in frames],
        rule.threshold,
        rule.confirm_defect_with_3d,
        rule.context_frames,
        rule.decide_3d,
    )
    out = []
    for f in frames:
        d = fused[f.filename]
        if f.defect is None and d.source != "cnn":  # neither 3D nor a confident CNN
            out.append(f)
            continue
        p = d.p_defect if d.source == "cnn" else f.p_defect if d.source == "3d" else d.p_defect
        if p is None or not math.isfinite(p):
            p = f.p_defect if f.p_defect is not None else d.p_defect
        out.append(FrameLabel(f.filename, int(d.defect), float(p), d.source))
    return out
