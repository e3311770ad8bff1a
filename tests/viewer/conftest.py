"""Shared fixtures: one synthetic run (with GPS and defects) and its .rrd, built once."""

from __future__ import annotations

from pathlib import Path

import pytest

from roadsurf.viewer.browser import find_chromium
from tests.viewer.synthetic_run import SyntheticRun, make_synthetic_run


@pytest.fixture(scope="module")
def synthetic_run(tmp_path_factory: pytest.TempPathFactory) -> SyntheticRun:
    return make_synthetic_run(tmp_path_factory.mktemp("viewer_run"))


@pytest.fixture(scope="module")
def saved_rrd(synthetic_run: SyntheticRun) -> Path:
    from roadsurf.viewer.api import save_rrd

    return save_rrd(synthetic_run.run, synthetic_run.run / "run.rrd").rrd


@pytest.fixture()
def chromium() -> str:
    exe = find_chromium()
    if exe is None:
        pytest.skip(
            "SKIPPED browser check: Chromium is not installed "
            "(Debian: `apt-get install chromium`, or `make browser-deps`)"
        )
    return exe
