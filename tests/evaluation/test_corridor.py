"""The imaged corridor of the surface evaluation: true camera footprints from camera.yaml, cast
on the truth road (truth/height.tif) or, without it, on a flat road."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from roadsurf.evaluation.corridor import _corridor_polygon


def _drive(tmp_path: Path, dist: list[float]) -> Path:
    (tmp_path / "truth").mkdir()
    (tmp_path / "camera.yaml").write_text(
        "model: pinhole\nwidth: 640\nheight: 480\nfx: 600.0\nfy: 600.0\ncx: 319.5\ncy: 239.5\n"
        f"dist: {dist}\nheight_m: 1.1\nfps: 15.0\n"
    )
    return tmp_path / "truth"


def _nadir_truth() -> dict[str, object]:
    # one camera looking straight down (180° about x: camera z -> world -z), at the origin
    return {"filename": ["a.png"], "xy": np.zeros((1, 2)), "q": np.array([[0.0, 1.0, 0.0, 0.0]])}


def test_corridor_of_an_ideal_camera_is_its_pixel_centre_rectangle(tmp_path: Path) -> None:
    poly = _corridor_polygon(_drive(tmp_path, [0.0] * 5), _nadir_truth(), {"a.png"})
    assert poly is not None
    assert poly.area == pytest.approx((639 / 600 * 1.1) * (479 / 600 * 1.1), rel=1e-12)


def test_corridor_follows_the_lens_distortion(tmp_path: Path) -> None:
    # barrel distortion: the raw image's corners see further out than an ideal camera's
    poly = _corridor_polygon(
        _drive(tmp_path, [-0.12, 0.03, 0.0, 0.0, 0.0]), _nadir_truth(), {"a.png"}
    )
    assert poly is not None
    assert poly.area > 1.05 * (639 / 600 * 1.1) * (479 / 600 * 1.1)


def test_no_camera_yaml_no_corridor(tmp_path: Path) -> None:
    (tmp_path / "truth").mkdir()
    assert _corridor_polygon(tmp_path / "truth", _nadir_truth(), {"a.png"}) is None


def test_two_view_corridor_pairs_consecutive_frames_after_a_skyward_frame(tmp_path: Path) -> None:
    """Frames a, b (nadir, far apart), c (looking up: no footprint), d, e (nadir, overlapping).
    The two-view corridor is d∩e only; a shifted list would also intersect b with d."""
    up = [1.0, 0.0, 0.0, 0.0]  # identity: camera z points up, its rays miss the road
    down = [0.0, 1.0, 0.0, 0.0]
    truth = {
        "filename": ["a", "b", "c", "d", "e"],
        "xy": np.array([[0.0, 0.0], [5.0, 0.0], [9.0, 0.0], [5.2, 0.0], [5.4, 0.0]]),
        "q": np.array([down, down, up, down, down]),
    }
    seen = {"a", "b", "c", "d", "e"}
    poly = _corridor_polygon(_drive(tmp_path, [0.0] * 5), truth, seen, stereo=True)
    assert poly is not None
    w, h = 639 / 600 * 1.1, 479 / 600 * 1.1
    assert poly.area == pytest.approx((w - 0.2) * h, rel=1e-9)


# ------------------------------------------------------------------ the corridor on the true road
# a tilted camera over a road with the simulator's grade (1 %), cross slope (2 %) and a 1 cm
# undulation, in UTM-sized coordinates; truth/height.tif at 1 cm cells
X0, Y0, Z0 = 630_000.0, 4_834_000.0, 95.0
CELL = 0.01


def _road_z(x: np.ndarray, y: np.ndarray, phase: float) -> np.ndarray:
    dx, dy = x - X0, y - Y0
    return Z0 + 0.01 * dy - 0.02 * dx + 0.01 * np.sin(2 * np.pi * dy / 8.0 + phase)


def _write_raster(path: Path, a: np.ndarray, transform: object) -> None:
    import rasterio

    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        height=a.shape[0],
        width=a.shape[1],
        count=1,
        dtype=a.dtype,
        crs="EPSG:32617",
        transform=transform,
        nodata=None,
    ) as dst:
        dst.write(a, 1)


def _tilted_drive(tmp_path: Path, pitch_deg: float, seed: int) -> tuple[Path, dict, float]:
    """Six frames 0.3 m apart heading north, pitched forward, rolled 2°, 1.1 m above the road
    (plus a seeded bounce of up to 1 cm); the truth height raster; returns (truth_dir, truth,
    phase)."""
    from rasterio.transform import from_origin
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    phase = float(rng.uniform(0, 2 * np.pi))
    td = _drive(tmp_path, [0.0] * 5)
    west, north, w, h = X0 - 3.0, Y0 + 7.0, 600, 900
    T = from_origin(west, north, CELL, CELL)
    cx = west + (np.arange(w) + 0.5) * CELL
    cy = north - (np.arange(h) + 0.5) * CELL
    z = _road_z(cx[None, :], cy[:, None], phase).astype(np.float32)
    _write_raster(td / "height.tif", z, T)
    _write_raster(td / "residual.tif", np.zeros_like(z), T)
    # camera looking down (180° about x), then pitched forward (about east) and rolled
    R = (
        Rotation.from_euler("x", pitch_deg, degrees=True)
        * Rotation.from_euler("y", 2.0, degrees=True)
        * Rotation.from_euler("x", 180.0, degrees=True)
    )
    xy = np.column_stack([X0 + 0.05 * np.arange(6), Y0 + 0.3 * np.arange(6)])
    up = _road_z(xy[:, 0], xy[:, 1], phase) + 1.1 + rng.uniform(-0.01, 0.01, 6)
    qx, qy, qz, qw = R.as_quat()
    truth = {
        "filename": [f"f{k}.png" for k in range(6)],
        "xy": xy,
        "up": up,
        "q": np.tile([qw, qx, qy, qz], (6, 1)),
    }
    return td, truth, phase


def _brute_force_footprints(
    truth: dict, phase: float, readout_s: float = 0.0, vel: np.ndarray | None = None
) -> list:
    """Each frame's border rays (8 a side, pixel centres) marched from the camera in 0.5 mm steps
    to their first point under the analytic road; with a rolling shutter, each row's ray from
    the frame's centre moved by its velocity ``vel`` (frames, 3) over readout_s · v / 480."""
    import shapely
    from scipy.spatial.transform import Rotation

    n = 8
    t = np.linspace(0.0, 1.0, n + 1)[:-1]
    u = np.concatenate([t * 639, np.full(n, 639.0), (1 - t) * 639, np.zeros(n)])
    v = np.concatenate([np.zeros(n), t * 479, np.full(n, 479.0), (1 - t) * 479])
    rays = np.column_stack([(u - 319.5) / 600, (v - 239.5) / 600, np.ones(4 * n)])
    lam = np.arange(0.2, 6.0, 0.0005)
    out = []
    for k in range(len(truth["filename"])):
        q = truth["q"][k]
        rw = rays @ Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix().T
        C = np.array([*truth["xy"][k], truth["up"][k]])[None, :]
        if vel is not None:
            C = C + vel[k][None, :] * (readout_s * v / 480.0)[:, None]  # (rays, 3)
        P = C[:, None, :] + lam[None, :, None] * rw[:, None, :]  # (rays, steps, 3)
        below = P[..., 2] <= _road_z(P[..., 0], P[..., 1], phase)
        assert below.any(axis=1).all()
        out.append(shapely.Polygon(P[np.arange(len(rw)), np.argmax(below, axis=1), :2]))
    return out


