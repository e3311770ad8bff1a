"""CNN + 3D fusion (dissertation Fig. 5.6).

The CNN gives p = (p_non_defect, p_defect) per frame. When max(p) >= threshold the CNN decision
stands; otherwise the 3D physics result decides, which means reconstructing that pair. Frames the
CNN calls "defect" are reconstructed as well, because a defect must be measured: their source is
``fused`` (CNN decision, 3D measurement). Pure Python, no torch import.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

Source = Literal["cnn", "3d", "fused"]

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


def fuse_frames(
    frame_probs: Mapping[str, float] | None,
    labels_3d: Mapping[str, bool],
    filenames: Sequence[str],
    threshold: float = 0.95,
    confirm_defect_with_3d: bool = False,
) -> dict[str, FusedDecision]:
    """Fuse every frame in ``filenames``; frames missing from a mapping count as not available."""
    probs = frame_probs or {}
    return {
        fn: fuse(probs.get(fn), labels_3d.get(fn), threshold, confirm_defect_with_3d)
        for fn in filenames
    }


def pairs_to_reconstruct(
    frame_probs: Mapping[str, float],
    filenames: Sequence[str],
    threshold: float = 0.95,
) -> set[tuple[int, int]]:
    """Consecutive pairs (i, i+1) the physics pipeline must reconstruct.

    ``filenames`` are the drive's valid frames in capture order (position = ``Frame.index``).
    Frame i is measured from pair (i, i+1) (points live in camera i); the last frame uses
    (i-1, i). A frame without a CNN probability is always reconstructed.
    """
    n = len(filenames)
    out: set[tuple[int, int]] = set()
    for i, fn in enumerate(filenames):
        if not needs_3d(frame_probs.get(fn), threshold):
            continue
        if i + 1 < n:
            out.add((i, i + 1))
        elif i > 0:
            out.add((i - 1, i))
    return out
