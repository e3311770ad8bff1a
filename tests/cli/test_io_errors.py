"""Broken files and unusable output folders give one line (naming the file and what to do),
exit status 2 and no traceback: a truncated report.json in `report`/`view`, a bad checkpoint
in `train`, a bad model for `run --classifier`, an --out that is a file for `train`, `label`,
`report` and `view --save`, a read-only --out (when not root)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.cli.test_signals import small_drive

REPO = Path(__file__).resolve().parents[2]
LOG_LINE = re.compile(r"^\d\d:\d\d:\d\d (DEBUG|INFO|WARNING) ")


def cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "roadsurf", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=300,
    )


def one_error_line(r: subprocess.CompletedProcess[str], *needles: str) -> str:
    """The one line the CLI printed for a user error (log lines aside); checks exit status 2,
    no traceback and that the line holds every needle."""
    assert r.returncode == 2, r.stderr[-3000:]
    assert "Traceback" not in r.stderr and "Traceback" not in r.stdout, r.stderr[-3000:]
    lines = [ln for ln in r.stderr.splitlines() if ln.strip() and not LOG_LINE.match(ln)]
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr[-3000:]
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


@pytest.fixture()
def truncated_run(tmp_path: Path) -> Path:
    run = tmp_path / "run"
    run.mkdir()
    (run / "report.json").write_text('{"drive": "/somewhere", "timings_s": {"tot')
    return run


def test_truncated_report_json_in_report_and_view(truncated_run: Path, tmp_path: Path) -> None:
    report = str(truncated_run / "report.json")
    one_error_line(cli("report", truncated_run), report, "roadsurf run", "resumes")
    one_error_line(cli("view", truncated_run, "--save", tmp_path / "x.rrd"), report, "roadsurf run")
    assert not (tmp_path / "x.rrd").exists()
    (truncated_run / "report.json").write_text("[1, 2]")  # valid JSON, not a report
    one_error_line(cli("report", truncated_run), report, "not an object")


def test_an_out_that_is_a_file(truncated_run: Path, tmp_path: Path) -> None:
    (truncated_run / "report.json").write_text("{}")
    afile = tmp_path / "afile"
    afile.write_text("x")
    one_error_line(cli("train", tmp_path / "ds", "--out", afile), str(afile))
    one_error_line(cli("label", tmp_path / "drive", "--out", afile), str(afile))
    one_error_line(cli("report", truncated_run, "--html", afile / "r.html"), str(afile))
    one_error_line(cli("view", truncated_run, "--save", afile / "x.rrd"), str(afile))
    one_error_line(cli("view", truncated_run, "--save", tmp_path), "is a folder")
    assert afile.read_text() == "x"


@pytest.mark.skipif(
    not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root writes into read-only folders"
)
def test_a_read_only_out(truncated_run: Path, tmp_path: Path) -> None:
    (truncated_run / "report.json").write_text("{}")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        one_error_line(cli("train", tmp_path / "ds", "--out", ro / "m"), "cannot write")
        one_error_line(cli("label", tmp_path / "drive", "--out", ro / "l"), "cannot write")
        one_error_line(cli("report", truncated_run, "--html", ro / "r.html"), "cannot write")
        one_error_line(cli("view", truncated_run, "--save", ro / "x.rrd"), "cannot write")
    finally:
        ro.chmod(0o755)


def test_a_bad_checkpoint_in_train(tmp_path: Path) -> None:
    import torch

    from roadsurf.core.errors import ModelFileError
    from roadsurf.detection.classifier.config import ClassifierConfig
    from roadsurf.detection.classifier.train import train
    from tests.detection.test_classifier_model import write_dataset

    ds = write_dataset(tmp_path / "ds", n_per_class=6, size=48)
    out = tmp_path / "m"
    out.mkdir()
    ckpt = out / "checkpoint.pt"
    ckpt.write_bytes(b"\x00garbage" * 10)
    one_error_line(
        cli("train", ds, "--out", out, "--epochs", "1", "--input-size", "48"),
        str(ckpt),
        "--overwrite",
    )
    cfg = ClassifierConfig(input_size_px=48, epochs=1, num_threads=1)
    torch.save([1, 2], ckpt)  # readable, but not a training state
    for junk in (None, b"PK\x03\x04truncated"):
        if junk is not None:
            ckpt.write_bytes(junk)
        with pytest.raises(ModelFileError, match="checkpoint.pt.*Delete it"):
            train(ds, out, cfg, progress=False)
    train(ds, out, cfg, resume=False, progress=False)  # what --overwrite does
    assert (out / "model.safetensors").is_file()


def test_a_bad_model_file_for_run_classifier(tmp_path: Path) -> None:
    drive = small_drive(tmp_path / "drive", n_frames=3)
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"\x00garbage" * 10)
    one_error_line(cli("run", drive, "--out", tmp_path / "run", "--classifier", bad), str(bad))
