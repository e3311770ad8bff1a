"""Fusion rule, augmentation and self-labelling (eq. 5.8-5.9) on seeded synthetic inputs."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from roadsurf.core.errors import RoadsurfError
from roadsurf.detection.classifier import augment
from roadsurf.detection.classifier.config import ClassifierConfig
from roadsurf.detection.classifier.fusion import fuse, fuse_frames, needs_3d, pairs_to_reconstruct
from roadsurf.detection.classifier.selflabel import FrameFigures, frame_figures, label_frame
from roadsurf.io.formats import write_geojson
from roadsurf.io.runfolder import SCREENING_JSON, pair_filename
from roadsurf.reconstruction.types import PairResult, save_pair


@pytest.mark.parametrize("thr", [0.8, 0.95])
def test_fusion_switches_at_the_threshold(thr: float) -> None:
    eps = 1e-6
    # confident non-defect: the CNN decision stands, no 3D needed
    d = fuse(1 - thr, defect_3d=None, threshold=thr)
    assert (d.defect, d.source) == (False, "cnn") and not needs_3d(1 - thr, thr)
    # just below the threshold: 3D decides, whatever the CNN leans to
    for p in (1 - thr + eps, 0.5, thr - eps):
        assert needs_3d(p, thr)
        assert fuse(p, defect_3d=True, threshold=thr).source == "3d"
        assert fuse(p, defect_3d=True, threshold=thr).defect is True
        assert fuse(p, defect_3d=False, threshold=thr).defect is False
    # confident defect: the CNN decision stands; 3D runs to measure it -> "fused"
    d = fuse(thr, defect_3d=False, threshold=thr)
    assert (d.defect, d.source) == (True, "fused") and needs_3d(thr, thr)
    assert fuse(thr, defect_3d=False, threshold=thr, confirm_defect_with_3d=True).defect is False
    # no CNN: 3D as usual
    d = fuse(None, defect_3d=True, threshold=thr)
    assert (d.defect, d.source) == (True, "3d") and math.isnan(d.p_defect)


def test_fuse_frames_and_pairs_to_reconstruct() -> None:
    names = ["a", "b", "c", "d", "e", "f"]
    probs = {"a": 0.001, "b": 0.6, "c": 0.001, "d": 0.002, "e": 0.001, "f": 0.999}
    # the dissertation's per-frame rule: only unsure (b) and defect (f) frames
    assert pairs_to_reconstruct(probs, names, 0.95, context_frames=0) == {(0, 1), (1, 2), (4, 5)}
    d3 = {"b": True, "c": True, "e": True, "f": True}
    fused = fuse_frames(probs, d3, names, 0.95, context_frames=0)
    assert [fused[n].source for n in names] == ["cnn", "3d", "cnn", "cnn", "cnn", "fused"]
    assert [fused[n].defect for n in names] == [False, True, False, False, False, True]
    # temporal context: neighbours a, c of b and e of f get 3D, which decides them, but only
    # from the pair each shares with its defect-leaning neighbour (a sliver of b's defect lies
    # in that shared part): c gets (1, 2), not (2, 3). Their far sides are reconstructed only
    # when the shared pair shows depth (growth, test below)
    assert pairs_to_reconstruct(probs, names, 0.95, context_frames=1) == {(0, 1), (1, 2), (4, 5)}
    # with a wider context the pairs link each context frame to the defect-leaning frame
    assert pairs_to_reconstruct(probs, names, 0.95, context_frames=2) == {
        (0, 1),
        (1, 2),
        (2, 3),
        (3, 4),
        (4, 5),
    }
    fused = fuse_frames(probs, d3, names, 0.95, context_frames=1)
    assert [fused[n].source for n in names] == ["cnn", "3d", "3d", "cnn", "3d", "fused"]
    assert [fused[n].defect for n in names] == [False, True, True, False, True, True]
    # a frame the CNN is unsure about but leans "clear" on (p < 0.5) gets 3D itself, but its
    # neighbours are not pulled in: on plain road they would double the cost for nothing. One
    # pair is enough: the strip (1, 2) misses of b is in sure-clear a
    probs_u = {**probs, "b": 0.3}
    assert pairs_to_reconstruct(probs_u, names, 0.95, context_frames=1) == {(1, 2), (4, 5)}
    # a run of unsure frames costs one pair per frame; one leaning "defect" keeps both
    probs_r = {**probs_u, "c": 0.2, "d": 0.4}
    assert pairs_to_reconstruct(probs_r, names, 0.95, context_frames=0) == {
        (1, 2),
        (2, 3),
        (3, 4),
        (4, 5),
    }
    assert (0, 1) in pairs_to_reconstruct({**probs_u, "b": 0.7}, names, 0.95, context_frames=0)
    fused = fuse_frames(probs_u, d3, names, 0.95, context_frames=1)
    assert [fused[n].source for n in names] == ["cnn", "3d", "cnn", "cnn", "3d", "fused"]
    # a frame the CNN could not read is reconstructed
    assert (0, 1) in pairs_to_reconstruct({}, names, 0.95)
    assert all(d.source == "3d" for d in fuse_frames(None, d3, names).values())


def _blob(size: int = 64, cx: int = 20, cy: int = 40) -> np.ndarray:
    img = np.full((size, size), 120, np.uint8)
    cv2.circle(img, (cx, cy), 5, 20, -1)
    return img


def _dark_centre(img: np.ndarray) -> tuple[float, float]:
    ys, xs = np.nonzero(img < 70)
    return float(xs.mean()), float(ys.mean())


def test_augmentations_move_rotate_and_flip_the_defect() -> None:
    img = _blob()
    bbox = (15.0, 35.0, 25.0, 45.0)
    cx, cy = _dark_centre(augment.translate_to(img, bbox, "left"))
    assert abs(cx - 16) < 1.5 and abs(cy - 32) < 1.5
    cx, cy = _dark_centre(augment.translate_to(img, bbox, "down"))
    assert abs(cx - 32) < 1.5 and abs(cy - 48) < 1.5
    cx, cy = _dark_centre(augment.rotate(img, 2))
    assert abs(cx - 43) < 1.5 and abs(cy - 23) < 1.5
    cx, _ = _dark_centre(augment.flip(img, "h"))
    assert abs(cx - 43) < 1.5
    big = augment.rescale(img, bbox, 1.25)
    assert (big < 70).sum() > 1.3 * (img < 70).sum()
    rng = np.random.default_rng(0)
    outs = augment.augment_image(img, bbox, 15, rng)
    assert len(outs) == 15 and len({n for n, _ in outs}) == 15
    assert all(o.shape == img.shape and o.dtype == np.uint8 for _, o in outs)
    assert augment.copies_needed(10, 1000, 1.0, 12) == 12
    assert augment.copies_needed(10, 50, 1.0, 12) == 4
    assert augment.copies_needed(0, 50, 1.0, 12) == 0


def test_photometric_augmentation_varies_lighting_but_keeps_the_image() -> None:
    import torch

    rng = np.random.default_rng(3)
    x = torch.from_numpy(np.stack([_blob() for _ in range(64)]) + rng.integers(0, 3, (64, 64, 64)))
    x = x.to(torch.uint8).unsqueeze(1)
    same = augment.photometric(x, torch.Generator().manual_seed(0), 0.0)
    assert torch.equal(same, x.float())  # strength 0 is the identity
    a = augment.photometric(x, torch.Generator().manual_seed(1))
    b = augment.photometric(x, torch.Generator().manual_seed(1))
    assert torch.equal(a, b) and a.shape == x.shape  # seeded
    assert float(a.min()) >= 0.0 and float(a.max()) <= 255.0
    # every image gets its own exposure / tone: the batch's brightness spreads out
    means = a.mean(dim=(1, 2, 3))
    assert float(means.std()) > 5.0 > float(x.float().mean(dim=(1, 2, 3)).std())
    # the defect (dark blob) stays darker than the road in (nearly) every image
    core = a[:, 0, 36:44, 16:24].mean(dim=(1, 2))
    road = a[:, 0, 5:15, 45:60].mean(dim=(1, 2))
    assert float((core < road).float().mean()) >= 0.95
    assert ClassifierConfig().photometric_strength > 0  # on by default for training


def _pair(i: int, depth_m: float, n_deep: int, rng: np.random.Generator) -> PairResult:
    """Road points at 1 m (camera z down) plus n_deep points depth_m below, in a 10 cm patch."""
    road = np.column_stack([rng.uniform(-0.5, 0.5, 300), rng.uniform(-0.4, 0.4, 300)])
    d = rng.normal(0, 0.0008, 300)
    if n_deep:
        hole = rng.uniform(-0.05, 0.05, (n_deep, 2)) + [0.1, 0.0]
        road = np.vstack([road, hole])
        d = np.concatenate([d, -depth_m * rng.uniform(0.6, 1.0, n_deep)])
    pts = np.column_stack([road, 1.0 - d])
    px = 500 * pts[:, :2] + [320, 240]
    return PairResult(
        f"{i:04d}.png",
        f"{i + 1:04d}.png",
        i,
        i + 1,
        "proposed",
        "ok",
        points_cam_a_m=pts,
        px_a=px,
        px_b=px - [0, 40],
        plane_dist_m=d,
    )


def test_frame_figures_and_labels_from_pairs(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    names = [f"{i:04d}.png" for i in range(5)]
    (tmp_path / "pairs").mkdir()
    specs = {0: (0.0, 0), 1: (0.03, 40), 2: (0.03, 40), 3: (0.0, 0)}
    for i, (dep, n) in specs.items():
        save_pair(tmp_path / "pairs" / pair_filename(i, i + 1), _pair(i, dep, n, rng))
    cfg = ClassifierConfig()
    figs = frame_figures(tmp_path, names, 1.0, cfg)
    assert figs["0000.png"].n_deep == 0 and figs["0000.png"].max_depth_m < 0.005
    assert figs["0002.png"].n_deep >= 30 and 0.02 < figs["0002.png"].max_depth_m <= 0.03
    assert 40 < figs["0002.png"].extent_cm2 <= 100  # hull inside the 10 cm x 10 cm patch
    x0, y0, x1, y1 = figs["0002.png"].bbox_px
    assert 320 + 500 * 0.05 - 1 <= x0 and x1 <= 320 + 500 * 0.15 + 1
    # frame 4 is only in pair (3, 4): clear road
    assert figs["0004.png"].n_deep == 0
    # α = Z^d / h scales with the camera height: at h = 4 m and α = 0.01, Z^d = 40 mm > 30 mm
    deep_cfg = ClassifierConfig(defect_alpha=0.01)
    assert frame_figures(tmp_path, names, 4.0, deep_cfg)["0002.png"].n_deep == 0

    assert label_frame(figs["0002.png"], (True, "3d"), cfg) == (1, "physics+depth+extent")
    assert label_frame(figs["0000.png"], (False, "3d"), cfg) == (0, "physics+depth+extent")
    assert label_frame(figs["0002.png"], (False, "3d"), cfg)[0] is None  # disagreement dropped
    assert label_frame(figs["0002.png"], None, cfg) == (1, "depth+extent")
    assert label_frame(None, (True, "3d"), cfg)[0] is None
    assert label_frame(figs["0000.png"], (False, "cnn"), cfg)[0] is None
    speck = FrameFigures(0.02, 4.0, 3, 300, None)  # a few deep points, tiny footprint: road
    assert label_frame(speck, (False, "3d"), cfg) == (0, "physics+depth+extent")
    some = FrameFigures(0.02, 12.0, 6, 300, None)  # some depth below the extent: not clear
    assert label_frame(some, (False, "3d"), cfg)[0] is None
    assert label_frame(some, (False, "3d"), ClassifierConfig(drop_ambiguous=False))[0] == 0


def test_defect_types_per_frame_and_the_cnn_skip_rule(tmp_path: Path) -> None:
    from roadsurf.detection.classifier.selflabel import read_defect_types, skip_for_cnn

    def feat(kind: str, frames: list[str]) -> dict:
        ring = [[0.0, 0.0], [1e-5, 0.0], [1e-5, 1e-5], [0.0, 0.0]]
        return {
            "type": "Feature",
            "geometry": {"type": "Polygon", "coordinates": [ring]},
            "properties": {"type": kind, "frames": frames},
        }

    write_geojson(
        tmp_path / "defects.geojson",
        [feat("rut", ["a.png", "b.png"]), feat("pothole", ["b.png", "c.png"])],
    )
    types = read_defect_types(tmp_path)
    assert types == {"a.png": {"rut"}, "b.png": {"rut", "pothole"}, "c.png": {"pothole"}}
    cfg = ClassifierConfig()
    assert cfg.cnn_skip_types == ("rut",)
    assert skip_for_cnn(1, types["a.png"], cfg) == "left_to_3d(rut)"
    assert skip_for_cnn(1, types["b.png"], cfg) is None  # a pothole shows: taught
    assert skip_for_cnn(0, types["a.png"], cfg) is None  # clear frames stay clear
    assert skip_for_cnn(1, None, cfg) is None  # defect depth without a typed defect: taught
    assert skip_for_cnn(1, types["a.png"], ClassifierConfig(cnn_skip_types=())) is None
    assert read_defect_types(tmp_path / "nowhere") == {}
    old = feat("rut", ["a.png"])
    del old["properties"]["frames"]  # a defect without frames (older run folders): no types
    write_geojson(tmp_path / "old" / "defects.geojson", [old])
    assert read_defect_types(tmp_path / "old") == {}
    bad = feat("rut", ["a.png"])
    bad["properties"]["frames"] = "a.png"
    write_geojson(tmp_path / "bad" / "defects.geojson", [bad])
    with pytest.raises(RoadsurfError, match="frames"):
        read_defect_types(tmp_path / "bad")


def test_growth_goes_through_a_tapered_end_and_an_isolated_depression_stays_cnn(
    tmp_path: Path,
) -> None:
    """With low overlap a rut's frame may have only some depth in its pairs (the rule's
    "ambiguous": 3 deep points). Growth goes on through it, across a clear pair (15, 16), and
    finds the rest of the rut beyond; that frame is decided by 3D because its neighbour is a
    3D defect. So are ambiguous
    neighbours of a frame the CNN was unsure about whose 3D shows some depth (a small pothole's
    rim). An ambiguous audited frame with no such anchor beside it keeps the CNN's decision."""
    from roadsurf.detection.classifier import guided

    n = 30
    names = [f"{i:04d}.png" for i in range(n)]
    deep = {(9, 10), (10, 11), (11, 12), (12, 13), (13, 14), (16, 17)}
    some = {(14, 15), (19, 20), (23, 24), (24, 25), (25, 26)}
    rng = np.random.default_rng(4)
    calls: list[set[tuple[int, int]]] = []

    def reconstruct(only: set[tuple[int, int]]) -> list[PairResult]:
        calls.append(set(only))
        return [_pair(a, 0.03, 40 if (a, b) in deep else 3 if (a, b) in some else 0, rng)
                for a, b in sorted(only)]  # fmt: skip

    probs = dict.fromkeys(names, 0.001)
    probs["0024.png"] = 0.3  # the CNN is unsure here and the 3D shows some depth: an anchor
    res = guided.run(ClassifierConfig(audit_every_frames=10), names, probs, 1.0, reconstruct)
    done = calls[-1]
    assert {"0023.png", "0025.png"} <= res.rule.decide_3d and "0022.png" not in res.rule.decide_3d
    assert {(14, 15), (15, 16), (16, 17), (17, 18)} <= done  # through frame 15 to the rest
    assert {"0015.png", "0016.png", "0017.png"} <= res.rule.decide_3d
    assert res.reasons["0019.png"] == "audit" and "0019.png" not in res.rule.decide_3d
    # growth stops on clear road: frame 8's shared pair (8, 9) is clear, so its far side is
    # not reconstructed
    assert (8, 9) in done and (7, 8) not in done


