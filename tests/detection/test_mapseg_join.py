"""Outline regions one mean-shift cluster holds are one defect only when they lie within
``join_gap_m`` of each other: two potholes with measured road between them stay two (two
potholes 22 cm apart were reported as one 1.65 m pothole on a tilted drive)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import roadsurf.detection.mapseg as mapseg
from roadsurf.detection.config import MapSegmentConfig
from roadsurf.detection.mapseg import Surface, segment
from roadsurf.io.formats import GridSpec

GSD = 0.004


def _surface(pits: list[tuple[float, float, float]]) -> Surface:
    rng = np.random.default_rng(4)
    h, w = 250, 400  # 1.0 x 1.6 m
    z = rng.normal(0.0, 0.0004, (h, w)).astype(np.float32)
    yy, xx = (np.mgrid[0:h, 0:w] + 0.5) * GSD
    for cx, cy, radius in pits:
        r = np.hypot(xx - cx, yy - cy) / radius
        z -= np.where(r < 1, 0.04 * (1 - r**4), 0).astype(np.float32)
    return Surface(z, GridSpec("local ENU", 0.0, h * GSD, GSD, w, h), "surface.tif")


@pytest.fixture()
def one_cluster(monkeypatch: pytest.MonkeyPatch) -> None:
    """Mean shift that puts every point in one cluster (as a window spanning both did)."""

    def flat(pts: np.ndarray, *a: object, **k: object) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(len(pts), int), np.zeros((1, 2))

    monkeypatch.setattr(mapseg, "mean_shift_flat", flat)


def test_regions_of_one_cluster_join_only_within_the_gap(one_cluster: None) -> None:
    cfg = MapSegmentConfig()
    two = _surface([(0.5, 0.5, 0.1), (0.92, 0.5, 0.1)])  # 22 cm of road between the rims
    assert len(segment(two, cfg).regions) == 2
    assert len(segment(two, dataclasses.replace(cfg, join_gap_m=0.0)).regions) == 1
    assert len(segment(two, dataclasses.replace(cfg, join_gap_m=0.25)).regions) == 1
    near = _surface([(0.5, 0.5, 0.1), (0.74, 0.5, 0.1)])  # 4 cm apart: pieces of one defect
    assert len(segment(near, cfg).regions) == 1
    # the same 22 cm, but a floor below road level between them (1.5 mm: under the 2 mm rim
    # threshold, as noise leaves a real pothole's shallow part): one defect
    floor = two.residual_m.copy()
    floor[115:135, 150:232] = np.minimum(floor[115:135, 150:232], -0.0015)
    assert len(segment(Surface(floor, two.grid, two.source), cfg).regions) == 1


def test_one_pothole_cut_by_a_thin_ridge_is_one_defect() -> None:
    one = _surface([(0.5, 0.5, 0.12)])
    cut = one.residual_m.copy()
    cut[:, 123:126] = 0.0  # a 1.2 cm ridge of road level across it
    assert len(segment(Surface(cut, one.grid, one.source), MapSegmentConfig()).regions) == 1
