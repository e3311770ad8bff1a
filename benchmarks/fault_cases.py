"""Fault cases of issue 31, items 1-5: stale caches, writing into the drive, a run with no 3D
result, implausible inputs (camera height, GPS, OBD, NMEA) and the measured depth.

Each case builds its inputs from the shared base drive (a 12-frame simulated drive with RTK
GPS) in its own folder, runs the real CLI and returns a ``Verdict`` (see ``_fault_kit``).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from benchmarks._fault_kit import (
    Case,
    Ctx,
    Verdict,
    classify,
    map_csv,
    prelude,
    read_report,
    register,
    report_warnings,
    same_outputs,
    set_yaml_key,
)

CASES: list[Case] = []
case = register(CASES)
GPS_WARN = r"(?i)gps"


def no_false_clear(run: Path) -> str | None:
    """What is wrong when frames are labelled "no defect" (0) by a run that must not."""
    try:
        lines = (run / "frames.csv").read_text(encoding="utf-8").splitlines()[1:]
    except OSError:
        return "no frames.csv"
    zero = sum(1 for ln in lines if ln.split(",")[1:2] == ["0"])
    return (
        f"{zero} of {len(lines)} frames labelled 'no defect' without a 3D result" if zero else None
    )


def _config(cx: Ctx, text: str, name: str = "config.yaml") -> Path:
    p = cx.dir / name
    p.write_text(text, encoding="utf-8")
    return p


def _run_with(cx: Ctx, drive: Path, accept: set[str], warn_re: str, *extra: object) -> Verdict:
    """Run ``drive`` into a fresh folder; judged on exit, error line and report warnings."""
    run = cx.dir / "run"
    p = cx.cli("run", drive, "--out", run, *extra)
    return classify(p, accept=accept, warn_re=warn_re, warnings=report_warnings(run))


# --- item 1: caches keyed by what produced them ------------------------------------------


@case("drive B run into drive A's run folder", "1")
def _b_into_a(cx: Ctx) -> Verdict:
    run = cx.copy_run(cx.shared["run"])
    b = cx.drive(cx.shared["drive_b"], "drive_b")
    p = cx.cli("run", b, "--out", run)
    return classify(p, accept={"error", "ok"}, check=lambda: same_outputs(run, cx.shared["run_b"]))


@case("drive A run into drive B's run folder", "1")
def _a_into_b(cx: Ctx) -> Verdict:
    run = cx.copy_run(cx.shared["run_b"])
    a = cx.drive()
    p = cx.cli("run", a, "--out", run)
    return classify(p, accept={"error", "ok"}, check=lambda: same_outputs(run, cx.shared["run"]))


@case("camera.yaml height_m changed after a run", "1")
def _height_changed(cx: Ctx) -> Verdict:
    d, run, ref = cx.drive(), cx.dir / "run", cx.dir / "ref"
    if bad := prelude(cx.cli("run", d, "--out", run), "first run"):
        return bad
    set_yaml_key(d / "camera.yaml", "height_m", "1.2")
    p = cx.cli("run", d, "--out", run)
    if bad := prelude(cx.cli("run", d, "--out", ref), "reference run"):
        return bad
    return classify(p, accept={"ok"}, check=lambda: same_outputs(run, ref))


@case("frame image removed, run, restored, resumed", "1")
def _frame_restored(cx: Ctx) -> Verdict:
    d, run = cx.drive(), cx.dir / "run"
    img = sorted((d / "frames").iterdir())[5]
    data = img.read_bytes()
    img.unlink()
    if bad := prelude(cx.cli("run", d, "--out", run), "run without it", {"ok", "error"}):
        return bad
    img.write_bytes(data)
    p = cx.cli("run", d, "--out", run)
    return classify(p, accept={"ok"}, check=lambda: same_outputs(run, cx.shared["run"]))


# --- item 2: never write inside the drive folder ------------------------------------------


@case("--out equal to the drive folder", "2")
def _out_is_drive(cx: Ctx) -> Verdict:
    d = cx.drive()
    return classify(cx.cli("run", d, "--out", d), accept={"error"})


@case("--out inside the drive folder", "2")
def _out_in_drive(cx: Ctx) -> Verdict:
    d = cx.drive()
    return classify(cx.cli("run", d, "--out", d / "out"), accept={"error"})


# --- item 3: a run with no 3D result ------------------------------------------------------


@case("reconstruction.min_matches: 100000", "3")
def _min_matches(cx: Ctx) -> Verdict:
    cfg = _config(cx, "reconstruction:\n  min_matches: 100000\n")
    run = cx.dir / "run"
    p = cx.cli("run", cx.drive(), "--out", run, "--config", cfg)
    return classify(
        p,
        accept={"error", "warn+ok"},
        warn_re=r"(?i)pair|reconstruct|3d",
        warnings=report_warnings(run),
        check=lambda: no_false_clear(run),
    )


@case("camera.yaml height_m: 110 (cm typed as m)", "3, 4")
def _height_cm(cx: Ctx) -> Verdict:
    d = cx.drive()
    set_yaml_key(d / "camera.yaml", "height_m", "110")
    return _run_with(cx, d, {"error", "warn"}, r"(?i)height")


# --- item 4: implausible inputs ----------------------------------------------------------


@case("height_m 20 % too large, RTK GPS", "4")
def _height_20(cx: Ctx) -> Verdict:
    d = cx.drive()
    set_yaml_key(d / "camera.yaml", "height_m", "1.32")
    return _run_with(cx, d, {"error", "warn"}, r"(?i)height")


@case("lat/lon values swapped in gps.csv", "4")
def _latlon_swapped(cx: Ctx) -> Verdict:
    d = cx.drive()
    map_csv(d / "gps.csv", lambda i, r: {**r, "lat": r["lon"], "lon": r["lat"]})
    return _run_with(cx, d, {"error", "warn"}, r"(?i)swap|lat.{0,40}lon|lon.{0,40}lat")


@case("OBD speed in km/h", "4")
def _obd_kmh(cx: Ctx) -> Verdict:
    d = cx.drive()
    map_csv(d / "obd.csv", lambda i, r: {**r, "speed_mps": f"{float(r['speed_mps']) * 3.6:.4f}"})
    return _run_with(cx, d, {"error", "warn"}, r"(?i)obd|km/h")


@case("GPS scatter 3 m with hdop 0.7 (sigma inflated)", "4")
def _gps_sigma(cx: Ctx) -> Verdict:
    d = cx.drive()
    rng = np.random.default_rng(7)

    def noisy(i: int, r: dict[str, str]) -> dict[str, str]:
        dn, de = rng.normal(0.0, 3.0, 2)
        lat = float(r["lat"])
        lon = float(r["lon"]) + de / (111_320.0 * np.cos(np.radians(lat)))
        return {**r, "lat": f"{lat + dn / 111_320.0:.9f}", "lon": f"{lon:.9f}"}

    map_csv(d / "gps.csv", noisy)
    v = _run_with(cx, d, {"error", "warn"}, r"(?i)σ|sigma")
    if v.outcome == "SILENT WRONG":
        scale = read_report(cx.dir / "run").get("poses", {}).get("gps_sigma_scale")
        v.message += f"; gps_sigma_scale {scale}"
    return v


@case("all GPS rows invalid (lat NaN)", "4")
def _gps_all_bad(cx: Ctx) -> Verdict:
    d = cx.drive()
    map_csv(d / "gps.csv", lambda i, r: {**r, "lat": "nan"})
    return _run_with(cx, d, {"error", "warn"}, GPS_WARN)


@case("GPS static receiver (one position)", "4")
def _gps_static(cx: Ctx) -> Verdict:
    d = cx.drive()
    first: dict[str, str] = {}

    def static(i: int, r: dict[str, str]) -> dict[str, str]:
        first.update({} if first else r)
        return {**r, "lat": first["lat"], "lon": first["lon"]}

    map_csv(d / "gps.csv", static)
    return _run_with(cx, d, {"error", "warn"}, r"(?i)static|stationar|not mov|standing")


@case("GPS hemisphere jump (second half lat negated)", "4")
def _gps_jump(cx: Ctx) -> Verdict:
    d = cx.drive()
    n = len((d / "gps.csv").read_text().splitlines()) - 1
    map_csv(d / "gps.csv", lambda i, r: {**r, "lat": f"-{r['lat']}" if i >= n // 2 else r["lat"]})
    return _run_with(cx, d, {"error", "warn"}, r"(?i)jump|hemisphere|zone|reject|outlier")


# --- NMEA --------------------------------------------------------------------------------


def nmea_drive(cx: Ctx) -> tuple[Path, Path]:
    """The base scenario simulated with gps.nmea, and its clean run (built once)."""
    if "nmea" not in cx.shared:
        root = cx.shared["work"] / "base"
        d, run = root / "drive_nmea", root / "run_nmea"
        for p in (
            cx.cli(*cx.shared["simulate"], "--out", d, "--set", "gps_format=nmea"),
            cx.cli("run", d, "--out", run),
        ):
            if p.rc != 0:
                raise RuntimeError(f"NMEA base failed: {p.stderr[-300:]}")
        cx.shared["nmea"] = (d, run)
    return cx.shared["nmea"]


def _checksum(body: str) -> str:
    c = 0
    for ch in body.encode():
        c ^= ch
    return f"{c:02X}"


def rewrite_nmea(path: Path, fn) -> None:  # noqa: ANN001 (fn: (kind, fields) -> fields)
    """Apply ``fn(kind, fields)`` to every sentence, recomputing the checksums."""
    out = []
    for ln in path.read_text(encoding="ascii").splitlines():
        m = re.match(r"^\$([A-Z]{2}(RMC|GGA)),(.*)\*[0-9A-F]{2}$", ln)
        if m:
            body = ",".join([m.group(1), *fn(m.group(2), m.group(3).split(","))])
            ln = f"${body}*{_checksum(body)}"
        out.append(ln)
    path.write_text("\r\n".join(out) + "\r\n", encoding="ascii")


def gps_fixes(run: Path) -> int | None:
    return read_report(run).get("counts", {}).get("gps_fixes")


@case("NMEA log (control for the NMEA cases)", "4")
def _nmea_clean(cx: Ctx) -> Verdict:
    _, run = nmea_drive(cx)  # its clean run is made once and shared

    def check() -> str | None:
        want, got = gps_fixes(cx.shared["run"]), gps_fixes(run)
        return None if got == want else f"{got} fixes, not {want} as from gps.csv"

    return classify(None, accept={"ok"}, check=check)


@case("NMEA with UBX binary before sentences on a line", "4")
def _nmea_ubx(cx: Ctx) -> Verdict:
    src, ref = nmea_drive(cx)
    d = cx.drive(src)
    ubx = b"\xb5\x62\x01\x07\x5c\x00\x10\x27\x00\x00\xe8\x03"
    raw = (d / "gps.nmea").read_bytes().split(b"\r\n")
    # every second epoch (one RMC + one GGA line) follows binary data on the same line
    raw = [ubx + ln if ln and (i // 2) % 2 else ln for i, ln in enumerate(raw)]
    (d / "gps.nmea").write_bytes(b"\r\n".join(raw))
    run = cx.dir / "run"
    p = cx.cli("run", d, "--out", run)
    want = gps_fixes(ref)
    return classify(
        p,
        accept={"ok", "warn+ok"},  # every fix kept; a warning about the binary is welcome
        warn_re=r"(?i)nmea|binary|ubx|sentence",
        warnings=report_warnings(run),
        check=lambda: None if gps_fixes(run) == want else f"{gps_fixes(run)} of {want} fixes kept",
    )


@case("NMEA GGA with geoid separation -35 m", "4")
def _nmea_geoid(cx: Ctx) -> Verdict:
    src, ref = nmea_drive(cx)
    d = cx.drive(src)
    sep = -35.0

    def msl(kind: str, f: list[str]) -> list[str]:
        if kind == "GGA":  # fields after the talker: hms,lat,N,lon,W,q,sats,hdop,alt,M,sep,M,,
            f[8], f[10] = f"{float(f[8]) - sep:.3f}", f"{sep:.1f}"
        return f

    rewrite_nmea(d / "gps.nmea", msl)
    run = cx.dir / "run"
    p = cx.cli("run", d, "--out", run)

    def check() -> str | None:
        want = read_report(ref).get("reference", {}).get("alt_m")
        got = read_report(run).get("reference", {}).get("alt_m")
        text = (run / "report.json").read_text(encoding="utf-8", errors="replace")
        wrong = []
        if want is None or got is None or abs(got - want) > 0.01:
            wrong.append(f"reference height {got} m, ellipsoidal is {want} m")
        if not re.search(r"(?i)ellipsoid|vertical|EPSG:4979|geoid|EGM", text):
            wrong.append("report.json names no vertical datum")
        return "; ".join(wrong) or None

    return classify(p, accept={"ok"}, check=check)


# --- item 5: robust depth ----------------------------------------------------------------


@case("pothole max depth against truth (base run)", "5")
def _depth_truth(cx: Ctx) -> Verdict:
    """A proxy: one outlier point cannot be injected through the CLI's inputs; the measured
    maximum depth of the base drive's pothole must be within max(5 mm, 25 %) of the truth."""

    def feats(p: Path) -> list[dict]:
        return [f["properties"] for f in json.loads(p.read_text())["features"]]

    def check() -> str | None:
        found = feats(cx.shared["run"] / "defects.geojson")
        bad = []
        for t in feats(cx.shared["drive"] / "truth" / "defects.geojson"):
            if t["type"] != "pothole":
                continue
            near = [
                f
                for f in found
                if np.hypot(
                    f["centroid_e_m"] - t["centroid_e_m"], f["centroid_n_m"] - t["centroid_n_m"]
                )
                < 0.5
            ]
            got = max((f["max_depth_m"] for f in near), default=None)
            tol = max(0.005, 0.25 * t["max_depth_m"])
            if got is None or abs(got - t["max_depth_m"]) > tol:
                bad.append(f"pothole {t['id']}: {got} m measured, truth {t['max_depth_m']} m")
        return "; ".join(bad) or None

    return classify(None, accept={"ok"}, check=check)
