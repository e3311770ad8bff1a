"""`roadsurf simulate --stereo-pair` writes a two-frame drive without GPS, and `roadsurf
evaluate` scores a pair's run with the pair's figures."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "roadsurf", *args], capture_output=True, text=True, cwd=REPO
    )


def test_simulate_run_and_evaluate_a_stereo_pair(tmp_path: Path) -> None:
    drive, run = tmp_path / "pair", tmp_path / "run"
    small = ["--set", "width=480", "--set", "height=288", "--set", "fx=390"]
    r = _cli("simulate", "--stereo-pair", "0.1", "--seed", "11", "-o", str(drive), *small)
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in drive.iterdir()) == [
        "camera.yaml",
        "frames",
        "frames.csv",
        "truth",
    ]
    assert "mount_pitch_deg" not in (drive / "camera.yaml").read_text()
    assert (drive / "truth" / "stereo_pair.json").is_file()
    r = _cli("run", str(drive), "--out", str(run))
    assert r.returncode == 0, r.stderr
    r = _cli("evaluate", str(run), "--truth", str(drive / "truth"))
    assert r.returncode == 0, r.stderr
    score = json.loads(r.stdout.split(": ", 1)[1])
    assert score["found"] and score["pothole_rms_m"] < 0.005
    bad = _cli("simulate", "--stereo-pair", "5", "-o", str(tmp_path / "bad"))
    assert bad.returncode != 0 and "baseline_m" in bad.stderr and "Traceback" not in bad.stderr
