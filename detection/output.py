"""Writers, the resume signature and the resume reader of the detection outputs (output
contract).

- ``defects.geojson``: RFC 7946 FeatureCollection in WGS84 lon/lat, one Polygon per defect with
  properties id, type, severity, max_depth_m, mean_depth_m, area_m2, volume_m3, length_m,
  width_m, confidence, frames (+ centroid_lon/lat, centroid_e_m/n_m). Without GPS the same
  layout holds local metres (``formats.write_local_geojson``: not RFC 7946, and says so in a
  legacy "crs" member GIS readers honour).
- ``defects.csv``: the same, one row per defect, frames joined with ';'.
- ``frames.csv``: filename,defect,p_defect,source for every frame.
- ``detection.json``: provenance (config, noise, thresholds, crs) and the resume signature.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from roadsurf.core.atomic import UNREADABLE, read_json_object, write_json_atomic
from roadsurf.core.config import to_dict
from roadsurf.core.fingerprint import Fingerprint
from roadsurf.detection.config import DetectionConfig
from roadsurf.detection.mapframe import MapFrame
from roadsurf.detection.types import DEFECT_COLUMNS, Defect, DetectionResult, FrameLabel
from roadsurf.io.formats import (
    LOCAL_FRAME_TEXT,
    feature,
    polygon_geometry,
    write_csv,
    write_geojson,
    write_local_geojson,
)
from roadsurf.io.runfolder import (
    DEFECTS_CSV,
    DEFECTS_GEOJSON,
    DETECTION_JSON,
    FRAME_LABELS_CSV,
    MAP_POINTS,
    SURFACE_TIF,
    SURFACE_VRT,
    RunFolder,
)
from roadsurf.mapping.types import Trajectory
from roadsurf.reconstruction.types import PairResult

if TYPE_CHECKING:
    from roadsurf.detection.classifier.fusion import FusionRule

log = logging.getLogger(__name__)

FRAME_COLUMNS = ("filename", "defect", "p_defect", "source")


def write_outputs(
    result: DetectionResult, mframe: MapFrame, signature: str, config: dict[str, Any]
) -> None:
    """Write defects.geojson, defects.csv, frames.csv and detection.json into result.run_dir."""
    run = RunFolder(result.run_dir)
    run.root.mkdir(parents=True, exist_ok=True)
    feats, rows, cents = [], [], []
    for d in result.defects:
        if mframe.georeferenced:
            ring = mframe.lonlat_from_grid(d.outline_xy_m)
            c = mframe.lonlat_from_grid(d.centroid_xy_m[None])[0]
        else:
            ring, c = np.asarray(d.outline_xy_m, float), None
        props = d.to_properties(c)
        cents.append(c)
        feats.append(feature(polygon_geometry(ring), props))
        row = [props[k] if k != "frames" else ";".join(d.frames) for k in DEFECT_COLUMNS]
        rows.append([*row, result.crs if result.georeferenced else LOCAL_CRS_CSV])
    meta = {
        "crs_of_e_n": result.crs,
        "georeferenced": result.georeferenced,
        "noise_m": result.noise_m,
        "seed_threshold_m": result.seed_threshold_m,
        "surface_source": result.surface_source,
    }
    gj = run.defects_geojson
    if mframe.georeferenced:
        write_geojson(gj, feats, {"generator": "roadsurf detection", **meta})
    else:
        write_local_geojson(gj, feats, {"generator": "roadsurf detection", **meta})
        log.warning("detection: no GPS reference; defects are written in %s", LOCAL_FRAME_TEXT)
    # the CRS of centroid_e_m/n_m on every row (the GeoJSON has it once, as crs_of_e_n)
    write_csv(run.path(DEFECTS_CSV), (*DEFECT_COLUMNS, "crs_of_e_n"), rows)
    write_csv(
        run.frame_labels,
        FRAME_COLUMNS,
        [
            (f.filename, "" if f.defect is None else f.defect, _round(f.p_defect), f.source)
            for f in result.frames
        ],
    )
    write_json_atomic(
        run.path(DETECTION_JSON),
        {
            "signature": signature,
            **meta,
            "config": config,
            "warnings": list(result.warnings),
            "defects": [
                {
                    **d.to_properties(c, exact=True),
                    "outline_xy_m": np.asarray(d.outline_xy_m).tolist(),
                }
                for d, c in zip(result.defects, cents, strict=True)
            ],
            "frames": [[f.filename, f.defect, f.p_defect, f.source] for f in result.frames],
        },
    )
    result.files = {
        name: run.path(name)
        for name in (DEFECTS_GEOJSON, DEFECTS_CSV, FRAME_LABELS_CSV, DETECTION_JSON)
    }


def load_result(run_dir: Path, signature: str) -> DetectionResult | None:
    """The saved result when detection.json matches ``signature`` and all files exist."""
    run_dir = Path(run_dir)
    meta_p = run_dir / DETECTION_JSON
    names = (DEFECTS_GEOJSON, DEFECTS_CSV, FRAME_LABELS_CSV)
    if not meta_p.exists() or not all((run_dir / n).exists() for n in names):
        return None
    try:
        meta = read_json_object(meta_p)
    except UNREADABLE as e:
        log.warning("detection: %s unreadable (%s); detecting again", meta_p, e)
        return None
    if meta.get("signature") != signature:
        return None
    defects = [
        Defect(
            **Defect.fields_from_properties(d),
            outline_xy_m=np.asarray(d["outline_xy_m"], float),
            centroid_xy_m=np.array([d["centroid_e_m"], d["centroid_n_m"]], float),
        )
        for d in meta.get("defects", [])
    ]
    frames = [
        FrameLabel(str(a), None if b is None else int(b), None if c is None else float(c), str(s))
        for a, b, c, s in meta["frames"]
    ]
    res = DetectionResult(
        defects=defects,
        frames=frames,
        run_dir=run_dir,
        noise_m=float(meta["noise_m"]) if meta.get("noise_m") is not None else float("nan"),
        seed_threshold_m=float(meta["seed_threshold_m"])
        if meta.get("seed_threshold_m") is not None
        else float("nan"),
        georeferenced=bool(meta.get("georeferenced", True)),
        crs=str(meta.get("crs_of_e_n", "")),
        surface_source=str(meta.get("surface_source", "")),
        warnings=[str(w) for w in meta.get("warnings") or []],
    )
    res.files = {n: run_dir / n for n in (*names, DETECTION_JSON)}
    return res


# bump when detection changes its outputs for the same inputs and settings: a resumed run then
# re-detects instead of keeping the earlier outputs. 2: one pair's dense cells deeper than 2 T_d
# support a region (windows.segment_windows); 3: the parts of a defect cut by an unknown strip
# are one (mapbridge.bridged_components); 4: a seed deeper than noise_k x its own cell's σ too;
# 5: frames nothing measured are not analysed (empty defect), not "no defect"; the dense area
# within the outline, the mean depth within the maximum; 6: regions of one mean-shift cluster
# join only within join_gap_m; 7: windows also around the dense surface's deep cells (rasterseeds);
# 8: traced ruts skip the point-support veto, a crack's depth takes its dense reading when
# deeper, a surface at its search depth bounds no deeper reading, warnings in detection.json;
# 9: a crack's centroid is its outline's, defects.geojson without GPS names its local frame
DETECTION_VERSION = 9
LOCAL_CRS_CSV = "local (no GPS)"  # defects.csv crs_of_e_n without GPS


def _round(p: float | None) -> float | str:
    return "" if p is None else round(p, 4)


def signature(
    cfg: DetectionConfig,
    pairs: list[PairResult],
    traj: Trajectory,
    run_dir: Path,
    frame_probs: dict[str, float] | None,
    fusion: FusionRule | None = None,
    mask_digest: str | None = None,
) -> str:
    """Hash of everything the outputs depend on (config, pairs, poses, raster, CNN scores, the
    camera's image mask (``mask_digest``, None: none) and ``DETECTION_VERSION``)."""
    fp = Fingerprint().add_json(to_dict(cfg), default_str=False)
    fp.add_text(f"detection v{DETECTION_VERSION}")
    if mask_digest:
        fp.add_text(f"|mask {mask_digest}")
    for p in pairs:
        fp.add_text(f"{p.frame_a}|{p.frame_b}|{p.status}|{p.n_points}|{p.method}")
        if p.n_points:
            fp.add_array(p.plane_dist_m, max_bytes=4096)
    fp.add_array(traj.world_from_cam)
    # the reference as json.dumps writes it (keys in their own order)
    fp.add_text(json.dumps(traj.reference.to_dict() if traj.reference else None))
    for name in (SURFACE_TIF, SURFACE_VRT, MAP_POINTS):
        fp.add_file_stat(Path(run_dir) / name, label=name)
    fp.add_json(sorted((frame_probs or {}).items()), default_str=False)
    if fusion is not None:
        fp.add_repr((fusion.threshold, fusion.confirm_defect_with_3d, fusion.context_frames))
        fp.add_json(sorted(fusion.decide_3d), default_str=False)
    return fp.hexdigest()
