"""Dense surface fusion (mapping.dense_fuse): the robust per-cell estimate, and the whole map
of a short rendered drive (simulator, 320 x 240, a 50 mm pothole) built with
``surface_source = "dense"`` against the truth and against the sparse surface."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.warp import Resampling, reproject

from roadsurf.io.drive import load_drive
from roadsurf.mapping import globalmap, poses
from roadsurf.mapping.config import MappingConfig
from roadsurf.mapping.dense_fuse import DenseSurface, fuse_cells
from roadsurf.reconstruction import stage as recon_stage
from roadsurf.reconstruction.config import ReconstructionConfig


def test_fuse_cells_weighted_median_then_trimmed_mean() -> None:
    cell = np.array([0, 0, 0, 1, 1, 3])
    val = np.array([0.001, 0.0012, 0.02, -0.01, -0.012, 0.005])
    var = np.array([1e-6, 1e-6, 1e-6, 1e-6, 4e-6, 2.5e-7])
    est, n, sig = fuse_cells(cell, val, var, 5, 3.0)
    # cell 0: the 20 mm outlier is left out, the two others averaged
    assert est[0] == pytest.approx(0.0011, abs=1e-9) and n[0] == 2
    # cell 1: variance-weighted mean (weights 4:1), σ = sqrt(1 / Σw)
    assert est[1] == pytest.approx((4 * -0.01 + -0.012) / 5, abs=1e-9) and n[1] == 2
    assert sig[1] == pytest.approx(np.sqrt(1 / (1e6 + 2.5e5)), rel=1e-5)
    # cell 3: one sample, its own σ; cells 2 and 4: nothing
    assert est[3] == pytest.approx(0.005) and n[3] == 1 and sig[3] == pytest.approx(5e-4)
    assert np.isnan(est[[2, 4]]).all() and (n[[2, 4]] == 0).all()
    # two samples that disagree: σ grows with their scatter, not only with 1 / Σw
    est2, _, sig2 = fuse_cells(np.array([0, 0]), np.array([0.0, 0.002]), np.full(2, 1e-6), 1, 3)
    assert est2[0] == pytest.approx(0.001) and sig2[0] > 1e-3 / np.sqrt(2) * 0.99


def test_fuse_cells_weights_decide_the_median() -> None:
    # three samples, the precise one far from the two loose ones: it wins the median
    est, n, _ = fuse_cells(
        np.zeros(3, int), np.array([0.0, 0.0001, 0.01]), np.array([1e-6, 1e-6, 1e-8]), 1, 3.0
    )
    assert est[0] == pytest.approx(0.01, abs=1e-5) and n[0] == 1


@pytest.fixture(scope="module")
def drive_maps(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    from roadsurf.simulation.scenarios import simulate

    root = tmp_path_factory.mktemp("dense_drive")
    simulate(
        "potholes",
        root / "D",
        n_frames=10,
        progress=False,
        width=320,
        height=240,
        fx=300.0,
        n_potholes=1,
        n_cracks=0,
        n_ruts=0,
        n_shadows=0,
        n_oil_stains=0,
    )
    drive = load_drive(root / "D")
    run = root / "run"
    pairs = recon_stage.run(ReconstructionConfig(), drive, run)
    traj = poses.run(MappingConfig(), drive, pairs, run)
    out: dict[str, object] = {"root": root, "drive": drive, "pairs": pairs, "traj": traj}
    for src in ("sparse", "dense"):
        cfg = MappingConfig(surface_source=src)  # type: ignore[arg-type]
        out[src] = globalmap.run(cfg, drive, pairs, traj, root / src)
    cfg = MappingConfig(dense_single_view="empty")
    out["dense_empty"] = globalmap.run(cfg, drive, pairs, traj, root / "dense_empty")
    return out


def _errors(run: Path, truth: Path, traj_dir: Path) -> tuple[np.ndarray, ...]:
    """Surface minus truth residual on the truth grid, and the truth's flat / pothole masks. The
    surface is moved by the mean offset of the fused camera centres from the true ones (the
    drive's few RTK fixes place it ~2 cm off; both surfaces share it)."""
    import csv

    from roadsurf.mapping.export import export_xyz
    from roadsurf.mapping.types import load_trajectory

    traj = load_trajectory(traj_dir)
    with open(truth / "poses.csv", newline="") as f:
        rows = {r["filename"]: r for r in csv.DictReader(f)}
    g = export_xyz(traj.positions_enu_m, traj.export_frame)[:, :2]
    t = np.array(
        [[float(rows[fn]["easting_m"]), float(rows[fn]["northing_m"])] for fn in traj.filenames]
    )
    off = np.mean(g - t, axis=0)
    with rasterio.open(truth / "residual.tif") as tr_:
        tr, tT, crs = tr_.read(1), tr_.transform, tr_.crs
    with rasterio.open(run / "surface.tif") as s:
        sT = s.transform
        sT = rasterio.Affine(sT.a, sT.b, sT.c - off[0], sT.d, sT.e, sT.f - off[1])
        dst = np.full(tr.shape, np.nan, np.float32)
        reproject(
            s.read(1), dst, src_transform=sT, src_crs=s.crs, dst_transform=tT,
            dst_crs=crs, resampling=Resampling.nearest, src_nodata=np.nan, dst_nodata=np.nan,
        )  # fmt: skip
    err = dst - tr
    return err, np.abs(tr) < 0.003, tr < -0.01


def test_dense_surface_against_truth_and_sparse(drive_maps: dict[str, object]) -> None:
    root = drive_maps["root"]
    assert isinstance(root, Path)
    figs = {}
    for src in ("sparse", "dense"):
        err, flat, pot = _errors(root / src, root / "D" / "truth", root / "run")
        m = np.isfinite(err)
        figs[src] = (
            float(np.mean(np.abs(err[m & flat]))),
            float(np.mean(np.abs(err[m & pot]))),
            int((m & pot).sum()),
        )
    # measured (320 x 240): dense flat 1.18 mm / pothole 2.93 mm; sparse 1.60 / 4.17 mm
    assert figs["dense"][0] < 1.5 and figs["dense"][1] < 4.0
    assert figs["dense"][0] < figs["sparse"][0]
    assert figs["dense"][1] < figs["sparse"][1]
    assert figs["dense"][2] >= 0.9 * figs["sparse"][2]  # the pothole is covered


def test_dense_products_and_grid(drive_maps: dict[str, object]) -> None:
    root = drive_maps["root"]
    prod = drive_maps["dense"]
    assert isinstance(root, Path)
    d = root / "dense"
    with rasterio.open(d / "surface.tif") as s, rasterio.open(d / "mosaic.tif") as m:
        assert s.transform == m.transform and s.shape == m.shape
        # 2 px of the images' ground sampling (1.1 / 300 = 3.7 mm), capped at the sparse 5 mm
        assert s.transform.a == pytest.approx(0.005)
        res = s.read(1)
    with rasterio.open(d / "surface_nobs.tif") as n, rasterio.open(d / "surface_sigma.tif") as g:
        nobs, sig = n.read(1), g.read(1)
    fin = np.isfinite(res)
    assert fin.sum() == prod.surface_px > 0  # type: ignore[attr-defined]
    with rasterio.open(root / "dense_empty" / "surface.tif") as s:
        fin2 = np.isfinite(s.read(1))  # the cells seen by one frame only left empty
    # measured cells (the rest: holes filled from the measured cells around them,
    # dense.hole_fill_m, the sparse fill and the capped fill along the two-view border)
    meas = fin & (nobs >= 1)
    assert meas.sum() > 0.9 * fin2.sum() and (nobs[~fin] == 0).all()  # measured 92.7%
    assert np.isfinite(sig[meas]).all() and np.median(sig[meas]) < 0.003
    # consecutive pairs' parts overlap where three frames saw the road (55% frame overlap: a
    # strip of ~20%; measured 19%)
    assert (nobs >= 2).sum() > 0.1 * fin.sum()
    assert prod.files["surface_nobs"] == "surface_nobs.tif"  # type: ignore[attr-defined]
    # the pairs' own samples where two measured a cell, for evaluate's seam steps
    from roadsurf.evaluation.seams import seam_report

    assert prod.files["dense_seams"] == "dense_seams.npz"  # type: ignore[attr-defined]
    seams = seam_report(d)
    assert seams["seam_source"] == "dense" and seams["seam_pairs"] == 8
    # measured: 298 samples a seam, standard error 0.05 mm (the sparse points: 0.2-0.4 mm)
    assert seams["seam_step_se_median_m"] < 0.1e-3 and seams["seam_samples_median"] > 200
    # what one value measures on the ground: the 5 px window at ~3.7 mm a pixel, for detection
    from roadsurf.detection.windows import RasterSource

    src = RasterSource(d / "surface.tif")
    assert src.footprint_m == pytest.approx(5 * 1.1 / 300, rel=0.1)
    assert np.isnan(RasterSource(root / "sparse" / "surface.tif").footprint_m)


def test_dense_cloud_holds_every_measured_cell(drive_maps: dict[str, object]) -> None:
    """cloud.ply of a dense run: one point per measured cell (5 mm cells: 40,000 points/m²),
    at the cell's centre, its residual the surface's, z = road + residual (smooth)."""
    from plyfile import PlyData

    root = drive_maps["root"]
    prod = drive_maps["dense"]
    assert isinstance(root, Path)
    d = root / "dense"
    with rasterio.open(d / "surface.tif") as s, rasterio.open(d / "surface_nobs.tif") as n:
        res, nobs, T = s.read(1), n.read(1), s.transform
    v = PlyData.read(str(d / "cloud.ply"))["vertex"]
    meas = np.isfinite(res) & (nobs > 0)
    assert len(v) == meas.sum() == prod.residual_stats_m["dense_cloud_points"]  # type: ignore[attr-defined]
    density = len(v) / ((np.isfinite(res) & ~model_cells(root)).sum() * T.a * T.a)
    assert density >= 0.9 * 40_000  # measured cells / surface cells: the fill has no points
    col, row = ~T * (np.asarray(v["x"]), np.asarray(v["y"]))
    assert np.allclose(col % 1, 0.5, atol=1e-3) and np.allclose(row % 1, 0.5, atol=1e-3)
    r, c = row.astype(int), col.astype(int)
    assert meas[r, c].all()
    assert np.allclose(v["residual_m"], res[r, c], atol=1e-7)
    road = np.asarray(v["z"]) - np.asarray(v["residual_m"])
    assert np.nanstd(road) < 0.05  # the road's own height: a ~1 m stretch of street
    comments = PlyData.read(str(d / "cloud.ply")).comments
    assert any(c.startswith("crs: ") for c in comments)
    assert any(c.startswith("vertical_datum: ") for c in comments)


def test_pairs_are_matched_once_and_dropped(drive_maps: dict[str, object]) -> None:
    from roadsurf.mapping.raster import GridToEnu, corridor_tiles
    from roadsurf.mapping.surface import LocalSurface

    drive, pairs, traj = drive_maps["drive"], drive_maps["pairs"], drive_maps["traj"]
    cfg = dataclasses.replace(MappingConfig(surface_source="dense"), tile_px=64)
    cam = drive.camera  # type: ignore[attr-defined]
    W = traj.world_from_cam  # type: ignore[attr-defined]
    fp = [cam.footprint_grid_enu(T, T[2, 3] - cam.height_m)[:, :2] for T in W]
    lat, tiles = corridor_tiles(np.concatenate(fp), "LOCAL", 0.0037, 64)
    surf = LocalSurface(cfg, np.column_stack([W[:, :2, 3], W[:, 2, 3] - cam.height_m]))
    ds = DenseSurface(cfg, drive, pairs, traj, surf, GridToEnu(None, None), lat, tiles, fp, 1)  # type: ignore[arg-type]
    peak = 0
    # in drive order, as rasterise visits them
    for t in sorted(tiles, key=lambda t: (min(ds.tile_pairs[t], default=1 << 30), t)):
        ds.tile(t)
        peak = max(peak, len(ds._done))
    assert ds.stats["pairs"] == len(ds.pairs) == sum(p.ok for p in pairs)  # type: ignore[attr-defined]
    assert not ds._done  # every pair dropped once its last tile was fused
    assert peak <= 4  # a few pairs held at a time (9 pairs, tiles of 24 cm)


def test_map_key_holds_the_dense_settings_only_when_dense() -> None:
    from roadsurf.mapping.types import Trajectory
    from roadsurf.reconstruction.dense.config import DenseHeightConfig
    from tests.mapping.synth import make_synthetic

    syn = make_synthetic(n=4, seed=3)
    traj = Trajectory(
        filenames=[f.filename for f in syn.drive.frames],
        frame_indices=np.arange(4),
        timestamp_s=np.arange(4) * 0.05,
        world_from_cam=syn.world_from_cam,
        source=["fused"] * 4,
        reference=None,
    )

    def key(**kw: object) -> str:
        return globalmap._fingerprint(MappingConfig(**kw), syn.pairs, traj)  # type: ignore[arg-type]

    sparse = key(surface_source="sparse")
    assert key(surface_source="sparse", dense_gsd_m=0.003) == sparse  # ignored when sparse
    dense = key(surface_source="dense")
    assert dense != sparse
    assert key(surface_source="dense", dense_gsd_m=0.003) != dense
    assert key(surface_source="dense", dense=DenseHeightConfig(window_px=7)) != dense
    same = DenseHeightConfig(device="cpu", smooth_px=MappingConfig().dense.smooth_px)
    assert key(surface_source="dense", dense=same) == dense


def test_pair_levelling_ignores_a_pothole_filling_a_third_of_the_view() -> None:
    """The RANSAC start of the pair's road plane (tilted 10 mm/m, 0.5 mm noise) is not pulled
    into a 30 mm deep pothole over a third of the points; a least-squares start would be."""
    from roadsurf.mapping.dense_fuse import _robust_plane

    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.5, 0.5, (20000, 2))
    r = 0.002 + 0.01 * xy[:, 0] - 0.004 * xy[:, 1] + rng.normal(0, 0.0005, len(xy))
    pot = np.hypot(xy[:, 0] - 0.2, xy[:, 1]) < 0.3
    r[pot] -= 0.03
    coef, at = _robust_plane(xy, r, 0.01, near_zero=False)
    road = 0.002 + 0.01 * at[0] - 0.004 * at[1]
    assert abs(coef[0] - road) < 2e-4
    assert abs(coef[1] - 0.01) < 1e-3 and abs(coef[2] + 0.004) < 1e-3
    lsq = np.linalg.lstsq(np.column_stack([np.ones(len(xy)), xy - at]), r, rcond=None)[0]
    assert abs(lsq[0] - road) > 5e-3  # what the robust start avoids


