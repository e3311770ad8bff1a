"""Fault battery (issue 31): run every case of the fault campaign through the real CLI and print
a table of case, exit code, message and outcome.

A base drive (the "potholes" scenario, seed 202, 12 frames, RTK GPS) and its clean run are made
once; a second drive B (the first 12 frames of ``data_samples/drive``) and its clean run serve
the run-folder mix-ups. Every case copies what it needs into ``WORK/cases/<case>/``, runs
``python -m roadsurf ...`` in a subprocess (own session, own TMPDIR, a timeout), hashes the
drive folders before and after every command, and looks for processes left behind. Outcomes
are defined in ``benchmarks/_fault_kit.py``; the target is 0 ``TRACEBACK``, 0 ``SILENT WRONG``
and 0 ``DATA LOST``.

    python -m benchmarks.fault_battery --work /tmp/faults [--only REGEX] [--json FILE]
"""

from __future__ import annotations

import re
import shutil
import time
import traceback
from collections import Counter
from pathlib import Path

from benchmarks._fault_kit import BAD, OUTCOMES, Case, Ctx, Verdict, short_paths, slug
from benchmarks.fault_cases import CASES as CASES_INPUT
from benchmarks.fault_cases_env import CASES as CASES_ENV

ROOT = Path(__file__).resolve().parents[1]
CASES: list[Case] = CASES_INPUT + CASES_ENV
SIMULATE = ("simulate", "--scenario", "potholes", "--seed", "202", "--frames", "12")
N_FRAMES_B = 12


def _cut_drive(src: Path, dst: Path, n: int) -> None:
    """Copy the first ``n`` frames of drive ``src`` (camera, GPS and OBD whole) to ``dst``."""
    (dst / "frames").mkdir(parents=True)
    for name in ("camera.yaml", "gps.csv", "obd.csv"):
        if (src / name).exists():
            shutil.copy2(src / name, dst / name)
    lines = (src / "frames.csv").read_text(encoding="utf-8").splitlines()
    keep = lines[: n + 1]
    (dst / "frames.csv").write_text("\n".join(keep) + "\n", encoding="utf-8")
    for ln in keep[1:]:
        name = ln.split(",")[0]
        shutil.copy2(src / "frames" / Path(name).name, dst / "frames" / Path(name).name)


def prepare(work: Path, pythonpath: str | None = None) -> dict:
    """Base drive A and its run, drive B and its run, under ``work/base``."""
    base = work / "base"
    if base.exists():
        shutil.rmtree(base)
    shared: dict = {"work": work, "simulate": SIMULATE}
    cx = Ctx(base, shared, pythonpath)
    a, b = base / "drive", base / "drive_b"
    _cut_drive(ROOT / "data_samples" / "drive", b, N_FRAMES_B)
    steps = [
        cx.cli(*SIMULATE, "--out", a),
        cx.cli("run", a, "--out", base / "run"),
        cx.cli("run", b, "--out", base / "run_b"),
    ]
    for p in steps:
        if p.rc != 0:
            raise SystemExit(
                f"fault battery: base step failed: {' '.join(p.argv[2:])}\n{p.stderr[-2000:]}"
            )
    shared.update(drive=a, run=base / "run", drive_b=b, run_b=base / "run_b")
    return shared


def run_case(c: Case, work: Path, shared: dict, pythonpath: str | None = None) -> Verdict:
    """One case in a fresh folder; an exception of the battery itself is reported, not raised."""
    root = work / "cases" / slug(c.name)
    if root.exists():
        shutil.rmtree(root)
    t0 = time.monotonic()
    try:
        v = c.fn(Ctx(root, shared, pythonpath))
    except Exception as e:  # noqa: BLE001 (a broken case must not stop the battery)
        tb = traceback.format_exc(limit=3).strip().splitlines()[-1]
        v = Verdict("skipped", None, f"battery error: {type(e).__name__}: {e} ({tb})")
    v.wall_s = time.monotonic() - t0
    v.message = short_paths(v.message)
    return v


def _cell(text: str, width: int = 120) -> str:
    text = re.sub(r"\s+", " ", text).replace("|", "\\|")
    return text if len(text) <= width else text[: width - 1] + "…"


def table(rows: list[tuple[Case, Verdict]]) -> str:
    """The markdown table of the results plus one line of counts per outcome."""
    out = ["| # | case | item | exit | outcome | message | s |", "|---|---|---|---|---|---|---|"]
    for i, (c, v) in enumerate(rows, 1):
        outcome = f"**{v.outcome}**" if v.outcome in BAD else v.outcome
        rc = "" if v.rc is None else str(v.rc)
        out.append(
            f"| {i} | {_cell(c.name, 60)} | {c.item} | {rc} | {outcome} | {_cell(v.message)} | {v.wall_s:.0f} |"
        )
    return "\n".join(out) + "\n\n" + counts_line(rows)


def counts_line(rows: list[tuple[Case, Verdict]]) -> str:
    n = Counter(v.outcome for _, v in rows)
    return "Counts: " + ", ".join(f"{o} {n[o]}" for o in OUTCOMES if n[o] or o in BAD)


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.fault_battery`` (``make bench-fault_battery``)."""
    import argparse

    from benchmarks._result import write_result

    ap = argparse.ArgumentParser(description="Run the fault campaign of issue 31 through the CLI.")
    ap.add_argument(
        "--work", type=Path, default=Path("/tmp/roadsurf_faults"), help="scratch folder"
    )
    ap.add_argument("--only", default=None, help="run only the cases whose name matches this regex")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    ap.add_argument(
        "--pythonpath", default=None, help="run the CLI of another checkout (PYTHONPATH)"
    )
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    a = ap.parse_args(argv)
    cases = [c for c in CASES if a.only is None or re.search(a.only, c.name, re.I)]
    if a.list or not cases:
        print("\n".join(f"{c.item:>5}  {c.name}" for c in cases) or "no case matches --only")
        return 0 if cases else 2
    a.work.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    shared = prepare(a.work, a.pythonpath)
    rows = []
    for c in cases:
        v = run_case(c, a.work, shared, a.pythonpath)
        rows.append((c, v))
        print(f"{v.outcome:>12}  {c.name}: {_cell(v.message, 100)}", flush=True)
    text = table(rows)
    print()
    print(text)
    print(f"\n{len(rows)} cases in {time.monotonic() - t0:.0f} s")
    figures = {
        "markdown": text,
        "counts": dict(Counter(v.outcome for _, v in rows)),
        "cases": [
            {
                "case": c.name,
                "item": c.item,
                "exit": v.rc,
                "outcome": v.outcome,
                "message": v.message,
                "wall_s": round(v.wall_s, 1),
            }
            for c, v in rows
        ],
    }
    write_result(a.json, "fault_battery" if a.only is None else "fault_battery_partial", figures)
    return 1 if any(v.outcome in BAD for _, v in rows) else 0


if __name__ == "__main__":
    raise SystemExit(main())