@pytest.mark.parametrize("pitch_deg", [25.0, 45.0])
def test_tilted_corridor_is_the_border_cast_on_the_true_road(tmp_path: Path, pitch_deg: float):
    import shapely

    from roadsurf.evaluation.corridor import corridor_from_footprints, true_footprints

    td, truth, phase = _tilted_drive(tmp_path, pitch_deg, seed=23)
    seen = set(truth["filename"])
    ref = _brute_force_footprints(truth, phase)
    feet = true_footprints(td, truth, seen)
    assert feet is not None
    for got, want in zip(feet, ref, strict=True):
        assert got is not None
        # vertices within half a truth cell (the reference marches 0.5 mm steps)
        assert got.hausdorff_distance(want) < 0.5 * CELL
    want2 = shapely.union_all([a.intersection(b) for a, b in zip(ref[:-1], ref[1:], strict=True)])
    got2 = corridor_from_footprints(feet, stereo=True)
    assert got2 is not None
    assert got2.symmetric_difference(want2).area < 2e-3 * want2.area
    # the flat-road corridor (no truth heights) misplaces the far corners by centimetres
    flat = corridor_from_footprints(true_footprints(td, truth, seen, road=False), stereo=True)
    assert flat is not None
    assert flat.hausdorff_distance(want2) > (0.01 if pitch_deg < 30 else 0.05)


