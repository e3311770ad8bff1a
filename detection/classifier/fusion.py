"""CNN + 3D fusion (dissertation Fig. 5.6).

The CNN gives p = (p_non_defect, p_defect) per frame. When max(p) >= threshold the CNN decision
stands; otherwise the 3D physics result decides, which means reconstructing that pair. Frames the
CNN calls "defect" are reconstructed as well, because a defect must be measured: their source is
``fused``: CNN decision and 3D measurement; with ``confirm_defect_with_3d`` (the product's
default) the 3D label, which exists anyway, confirms or overrules the sure CNN "defect".
Pure Python, no torch import.

Beyond the dissertation, ``context_frames`` (default 1) uses the drive's temporal context:
consecutive frames overlap, so a defect the CNN sees in frame i usually enters the view in
frame i-1 or leaves it in i+1, where only a sliver shows and the CNN tends to call the frame
clear with confidence. A frame within ``context_frames`` of a frame the CNN leans "defect" on
(p_defect >= 0.5, sure or not, or no CNN probability) is therefore decided by 3D (source
``3d``), from the pair it shares with that frame, where such a sliver lies; its far side is
reconstructed only when that pair shows depth (session 18: 78 instead of 111 pairs on a
1000-frame drive). Frames the CNN is merely unsure about but leans "clear" on get
3D themselves but do not pull in their neighbours: on a long drive those are scattered over
plain road, where neighbours would double the cost without a defect to catch (round 3; round 2
took the neighbours of every frame that needed 3D). ``context_frames=0`` is the dissertation's
per-frame rule.
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

Source = Literal["cnn", "3d", "fused"]

CONTEXT_FRAMES = 1  # default neighbourhood (frames) of the temporal-context extension

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FusedDecision:
    """The fused label of one frame."""

    defect: bool  # final frame label
    p_defect: float  # CNN probability of "defect" (NaN when no CNN ran)
    source: Source  # cnn: CNN alone; 3d: CNN unsure, 3D decided; fused: CNN sure + 3D measured


def cnn_confident(p_defect: float, threshold: float = 0.95) -> bool:
    """True when max(p_defect, 1 - p_defect) >= threshold (the CNN decision stands)."""
    return max(p_defect, 1.0 - p_defect) >= threshold


def needs_3d(p_defect: float | None, threshold: float = 0.95) -> bool:
    """Whether the physics pipeline must run for this frame: CNN unsure, or CNN says defect."""
    if p_defect is None or p_defect != p_defect:  # no CNN (or NaN): 3D as usual
        return True
    return not cnn_confident(p_defect, threshold) or p_defect >= 0.5


def fuse(
    p_defect: float | None,
    defect_3d: bool | None,
    threshold: float = 0.95,
    confirm_defect_with_3d: bool = False,
) -> FusedDecision:
    """Fig. 5.6 for one frame.

    ``p_defect``: CNN probability of the defect class in [0, 1], or None when no CNN ran.
    ``defect_3d``: the physics label, or None when the pair was not reconstructed (or failed).
    """
    if not 0.5 <= threshold <= 1.0:
        raise ValueError(f"fusion threshold must be in [0.5, 1], got {threshold}")
    if p_defect is None or p_defect != p_defect:
        return FusedDecision(bool(defect_3d), float("nan"), "3d")
    p = float(p_defect)
    cnn_says = p >= 0.5
    if cnn_confident(p, threshold):
        if cnn_says and defect_3d is not None:
            label = bool(defect_3d) if confirm_defect_with_3d else True
            return FusedDecision(label, p, "fused")
        return FusedDecision(cnn_says, p, "cnn")
    if defect_3d is None:
        # nothing better available (reconstruction failed for the pair): fall back to the CNN
        return FusedDecision(cnn_says, p, "cnn")
    return FusedDecision(bool(defect_3d), p, "3d")


def leans_defect(p_defect: float | None) -> bool:
    """CNN says "defect" (p >= 0.5, confident or not), or there is no CNN probability."""
    return p_defect is None or p_defect != p_defect or p_defect >= 0.5


def frames_needing_3d(
    frame_probs: Mapping[str, float],
    filenames: Sequence[str],
    threshold: float = 0.95,
    context_frames: int = CONTEXT_FRAMES,
) -> list[bool]:
    """Per frame (capture order): must the physics pipeline see it? Unsure or defect frames,
    frames without a CNN probability, and the neighbours within ``context_frames`` of frames
    the CNN leans "defect" on (``leans_defect``)."""
    flags = [needs_3d(frame_probs.get(fn), threshold) for fn in filenames]
    lean = [leans_defect(frame_probs.get(fn)) for fn in filenames]
    k = max(0, int(context_frames))
    n = len(flags)
    return [flags[i] or any(lean[max(0, i - k) : min(n, i + k + 1)]) for i in range(n)]


@dataclass(frozen=True)
class FusionRule:
    """The parameters of one fused run, shared by the pair selection and the frame fusion."""

    threshold: float = 0.95  # the CNN decision stands when max(p) >= this (Fig. 5.6)
    confirm_defect_with_3d: bool = True  # a sure CNN "defect" needs the 3D result to agree
    context_frames: int = CONTEXT_FRAMES  # neighbours of defect-leaning frames decided by 3D
    # frames reconstructed whatever the CNN said (audit, growth along a 3D defect): their 3D
    # result, when there is one, decides over a CNN "non-defect"
    decide_3d: frozenset[str] = field(default_factory=frozenset)


def fuse_frames(
    frame_probs: Mapping[str, float] | None,
    labels_3d: Mapping[str, bool],
    filenames: Sequence[str],
    threshold: float = 0.95,
    confirm_defect_with_3d: bool = False,
    context_frames: int = CONTEXT_FRAMES,
    decide_3d: Collection[str] = (),
) -> dict[str, FusedDecision]:
    """Fuse every frame in ``filenames`` (capture order); frames missing from a mapping count
    as not available. A confident CNN "non-defect" next to a frame that needed 3D (temporal
    context, see the module docstring), or listed in ``decide_3d`` (audited or grown frames,
    see ``detection.classifier.guided``), is decided by 3D when its 3D result exists."""
    probs = frame_probs or {}
    if not probs:
        return {fn: fuse(None, labels_3d.get(fn), threshold) for fn in filenames}
    ctx = frames_needing_3d(probs, filenames, threshold, context_frames)
    forced = set(decide_3d)
    out: dict[str, FusedDecision] = {}
    for fn, need in zip(filenames, ctx, strict=True):
        p, d3 = probs.get(fn), labels_3d.get(fn)
        d = fuse(p, d3, threshold, confirm_defect_with_3d)
        if (need or fn in forced) and d.source == "cnn" and d3 is not None and p is not None:
            d = FusedDecision(bool(d3), float(p), "3d")
        out[fn] = d
    return out


def pairs_to_reconstruct(
    frame_probs: Mapping[str, float],
    filenames: Sequence[str],
    threshold: float = 0.95,
    context_frames: int = CONTEXT_FRAMES,
) -> set[tuple[int, int]]:
    """Consecutive pairs (i, i+1) the physics pipeline must reconstruct.

    ``filenames`` are the drive's valid frames in capture order (position = ``Frame.index``).
    A frame that needs 3D on its own (unsure, "defect" or no CNN probability) gets its forward
    pair (i, i+1) (the last frame: (i-1, i)). Its backward pair (i-1, i) is added as well when
    the frame leans "defect" (a defect is measured over the whole image) or when frame i-1
    needs 3D itself (the pair is then i-1's forward pair anyway). Otherwise frame i-1 is one
    the CNN is sure is clear, and the part of frame i that (i, i+1) misses (what leaves the
    view) is the part frame i-1 also showed, so a run of k frames the CNN is unsure about costs
    k pairs, not k+1. When a frame's pairs all fail, ``detection.classifier.guided`` adds its
    other pair in the next round.

    A context frame (within ``context_frames`` of a frame the CNN leans "defect" on) gets only
    the pairs that link it to that frame: the sliver of the defect it may show lies in the part
    it shares with its neighbour. Its far side, which the CNN is sure is clear, is
    reconstructed only when that shared 3D shows depth (growth, ``grow_pairs``).
    """
    n = len(filenames)
    need = frames_needing_3d(frame_probs, filenames, threshold, context_frames)
    own = [needs_3d(frame_probs.get(fn), threshold) for fn in filenames]
    lean = [leans_defect(frame_probs.get(fn)) for fn in filenames]
    k = max(0, int(context_frames))
    out: set[tuple[int, int]] = set()
    for i, nd in enumerate(need):
        if not nd:
            continue
        if not own[i]:  # context only: the pairs toward the defect-leaning frame(s)
            if i + 1 < n and any(lean[i + 1 : i + k + 1]):
                out.add((i, i + 1))
            if i >= 1 and any(lean[max(0, i - k) : i]):
                out.add((i - 1, i))
            continue
        if i + 1 < n:
            out.add((i, i + 1))
        if i >= 1 and (i + 1 >= n or need[i - 1] or lean[i]):
            out.add((i - 1, i))
    return out


def frame_pairs(i: int, n: int) -> set[tuple[int, int]]:
    """Both pairs that see frame ``i`` of ``n`` (its whole image): (i-1, i) and (i, i+1)."""
    return {(j, j + 1) for j in (i - 1, i) if 0 <= j and j + 1 < n}


def audit_pairs(
    n: int,
    every: float,
    have_3d: Collection[int] = (),
    along: Sequence[float] | np.ndarray | None = None,
) -> dict[int, tuple[int, int]]:
    """{frame: pair} for the sparse 3D audit: frames get one pair (i, i+1) wherever needed so
    that every stretch of ``every`` along the drive holds at least one frame with 3D, counting
    the frames in ``have_3d`` (already reconstructed for another reason). A defect longer than
    ``every`` therefore always meets a 3D sample. ``along`` (n,) is each frame's position
    along the drive (m, non-decreasing) and ``every`` is then in metres; without it both count
    frames. ``every <= 0`` means no audit."""
    if every <= 0 or n < 2:
        return {}
    pos = np.arange(n, dtype=float) if along is None else np.asarray(along, dtype=float)
    if pos.shape != (n,):
        raise ValueError(f"along has shape {pos.shape}, expected ({n},)")
    have = set(have_3d)
    out = {}
    last = pos[0] - max(pos[1] - pos[0], 0.0)  # a virtual frame before the first
    for i in range(n):
        if i in have:
            last = pos[i]
        elif pos[i] - last >= every - 1e-9:  # 10 steps of 0.4 m are 4 m
            out[i] = (i, i + 1) if i + 1 < n else (i - 1, i)
            last = pos[i]
    return out


def grow_pairs(
    defect_frames: Iterable[int], n: int, ambiguous: Collection[int] = ()
) -> dict[int, set[tuple[int, int]]]:
    """{frame: pairs} for the growth along 3D defects.

    A 3D defect frame i gets its whole image, both of its pairs; its neighbours i-1 and i+1
    get the pair they share with i. A defect that goes on into a neighbour crosses that shared
    part, so the neighbour shows depth there, is a defect frame of the next round and grows in
    turn: the defect is followed along the drive to its ends, and the far side of a clear
    neighbour is not reconstructed. A frame in ``ambiguous`` (some depth, too little for the
    rule: a tapered end, or the edge of a defect that a low-overlap pair barely sees) gives
    its neighbours their whole images too, so growth goes on through it."""
    amb = set(ambiguous)
    out: dict[int, set[tuple[int, int]]] = {}
    for i in defect_frames:
        if not 0 <= i < n:
            continue
        out.setdefault(i, set()).update(frame_pairs(i, n))
        for j, pr in ((i - 1, (i - 1, i)), (i + 1, (i, i + 1))):
            if 0 <= j < n:
                out.setdefault(j, set()).update(frame_pairs(j, n) if i in amb else {pr})
    return out
