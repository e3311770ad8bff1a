"""The trajectory figures: the revisit agreement (issue 30) measures only how two passes over
the same place agree, whatever the drive's global offset."""

from __future__ import annotations

import math

import numpy as np
import pytest

from roadsurf.evaluation.trajectory import revisit_agreement


def _two_passes(n: int = 30, step: float = 0.4) -> np.ndarray:
    x = np.arange(n) * step
    return np.concatenate([np.column_stack([x, 0 * x]), np.column_stack([x, 0 * x + 0.05])])


def test_passes_that_agree_read_zero_whatever_the_global_offset() -> None:
    t = _two_passes()
    k, med, mx = revisit_agreement(t + [3.0, -2.0], t)
    assert k == 30 and med < 1e-12 and mx < 1e-12


def test_a_pass_placed_apart_reads_its_offset() -> None:
    t = _two_passes()
    e = t.copy()
    e[30:] += [0.0, 0.12]  # the second pass 12 cm off (e.g. each pass on its own GPS bias)
    e[5] += [0.02, 0.0]  # one first-pass frame 2 cm off
    k, med, mx = revisit_agreement(e, t)
    assert k == 30
    assert med == pytest.approx(0.12, abs=1e-9)
    assert mx == pytest.approx(math.hypot(0.02, 0.12), abs=1e-9)


def test_no_revisit_no_figure() -> None:
    x = np.arange(40) * 0.4
    t = np.column_stack([x, 0 * x])
    k, med, mx = revisit_agreement(t, t)
    assert k == 0 and math.isnan(med) and math.isnan(mx)
    # a vehicle that stops does not revisit: frames at one place without 5 m of travel between
    t_stop = np.concatenate([t[:10], np.repeat(t[9:10], 10, axis=0), t[10:]])
    assert revisit_agreement(t_stop, t_stop)[0] == 0


def test_cloud_density_reads_the_ply_header(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from roadsurf.evaluation.report import cloud_density

    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 5000\nproperty float x\nend_header\n"
    )
    (tmp_path / "cloud.ply").write_bytes(header.encode() + b"\0" * 16)
    assert cloud_density(tmp_path, 0.1) == pytest.approx(50000.0)
    assert cloud_density(tmp_path, None) is None
    assert cloud_density(tmp_path / "none", 0.1) is None


def test_a_run_whose_frame_names_the_truth_lacks_is_a_clear_error() -> None:
    """Frames converted to PNG after the render: no name matches truth/poses.csv. The evaluation
    says so (an InputError, exit 2) instead of a traceback from an empty fit."""
    import pytest

    from roadsurf.core.errors import InputError
    from roadsurf.evaluation.trajectory import trajectory_metrics

    xy = np.column_stack([np.arange(5.0), np.zeros(5)])
    truth = {"filename": [f"f{i}.jpg" for i in range(5)], "xy": xy, "heading_deg": np.zeros(5)}
    est = {"filename": [f"f{i}.png" for i in range(5)], "xy": xy, "heading_deg": np.zeros(5)}
    with pytest.raises(InputError, match=r"0 of the run's 5 frames .* f0.png, f1.png, .* f0.jpg"):
        trajectory_metrics(est, truth)
    est["filename"] = truth["filename"]
    assert trajectory_metrics(est, truth)["metrics"]["trajectory_rmse_m"] == 0.0


def test_gps_rmse_is_measured_against_the_antenna_not_the_camera(tmp_path) -> None:
    """Fixes exact at an antenna 1.5 m behind and 0.4 m left of the camera, on a drive heading
    east: 0 against the antenna's path, 1.55 m against the camera's."""
    from pyproj import Transformer

    from roadsurf.evaluation.trajectory import gps_rmse_m

    crs = "EPSG:32617"
    truth = tmp_path / "truth"
    truth.mkdir()
    t = np.arange(0.0, 10.0, 0.5)
    e, n = 630000.0 + 2.0 * t, np.full_like(t, 4834000.0)
    from scipy.spatial.transform import Rotation

    from roadsurf.core.geometry import world_from_cam

    # the truth's camera rotation (a nadir camera, vehicle heading east) as its quaternion
    qx, qy, qz, qw = Rotation.from_matrix(world_from_cam(90.0)[:3, :3]).as_quat()
    rows = ["filename,timestamp_s,easting_m,northing_m,up_m,heading_deg,qw,qx,qy,qz"]
    rows += [
        f"f{i}.jpg,{ti},{ei},{ni},100.0,90.0,{qw},{qx},{qy},{qz}"
        for i, (ti, ei, ni) in enumerate(zip(t, e, n, strict=True))
    ]
    (truth / "poses.csv").write_text("\n".join(rows) + "\n")
    # heading east: forward = +E, left = +N
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(e - 1.5, n + 0.4)
    g = ["timestamp_s,lat,lon"] + [
        f"{ti},{la:.10f},{lo:.10f}" for ti, la, lo in zip(t, lat, lon, strict=True)
    ]
    (tmp_path / "gps.csv").write_text("\n".join(g) + "\n")
    assert gps_rmse_m(truth, crs, (-1.5, 0.4, 0.9)) < 1e-3
    assert gps_rmse_m(truth, crs) == pytest.approx(math.hypot(1.5, 0.4), abs=1e-3)