@pytest.mark.parametrize("offset_m", [0.0, 0.004])
def test_pair_levelling_keeps_to_the_road_when_a_pothole_fills_most_of_the_view(
    offset_m: float,
) -> None:
    """A pothole's flat floor 30 mm down holds 85 % of the pair's points: the most populous
    plane is the floor, and the trimming from a RANSAC start stays there. With the local road
    surface (``road``) the levelling keeps to the road's 15 %, whatever the pair's own offset
    to that surface (a few mm from its scale), and its refit does not creep into the walls."""
    from roadsurf.mapping.dense_fuse import _robust_plane

    rng = np.random.default_rng(2)
    xy = rng.uniform(-0.5, 0.5, (20000, 2))
    road = 0.01 * xy[:, 0]
    z = road + offset_m + rng.normal(0, 0.0005, len(xy))
    rr = np.maximum(np.abs(xy[:, 0]), np.abs(xy[:, 1]))  # a square bowl with 10 cm walls
    z -= 0.03 * np.clip((0.46 - rr) / 0.1, 0, 1)
    floor_share = float(np.mean(rr < 0.36))
    assert floor_share > 0.5
    alone, at = _robust_plane(xy, z, 0.008, near_zero=False)
    assert alone[0] < -0.02  # the floor: what the road surface prevents
    coef, at = _robust_plane(xy, z, 0.008, near_zero=False, road=road)
    assert abs(coef[0] - (0.01 * at[0] + offset_m)) < 5e-4
    assert abs(coef[1] - 0.01) < 2e-3 and abs(coef[2]) < 2e-3
    # a pair that is all road but 10 mm off the surface (its own offset) keeps its own plane
    flat = road + 0.01 + rng.normal(0, 0.0005, len(xy))
    coef2, at2 = _robust_plane(xy, flat, 0.008, near_zero=False, road=road)
    assert abs(coef2[0] - (0.01 * at2[0] + 0.01)) < 3e-4