def test_a_context_frame_far_side_is_reconstructed_only_when_its_shared_pair_is_deep() -> None:
    """The CNN says "defect" on frames 5 and 6 and is sure 4 and 7 are clear. A pothole seen
    by (5, 6) only: the run reconstructs (4, 5), (5, 6), (6, 7) in one round, not the far
    sides (3, 4) and (7, 8) of the context frames. A defect that goes on into frame 7 shows in
    the shared pair (6, 7), and growth follows it until the 3D shows clear road."""
    from roadsurf.detection.classifier import guided

    n = 20
    names = [f"{i:04d}.png" for i in range(n)]
    probs = dict.fromkeys(names, 0.001) | {"0005.png": 0.99, "0006.png": 0.99}
    cfg = ClassifierConfig(audit_every_frames=0)
    rng = np.random.default_rng(8)

    def run(deep: set[tuple[int, int]]) -> tuple[set[tuple[int, int]], guided.GuidedResult]:
        calls: list[set[tuple[int, int]]] = []

        def reconstruct(only: set[tuple[int, int]]) -> list[PairResult]:
            calls.append(set(only))
            return [_pair(a, 0.03, 40 if (a, b) in deep else 0, rng) for a, b in sorted(only)]

        res = guided.run(cfg, names, probs, 1.0, reconstruct)
        return calls[-1], res

    done, res = run({(5, 6)})
    assert done == {(4, 5), (5, 6), (6, 7)} and res.rounds == 1
    done, res = run({(5, 6), (6, 7), (7, 8)})
    assert {(4, 5), (5, 6), (6, 7), (7, 8), (8, 9)} <= done
    assert (9, 10) not in done and (3, 4) not in done
    assert res.reasons["0008.png"] == "grown" and "0008.png" in res.rule.decide_3d


