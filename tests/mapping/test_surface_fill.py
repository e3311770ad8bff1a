"""The residual surface covers the part of the road seen by both frames of a pair, not only the
hull of its sparse points: matches stop short of the image borders (SIFT needs a margin), so the
surface is extended from the points by at most ``surface_fill_max_m`` in the strip along the
border of the two-view part (``raster.fill_nodata_capped``), never beyond it, never further than
the cap, never into holes away from the border wider than twice the cap (dark pothole floors stay
holes; narrower ones are closed, as the interpolation would with points around) and never
extrapolating relief (a pothole running off the measured part is not continued). Before, the raster stopped at the point hull: 89-92 % coverage
of the imaged corridor on the sample and potholes drives."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio

from roadsurf.core.geometry import enu_from_lla, lla_from_utm
from roadsurf.io.formats import GridSpec
from roadsurf.mapping import globalmap, poses, surface_raster
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.raster import fill_nodata_capped
from tests.mapping.synth import make_pair, make_synthetic, write_images

# ------------------------------------------------------------------ one tile, known geometry
BOX = (0.2, 1.08)  # the points cover x and -y in this range (m, grid CRS)
# ... the two-view part is 4 cm wider (matches stop short of the image borders), 10 cm on the
# left (x < 0.2), where the gap is wider than the cap
OVERLAP_X, OVERLAP_Y = (0.1, 1.12), (0.16, 1.12)
HOLE_C, HOLE_R = np.array([0.45, -0.45]), 0.10  # no points in this disk (flat road)
SMALL_C, SMALL_R = np.array([0.8, -0.45]), 0.035  # ... nor in this small one
BOWL_C, BOWL_R, BOWL_D = np.array([1.08, -0.8]), 0.12, 0.03  # pothole cut by the point border


def _truth(xy: np.ndarray) -> np.ndarray:
    r = np.linalg.norm(xy - BOWL_C, axis=1)
    return -BOWL_D * 0.5 * (1 + np.cos(np.pi * np.clip(r / BOWL_R, 0, 1)))


def _overlap_mask(g: GridSpec) -> np.ndarray:
    c = np.arange(g.width)
    r = np.arange(g.height)
    x = g.x0_m + (c + 0.5) * g.gsd_m
    y = g.y0_m - (r + 0.5) * g.gsd_m
    inx = (x >= OVERLAP_X[0]) & (x <= OVERLAP_X[1])
    iny = (-y >= OVERLAP_Y[0]) & (-y <= OVERLAP_Y[1])
    return iny[:, None] & inx[None, :]


def _box_dist(xy: np.ndarray, bx: tuple[float, float], by: tuple[float, float]) -> np.ndarray:
    """Distance (m) outside the rectangle bx x (-by) (0 inside)."""
    dx = np.maximum(np.maximum(bx[0] - xy[:, 0], xy[:, 0] - bx[1]), 0)
    dy = np.maximum(np.maximum(by[0] + xy[:, 1], -xy[:, 1] - by[1]), 0)
    return np.hypot(dx, dy)


def test_surface_tile_fills_to_the_overlap_up_to_the_cap() -> None:
    rng = np.random.default_rng(3)
    cfg = MappingConfig()
    grid = GridSpec("EPSG:32617", 0.0, 0.0, cfg.gsd_m, 256, 256)
    n = 6000  # ~1.4 cm spacing
    xy = np.column_stack([rng.uniform(*BOX, n), -rng.uniform(*BOX, n)])
    xy = xy[np.linalg.norm(xy - HOLE_C, axis=1) > HOLE_R]
    xy = xy[np.linalg.norm(xy - SMALL_C, axis=1) > SMALL_R]
    noise = 0.001
    z = _truth(xy) + rng.normal(0, noise, len(xy))
    old = surface_raster.surface_tile_filled(cfg, xy, z, grid, noise_m=noise)[0]
    new = surface_raster.surface_tile_filled(
        cfg, xy, z, grid, noise_m=noise, fill_mask=_overlap_mask
    )[0]
    rr, cc = np.mgrid[0 : grid.height, 0 : grid.width]
    pix = grid.xy_from_rowcol(rr.ravel(), cc.ravel())
    old, new = old.ravel(), new.ravel()
    out = _box_dist(pix, BOX, BOX)  # distance beyond the points' square
    far_bowl = np.linalg.norm(pix - BOWL_C, axis=1) > BOWL_R + 0.08
    left = pix[:, 0] < BOX[0]
    # flat road between the points and the overlap border (4 cm away)
    band = (out > 0.01) & (out < 0.03) & far_bowl & ~left
    assert band.sum() > 1000
    assert np.isfinite(old[band]).mean() < 0.1  # old: the raster stopped at the point hull
    assert np.isfinite(new[band]).mean() > 0.99  # new: the overlap is covered up to the cap
    assert np.max(np.abs(new[band])) < 2 * noise  # flat road continued, nothing invented
    # never further than the cap (5 cm, + one coarse pixel), never outside the overlap; where
    # the points stop 10 cm short (left), the gap is not bridged
    assert not np.isfinite(new[out > cfg.surface_fill_max_m + 0.012]).any()
    assert not np.isfinite(new[_box_dist(pix, OVERLAP_X, OVERLAP_Y) > 0.012]).any()
    assert np.isfinite(new[left & (out > 0.015)]).mean() < 0.02
    # a hole without points away from the overlap border (a dark pothole floor, a textureless
    # stain) wider than twice the cap is not filled at all (no flat rim creeping in); a small
    # one (every pixel within the cap) is closed
    d_hole = np.linalg.norm(pix - HOLE_C, axis=1)
    assert np.array_equal(np.isfinite(new[d_hole < HOLE_R]), np.isfinite(old[d_hole < HOLE_R]))
    assert not np.isfinite(new[d_hole < 0.06]).any()
    d_small = np.linalg.norm(pix - SMALL_C, axis=1) < SMALL_R
    assert not np.isfinite(old[d_small]).all()
    assert np.isfinite(new[d_small]).all() and np.abs(new[d_small]).max() < 2 * noise
    # the pothole cut by the point border is not continued beyond it (depth unknown there)
    beyond_bowl = (out > 0.01) & (np.linalg.norm(pix - BOWL_C, axis=1) < 0.6 * BOWL_R)
    assert beyond_bowl.sum() > 100
    assert not np.isfinite(new[beyond_bowl]).any()
    # measured pixels are kept (up to the bilinear upsampling blend at the hull's edge)
    both = np.isfinite(old)
    assert np.isfinite(new[both]).all()
    np.testing.assert_allclose(new[both], old[both], atol=0.2 * noise)


def test_fill_nodata_capped_stays_within_the_measured_range() -> None:
    v = np.full((40, 40), np.nan, np.float32)
    v[:, :20] = np.linspace(-0.002, 0.002, 20)[None, :]
    allowed = np.ones_like(v, bool)
    allowed[:, 30:] = False
    out = fill_nodata_capped(v, allowed, max_px=6)
    filled = np.isfinite(out) & ~np.isfinite(v)
    cols = np.nonzero(filled.any(axis=0))[0]
    assert cols.min() == 20 and cols.max() == 25  # up to the cap
    assert np.all(out[filled] <= 0.002) and np.all(out[filled] >= -0.002)
    lim = fill_nodata_capped(v, allowed, max_px=6, max_abs=0.0015)
    assert np.all(np.abs(lim[np.isfinite(lim) & ~np.isfinite(v)]) <= 0.0015)
    assert np.array_equal(fill_nodata_capped(v, allowed, max_px=0), v, equal_nan=True)


# ------------------------------------------------------------------ the whole map stage


def _two_view_fraction(
    run: Path, syn, traj, pairs, tol_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per surface pixel: finite?, inside both images of a pair (shrunk by tol_px; negative
    tol_px widens them), with the run's own fused poses, on the (flat) road."""
    with rasterio.open(run / "surface.tif") as s:
        res = s.read(1)
        T = s.transform
    rows, cols = np.mgrid[0 : res.shape[0], 0 : res.shape[1]]
    rows, cols = rows.ravel(), cols.ravel()
    xy = np.column_stack([T.c + (cols + 0.5) * T.a, T.f + (rows + 0.5) * T.e])
    lla = lla_from_utm(xy[:, 0], xy[:, 1], 32617)
    enu = enu_from_lla(lla[:, 0], lla[:, 1], 0.0, traj.reference)  # the run's own ENU frame
    with np.load(run / "map_points.npz") as z:
        enu[:, 2] = np.median(z["xyz"][:, 2])  # the flat road, in the run's frame
    cam = syn.drive.camera
    idx = {fn: i for i, fn in enumerate(traj.filenames)}

    def inside(i: int) -> np.ndarray:
        W = traj.world_from_cam[i]
        Xc = (enu - W[:3, 3]) @ W[:3, :3]
        u, v = cam.project(Xc)
        with np.errstate(invalid="ignore"):
            return (
                (u >= tol_px)
                & (u <= cam.width - 1 - tol_px)
                & (v >= tol_px)
                & (v <= cam.height - 1 - tol_px)
            )

    two = np.zeros(len(enu), bool)
    for p in pairs:
        two |= inside(idx[p.frame_a]) & inside(idx[p.frame_b])
    return np.isfinite(res.ravel()), two, res.ravel()


