"""The fault battery's tools: run the real CLI on a case, watch the drive for changes and the
processes for leftovers, and classify what came back (``classify``, pure and unit-tested).

Outcomes. Good: ``ok`` (exit 0, outputs right), ``warned ok`` (exit 0, the expected warning in
report.json), ``error ok`` (non-zero exit, the last stderr line is one ``error:``/``stopped:``
line, no traceback), ``skipped`` (with the reason). Bad: ``TRACEBACK``, ``SILENT WRONG`` (exit 0
without the expected error or warning, or wrong outputs, or processes/files left behind),
``DATA LOST`` (a file of the drive changed or vanished), ``BAD ERROR`` (non-zero exit without a
one-line error, or a refusal where the case must work), ``TIMEOUT``.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

GOOD = ("ok", "warned ok", "error ok", "skipped")
BAD = ("TRACEBACK", "SILENT WRONG", "DATA LOST", "BAD ERROR", "TIMEOUT")
OUTCOMES = GOOD + BAD
ERROR_PREFIXES = ("error:", "stopped:")
# files that must come out byte-identical when a run is resumed or redone on the same inputs
SAME_FILES = ("defects.geojson", "defects.csv", "frames.csv", "trajectory.geojson", "surface.tif")


@dataclass
class Proc:
    """One finished CLI call."""

    argv: list[str]
    rc: int
    stdout: str
    stderr: str
    wall_s: float
    timed_out: bool = False
    signalled: bool = False  # the `when` condition fired and the signal was sent
    drive_lost: list[str] = field(default_factory=list)  # drive files changed or removed
    drive_added: list[str] = field(default_factory=list)  # files the command wrote into a drive
    leftovers: list[str] = field(default_factory=list)  # processes still alive after it ended


@dataclass
class Verdict:
    outcome: str
    rc: int | None
    message: str
    wall_s: float = 0.0


def error_line(stderr: str) -> str | None:
    """The one-line error a clean failure ends with, else None."""
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    if lines and lines[-1].startswith(ERROR_PREFIXES):
        return lines[-1]
    return None


def traceback_line(text: str) -> str | None:
    """The exception line of a (plain or rich) traceback in ``text``, else None."""
    if "Traceback" not in text:
        return None
    lines = [ln.strip(" │╰╯─") for ln in text.splitlines()]
    for ln in reversed(lines):
        if re.match(r"^[A-Za-z_][\w.]*(Error|Exception|Interrupt|Exit|Terminated)\b", ln):
            return ln
    return "Traceback"


def classify(
    proc: Proc | None,
    *,
    accept: Iterable[str],
    warn_re: str | None = None,
    warnings: Sequence[str] = (),
    check: Callable[[], str | None] | None = None,
) -> Verdict:
    """Outcome of one case. ``accept``: what counts as a right answer: "error" (a one-line
    error), "warn" (exit 0 and a warning matching ``warn_re``), "ok" (exit 0 and ``check``
    returns None), "warn+ok" (both). ``check`` returns what is wrong with the outputs, or None;
    it runs only on exit 0. ``proc`` None: a case that only checks outputs."""
    accept = set(accept)
    if proc is None:
        wrong = check() if check is not None else None
        return Verdict("ok" if wrong is None else "SILENT WRONG", None, wrong or "outputs right")
    v = lambda outcome, msg: Verdict(outcome, proc.rc, msg, proc.wall_s)  # noqa: E731
    if proc.drive_lost:
        return v("DATA LOST", f"drive file(s) changed or removed: {', '.join(proc.drive_lost[:4])}")
    tb = traceback_line(proc.stderr) or traceback_line(proc.stdout)
    if tb is not None:
        err = error_line(proc.stderr) if proc.rc else None
        return v("TRACEBACK", f"traceback logged, then {err}" if err else tb)
    if proc.timed_out:
        return v("TIMEOUT", f"still running after {proc.wall_s:.0f} s; killed")
    if proc.leftovers:
        return v("SILENT WRONG", f"left running: {'; '.join(proc.leftovers[:2])}")
    if proc.rc != 0:
        err = error_line(proc.stderr)
        if err is None:
            last = [ln for ln in proc.stderr.splitlines() if ln.strip()][-1:] or ["(no stderr)"]
            return v("BAD ERROR", f"exit {proc.rc} without a one-line error; last: {last[0]}")
        if "error" not in accept:
            return v("BAD ERROR", f"refused, but this case must work: {err}")
        return v("error ok", err)
    if proc.drive_added:
        return v("SILENT WRONG", f"wrote into the drive: {', '.join(proc.drive_added[:3])}")
    matched = next((w for w in warnings if warn_re and re.search(warn_re, w)), None)
    if matched is not None and "warn" in accept:
        return v("warned ok", matched)
    wrong = check() if check is not None and accept & {"ok", "warn+ok"} else None
    if "warn+ok" in accept and matched is not None and wrong is None:
        return v("warned ok", matched)
    if "ok" in accept and wrong is None:
        return v("ok", "outputs right")
    if wrong is not None:
        return v("SILENT WRONG", wrong)
    want = " or ".join(sorted(accept - {"ok"}))
    hint = f" /{warn_re}/" if warn_re else ""
    has = f"; other warning: {warnings[0]}" if warnings else ""
    return v("SILENT WRONG", f"exit 0 without the expected {want}{hint}{has}")


# --- files --------------------------------------------------------------------------------


def tree_hash(root: Path) -> dict[str, str]:
    """sha256 of every file below ``root`` by relative path."""
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file() and not p.is_symlink():
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def report_warnings(run_dir: Path) -> list[str]:
    """report.json "warnings" of a run folder ([] when there is none or it is unreadable)."""
    try:
        doc = json.loads((run_dir / "report.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    # the case folder's name must not match a case's pattern ("…/lat_lon_swapped/…")
    return [short_paths(str(w)) for w in doc.get("warnings") or []]


def short_paths(text: str) -> str:
    """``/tmp/x/cases/<case>/drive/gps.csv`` -> ``drive/gps.csv``."""
    return re.sub(r"\S*/cases/[^/\s]+/", "", text)


def read_report(run_dir: Path) -> dict:
    try:
        return json.loads((run_dir / "report.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def same_outputs(run: Path, ref: Path, names: Sequence[str] = SAME_FILES) -> str | None:
    """None when ``run`` has the files ``names`` byte-identical to ``ref``; else what differs."""
    diff = [
        n
        for n in names
        if not (run / n).is_file() or (run / n).read_bytes() != (ref / n).read_bytes()
    ]
    if not diff:
        return None
    ref_n, run_n = defect_count(ref), defect_count(run)
    return f"differs from the clean run: {', '.join(diff)} (defects {run_n} vs {ref_n})"


def defect_count(run: Path) -> int | None:
    try:
        return len(json.loads((run / "defects.geojson").read_text())["features"])
    except (OSError, ValueError, KeyError):
        return None


def temp_files(run: Path) -> list[str]:
    return sorted(str(p.relative_to(run)) for p in run.rglob("*") if ".tmp" in p.name)


def set_yaml_key(path: Path, key: str, value: str) -> None:
    """Replace the top-level ``key: ...`` line of a flat YAML file."""
    text = path.read_text(encoding="utf-8")
    new, n = re.subn(rf"(?m)^{re.escape(key)}:.*$", f"{key}: {value}", text)
    if n != 1:
        raise ValueError(f"{path}: no single '{key}:' line")
    path.write_text(new, encoding="utf-8")


def map_csv(path: Path, fn: Callable[[int, dict[str, str]], dict[str, str]]) -> None:
    """Rewrite a CSV row by row (``fn(index, row) -> row``), keeping its header."""
    with path.open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    header = list(rows[0].keys())
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, header, lineterminator="\n")
        w.writeheader()
        w.writerows(fn(i, dict(r)) for i, r in enumerate(rows))


def slug(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", name.lower()).strip("_")[:60]


# --- processes ----------------------------------------------------------------------------


def _proc_table() -> list[tuple[int, int, str]]:
    """(pid, session id, command line) of every process we can read."""
    rows = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        rows.append((int(d.name), int(fields[3]), cmd.strip()))
    return rows


def leftovers(session: int, marker: str) -> list[tuple[int, str]]:
    """Processes in ``session`` (the CLI's own) or whose command line names ``marker``."""
    me = os.getpid()
    return [
        (pid, cmd)
        for pid, sid, cmd in _proc_table()
        if pid != me and cmd and (sid == session or marker in cmd)
    ]


class Ctx:
    """One case's folder, the drives it registered (hashed around every command), and the
    shared base artifacts (``shared``: base drive/run, drive B, lazily built extras)."""

    def __init__(self, root: Path, shared: dict, pythonpath: str | None = None) -> None:
        self.dir = root
        self.shared = shared
        self.pythonpath = pythonpath
        self.drives: list[Path] = []
        self.tmp = root / "tmp"
        self.tmp.mkdir(parents=True, exist_ok=True)
        self._n = 0

    def drive(self, src: Path | None = None, name: str = "drive") -> Path:
        """A private copy of a drive (default the base drive), watched for changes."""
        dst = self.dir / name
        shutil.copytree(src or self.shared["drive"], dst, symlinks=True)
        self.drives.append(dst)
        return dst

    def watch(self, drive: Path) -> Path:
        self.drives.append(drive)
        return drive

    def copy_run(self, src: Path | None = None, name: str = "run") -> Path:
        dst = self.dir / name
        shutil.copytree(src or self.shared["run"], dst, symlinks=True)
        return dst

    def cli(
        self,
        *args: object,
        timeout: float = 180.0,
        when: Callable[[], bool] | None = None,
        sig: int = signal.SIGTERM,
        group: bool = False,
    ) -> Proc:
        """Run ``python -m roadsurf ARGS`` in its own session; send ``sig`` once ``when()`` is
        true (to the whole process group with ``group``, as kill -9 of a job would)."""
        self._n += 1
        argv = [sys.executable, "-m", "roadsurf", *map(str, args)]
        before = {d: tree_hash(d) for d in self.drives}
        env = dict(os.environ, TMPDIR=str(self.tmp), PYTHONUNBUFFERED="1", COLUMNS="200")
        if self.pythonpath:
            env["PYTHONPATH"] = self.pythonpath
        out_p, err_p = self.dir / f"cmd{self._n}.stdout", self.dir / f"cmd{self._n}.stderr"
        t0 = time.monotonic()
        timed_out = signalled = False
        with out_p.open("wb") as fo, err_p.open("wb") as fe:
            # cwd: the case folder, so that `-m` does not put a checkout on sys.path
            p = subprocess.Popen(
                argv, stdout=fo, stderr=fe, cwd=self.dir, env=env, start_new_session=True
            )
            while p.poll() is None:
                if when is not None and not signalled and when():
                    (os.killpg if group else os.kill)(p.pid, sig)
                    signalled = True
                if time.monotonic() - t0 > timeout:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
                    timed_out = True
                    break
                time.sleep(0.05)
        wall = time.monotonic() - t0
        time.sleep(0.3)  # let children that are on their way out go
        left = leftovers(p.pid, str(self.dir))
        for pid, _cmd in left:  # ours: started by this command
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        lost, added = [], []
        for d, h in before.items():
            now = tree_hash(d) if d.exists() else {}
            lost += [f"{d.name}/{k}" for k in h if now.get(k) != h[k]]
            added += [f"{d.name}/{k}" for k in now if k not in h]
        return Proc(
            argv=argv,
            rc=p.returncode,
            stdout=out_p.read_text(errors="replace"),
            stderr=err_p.read_text(errors="replace"),
            wall_s=wall,
            timed_out=timed_out,
            signalled=signalled,
            drive_lost=lost,
            drive_added=added,
            leftovers=[f"pid {pid} {cmd[:80]}" for pid, cmd in left],
        )


@dataclass(frozen=True)
class Case:
    name: str
    item: str  # the issue item(s) it checks
    fn: Callable[[Ctx], Verdict]


def register(cases: list[Case]) -> Callable[[str, str], Callable]:
    """``@case(name, item)`` appends the decorated function to ``cases``."""

    def case(name: str, item: str) -> Callable:
        def deco(fn: Callable[[Ctx], Verdict]) -> Callable[[Ctx], Verdict]:
            cases.append(Case(name, item, fn))
            return fn

        return deco

    return case


def prelude(p: Proc, what: str, accept: Iterable[str] = ("ok",)) -> Verdict | None:
    """None when a preparatory command ended as expected; else its verdict, prefixed."""
    v = classify(p, accept=accept, check=None)
    if v.outcome in ("ok", "error ok", "warned ok"):
        return None
    return Verdict(v.outcome, v.rc, f"{what}: {v.message}", v.wall_s)