def test_audit_and_growth_follow_a_defect_the_cnn_cannot_see(tmp_path: Path) -> None:
    """A long shallow defect (frames 9-15) the CNN is sure is clear road: the sparse audit meets
    it, growth follows it to both ends, and 3D decides those frames (detection.classifier.guided).
    """
    from roadsurf.detection.classifier import guided
    from roadsurf.detection.classifier.fusion import audit_pairs, grow_pairs

    n = 30
    names = [f"{i:04d}.png" for i in range(n)]
    rut = set(range(9, 16))
    rng = np.random.default_rng(3)
    calls: list[set[tuple[int, int]]] = []

    def reconstruct(only: set[tuple[int, int]]) -> list[PairResult]:
        calls.append(set(only))
        # pair (i, i+1) sees the rut when either frame is on it
        return [_pair(a, 0.03 if {a, b} & rut else 0.0, 40 if {a, b} & rut else 0, rng)
                for a, b in sorted(only)]  # fmt: skip

    probs = dict.fromkeys(names, 0.001)  # the CNN is sure every frame is clear
    cfg = ClassifierConfig(audit_every_frames=10)
    assert audit_pairs(n, 10) == {9: (9, 10), 19: (19, 20), 29: (28, 29)}
    # frames that already have 3D count: the audit only fills gaps of 10 frames
    assert audit_pairs(n, 10, {4, 12}) == {22: (22, 23)}
    assert audit_pairs(n, 0) == {}
    # in metres: the same plan at 0.4 m per frame; at twice the frame rate, half the pairs per
    # frame (the audit's cost follows the road, not the frame rate)
    assert audit_pairs(n, 4.0, (), 0.4 * np.arange(n)) == audit_pairs(n, 10)
    assert audit_pairs(2 * n, 4.0, (), 0.2 * np.arange(2 * n)) == {
        19: (19, 20),
        39: (39, 40),
        59: (58, 59),
    }
    with pytest.raises(ValueError, match="shape"):
        audit_pairs(n, 4.0, (), np.arange(n - 1))
    # a 3D defect frame gets both of its pairs; a neighbour, the pair it shares with it
    assert grow_pairs([0], n) == {0: {(0, 1)}, 1: {(0, 1)}}
    assert grow_pairs([5], n) == {5: {(4, 5), (5, 6)}, 4: {(4, 5)}, 6: {(5, 6)}}
    res = guided.run(cfg, names, probs, 1.0, reconstruct, tmp_path)
    # round 1 is the audit only; growth walks the rut up from frame 9 and stops on clear road
    assert calls[0] == {(9, 10), (19, 20), (28, 29)}
    done = calls[-1]
    assert all({(i - 1, i), (i, i + 1)} <= done for i in rut)
    assert not any(p in done for p in [(0, 1), (3, 4), (21, 22), (26, 27)])
    assert res.reasons["0009.png"] == "audit" and res.reasons["0015.png"] == "grown"
    assert res.rounds > 2 and {"0009.png", "0015.png"} <= res.rule.decide_3d
    # frames on clear road keep the CNN's decision even when audited or grown
    assert res.reasons["0029.png"] == "audit" and "0029.png" not in res.rule.decide_3d
    assert res.reasons["0017.png"] == "grown" and "0017.png" not in res.rule.decide_3d
    # 3D decides the audited and grown frames; the CNN keeps the frames nobody checked
    d3 = {fn: int(fn[:4]) in rut for fn in res.rule.decide_3d}
    fused = fuse_frames(probs, d3, names, decide_3d=res.rule.decide_3d)
    assert [i for i, fn in enumerate(names) if fused[fn].defect] == sorted(rut)
    assert fused["0000.png"].source == "cnn" and fused["0012.png"].source == "3d"
    rec = json.loads((tmp_path / SCREENING_JSON).read_text())
    assert rec["frames"][12] == {
        "filename": "0012.png",
        "p_defect": 0.001,
        "3d_reason": "grown",
        "3d_overrules_cnn": True,
        "audit_probe": None,
    }
    assert rec["frames"][29]["3d_overrules_cnn"] is False  # audited, clear road
    assert rec["pairs_reconstructed"] == len(done)

    assert rec["warnings"] == []
    unsure = guided.run(cfg, names, dict.fromkeys(names, 0.5), 1.0, reconstruct, tmp_path)
    assert unsure.reasons["0000.png"] == "unsure"
    assert "roadsurf label" in json.loads((tmp_path / SCREENING_JSON).read_text())["warnings"][0]
    # without audit and growth it is the dissertation's rule: nothing to reconstruct, rut missed
    calls.clear()
    off = ClassifierConfig(audit_every_frames=0, grow_along_defects=False)
    res = guided.run(off, names, probs, 1.0, reconstruct)
    assert calls == [set()] and res.pairs == [] and not res.rule.decide_3d


