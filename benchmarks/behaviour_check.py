"""Behaviour check: run the CLI on drives and compare two sets of outputs file by file.

Used to prove that a refactor preserves behaviour. It drives the program only through its
command line (``python -m roadsurf``), so the same script records outputs of an old checkout
(``--pythonpath OLD_TREE``) and of the current one.

    python -m benchmarks.behaviour_check record --out /tmp/bc/new [--pythonpath TREE]
    python -m benchmarks.behaviour_check compare /tmp/bc/old /tmp/bc/new [--json RESULT]

``record`` simulates a few drives with fixed seeds (plus the committed ``data_samples/drive``),
runs ``roadsurf run`` on each, ``roadsurf sfm-baseline`` and ``roadsurf evaluate`` on one.
``compare`` checks every output file: byte for byte, else number for number (JSON without
timings/versions/paths, GeoTIFF pixels + georeferencing, PLY vertex arrays, PNG pixels).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

# (name, scenario, seed, frames); short drives so a check takes minutes on 2 cores
DRIVES: list[tuple[str, str, int, int]] = [
    ("potholes", "potholes", 202, 30),
    ("flat", "flat", 101, 20),
    ("varied", "varied", 707, 24),
    ("vibration", "vibration", 303, 24),
]
SFM_DRIVE = "flat"

# JSON keys whose values legitimately change between two runs (times, versions, paths)
VOLATILE_KEYS = {
    "timings_s",
    "timings_this_run_s",
    "stages",
    "resumed_stages",
    "versions",
    "elapsed_s",
    "drive",
    "run",
    "created",
    "date",
    "model",
    "seconds",
    "wall_s",
    "time_s",
    "run_dir",
    "truth",
    "runs",
    "signature",  # detection's resume hash includes the mtime of surface.tif
}
# npz members that hold wall times
VOLATILE_NPZ = ("timings",)
SKIP_SUFFIXES = {".rrd", ".log"}
CACHE_DIRS = {"features", "probes"}


def _cli(args: list[str], pythonpath: str | None) -> None:
    env = dict(os.environ)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    cmd = [sys.executable, "-m", "roadsurf", *args]
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, env=env, cwd=pythonpath or ROOT)


def record(out: Path, pythonpath: str | None) -> None:
    out.mkdir(parents=True, exist_ok=True)
    tree = Path(pythonpath) if pythonpath else ROOT
    rev = subprocess.run(
        ["git", "-C", str(tree), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    (out / "recorded_from.json").write_text(json.dumps({"tree": str(tree), "commit": rev}))
    drives = {"sample": ROOT / "data_samples" / "drive"}
    for name, scenario, seed, frames in DRIVES:
        d = out / "drives" / name
        if not (d / "frames.csv").is_file():
            _cli(
                ["simulate", "--scenario", scenario, "--seed", str(seed), "--frames", str(frames),
                 "--out", str(d)],
                pythonpath,
            )  # fmt: skip
        drives[name] = d
    for name, d in drives.items():
        _cli(["run", str(d), "--out", str(out / "runs" / name)], pythonpath)
    _cli(
        ["sfm-baseline", str(drives[SFM_DRIVE]), "--out", str(out / "sfm" / SFM_DRIVE)], pythonpath
    )
    truth = drives["potholes"] / "truth"
    _cli(["evaluate", str(out / "runs" / "potholes"), "--truth", str(truth)], pythonpath)


def _strip(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in VOLATILE_KEYS}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    if isinstance(obj, str) and ("/tmp/" in obj or obj.startswith("/")):
        return Path(obj).name  # absolute paths differ between checkouts
    return obj


def _same_json(a: Path, b: Path) -> bool:
    return _strip(json.loads(a.read_text())) == _strip(json.loads(b.read_text()))


def _same_tif(a: Path, b: Path) -> bool:
    import numpy as np
    import rasterio

    with rasterio.open(a) as ra, rasterio.open(b) as rb:
        if ra.crs != rb.crs or ra.transform != rb.transform or ra.shape != rb.shape:
            return False
        return bool(np.array_equal(ra.read(), rb.read(), equal_nan=True))


def _same_ply(a: Path, b: Path) -> bool:
    import numpy as np
    from plyfile import PlyData

    pa, pb = PlyData.read(str(a)), PlyData.read(str(b))
    va, vb = pa["vertex"].data, pb["vertex"].data
    return va.dtype == vb.dtype and bool(np.array_equal(va, vb))


def _same_npz(a: Path, b: Path) -> bool:
    import numpy as np

    with np.load(a, allow_pickle=False) as za, np.load(b, allow_pickle=False) as zb:
        keys = [k for k in za.files if not any(v in k for v in VOLATILE_NPZ)]
        if sorted(keys) != sorted(k for k in zb.files if not any(v in k for v in VOLATILE_NPZ)):
            return False
        return all(np.array_equal(za[k], zb[k], equal_nan=za[k].dtype.kind == "f") for k in keys)


def _same_png(a: Path, b: Path) -> bool:
    import cv2
    import numpy as np

    ia = cv2.imread(str(a), cv2.IMREAD_UNCHANGED)
    ib = cv2.imread(str(b), cv2.IMREAD_UNCHANGED)
    return ia is not None and ib is not None and bool(np.array_equal(ia, ib))


def _same_text(a: Path, b: Path) -> bool:
    # markdown/html reports embed dates and timings: compare lines without digits of time
    def norm(p: Path) -> list[str]:
        return [ln for ln in p.read_text(errors="replace").splitlines() if " s" not in ln]

    return norm(a) == norm(b)


def compare_file(a: Path, b: Path) -> str:
    """'bytes' / 'numbers' when equal, 'DIFFERENT' otherwise."""
    if hashlib.sha256(a.read_bytes()).digest() == hashlib.sha256(b.read_bytes()).digest():
        return "bytes"
    suffix = a.suffix.lower()
    same = {
        ".json": _same_json,
        ".geojson": _same_json,
        ".tif": _same_tif,
        ".ply": _same_ply,
        ".png": _same_png,
        ".npz": _same_npz,
        ".md": _same_text,
        ".html": _same_text,
    }.get(suffix)
    try:
        return "numbers" if same is not None and same(a, b) else "DIFFERENT"
    except Exception as e:  # noqa: BLE001 - an unreadable file is a difference to report
        return f"DIFFERENT ({e})"


def _key(rel: Path) -> str:
    """Match key of an output: cache files carry their settings' digest in the name
    (features/000003_sift4000_<digest>.npz), which changes when the digest scheme does."""
    if rel.parts and rel.parts[-2:-1] and rel.parts[-2] in CACHE_DIRS:
        return str(rel.parent / re.sub(r"_[0-9a-f]{8,}(?=\.npz$)", "", rel.name))
    return str(rel)


def _files(root: Path) -> dict[str, Path]:
    out = {}
    for sub in ("drives", "runs", "sfm"):
        for f in sorted((root / sub).rglob("*")):
            if f.is_file() and f.suffix not in SKIP_SUFFIXES:
                out[_key(f.relative_to(root))] = f
    return out


def compare(old: Path, new: Path) -> dict[str, Any]:
    """Every output of ``old`` against ``new``: 'bytes' / 'numbers' when equal, else
    DIFFERENT or MISSING; files only ``new`` has are listed as added (new artifacts)."""
    fa, fb = _files(old), _files(new)
    rows = {k: (compare_file(p, fb[k]) if k in fb else "MISSING") for k, p in fa.items()}
    bad = {k: v for k, v in rows.items() if v not in ("bytes", "numbers")}

    def origin(root: Path) -> str:
        try:
            return str(json.loads((root / "recorded_from.json").read_text())["commit"])
        except (OSError, ValueError, KeyError):
            return "unknown"

    return {
        "old_commit": origin(old),
        "new_commit": origin(new),
        "files": len(rows),
        "identical_bytes": sum(v == "bytes" for v in rows.values()),
        "identical_numbers": sum(v == "numbers" for v in rows.values()),
        "different": bad,
        "added": sorted(k for k in fb if k not in fa),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="simulate drives and run the CLI on them")
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--pythonpath", default=None, help="a checkout to run instead of this one")
    c = sub.add_parser("compare", help="compare two recorded output trees")
    c.add_argument("old", type=Path)
    c.add_argument("new", type=Path)
    c.add_argument("--json", type=Path, default=None, help="also write the result as JSON")
    a = ap.parse_args(argv)
    if a.cmd == "record":
        record(a.out, a.pythonpath)
        return 0
    res = compare(a.old, a.new)
    for k, v in res["different"].items():
        print(f"{v:12s} {k}")
    for k in res["added"]:
        print(f"{'added':12s} {k}")
    print(
        f"{res['files']} files: {res['identical_bytes']} byte-identical, "
        f"{res['identical_numbers']} identical in numbers, {len(res['different'])} different; "
        f"{len(res['added'])} new files"
    )
    if a.json is not None:
        from benchmarks._result import write_result

        write_result(a.json, "behaviour_check", res)
    return 0 if not res["different"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