def _run_with_measured(tmp_path: Path, td: Path, measured: object) -> Path:
    """A run whose surface covers the truth grid, measured (count 1) inside ``measured``."""
    import rasterio
    from rasterio.features import rasterize

    run = tmp_path / "run"
    run.mkdir(parents=True)
    with rasterio.open(td / "residual.tif") as t:
        shape, T = t.shape, t.transform
    nobs = rasterize([measured], out_shape=shape, transform=T, fill=0, default_value=1)
    _write_raster(run / "surface.tif", np.zeros(shape, np.float32), T)
    _write_raster(run / "surface_nobs.tif", nobs.astype(np.uint8), T)
    return run


def test_two_view_measured_coverage_on_the_true_road_and_an_unmeasured_strip(
    tmp_path: Path,
) -> None:
    """A run measuring exactly what two consecutive frames saw scores ~100 % on the road-cast
    corridor; one that leaves the far 15 cm unmeasured scores 1 - the strip's share (below
    98 %)."""
    import shapely

    from roadsurf.evaluation.surface import surface_metrics

    td, truth, phase = _tilted_drive(tmp_path, 45.0, seed=7)
    seen = set(truth["filename"])
    ref = _brute_force_footprints(truth, phase)
    seen_twice = shapely.union_all(
        [a.intersection(b) for a, b in zip(ref[:-1], ref[1:], strict=True)]
    )
    full = surface_metrics(
        _run_with_measured(tmp_path / "a", td, seen_twice), td, truth, None, None, {}, seen
    )
    assert full["corridor_road"] == "truth_height"
    assert full["coverage_two_view_measured"] > 0.995

    # the far rows' strip (where a tilted camera's matching fails first), 15 cm deep
    x0, _, x1, y1 = seen_twice.bounds
    strip = shapely.box(x0 - 1.0, y1 - 0.15, x1 + 1.0, y1 + 1.0)
    part = seen_twice.difference(strip)
    res = surface_metrics(
        _run_with_measured(tmp_path / "b", td, part), td, truth, None, None, {}, seen
    )
    expected = part.area / seen_twice.area
    assert res["coverage_two_view_measured"] < 0.98
    assert res["coverage_two_view_measured"] == pytest.approx(expected, abs=0.005)


def test_corridor_beyond_the_truth_heights_extrapolates_the_road_plane(tmp_path: Path) -> None:
    """Heights only up to 2 m ahead of the first camera: the far border rays meet the plane
    fitted under the footprint, off by the undulation's curvature only (a 1 cm wave of 8 m
    wavelength leaves <= 4 mm over 1.5 m, x 2.4 along a ray 23° below the horizon: < 1.5 cm),
    where the flat road misses by ~20 cm."""
    import rasterio

    from roadsurf.evaluation.corridor import true_footprints

    td, truth, phase = _tilted_drive(tmp_path, 45.0, seed=23)
    with rasterio.open(td / "height.tif") as src:
        z, T = src.read(1), src.transform
    z[T.f - (np.arange(z.shape[0]) + 0.5) * CELL > Y0 + 2.0, :] = np.nan
    _write_raster(td / "height.tif", z, T)
    ref = _brute_force_footprints(truth, phase)
    seen = set(truth["filename"])
    for got, flat, want in zip(
        true_footprints(td, truth, seen) or [],
        true_footprints(td, truth, seen, road=False) or [],
        ref,
        strict=True,
    ):
        assert got is not None and flat is not None
        assert got.hausdorff_distance(want) < 0.015
        assert flat.hausdorff_distance(want) > 0.1


