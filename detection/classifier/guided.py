"""CNN-guided reconstruction: which pairs a fused run reconstructs, and why.

Fig. 5.6 reconstructs a pair only where the CNN is unsure or says "defect". Two additions make
the fused run safe for defects a single image cannot show:

1. **Sparse 3D audit** (``audit_every_m``, or ``audit_every_frames`` for a drive without OBD
   and GPS): wherever a stretch of the drive that long would hold no frame with 3D, one pair
   (i, i+1) is added, whatever the CNN says. A shallow rut under diffuse light is invisible to
   the eye and to the CNN (the bench's test_grey drive: a 20 mm deep, 6 m long rut over 11
   frames, p_defect <= 0.01 in most), but it is long, so a sparse audit meets it.
2. **Growth along 3D defects**: a frame whose own 3D shows a defect (the self-labelling rule,
   eq. 5.8-5.9) gets its whole image reconstructed, which gives each neighbour the pair it
   shares with the frame; a neighbour whose shared pair shows depth grows in turn, again and
   again, until the 3D shows clear road on both sides (``fusion.grow_pairs``). A defect the
   audit meets, or one that outlasts the CNN's context, is followed to its ends.

Audited and grown frames whose own 3D shows a defect by that rule are decided by their 3D
result (``FusionRule.decide_3d``); the others keep the CNN's decision.

With ``audit_probe`` (the default) an audit pair is first *probed* (``reconstruction.probe``:
corners tracked by Lucas-Kanade through the same estimator chain, ~60 ms of CPU against ~450
ms for a full pair) and becomes a full pair only when the probe fails or shows some depth
(more than ``audit_probe_max_deep_points`` points deeper than ``audit_probe_depth_frac`` x
Z^d). A probe that shows clear road settles the frame the way a clear full pair did: the CNN's
decision stands. Probes are not map pairs; they are kept in ``RUN/probes``.
``RUN/screening.json`` records every frame's CNN probability and why it got 3D, if it did.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from roadsurf.core.atomic import write_json_atomic
from roadsurf.detection.classifier.config import ClassifierConfig
from roadsurf.detection.classifier.fusion import (
    FusionRule,
    audit_pairs,
    cnn_confident,
    frame_pairs,
    frames_needing_3d,
    grow_pairs,
    pairs_to_reconstruct,
)
from roadsurf.detection.classifier.selflabel import figures_from_pairs, label_frame
from roadsurf.io.runfolder import SCREENING_JSON, RunFolder

if TYPE_CHECKING:
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)

ProbeSummary = dict[str, str | int | float | None]  # one audit probe in RUN/screening.json

MAX_GROWTH_ROUNDS = 200  # safety bound; each round adds at least one pair
UNSURE_WARN_SHARE = 0.5  # warn when the CNN is unsure about more than this share of frames


@dataclass
class GuidedResult:
    """The pairs a fused run reconstructed and the fusion rule its detection stage applies."""

    pairs: list[PairResult]  # in frame order
    rule: FusionRule
    reasons: dict[str, str]  # filename -> why 3D ran (unsure, defect, context, audit, grown)
    rounds: int  # reconstruction rounds (1 + growth rounds)
    probes: list[PairResult] = field(default_factory=list)  # audit probes, frame order
    cleared: frozenset[str] = frozenset()  # audited frames a probe showed clear (no full pair)


def plan_pairs(
    frame_probs: Mapping[str, float],
    filenames: list[str],
    cfg: ClassifierConfig,
    along_m: Sequence[float] | np.ndarray | None = None,
) -> tuple[set[tuple[int, int]], dict[int, tuple[int, int]], dict[str, str]]:
    """Pairs before any 3D result is known: (pairs the CNN's decisions need, {audited frame:
    its audit pair} for pairs only the audit needs, the reason of each frame that gets 3D).
    ``along_m`` (n,): each frame's distance along the drive (m) for the audit's spacing
    (``audit_every_m``); None counts frames (``audit_every_frames``)."""
    n = len(filenames)
    thr = cfg.fusion_threshold
    pairs = pairs_to_reconstruct(frame_probs, filenames, thr, cfg.context_frames)
    need = frames_needing_3d(frame_probs, filenames, thr, cfg.context_frames)
    reasons: dict[str, str] = {}
    for fn, nd in zip(filenames, need, strict=True):
        if not nd:
            continue
        p = frame_probs.get(fn)
        if p is None or p != p:
            reasons[fn] = "no_cnn"
        elif not cnn_confident(p, thr):
            reasons[fn] = "unsure"
        elif p >= 0.5:
            reasons[fn] = "defect"
        else:
            reasons[fn] = "context"
    # frames with 3D: both frames of every planned pair
    have = {i for pr in pairs for i in pr}
    if along_m is not None and cfg.audit_every_m > 0:
        audit = audit_pairs(n, cfg.audit_every_m, have, along_m)
    else:
        audit = audit_pairs(n, cfg.audit_every_frames, have)
    own = {}
    for i, pr in audit.items():
        if pr not in pairs:
            own[i] = pr
            reasons.setdefault(filenames[i], "audit")
    return pairs, own, reasons


def probe_depth_points(probe: PairResult, camera_height_m: float, cfg: ClassifierConfig) -> int:
    """Points of a probe PairResult deeper than ``audit_probe_depth_frac`` x Z^d (count)."""
    zd = cfg.audit_probe_depth_frac * cfg.depth_threshold_m(camera_height_m)
    return int(np.count_nonzero(np.asarray(probe.plane_dist_m, float) < -zd))


def _probe_summary(probe: PairResult, n_deep: int | None) -> ProbeSummary:
    d = np.asarray(probe.plane_dist_m, float)
    return {
        "status": probe.status,
        "points": int(probe.n_points),
        "deep_points": n_deep,
        "max_depth_mm": round(float(-d.min()) * 1e3, 2) if probe.ok and d.size else None,
    }


def run(
    cfg: ClassifierConfig,
    filenames: list[str],
    frame_probs: Mapping[str, float],
    camera_height_m: float,
    reconstruct: Callable[[set[tuple[int, int]]], list[PairResult]],
    run_dir: Path | None = None,
    along_m: Sequence[float] | np.ndarray | None = None,
    probe: Callable[[set[tuple[int, int]]], list[PairResult]] | None = None,
) -> GuidedResult:
    """Reconstruct what the screened drive needs; ``reconstruct(only_pairs)`` runs the
    reconstruction stage on those (index_a, index_b) pairs (cached pairs are reused) and
    returns its PairResults. ``filenames`` are the drive's valid frames in capture order;
    ``along_m`` their distances along the drive (m, ``roadsurf.io.drive.along_track_m``), which
    space the audit in metres (None: in frames). ``probe(only_pairs)`` (``reconstruction.probe``)
    returns cheap PairResults for the audit pairs; None (or ``audit_probe: false``) makes every
    audit pair a full pair."""
    n = len(filenames)
    pos = {fn: i for i, fn in enumerate(filenames)}
    if along_m is not None and len(along_m) != n:
        raise ValueError(f"along_m has {len(along_m)} values for {n} frames")
    todo, audit, reasons = plan_pairs(frame_probs, filenames, cfg, along_m)
    probes: list[PairResult] = []
    probe_info: dict[str, ProbeSummary] = {}
    cleared: set[str] = set()
    if probe is not None and cfg.audit_probe and audit:
        probes = list(probe(set(audit.values())))
        by_pair = {(p.index_a, p.index_b): p for p in probes}
        for i, pr in audit.items():
            p = by_pair.get(pr)
            n_deep = probe_depth_points(p, camera_height_m, cfg) if p is not None and p.ok else None
            if p is not None:
                probe_info[filenames[i]] = _probe_summary(p, n_deep)
            if n_deep is not None and n_deep <= cfg.audit_probe_max_deep_points:
                cleared.add(filenames[i])
            else:  # failed, or some depth: the full pair decides
                todo.add(pr)
        log.info(
            "3D audit: %d probe(s), %d clear, %d to full pairs",
            len(audit),
            len(cleared),
            len(audit) - len(cleared),
        )
    else:
        todo |= set(audit.values())
    rounds = 0
    while True:
        rounds += 1
        pairs = reconstruct(set(todo))
        # depth and extent per frame (eq. 5.8-5.9): the 3D evidence for growth and overruling
        figs = figures_from_pairs(pairs, camera_height_m, cfg)
        if rounds > MAX_GROWTH_ROUNDS:
            break
        new: set[tuple[int, int]] = set()
        # a frame that needed 3D but whose pairs all failed (e.g. too little overlap on one
        # side) gets its other pair: one pair per frame is the plan, not the limit
        ok = {fn for p in pairs if p.ok for fn in (p.frame_a, p.frame_b)} | cleared
        for fn in reasons:
            if fn not in ok and fn in pos:
                new |= frame_pairs(pos[fn], n) - todo
        if cfg.grow_along_defects:
            # a frame with some depth but too little for the rule (ambiguous) grows too: a rut
            # tapers at its ends, and with low overlap a frame's pair may see only its edge
            lab_now = {pos[fn]: label_frame(f, None, cfg)[0] for fn, f in figs.items() if fn in pos}
            defect = [i for i, v in lab_now.items() if v != 0]
            ambiguous = [i for i, v in lab_now.items() if v is None]
            for j, prs in grow_pairs(defect, n, ambiguous).items():
                new |= prs - todo
                # a neighbour of a 3D defect is decided by 3D, even when others' pairs cover it
                reasons.setdefault(filenames[j], "grown")
        if not new:
            break
        todo |= new
    # a sure CNN "non-defect" is overturned only by clear 3D evidence: the depth-and-extent rule
    # that drives the growth (eq. 5.8-5.9) must see a defect in the frame, or some depth in a
    # frame next to an anchor (below); the detection stage's label then decides. A
    # frame grown only because its neighbour is deep, or an audited frame on clear road, keeps
    # the CNN's decision (borderline depressions near Z^d would otherwise flip with the map's
    # global noise estimate)
    lab = {fn: label_frame(f, None, cfg)[0] for fn, f in figs.items()}
    # frames that anchor a defect: the rule sees one, or the CNN was not sure the frame is
    # clear and its 3D has some depth too
    anchor = {pos[fn] for fn, v in lab.items() if v == 1 and fn in pos} | {
        pos[fn]
        for fn, r in reasons.items()
        if r in ("unsure", "defect", "no_cnn") and lab.get(fn, 0) != 0 and fn in pos
    }
    decide = frozenset(
        fn
        for fn, r in reasons.items()
        if r in ("audit", "grown")
        and fn in lab
        # the rule sees a defect, or some depth right next to an anchor (the tapered end or
        # the rim of the same defect, not an isolated borderline depression)
        and (lab[fn] == 1 or (lab[fn] is None and {pos[fn] - 1, pos[fn] + 1} & anchor))
    )
    rule = FusionRule(
        threshold=cfg.fusion_threshold,
        confirm_defect_with_3d=cfg.confirm_defect_with_3d,
        context_frames=cfg.context_frames,
        decide_3d=decide,
    )
    counts = {r: sum(1 for v in reasons.values() if v == r) for r in sorted(set(reasons.values()))}
    log.info(
        "CNN-guided reconstruction: %d of %d pairs in %d round(s); frames with 3D by reason %s",
        len(todo),
        max(0, n - 1),
        rounds,
        counts,
    )
    warnings = []
    n_unsure = counts.get("unsure", 0) + counts.get("no_cnn", 0)
    if n and n_unsure > UNSURE_WARN_SHARE * n:
        warnings.append(
            f"the CNN was unsure about (or could not screen) {n_unsure} of {n} frames, so the "
            "fused run saves little time: the model may not know this road, camera or light. "
            "Label some of these drives (`roadsurf label`) and retrain (`roadsurf train`)."
        )
        log.warning(warnings[-1])
    if run_dir is not None:
        write_json_atomic(
            RunFolder(run_dir).path(SCREENING_JSON),
            {
                "fusion_threshold": cfg.fusion_threshold,
                "context_frames": cfg.context_frames,
                "audit_every_m": cfg.audit_every_m if along_m is not None else None,
                "audit_every_frames": cfg.audit_every_frames if along_m is None else None,
                "audit_probe": bool(probe is not None and cfg.audit_probe),
                "audit_probes": len(probes),
                "audit_probes_clear": len(cleared),
                "grow_along_defects": cfg.grow_along_defects,
                "confirm_defect_with_3d": cfg.confirm_defect_with_3d,
                "pairs_reconstructed": len(todo),
                "pairs_total": max(0, n - 1),
                "rounds": rounds,
                "frames_with_3d_by_reason": counts,
                "warnings": warnings,
                "frames": [
                    {
                        "filename": fn,
                        "p_defect": _num(frame_probs.get(fn)),
                        "3d_reason": reasons.get(fn),
                        # an audited/grown frame whose 3D shows a defect: 3D overrules the CNN
                        "3d_overrules_cnn": fn in decide,
                        # the audit probe of this frame, if it had one (RUN/probes)
                        "audit_probe": probe_info.get(fn),
                    }
                    for fn in filenames
                ],
            },
        )
    return GuidedResult(
        pairs=pairs,
        rule=rule,
        reasons=reasons,
        rounds=rounds,
        probes=probes,
        cleared=frozenset(cleared),
    )


def _num(p: float | None) -> float | None:
    return None if p is None or p != p else round(float(p), 6)
