"""Cracks on the map: the crack pieces every pair confirmed in its own images (``cracks``) are
placed in the map with the trajectory, pooled and clustered, so that one crack seen by several
pairs is one defect and its 3D evidence is tested over all of them (``crack_evidence``).

Pieces inside a map defect's outline belong to that defect (a pothole's rim gives many).
A candidate the 3D tests leave unconfirmed where they are blind (``crackimage``: along the
epipolar direction, or its pairs' readings contradicting each other) is decided by the images:
kept when its dark line was extracted by enough pairs there, with its depth not measured (NaN,
``measured_on`` "image").
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import cv2
import numpy as np

from roadsurf.detection.config import CrackConfig, DetectionConfig
from roadsurf.detection.crackimage import aperture_blind, image_consistent, readings_disagree
from roadsurf.detection.crackraster import measure_crack_on_raster, raster_crack_evidence
from roadsurf.detection.mapframe import MapFrame
from roadsurf.detection.mapseg import Measured, severity
from roadsurf.detection.pairs import PairDefects
from roadsurf.detection.types import Defect
from roadsurf.detection.windows import WindowSource
from roadsurf.mapping.types import Trajectory

if TYPE_CHECKING:
    from shapely.geometry import Polygon

log = logging.getLogger(__name__)


def crack_evidence(
    sum_depth_m: float, n_points: int, n_below: int, var_m2: float, cfg: CrackConfig
) -> tuple[bool, float]:
    """Pooled 3D test of one crack over all pairs that saw it: (confirmed, z).

    z = Σ depth / √(Σ n σ²) (the mean depth over its standard error); confirmed when
    z ≥ ``z_k``, at least ``min_points`` points and a share ≥ ``min_below_share`` below the road.
    """
    if n_points <= 0 or var_m2 <= 0:
        return False, 0.0
    z = float(sum_depth_m / math.sqrt(var_m2))
    ok = z >= cfg.z_k and n_points >= cfg.min_points and n_below >= cfg.min_below_share * n_points
    return bool(ok), z


def _reading(sum_m: float, n: float, var_m2: float) -> tuple[float, float]:
    """(mean depth, its standard error) of one source of a piece (sum of n samples with
    variance var_m2); (nan, nan) when it holds no sample."""
    if n <= 0 or var_m2 <= 0:
        return math.nan, math.nan
    return float(sum_m / n), float(math.sqrt(var_m2) / n)


def cluster_cracks(xy_m: np.ndarray, link_m: float) -> np.ndarray:
    """(N,) cluster label of crack samples: samples closer than ``link_m`` are linked."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(xy_m)
    if n == 0:
        return np.zeros(0, int)
    pairs = cKDTree(xy_m).query_pairs(link_m, output_type="ndarray")
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)[1]


