"""Test-suite settings. Under CI the hypothesis fuzz tests run derandomised, so a run is
repeatable (a crash found locally is fixed and pinned as an example); locally they explore."""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
