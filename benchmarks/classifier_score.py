"""Scoring of the classifier benchmark: frame labels against the simulator's truth, with false
positives broken down by the distractors (lane marking, shadow, oil stain) in view."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from roadsurf.core.atomic import read_json
from roadsurf.evaluation.detection import frame_metrics
from roadsurf.io.formats import read_csv, read_geojson


def frame_labels(path: Path) -> dict[str, int]:
    """frames.csv (a run's or the truth's) -> {filename: 0/1}."""
    return {r["filename"]: int(float(r["defect"] or 0)) for r in read_csv(path)}


def frame_sources(path: Path) -> dict[str, str]:
    """A fused run's frames.csv -> {filename: source (cnn, 3d, fused)}."""
    return {r["filename"]: r.get("source", "") for r in read_csv(path)}


def distractors_in_view(drive: Path) -> dict[str, set[str]]:
    """{filename: distractor types whose outline meets the frame's ground footprint}.

    The footprint is the image rectangle cast onto the plane ``h`` below the camera, using the
    true poses (truth/poses.csv, UTM) and the camera model; distractors come from
    truth/distractors.geojson (WGS84), projected to the scenario's CRS.
    """
    import yaml
    from pyproj import Transformer
    from scipy.spatial.transform import Rotation
    from shapely.geometry import Polygon, shape

    truth = drive / "truth"
    dpath = truth / "distractors.geojson"
    if not dpath.is_file():
        return {}
    crs = read_json(truth / "scenario.json")["crs"]
    tf = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    dis = []
    for f in read_geojson(dpath)["features"]:
        g = shape(f["geometry"])
        ring = np.asarray(g.exterior.coords)
        x, y = tf.transform(ring[:, 0], ring[:, 1])
        dis.append((f["properties"].get("type", "distractor"), Polygon(np.column_stack([x, y]))))
    cam = yaml.safe_load((drive / "camera.yaml").read_text())
    w, h = float(cam["width"]), float(cam["height"])
    fx, fy, cx, cy, hm = (float(cam[k]) for k in ("fx", "fy", "cx", "cy", "height_m"))
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
    cam_pts = np.column_stack([(corners[:, 0] - cx) / fx * hm, (corners[:, 1] - cy) / fy * hm])
    cam_pts = np.column_stack([cam_pts, np.full(4, hm)])
    out: dict[str, set[str]] = {}
    for r in read_csv(truth / "poses.csv"):
        q = [float(r[k]) for k in ("qx", "qy", "qz", "qw")]
        world = Rotation.from_quat(q).apply(cam_pts)
        e = world[:, 0] + float(r["easting_m"])
        n = world[:, 1] + float(r["northing_m"])
        fp = Polygon(np.column_stack([e, n]))
        out[r["filename"]] = {t for t, g in dis if fp.intersects(g)}
    return out


def score(
    pred: dict[str, int], truth: dict[str, int], distractors: dict[str, set[str]]
) -> dict[str, Any]:
    """Frame metrics plus false positives broken down by the distractor types in view."""
    m = frame_metrics(pred, truth)
    fp_by: dict[str, int] = {}
    clean_fp = 0
    for f, p in pred.items():
        if p and not truth.get(f, 0):
            kinds = distractors.get(f, set())
            for k in kinds:
                fp_by[k] = fp_by.get(k, 0) + 1
            clean_fp += not kinds
    m["fp_with_distractor"] = fp_by
    m["fp_on_plain_road"] = clean_fp
    return m
