"""report.html is self-contained, complete, and renders in a real browser."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from roadsurf.viewer.browser import is_blank, screenshot
from roadsurf.viewer.report import write_report
from tests.viewer.synthetic_run import SyntheticRun, make_synthetic_run


@pytest.fixture(scope="module")
def report_html(synthetic_run: SyntheticRun, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_report(synthetic_run.run, tmp_path_factory.mktemp("report") / "report.html")


def test_report_contents(synthetic_run: SyntheticRun, report_html: Path) -> None:
    text = report_html.read_text()
    # self-contained: images are embedded, nothing is fetched from elsewhere
    assert len(re.findall(r"src='data:image/png;base64,", text)) >= 4
    assert not re.search(r"(src|href)=['\"]?(https?:)?//", text)
    # defect table sorted by severity (medium pothole id 1 before low crack id 2)
    table = text[text.index("id='defects'") :]
    ids = re.findall(r"<tr><td class='num'>\d+</td><td>([^<]+)</td>", table)
    assert ids[: len(synthetic_run.defect_ids_by_severity)] == (
        synthetic_run.defect_ids_by_severity
    )
    assert "30.0" in table and "12.0" in table  # depths in mm
    # skipped frames, failed pairs, timings from report.json
    assert "frames/broken.jpg" in text and "truncated JPEG" in text
    assert "too_few_matches" in text
    assert "reconstruction" in text[text.index("id='timings'") :]
    # image evidence: a frame per defect with the outline projected in
    evidence = text[text.index("Image evidence") : text.index("<h2>Figures")]
    assert evidence.count("data:image/jpeg;base64,") == len(synthetic_run.defect_ids_by_severity)
    assert "#1 pothole, 30.0 mm, medium" in evidence


def test_report_without_gps_or_defects(tmp_path: Path) -> None:
    syn = make_synthetic_run(tmp_path, gps=False, defects=False, n_frames=4)
    (syn.run / "mosaic.tif").unlink()
    text = write_report(syn.run).read_text()
    assert "no defects were found" in text
    assert "No mosaic.tif" in text
    assert "never lon/lat" in text


def test_report_renders_in_headless_chromium(
    report_html: Path, tmp_path: Path, chromium: str
) -> None:
    out = report_html
    shot = screenshot(out.resolve().as_uri(), tmp_path / "report.png", size=(1200, 1600))
    assert shot.path.stat().st_size > 10_000
    assert not is_blank(shot.path)


def test_screenshot_without_chromium_says_how_to_install(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import roadsurf.viewer.browser as browser
    from roadsurf.core.errors import RoadsurfError

    monkeypatch.setattr(browser.shutil, "which", lambda name: None)
    assert browser.find_chromium() is None
    with pytest.raises(RoadsurfError, match="apt-get install chromium"):
        browser.screenshot("file:///nonexistent.html", tmp_path / "x.png")


def test_a_crack_without_depth_reads_not_measured(tmp_path: Path) -> None:
    # a crack kept on the images alone (detection.crackimage) has a null depth in the GeoJSON
    import json

    from roadsurf.viewer.recording import summary_markdown
    from roadsurf.viewer.runfolder import load_run

    syn = make_synthetic_run(tmp_path, n_frames=4)
    gj = syn.run / "defects.geojson"
    fc = json.loads(gj.read_text())
    crack = next(f for f in fc["features"] if f["properties"]["type"] == "crack")
    for k in ("max_depth_m", "mean_depth_m", "volume_m3"):
        crack["properties"][k] = None
    crack["properties"]["measured_on"] = "image"
    gj.write_text(json.dumps(fc))
    text = write_report(syn.run).read_text()
    assert not re.search(r"\bnan\b", text, re.IGNORECASE)
    data = load_run(syn.run)
    labels = [d.label for d in data.defects if d.type == "crack"]
    assert labels and all("depth not measured" in s for s in labels)
    assert not re.search(r"\bnan\b", summary_markdown(data, {}), re.IGNORECASE)


def test_path_length_leaves_out_the_jumps_between_segments() -> None:
    """spd2: 43 of the 48.5 m 'path length' were steps between segments placed by a guess."""
    from types import SimpleNamespace

    from roadsurf.viewer.report_sections import _path_length_m

    pos = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [30, 0, 0], [31, 0, 0]], float)

    class T(SimpleNamespace):
        def __len__(self) -> int:
            return len(self.positions_enu_m)

    data = SimpleNamespace(trajectory=T(positions_enu_m=pos, segment=np.array([0, 0, 0, 1, 1])))
    assert _path_length_m(data) == 3.0  # type: ignore[arg-type]
    data.trajectory.segment = None
    assert _path_length_m(data) == 31.0  # type: ignore[arg-type]


def test_report_of_a_folder_that_is_no_run_is_refused(tmp_path: Path) -> None:
    from roadsurf.core.errors import RoadsurfError

    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(RoadsurfError, match="not a roadsurf run folder"):
        write_report(tmp_path)
    assert not (tmp_path / "report.html").exists()