def test_map_covers_the_pairs_overlap_and_not_beyond(tmp_path: Path) -> None:
    syn = make_synthetic(n=8, seed=5, gps_hz=5.0)
    rng = np.random.default_rng(1)
    W = syn.world_from_cam
    cam = syn.drive.camera
    # matches stop 6 px (~4 cm) short of every image border
    syn.pairs = [make_pair(i, W[i], W[i + 1], cam, rng, n_pts=900, px_margin=6) for i in range(7)]
    syn = write_images(syn, tmp_path / "drive")
    cov = {}
    for name, fill in (("old", 0.0), ("new", 0.05)):
        cfg = MappingConfig(
            gps_sigma_m=0.02, tile_px=256, surface_fill_max_m=fill, surface_source="sparse"
        )
        run = tmp_path / name
        traj = poses.run(cfg, syn.drive, syn.pairs, run)
        globalmap.run(cfg, syn.drive, syn.pairs, traj, run)
        fin, two, res = _two_view_fraction(run, syn, traj, syn.pairs, tol_px=1.0)
        cov[name] = fin[two].mean()
        if name == "new":
            # nothing beyond the pairs' two-view part (half a pixel for the road height used;
            # this drive has no strip seen by one frame only between two pairs)
            _, two_wide, _ = _two_view_fraction(run, syn, traj, syn.pairs, tol_px=-0.5)
            assert not (fin & ~two_wide).any()
            assert np.abs(res[fin]).max() < 0.003  # flat road stays flat
    assert cov["old"] < 0.93
    assert cov["new"] > 0.98
