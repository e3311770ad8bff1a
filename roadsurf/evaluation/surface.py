"""Surface figures of a run against simulator truth: height errors on flat road and inside
defects (raw and aligned) and coverage of the imaged corridor (the seam steps between pair
patches: ``evaluation.seams``)."""

from __future__ import annotations

import math
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from roadsurf.evaluation.corridor import corridor_from_footprints, true_footprints
from roadsurf.io import drivefolder as df
from roadsurf.io import runfolder as rf
from roadsurf.io.formats import read_geojson

if TYPE_CHECKING:
    from shapely import Geometry


def _open_surface(run_dir: Path) -> Path | None:
    for name in (rf.SURFACE_TIF, rf.SURFACE_VRT):
        if (run_dir / name).exists():
            return run_dir / name
    return None


def _nobs_paths(run_dir: Path) -> list[Path]:
    return [run_dir / f"{rf.SURFACE_NOBS}.tif", run_dir / f"{rf.SURFACE_NOBS}.vrt"]


def surface_metrics(
    run_dir: Path,
    truth_dir: Path,
    truth: dict[str, Any],
    align: tuple[np.ndarray, np.ndarray] | None,
    crs: str | None,
    scen: dict[str, Any],
    seen: set[str],
) -> dict[str, Any]:
    import rasterio
    from rasterio.features import rasterize
    from rasterio.windows import Window

    res: dict[str, Any] = {"metrics": {}}
    path = _open_surface(run_dir)
    tpath = truth_dir / df.TRUTH_RESIDUAL_TIF
    if path is None or not tpath.is_file():
        res["metrics"]["note"] = "no surface raster or no truth residual"
        return res
    with rasterio.open(tpath) as t:
        tres = t.read(1).astype(np.float32)
        tnd = t.nodata
        tT = t.transform
        tshape = (t.height, t.width)
    if tnd is not None and not math.isnan(tnd):
        tres[tres == tnd] = np.nan
    defects_path = truth_dir / df.TRUTH_DEFECTS_GEOJSON
    dmask = np.zeros(tshape, bool)
    if defects_path.is_file() and crs:
        from pyproj import Transformer

        trf = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
        from shapely.geometry import shape
        from shapely.ops import transform

        shapes = [
            transform(lambda x, y, z=None: trf.transform(x, y), shape(f["geometry"]))
            for f in read_geojson(defects_path)["features"]
        ]
        if shapes:
            dmask = rasterize(
                shapes, out_shape=tshape, transform=tT, fill=0, default_value=1
            ).astype(bool)

    def burn(poly: Geometry | None) -> np.ndarray | None:
        if poly is None:
            return None
        return rasterize([poly], out_shape=tshape, transform=tT, fill=0, default_value=1) > 0

    feet = true_footprints(truth_dir, truth, seen)
    cmask = burn(corridor_from_footprints(feet))
    smask = burn(corridor_from_footprints(feet, stereo=True))
    n_in_stereo = 0
    inv_t = ~tT

    acc: dict[str, list[np.ndarray]] = {k: [] for k in ("raw_flat", "raw_def", "al_flat", "al_def")}
    n_in_corridor = 0
    our_px_area = 0.0
    observed_m2 = 0.0  # area of every observed cell of our surface (m²)
    # cells with a measurement (count > 0): the dense surface fills cells seen by one frame
    # only with the road model, at count 0 (mapping dense_single_view)
    npath = next((p for p in _nobs_paths(run_dir) if p.exists()), None)
    n_measured = n_stereo_measured = 0
    measured_m2 = 0.0
    with rasterio.open(path) as src, ExitStack() as stack:
        nsrc = stack.enter_context(rasterio.open(npath)) if npath is not None else None
        if nsrc is not None and (nsrc.width, nsrc.height) != (src.width, src.height):
            nsrc = None
        nd = src.nodata
        W, H = src.width, src.height
        to_truth = None  # a run in another UTM zone than the truth (a drive on a zone border)
        if crs and src.crs is not None:
            from pyproj import CRS, Transformer

            if CRS.from_user_input(src.crs.to_wkt()) != CRS.from_user_input(crs):
                to_truth = Transformer.from_crs(src.crs.to_wkt(), crs, always_xy=True)
        bs = 1024
        for r0 in range(0, H, bs):
            for c0 in range(0, W, bs):
                win = Window(c0, r0, min(bs, W - c0), min(bs, H - r0))
                a = src.read(1, window=win).astype(np.float32)
                if nd is not None and not math.isnan(nd):
                    a[a == nd] = np.nan
                rr, cc = np.nonzero(np.isfinite(a))
                if len(rr) == 0:
                    continue
                T = src.window_transform(win)
                meas = None
                if nsrc is not None:
                    meas = nsrc.read(1, window=win)[rr, cc] > 0
                    measured_m2 += int(meas.sum()) * abs(T.a * T.e)
                observed_m2 += len(rr) * abs(T.a * T.e)
                x = T.c + (cc + 0.5) * T.a
                y = T.f + (rr + 0.5) * T.e
                v = a[rr, cc]
                if to_truth is not None:
                    x, y = to_truth.transform(x, y)
                xy = np.column_stack([x, y])
                for tag, pts in (
                    ("raw", xy),
                    ("al", xy @ align[0].T + align[1] if align else None),
                ):
                    if pts is None:
                        continue
                    col, row = inv_t * (pts[:, 0], pts[:, 1])
                    col, row = np.floor(col).astype(int), np.floor(row).astype(int)
                    ok = (row >= 0) & (row < tshape[0]) & (col >= 0) & (col < tshape[1])
                    tv = np.full(len(v), np.nan, np.float32)
                    tv[ok] = tres[row[ok], col[ok]]
                    isdef = np.zeros(len(v), bool)
                    isdef[ok] = dmask[row[ok], col[ok]]
                    good = np.isfinite(tv)
                    d = (v - tv)[good]
                    acc[f"{tag}_flat"].append(d[~isdef[good]])
                    acc[f"{tag}_def"].append(d[isdef[good]])
                    if tag == ("al" if align else "raw") and cmask is not None:
                        n_in_corridor += int(cmask[row[ok], col[ok]].sum())
                        if meas is not None:
                            n_measured += int((cmask[row[ok], col[ok]] & meas[ok]).sum())
                        our_px_area = abs(T.a * T.e)
                        if smask is not None:
                            n_in_stereo += int(smask[row[ok], col[ok]].sum())
                            if meas is not None:
                                sm = smask[row[ok], col[ok]] & meas[ok]
                                n_stereo_measured += int(sm.sum())

    def stats(lst: list[np.ndarray]) -> dict[str, float]:
        d = np.concatenate(lst) if lst else np.zeros(0)
        if len(d) == 0:
            return {"n": 0, "mae_m": float("nan"), "rmse_m": float("nan"), "bias_m": float("nan")}
        return {
            "n": int(len(d)),
            "mae_m": float(np.mean(np.abs(d))),
            "rmse_m": float(np.sqrt(np.mean(d**2))),
            "bias_m": float(np.median(d)),
        }

    m = res["metrics"]
    for tag, name in (("raw", "raw"), ("al", "aligned")):
        f, dd = stats(acc[f"{tag}_flat"]), stats(acc[f"{tag}_def"])
        m[name] = {
            "flat_mae_m": f["mae_m"],
            "flat_rmse_m": f["rmse_m"],
            "flat_bias_m": f["bias_m"],
            "flat_n": f["n"],
            "defect_mae_m": dd["mae_m"],
            "defect_rmse_m": dd["rmse_m"],
            "defect_bias_m": dd["bias_m"],
            "defect_n": dd["n"],
        }
    res["observed_area_m2"] = observed_m2
    if npath is not None:
        res["measured_area_m2"] = measured_m2
    if cmask is not None and cmask.any():
        # the road the footprints were cast on: the truth heights, or flat without them
        road = "up" in truth and (truth_dir / df.TRUTH_HEIGHT_TIF).is_file()
        res["corridor_road"] = "truth_height" if road else "flat"
        # our pixels (their own area) inside the true corridor, over the corridor's area
        area = float(cmask.sum() * abs(tT.a * tT.e))
        res["coverage"] = float(min(1.0, n_in_corridor * our_px_area / area))
        res["corridor_area_m2"] = area
        if npath is not None:
            res["coverage_measured"] = float(min(1.0, n_measured * our_px_area / area))
    if smask is not None and smask.any():
        sarea = float(smask.sum() * abs(tT.a * tT.e))
        res["coverage_two_view"] = float(min(1.0, n_in_stereo * our_px_area / sarea))
        if npath is not None:
            res["coverage_two_view_measured"] = float(
                min(1.0, n_stereo_measured * our_px_area / sarea)
            )
        if cmask is not None and cmask.any():
            # the ceiling of a two-view method: the drive's ends are seen by one frame only
            res["coverage_two_view_share"] = float(min(1.0, sarea / area))
    return res