@pytest.mark.parametrize("offset_m", [-0.014, -0.016, -0.02])
def test_pair_levelling_is_not_taken_by_the_tail_of_a_noisy_offset_pair(offset_m: float) -> None:
    """An all-road pair 14-20 mm under the local surface with 5 mm of height noise: the upper
    tail of its own noise lies near the surface and over its plane, but is no density peak; the
    pair keeps its own plane (a review found it levelled 8-10 mm off)."""
    from roadsurf.mapping.dense_fuse import _robust_plane

    for seed in range(3):
        rng = np.random.default_rng(seed)
        xy = rng.uniform(-0.5, 0.5, (20000, 2))
        road = 0.01 * xy[:, 0]
        z = road + offset_m + rng.normal(0, 0.005, len(xy))
        coef, at = _robust_plane(xy, z, 0.008, near_zero=False, road=road)
        assert abs(coef[0] - (0.01 * at[0] + offset_m)) < 5e-4


def test_cells_the_dense_matching_leaves_empty_take_the_sparse_surface(
    drive_maps: dict[str, object], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A real pothole's dark floor fails the dense matcher's masks: those cells take the sparse
    surface's value where the fused points cover them (``dense_sparse_fill``), else stay NaN."""
    root, drive, pairs, traj = (drive_maps[k] for k in ("root", "drive", "pairs", "traj"))
    assert isinstance(root, Path)
    orig = DenseSurface.tile

    def holed(self: DenseSurface, t: tuple[int, int]):  # type: ignore[no-untyped-def]
        dt = orig(self, t)
        r = dt.residual_m.copy()
        r[(np.arange(r.shape[0]) // 16) % 2 == 0, :] = np.nan  # bands the matcher "failed"
        return dataclasses.replace(dt, residual_m=r)

    monkeypatch.setattr(DenseSurface, "tile", holed)
    cover = {}
    for fill in (False, True):
        # the dense hole fill off: these bands are wider than it reaches (dense.hole_fill_m)
        dense = dataclasses.replace(MappingConfig().dense, hole_fill_m=0.0)
        cfg = MappingConfig(surface_source="dense", dense_sparse_fill=fill, dense=dense)
        out = root / f"holed_{fill}"
        globalmap.run(cfg, drive, pairs, traj, out)  # type: ignore[arg-type]
        err, flat, _ = _errors(out, root / "D" / "truth", root / "run")
        m = np.isfinite(err)
        cover[fill] = m.sum()
        if fill:
            assert float(np.mean(np.abs(err[m & flat]))) < 2.0  # the sparse values are right
    assert (
        cover[True] > 1.25 * cover[False]
    )  # measured 1.42x (the 1 cm dense fill narrows the bands)


def model_cells(root: Path) -> np.ndarray:
    """Cells of the dense surface that the "empty" run leaves NaN (seen by one frame only)."""
    with rasterio.open(root / "dense" / "surface.tif") as a:
        fa = np.isfinite(a.read(1))
    with rasterio.open(root / "dense_empty" / "surface.tif") as b:
        fb = np.isfinite(b.read(1))
    return fa & ~fb


def test_single_view_cells_take_the_road_model(drive_maps: dict[str, object]) -> None:
    """Cells imaged by one frame only (here the drive's two ends) get the road model's height
    (0 above the local road) at count 0, with the road's spread as σ; every other cell is the
    same as with ``dense_single_view = "empty"``, and cloud.ply holds no modelled cell."""
    root = drive_maps["root"]
    assert isinstance(root, Path)
    prod, prod_e = drive_maps["dense"], drive_maps["dense_empty"]
    d, e = root / "dense", root / "dense_empty"
    with rasterio.open(d / "surface.tif") as a, rasterio.open(e / "surface.tif") as b:
        ra, rb = a.read(1), b.read(1)
    with rasterio.open(d / "surface_nobs.tif") as n, rasterio.open(d / "surface_sigma.tif") as g:
        nobs, sig = n.read(1), g.read(1)
    with rasterio.open(d / "mosaic.tif") as m:
        imaged = m.read().max(axis=0) > 0
    model = model_cells(root)
    # the two ends of a 10-frame nadir drive: a frame's advance each (measured 24 %)
    assert model.sum() > 0.1 * np.isfinite(rb).sum()
    assert model.sum() == prod.surface_model_px  # type: ignore[attr-defined]
    assert prod_e.surface_model_px == 0  # type: ignore[attr-defined]
    assert (ra[model] == 0).all() and (nobs[model] == 0).all()
    assert np.isfinite(sig[model]).all() and (sig[model] > 0).all()
    assert imaged[model].all()  # only inside the imaged corridor
    same = np.isfinite(rb)
    assert np.array_equal(ra[same], rb[same])
    assert (
        prod.residual_stats_m["dense_cloud_points"]
        == (  # type: ignore[attr-defined]
            prod_e.residual_stats_m["dense_cloud_points"]  # type: ignore[attr-defined]
        )
    )


def test_single_view_cells_next_to_relief_stay_unknown() -> None:
    """A strip seen once between two pairs' parts: the road model (0) beside road, NaN beside
    a pothole (the road model would split it, continuing its depth would join neighbours)."""
    from roadsurf.mapping.rasterfill import single_view_heights

    v = np.full((40, 60), np.nan, np.float32)
    v[:, :20] = 0.0005  # road before the strip
    v[:, 30:] = 0.0005  # ... and after it
    v[10:20, 12:20] = -0.04  # a pothole reaching the strip from the left
    v[10:20, 30:38] = -0.04  # ... and on from its right
    cells = ~np.isfinite(v)
    out = np.full(v.shape, np.nan, np.float32)
    out[cells] = single_view_heights(v, cells, near_px=6.0, road_m=0.002)
    assert np.isnan(out[12:18, 20:30]).all()  # across the pothole: unknown
    assert (out[30:, 20:30] == 0).all() and (out[:5, 20:30] == 0).all()  # across road: 0
    far = np.full((40, 60), np.nan, np.float32)
    far[:, :5] = -0.04
    cells = ~np.isfinite(far)
    got = single_view_heights(far, cells, near_px=6.0, road_m=0.002)
    row = np.full(far.shape, np.nan, np.float32)
    row[cells] = got
    assert np.isnan(row[:, 5:11]).all() and (row[:, 12:] == 0).all()  # beyond reach: 0
    assert (single_view_heights(far, cells, near_px=0.0, road_m=0.002) == 0).all()


def test_one_noisy_edge_cell_does_not_blank_the_single_view_road_behind_it() -> None:
    """The relief beside a single-view strip is judged on the block around the nearest known
    cell: one edge cell off by 5 mm (more than the 2 mm limit) among road cells leaves the road
    model behind it, a pothole's edge (a block of deep cells) still blanks it."""
    from roadsurf.mapping.rasterfill import single_view_heights

    rng = np.random.default_rng(3)
    v = np.full((40, 60), np.nan, np.float32)
    v[:, :20] = rng.normal(0, 0.0005, (40, 20))
    v[20, 19] = -0.005  # one noisy cell at the measured part's edge
    v[5:12, 14:20] = -0.03  # a pothole reaching the edge
    cells = ~np.isfinite(v)
    out = np.full(v.shape, np.nan, np.float32)
    out[cells] = single_view_heights(v, cells, near_px=10.0, road_m=0.002)
    assert (out[17:24, 20:28] == 0).all()  # behind the noisy cell: the road model
    assert np.isnan(out[7:10, 20:26]).all()  # beside the pothole: unknown


def test_the_relief_block_is_not_padded_at_a_tile_corner() -> None:
    """At a tile's corner the block holds only the cells inside the tile: one noisy corner cell
    among three road cells is outvoted there as anywhere else."""
    from roadsurf.mapping.rasterfill import single_view_heights

    v = np.full((30, 30), np.nan, np.float32)
    v[:2, :2] = 0.0003
    v[0, 0] = -0.005  # the noisy cell, in the corner
    cells = ~np.isfinite(v)
    got = single_view_heights(v, cells, near_px=8.0, road_m=0.002)
    assert (got == 0).all()


def test_switch_to_sparse_removes_the_dense_rasters(
    drive_maps: dict[str, object], tmp_path: Path
) -> None:
    """A run folder mapped densely, then again with the sparse surface: the dense-only rasters
    (count, σ) and the older grid's tiles are gone, so no reader takes them for this run's."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(drive_maps["root"] / "dense", run)  # type: ignore[operator]
    assert (run / "surface_nobs.tif").exists() or (run / "surface_nobs.vrt").exists()
    cfg = MappingConfig(surface_source="sparse")
    prod = globalmap.run(cfg, drive_maps["drive"], drive_maps["pairs"], drive_maps["traj"], run)  # type: ignore[arg-type]
    for stem in ("surface_nobs", "surface_sigma"):
        assert not (run / f"{stem}.tif").exists() and not (run / f"{stem}.vrt").exists()
    listed = {f for t in prod.tiles for k, f in t.items() if k in ("surface", "mosaic")}
    on_disk = {f"tiles/{p.name}" for p in (run / "tiles").glob("*.tif")}
    assert on_disk == listed, on_disk ^ listed
