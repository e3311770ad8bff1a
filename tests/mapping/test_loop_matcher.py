"""mapping.loops.frame_matcher: the pair API on two frames of a real drive folder, as the run
uses it to confirm revisits (issue 30)."""

from __future__ import annotations

from pathlib import Path

from roadsurf.io.drive import load_drive
from roadsurf.mapping.loops import confirm_loops, frame_matcher
from roadsurf.reconstruction.config import ReconstructionConfig

SAMPLE = Path(__file__).resolve().parents[2] / "data_samples" / "drive"


def test_matcher_confirms_overlapping_frames_and_rejects_distant_ones(tmp_path: Path) -> None:
    drive = load_drive(SAMPLE)
    match = frame_matcher(drive, ReconstructionConfig(), tmp_path)
    near = match(0, 1)
    assert near is not None and near.ok and near.n_points >= 30
    assert (near.index_a, near.index_b) == (drive.frames[0].index, drive.frames[1].index)
    assert match(0, len(drive.frames) - 1) is None  # no shared ground
    # its image retrieval ranks the frame that shares ground first
    assert match.score(0, 1) > 4 * match.score(0, len(drive.frames) - 1)
    # the features went to (and now come from) RUN/features, as the stage's do
    assert len(list((tmp_path / "features").iterdir())) == 3
    loops = confirm_loops([(0, len(drive.frames) - 1), (1, 2)], match)
    assert [(p.index_a, p.index_b) for p in loops] == [
        (drive.frames[1].index, drive.frames[2].index)
    ]
