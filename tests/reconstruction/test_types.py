from __future__ import annotations

import copy
import dataclasses
import pickle

import numpy as np

from roadsurf.reconstruction.api import reconstruct_pair
from roadsurf.reconstruction.config import FeatureConfig, ReconstructionConfig
from roadsurf.reconstruction.types import (
    ON_DISK_FIELDS,
    PairResult,
    StoredPairResult,
    load_pair,
    save_pair,
    stored,
)
from tests.reconstruction.conftest import render_pair


def test_pair_result_round_trip(tmp_path, cam) -> None:
    a, b = render_pair(cam, seed=2)
    res = reconstruct_pair(
        a, b, cam, ReconstructionConfig(features=FeatureConfig(max_features=500))
    )
    assert res.ok
    res.frame_a, res.frame_b, res.index_a, res.index_b = "a.jpg", "b.jpg", 3, 4
    back = load_pair(save_pair(tmp_path / "p.npz", res))
    assert isinstance(back, PairResult)
    for name in (
        "points_cam_a_m",
        "px_a",
        "px_b",
        "cov_m2",
        "plane_dist_m",
        "R_b_from_a",
        "H",
        "F",
        "match_idx",
    ):
        np.testing.assert_array_equal(getattr(back, name), getattr(res, name))
    assert (back.frame_a, back.index_b, back.status, back.method) == ("a.jpg", 4, "ok", res.method)
    assert back.timings_s == res.timings_s
    assert back.scale_alpha == res.scale_alpha


def test_failed_pair_round_trip(tmp_path) -> None:
    res = PairResult("a", "b", 0, 1, "proposed", "no_overlap", "nothing matched")
    back = load_pair(save_pair(tmp_path / "f.npz", res))
    assert back.status == "no_overlap" and back.reason == "nothing matched" and back.n_points == 0


def _pair(n: int, seed: int = 0) -> PairResult:
    rng = np.random.default_rng(seed)
    res = PairResult("a.jpg", "b.jpg", 3, 4, "proposed", "ok")
    res.points_cam_a_m = rng.normal(size=(n, 3))
    res.px_a, res.px_b = rng.normal(size=(n, 2)), rng.normal(size=(n, 2))
    res.cov_m2 = rng.normal(size=(n, 3, 3))
    res.plane_dist_m = rng.normal(size=n)
    res.match_idx = np.arange(n, dtype=np.int64)
    res.timings_s = {"solve": 0.5}
    return res


def test_stored_pair_keeps_only_what_later_stages_read(tmp_path) -> None:
    """A drive's pairs stay in memory for the whole run: the stored pair holds no array of
    ``ON_DISK_FIELDS`` (memory flat in the drive's length) yet reads the same values."""
    res = _pair(400)
    path = save_pair(tmp_path / "p.npz", res)
    s = stored(res, path)
    assert isinstance(s, PairResult) and isinstance(s, StoredPairResult)
    held = sum(v.nbytes for v in vars(s).values() if isinstance(v, np.ndarray))
    full = sum(v.nbytes for v in vars(res).values() if isinstance(v, np.ndarray))
    assert not set(ON_DISK_FIELDS) & set(vars(s))
    assert held < 0.5 * full, (held, full)  # the covariances were over half
    for f in dataclasses.fields(PairResult):
        a, b = getattr(s, f.name), getattr(res, f.name)
        if isinstance(b, np.ndarray):
            np.testing.assert_array_equal(a, b)
        else:
            assert a == b or (a != a and b != b), f.name  # NaN scalars too
    assert s.ok and s.n_points == 400
    # the usual dataclass tools and pickling see every field
    np.testing.assert_array_equal(dataclasses.asdict(s)["cov_m2"], res.cov_m2)
    np.testing.assert_array_equal(dataclasses.replace(s, status="ok").match_idx, res.match_idx)
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(s)).cov_m2, res.cov_m2)
    np.testing.assert_array_equal(copy.copy(s).cov_m2, res.cov_m2)
    # saved again (the consensus re-saves pairs) it writes the same file content
    again = load_pair(save_pair(tmp_path / "q.npz", s))
    np.testing.assert_array_equal(again.cov_m2, res.cov_m2)
    # an assigned field is held from then on
    s.match_idx = np.zeros(2, np.int64)
    assert len(s.match_idx) == 2
    try:
        s.no_such_field  # noqa: B018
    except AttributeError as e:
        assert "no_such_field" in str(e)
    else:
        raise AssertionError("an unknown attribute must raise AttributeError")
