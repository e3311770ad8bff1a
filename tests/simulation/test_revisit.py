"""A revisit in the simulator (issue 30): the second half of the frames drives the first half's
road again after a pause, so loop closure has a drive with images to close."""

from __future__ import annotations

import numpy as np
import pytest

from roadsurf.core.errors import ConfigError
from roadsurf.simulation.build import build_world
from roadsurf.simulation.scenarios import SCENARIOS, make_config

SMALL = {"width": 160, "height": 120, "fx": 150.0}


def test_the_second_pass_drives_the_first_pass_road_again() -> None:
    cfg = make_config("revisit", **SMALL)
    n = 12
    world = build_world(cfg, 7, n)
    ft = world.frame_times
    half = n // 2
    gap = ft[half] - ft[half - 1]
    assert gap == pytest.approx(cfg.revisit_after_s + 1.0 / cfg.fps, abs=1e-3)
    c = np.array([world.pose(float(ti)).C for ti in ft])
    # the same places again, within the lateral wander (not the 2.4 m the first pass covered)
    step = np.linalg.norm(c[1:half] - c[: half - 1], axis=1)
    assert np.linalg.norm(c[half] - c[0]) < 0.2 < step.sum()
    assert np.allclose(c[half:, :2], c[:half, :2], atol=0.3)
    # between the passes the vehicle goes back along the road: the logs stay continuous
    ts = np.linspace(ft[half - 1], ft[half], 50)  # 0.41 s apart: 1.6 m at the pass's 4 m/s
    mid = np.array([world.pose(float(ti)).C for ti in ts])
    assert np.max(np.linalg.norm(np.diff(mid[:, :2], axis=0), axis=1)) < 0.5  # no 2.4 m jump


def test_one_pass_is_the_default_and_a_revisit_needs_frames() -> None:
    assert make_config("potholes").revisit_after_s == 0
    assert SCENARIOS["revisit"].overrides["revisit_after_s"] > 0
    with pytest.raises(ConfigError, match="revisit needs at least 4 frames"):
        build_world(make_config("revisit", **SMALL), 7, 3)
    with pytest.raises(ConfigError, match="too short for a way back"):
        build_world(make_config("revisit", revisit_after_s=0.1, **SMALL), 7, 8)