def crack_defects(
    cfg: DetectionConfig,
    per_pair: dict[int, PairDefects],
    traj: Trajectory,
    pose_of: dict[str, int],
    mframe: MapFrame,
    footprints: dict[str, Polygon],
    others: list[Defect],
    raster: WindowSource | None = None,
) -> list[Defect]:
    """Cracks confirmed per pair, placed in the map and clustered (one crack seen by several
    pairs is one defect); pieces inside a map defect's outline belong to that defect.

    With ``raster`` (RUN/surface.tif) each crack's width and depth are read across its centre
    line on it where it sees the crack (``crackraster``); else they stay the pairs'."""
    from shapely import contains_xy, union_all
    from shapely.geometry import MultiPoint, Polygon

    xy_l, pair_l, piece_l, pieces = [], [], [], []
    for k, pd in per_pair.items():
        c = pd.cracks
        i = pose_of.get(pd.frame_a)
        if c is None or i is None or not len(c.label):
            continue
        T = traj.world_from_cam[i]
        xy_l.append(mframe.grid_from_enu(c.xyz_cam_m @ T[:3, :3].T + T[:3, 3]))
        pair_l.append(np.full(len(c.label), k))
        piece_l.append(c.label + len(pieces))
        for j in range(len(c.width_m)):
            # Sparse points and dense samples across the crack pool into one test, each sample
            # weighted by its inverse variance (w = n / σ² per source: Σ w d = S n / V,
            # Σ w = n² / V for a sum S of n samples with variance V).
            wd = wsum = 0.0
            for S, n, V in ((c.sum_depth_m[j], c.n_points[j], c.var_m2[j]),
                            (c.dense_sum_m[j], c.dense_n[j], c.dense_var_m2[j])):  # fmt: skip
                if n > 0 and V > 0:
                    wd, wsum = wd + S * n / V, wsum + n * n / V
            pieces.append(
                (c.width_m[j], wd, c.n_points[j] + c.dense_n[j], c.n_below[j] + c.dense_below[j],
                 wsum, c.max_depth_m[j], c.across_share[j],
                 *_reading(c.sum_depth_m[j], c.n_points[j], c.var_m2[j]),
                 *_reading(c.dense_sum_m[j], c.dense_n[j], c.dense_var_m2[j]))
            )  # fmt: skip
    if not xy_l:
        return []
    xy = np.vstack(xy_l)
    pair = np.concatenate(pair_l)
    piece = np.concatenate(piece_l)
    pc = np.asarray(pieces, float)
    lab = cluster_cracks(xy, cfg.crack.link_m)
    taken = [Polygon(d.outline_xy_m).buffer(0.01) for d in others]
    taken_all = union_all(taken) if taken else None
    out: list[Defect] = []

    def evidence(sel: np.ndarray) -> tuple[bool, float]:
        ids = np.unique(piece[sel])
        wsum = pc[ids, 4].sum()
        if wsum <= 0:
            return False, 0.0
        # The weighted mean Σ w d / Σ w and its variance 1 / Σ w: z = Σ w d / √(Σ w).
        return crack_evidence(
            pc[ids, 1].sum() / wsum, int(pc[ids, 2].sum()), int(pc[ids, 3].sum()), 1.0 / wsum,
            cfg.crack,
        )  # fmt: skip

    # Confirmed cracks whose samples come within ``join_m`` are one crack (a crack is often
    # confirmed in pieces where the texture hides its middle from the 2D detector).
    confirmed = [c for c in np.unique(lab) if evidence(lab == c)[0] and (lab == c).sum() >= 3]
    # A candidate the pooled test leaves unconfirmed is tested on the raster (its cross-section
    # below the road beyond its noise): z of the raster for those it confirms
    by_raster: dict[int, float] = {}
    if raster is not None and cfg.crack.raster and cfg.crack.raster_confirm:
        for c in np.unique(lab):
            sel = lab == c
            if c in confirmed or sel.sum() < 3:
                continue
            w_c = float(np.median(pc[np.unique(piece[sel]), 0]))
            ev = raster_crack_evidence(raster, xy[sel], w_c, cfg.crack)
            log.debug("crack candidate at %s: raster %s", np.round(xy[sel].mean(axis=0), 2), ev)
            if ev.confirmed:
                by_raster[int(c)] = ev.z
        confirmed = sorted(confirmed + list(by_raster))
    # A candidate the 3D tests cannot judge (``crackimage``) is decided by the images.
    by_image: set[int] = set()
    if cfg.crack.image_confirm:
        from shapely.geometry import Point

        frame_of = {int(k): pd.frame_a for k, pd in per_pair.items()}
        for c in np.unique(lab):
            sel = lab == c
            if c in confirmed or sel.sum() < 3:
                continue
            ids = np.unique(piece[sel])
            reads = np.r_[pc[ids][:, [7, 8]], pc[ids][:, [9, 10]]]  # (mean, SE): points, dense
            blind_ap = aperture_blind(pc[ids, 6], cfg.crack)
            dis, birge = readings_disagree(reads[:, 0], reads[:, 1], cfg.crack)
            blind = blind_ap or (cfg.crack.image_disagree and dis)
            cen = Point(*xy[sel].mean(axis=0))
            n_pairs = len({frame_of[int(k)] for k in np.unique(pair[sel])})
            n_cov = sum(
                1 for f in set(frame_of.values()) if f in footprints and footprints[f].contains(cen)
            )
            log.debug(
                "crack candidate at %s: aperture blind %s, readings Q/(k-1) %.1f, %d of %d pairs",
                np.round(xy[sel].mean(axis=0), 2), blind_ap, birge, n_pairs, n_cov,
            )  # fmt: skip
            if blind and image_consistent(n_pairs, n_cov, cfg.crack):
                by_image.add(int(c))
        confirmed = sorted(confirmed + sorted(by_image))
    if len(confirmed) > 1:
        keep = np.isin(lab, confirmed)
        joined = cluster_cracks(xy[keep], cfg.crack.join_m)
        first: dict[int, int] = {}
        # a joined crack holding raster-confirmed parts keeps their largest raster z
        z_of: dict[int, float] = {}
        img_of: set[int] = set()
        for c, j in zip(lab[keep].tolist(), joined.tolist(), strict=True):
            first.setdefault(j, c)
            if c in by_raster:
                z_of[first[j]] = max(z_of.get(first[j], -math.inf), by_raster[c])
            if c in by_image:
                img_of.add(first[j])
        lab = lab.copy()
        lab[keep] = [first[j] for j in joined.tolist()]
        confirmed = sorted(set(first.values()))
        by_raster = z_of
        by_image = img_of
    close = cfg.crack.join_m / 2
    for c in confirmed:
        sel = lab == c
        p = xy[sel]
        ids = np.unique(piece[sel])
        ok, z = evidence(sel)
        on_image = False
        if not ok and c in by_raster:
            ok, z = True, by_raster[c]
            log.info("crack at %s confirmed on the raster (z %.1f)", np.round(p.mean(axis=0), 2), z)
        elif not ok and c in by_image:
            ok, on_image, z = True, True, 0.0
            log.info(
                "crack at %s: the 3D tests are blind there; kept on the images, depth not measured",
                np.round(p.mean(axis=0), 2),
            )
        if not ok:
            continue
        # A crack sample inside a map defect's outline: the piece belongs to that defect.
        # Checked on the samples before the costly buffer (pothole rims give many such pieces).
        if taken_all is not None and contains_xy(taken_all, p[:, 0], p[:, 1]).any():
            continue
        w = float(np.median(pc[ids, 0]))
        # Outline: the samples dilated by half the width, then closed by ``close`` (the same set
        # as dilating by half the width + close and eroding by close, but the union of hundreds
        # of 10 cm discs cost seconds per crack; samples snapped to 1 mm first).
        snap = np.unique(np.round(p / 0.001), axis=0) * 0.001
        geom = MultiPoint(snap).buffer(max(0.5 * w, 0.003)).buffer(close).buffer(-close)
        if geom.geom_type != "Polygon":
            geom = max(geom.geoms, key=lambda g: g.area)
        if any(t.intersects(geom) for t in taken):
            continue
        (_, _), (a, b), _ = cv2.minAreaRect((p - p.mean(axis=0)).astype(np.float32))
        length = float(max(a, b)) + w
        # Robust max: the median over the pieces of each piece's second-deepest point.
        dmax = math.nan if on_image else float(np.median(pc[ids, 5]))
        if dmax > cfg.plane.max_depth_m:
            # Deeper than any defect the plane fit accepts: the pooled "evidence" comes from a
            # failed reconstruction (decimetre noise), not from a crack.
            continue
        src, n_prof = ("image" if on_image else "points"), 0
        if raster is not None and cfg.crack.raster:
            rc = measure_crack_on_raster(raster, p, w, cfg.crack)
            n_prof = rc.profiles
            # a raster reading beyond the dense tracks' bound is a failed surface, not a crack
            if rc.source != "points" and 0.0 < rc.max_depth_m <= cfg.crack.dense_max_depth_m:
                src, w, dmax = rc.source, rc.width_m, rc.max_depth_m
            log.debug("crack at %s: raster %s", np.round(p.mean(axis=0), 2), rc)
        # Parabolic groove profile (1 - q²): the mean over the width is 2/3 of the centre depth.
        dmean = dmax * 2.0 / 3.0
        area = length * w
        n_pairs = len(np.unique(pair[sel]))
        # kept on the images alone: confidence from the pairs that extracted it, at most 1/2
        conf = (0.5 if on_image else 1.0 - math.exp(-z / 6.0)) * (1.0 - 0.5 ** (n_pairs + 1))
        seen = sorted(fn for fn, fp in footprints.items() if fp.intersects(geom))
        m = Measured(
            outline_xy_m=np.asarray(geom.exterior.coords)[:-1],
            # the outline's centroid, as for every other defect (the samples cluster where the
            # pairs matched densely: their mean sat 20 cm along a 1 m crack)
            centroid_xy_m=np.asarray(geom.centroid.coords[0]),
            max_depth_m=dmax,
            mean_depth_m=dmean,
            area_m2=area,
            volume_m3=area * dmean,
            length_m=length,
            width_m=w,
            deep_xy_m=np.zeros((0, 2)),
        )
        out.append(
            Defect(
                id=0,
                type="crack",
                severity=severity("crack", m, cfg.severity),
                outline_xy_m=m.outline_xy_m,
                centroid_xy_m=m.centroid_xy_m,
                max_depth_m=dmax,
                mean_depth_m=dmean,
                area_m2=area,
                volume_m3=m.volume_m3,
                length_m=length,
                width_m=w,
                confidence=float(np.clip(conf, 0.0, 1.0)),
                frames=seen,
                measured_on=src,
                profiles=n_prof,
            )
        )
    if out:
        log.info("detection: %d crack(s) from %d confirmed piece(s)", len(out), len(np.unique(lab)))
    return out