def test_audit_probes_settle_clear_road_and_send_depth_to_full_pairs(tmp_path: Path) -> None:
    """With a probe, an audit pair becomes a full pair only when its probe fails or shows some
    depth (> audit_probe_max_deep_points points below audit_probe_depth_frac x Z^d); a clear
    probe settles the frame (the CNN's decision stands, no full pair, no "pair failed" retry).
    The rut the audit meets is still followed to its ends by full pairs."""
    from roadsurf.detection.classifier import guided

    n = 30
    names = [f"{i:04d}.png" for i in range(n)]
    rut = set(range(9, 16))
    rng = np.random.default_rng(8)
    full: list[set[tuple[int, int]]] = []
    probed: list[set[tuple[int, int]]] = []

    def reconstruct(only: set[tuple[int, int]]) -> list[PairResult]:
        full.append(set(only))
        return [_pair(a, 0.03 if {a, b} & rut else 0.0, 40 if {a, b} & rut else 0, rng)
                for a, b in sorted(only)]  # fmt: skip

    def probe(only: set[tuple[int, int]]) -> list[PairResult]:
        probed.append(set(only))
        out = []
        for a, b in sorted(only):
            # the probe of (19, 20) sees 2 points 5.4-9 mm deep: some depth at half of Z^d = 10 mm
            p = _pair(
                a, 0.03 if {a, b} & rut else 0.009, 40 if {a, b} & rut else 2 * (a == 19), rng
            )
            if a == 28:
                p.status, p.reason = "too_few_matches", "coarse alignment: 3 mutual matches"
            out.append(p)
        return out

    probs = dict.fromkeys(names, 0.001)
    cfg = ClassifierConfig(audit_every_frames=10)
    res = guided.run(cfg, names, probs, 1.0, reconstruct, tmp_path, probe=probe)
    assert probed == [{(9, 10), (19, 20), (28, 29)}]
    # the rut's probe, the probe with some depth and the failed one go to full pairs
    assert full[0] == {(9, 10), (19, 20), (28, 29)}
    assert all({(i - 1, i), (i, i + 1)} <= full[-1] for i in rut)
    assert {"0009.png", "0015.png"} <= res.rule.decide_3d and not res.cleared
    # a stricter count clears (19, 20): it is never reconstructed, and keeps the CNN's decision
    full.clear()
    strict = ClassifierConfig(audit_every_frames=10, audit_probe_max_deep_points=2)
    res = guided.run(strict, names, probs, 1.0, reconstruct, tmp_path, probe=probe)
    assert res.cleared == {"0019.png"} and (19, 20) not in full[-1] and (18, 19) not in full[-1]
    assert res.reasons["0019.png"] == "audit" and "0019.png" not in res.rule.decide_3d
    assert [(p.index_a, p.index_b) for p in res.probes] == [(9, 10), (19, 20), (28, 29)]
    rec = json.loads((tmp_path / SCREENING_JSON).read_text())
    assert (
        rec["audit_probe"] is True and rec["audit_probes"] == 3 and rec["audit_probes_clear"] == 1
    )
    assert rec["frames"][19]["audit_probe"]["deep_points"] == 2
    assert rec["frames"][29]["audit_probe"] == {  # frame 29 is audited with (28, 29)
        "status": "too_few_matches",
        "points": 300,
        "deep_points": None,
        "max_depth_mm": None,
    }
    assert rec["frames"][12]["audit_probe"] is None
    fused = fuse_frames(
        probs, {fn: int(fn[:4]) in rut for fn in res.rule.decide_3d}, names,
        decide_3d=res.rule.decide_3d,
    )  # fmt: skip
    assert [i for i, fn in enumerate(names) if fused[fn].defect] == sorted(rut)
    # audit_probe: false makes every audit pair a full pair again
    probed.clear()
    full.clear()
    off = ClassifierConfig(audit_every_frames=10, audit_probe=False)
    guided.run(off, names, probs, 1.0, reconstruct, probe=probe)
    assert probed == [] and full[0] == {(9, 10), (19, 20), (28, 29)}