def test_rolling_shutter_border_rows_are_cast_from_their_own_poses(tmp_path: Path) -> None:
    """A 30 ms readout at 3 m/s: each border row is exposed readout·v/height after the frame's
    first row, 9 cm of travel for the bottom row. The cast footprint follows the brute-force
    march from each row's own centre (velocity from the neighbouring frames), where the
    first-row pose alone misplaces the late rows by centimetres."""
    from roadsurf.evaluation.corridor import true_footprints

    td, truth, phase = _tilted_drive(tmp_path, 25.0, seed=5)
    cam_yaml = td.parent / "camera.yaml"
    cam_yaml.write_text(cam_yaml.read_text() + "readout_s: 0.03\n")
    truth["t"] = 0.1 * np.arange(6)
    C_all = np.column_stack([truth["xy"], truth["up"]])
    vel = np.gradient(C_all, truth["t"], axis=0)  # central differences, one-sided at the ends
    ref = _brute_force_footprints(truth, phase, 0.03, vel)
    seen = set(truth["filename"])
    feet = true_footprints(td, truth, seen)
    gs = dict(truth, t=np.full(6, np.nan))  # no times: every ray from the first row's pose
    feet_gs = true_footprints(td, gs, seen)
    assert feet is not None and feet_gs is not None
    for got, first_row, want in zip(feet, feet_gs, ref, strict=True):
        assert got is not None and first_row is not None
        assert got.hausdorff_distance(want) < 0.5 * CELL
        assert first_row.hausdorff_distance(want) > 0.05


def test_a_run_in_the_neighbouring_utm_zone_is_scored_in_the_truths(tmp_path: Path) -> None:
    """A drive on a zone border: the run may choose the zone west of the truth's (both valid).
    Its cells are taken into the truth's CRS before they are compared (a fault battery's run
    in zone 35 against truth in 36 scored 0 % coverage and no height figure)."""
    import rasterio
    import shapely
    from rasterio.warp import Resampling, calculate_default_transform, reproject

    from roadsurf.evaluation.surface import surface_metrics

    td, truth, phase = _tilted_drive(tmp_path, 25.0, seed=7)
    seen = set(truth["filename"])
    ref = _brute_force_footprints(truth, phase)
    twice = shapely.union_all([a.intersection(b) for a, b in zip(ref[:-1], ref[1:], strict=True)])
    run = _run_with_measured(tmp_path / "a", td, twice)
    same = surface_metrics(run, td, truth, None, "EPSG:32617", {}, seen)
    for name in ("surface.tif", "surface_nobs.tif"):  # the run's rasters in zone 16
        with rasterio.open(run / name) as src:
            T, w, h = calculate_default_transform(
                src.crs, "EPSG:32616", src.width, src.height, *src.bounds
            )
            dst = np.zeros((h, w), src.dtypes[0])
            reproject(rasterio.band(src, 1), dst, dst_transform=T, dst_crs="EPSG:32616",
                      resampling=Resampling.nearest)  # fmt: skip
        _write_raster(run / name, dst, T)
        with rasterio.open(run / name, "r+") as f:
            f.crs = "EPSG:32616"
    other = surface_metrics(run, td, truth, None, "EPSG:32617", {}, seen)
    assert same["coverage_two_view_measured"] > 0.99
    assert other["coverage_two_view_measured"] == pytest.approx(
        same["coverage_two_view_measured"], abs=0.02
    )
