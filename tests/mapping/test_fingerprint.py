"""The stage fingerprints stored in poses_report.json and map_report.json must stay valid across
refactors (a resumed old run must still resume): fixed inputs give fixed values.

The expected values were computed once with the hashlib code that the core Fingerprint replaced
(same byte stream, sha256[:16]). A change of MappingConfig's fields changes them legitimately."""

from __future__ import annotations

import numpy as np

from roadsurf.mapping import globalmap, poses
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.types import Trajectory
from tests.mapping.synth import make_synthetic


def test_poses_fingerprint_is_unchanged() -> None:
    syn = make_synthetic(n=6, seed=3, failed=(2,))
    assert poses._fingerprint(MappingConfig(), syn.drive, syn.pairs) == "e241e0646fbb85a6"
    syn = make_synthetic(n=6, seed=3, with_gps=False)
    assert poses._fingerprint(MappingConfig(), syn.drive, syn.pairs) == "583397a4f3b3b11b"


def test_globalmap_fingerprint_is_unchanged() -> None:
    syn = make_synthetic(n=6, seed=3, failed=(2,))
    traj = Trajectory(
        filenames=[f.filename for f in syn.drive.frames],
        frame_indices=np.arange(6),
        timestamp_s=np.arange(6) * 0.05,
        world_from_cam=syn.world_from_cam,
        source=["fused"] * 6,
        reference=None,
        segment=np.zeros(6, int),
    )
    assert globalmap._fingerprint(MappingConfig(), syn.pairs, traj) == "aea61267cee16429"