def test_a_frame_whose_pair_failed_gets_its_other_pair() -> None:
    """An unsure frame is planned with one pair; when that pair fails, the next round adds
    the other, so the frame still gets 3D (detection.classifier.guided)."""
    from roadsurf.detection.classifier import guided

    n = 12
    names = [f"{i:04d}.png" for i in range(n)]
    rng = np.random.default_rng(5)
    calls: list[set[tuple[int, int]]] = []

    def reconstruct(only: set[tuple[int, int]]) -> list[PairResult]:
        calls.append(set(only))
        out = []
        for a, _ in sorted(only):
            p = _pair(a, 0.0, 0, rng)
            if a == 6:  # (6, 7): too little overlap
                p.status = "geometry_failed"
            out.append(p)
        return out

    probs = dict.fromkeys(names, 0.001)
    probs["0006.png"] = 0.3  # unsure, leans clear
    cfg = ClassifierConfig(audit_every_frames=0, grow_along_defects=False)
    res = guided.run(cfg, names, probs, 1.0, reconstruct)
    assert calls == [{(6, 7)}, {(5, 6), (6, 7)}]
    assert res.rounds == 2 and res.reasons == {"0006.png": "unsure"}
    assert any(p.ok and "0006.png" in (p.frame_a, p.frame_b) for p in res.pairs)


def test_growth_extends_the_cnn_context_along_a_long_defect(tmp_path: Path) -> None:
    from roadsurf.detection.classifier import guided

    n = 20
    names = [f"{i:04d}.png" for i in range(n)]
    rut = set(range(4, 12))
    rng = np.random.default_rng(4)

    def reconstruct(only: set[tuple[int, int]]) -> list[PairResult]:
        return [_pair(a, 0.03 if {a, b} & rut else 0.0, 40 if {a, b} & rut else 0, rng)
                for a, b in sorted(only)]  # fmt: skip

    probs = dict.fromkeys(names, 0.001)
    probs["0005.png"] = 0.99  # the CNN sees only the start of the defect
    res = guided.run(ClassifierConfig(audit_every_frames=0), names, probs, 1.0, reconstruct)
    assert res.reasons["0005.png"] == "defect" and res.reasons["0004.png"] == "context"
    assert res.reasons["0011.png"] == "grown" and res.reasons["0012.png"] == "grown"
    assert "0014.png" not in res.reasons  # growth stops one frame past the defect's end
