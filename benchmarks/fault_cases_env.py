"""Fault cases of issue 31, items 6-9: disk full, unwritable outputs, stale temporary files,
config ranges, bad encodings, truncated reports, bad model files, signals and --serve.

Disk-full and read-only outputs use small tmpfs mounts (root only; skipped otherwise).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
from collections.abc import Callable
from pathlib import Path

from benchmarks._fault_kit import (
    Case,
    Ctx,
    Verdict,
    classify,
    prelude,
    register,
    report_warnings,
    same_outputs,
    temp_files,
)

CASES: list[Case] = []
case = register(CASES)


def _all(*checks: Callable[[], str | None]) -> Callable[[], str | None]:
    return lambda: "; ".join(w for w in (c() for c in checks) if w) or None


def _resumed_right(cx: Ctx, run: Path) -> Callable[[], str | None]:
    """The resumed run equals the clean base run and left no temporary file."""

    def tmp() -> str | None:
        left = temp_files(run)
        return f"temporary files left: {', '.join(left[:3])}" if left else None

    return _all(lambda: same_outputs(run, cx.shared["run"]), tmp)


def _mount_tmpfs(where: Path, opts: str) -> str | None:
    """Mount a tmpfs at ``where``; None on success, else why not."""
    where.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        return "needs root to mount a tmpfs"
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(where)], capture_output=True, text=True
    )
    return None if r.returncode == 0 else f"mount failed: {r.stderr.strip()}"


def _umount(where: Path) -> None:
    subprocess.run(["umount", str(where)], capture_output=True)


# --- item 6: disk full, output files -----------------------------------------------------


def _disk_full(cx: Ctx, size: str) -> Verdict:
    mnt = cx.dir / "small_disk"
    if why := _mount_tmpfs(mnt, f"size={size}"):
        return Verdict("skipped", None, why)
    d = cx.drive()
    try:
        p = cx.cli("run", d, "--out", mnt / "run")
        empty = sorted(
            str(f.relative_to(mnt))
            for f in (mnt / "run").rglob("*")
            if f.is_file() and f.stat().st_size == 0
        )
        if (mnt / "run").is_dir():
            shutil.copytree(mnt / "run", cx.dir / "run", symlinks=True)
    finally:
        _umount(mnt)
    v = classify(p, accept={"error"})
    if v.outcome != "error ok":
        return v
    if empty:
        return Verdict(
            "SILENT WRONG",
            p.rc,
            f"{len(empty)} empty files under final names: {empty[0]}",
            p.wall_s,
        )
    # the same run folder resumed on a disk with room: it must give the clean outputs
    p2 = cx.cli("run", d, "--out", cx.dir / "run")
    r = classify(p2, accept={"ok"}, check=_resumed_right(cx, cx.dir / "run"))
    if r.outcome != "ok":
        return Verdict(r.outcome, r.rc, f"resume after disk full: {r.message}", r.wall_s)
    return v


@case("disk full: --out on a 2 MB tmpfs, then resumed", "6")
def _disk_2m(cx: Ctx) -> Verdict:
    return _disk_full(cx, "2m")


@case("disk full: --out on a 6 MB tmpfs, then resumed", "6")
def _disk_6m(cx: Ctx) -> Verdict:
    return _disk_full(cx, "6m")


@case("stale .tmp files in the run folder removed on resume", "6")
def _stale_tmp(cx: Ctx) -> Verdict:
    run = cx.copy_run()
    (run / ".surface.k3j9x2.tmp.tif").write_bytes(b"\0" * 1000)
    (run / "masks" / ".frame_000003.q81z.tmp.png").write_bytes(b"")
    p = cx.cli("run", cx.watch(cx.shared["drive"]), "--out", run)
    return classify(p, accept={"ok"}, check=_resumed_right(cx, run))


@case("read-only --out", "9")
def _out_readonly(cx: Ctx) -> Verdict:
    mnt = cx.dir / "ro"
    if why := _mount_tmpfs(mnt, "ro,size=1m"):
        return Verdict("skipped", None, why)
    try:
        return classify(cx.cli("run", cx.drive(), "--out", mnt / "run"), accept={"error"})
    finally:
        _umount(mnt)


@case("--out an existing file", "9")
def _out_file(cx: Ctx) -> Verdict:
    f = cx.dir / "some_file.txt"
    f.write_text("not a folder\n")
    return classify(cx.cli("run", cx.drive(), "--out", f), accept={"error"})


# --- item 7 and 9: config ----------------------------------------------------------------


def _config_case(name: str, text: str, item: str = "7") -> None:
    @case(name, item)
    def _fn(cx: Ctx) -> Verdict:
        cfg = cx.dir / "config.yaml"
        cfg.write_text(text, encoding="utf-8")
        return classify(
            cx.cli("run", cx.drive(), "--out", cx.dir / "run", "--config", cfg), accept={"error"}
        )


_config_case("mapping.gsd_m: 0", "mapping:\n  gsd_m: 0\n")
_config_case("mapping.tile_px: 0", "mapping:\n  tile_px: 0\n")
_config_case("mapping.preview_max_px: 0", "mapping:\n  preview_max_px: 0\n")
_config_case(
    "detection.map.depth_threshold_m: -0.01", "detection:\n  map:\n    depth_threshold_m: -0.01\n"
)
_config_case("mapping.voxel_m: -1", "mapping:\n  voxel_m: -1\n")
_config_case("'~: 1' in --config", "~: 1\n", "9")


# --- item 9: encodings, truncated and bad files ------------------------------------------


def _inject(path: Path, row: int, byte: bytes) -> None:
    """Put ``byte`` at the end of the first field of line ``row`` (0 = header)."""
    lines = path.read_bytes().split(b"\n")
    head, sep, rest = lines[row].partition(b",")
    lines[row] = head + byte + sep + rest
    path.write_bytes(b"\n".join(lines))


def _encoding_case(name: str, file: str, row: int) -> None:
    @case(f"non-UTF-8 byte in {name}", "9")
    def _fn(cx: Ctx) -> Verdict:
        d = cx.drive()
        _inject(d / file, row, b"\xff")
        run = cx.dir / "run"
        p = cx.cli("run", d, "--out", run)
        return classify(p, accept={"error", "warn"}, warn_re=file, warnings=report_warnings(run))


_encoding_case("frames.csv (a file name)", "frames.csv", 6)
_encoding_case("gps.csv (a timestamp)", "gps.csv", 5)
_encoding_case("obd.csv (a timestamp)", "obd.csv", 3)


@case("non-UTF-8 byte in camera.yaml (Latin-1 comment)", "9")
def _enc_camera(cx: Ctx) -> Verdict:
    d = cx.drive()
    cam = d / "camera.yaml"
    cam.write_bytes(b"# Kamera f\xfcr die Testfahrt\n" + cam.read_bytes())
    run = cx.dir / "run"
    p = cx.cli("run", d, "--out", run)
    check = lambda: same_outputs(run, cx.shared["run"])  # noqa: E731 (a tolerant reader is fine)
    return classify(p, accept={"error", "ok"}, check=check)


@case("non-UTF-8 byte in --config (Latin-1 comment)", "9")
def _enc_config(cx: Ctx) -> Verdict:
    cfg = cx.dir / "config.yaml"
    cfg.write_bytes(b"# R\xe9glages\nreconstruction:\n  min_matches: 30\n")
    run = cx.dir / "run"
    p = cx.cli("run", cx.drive(), "--out", run, "--config", cfg)
    return classify(p, accept={"error", "ok"}, check=lambda: same_outputs(run, cx.shared["run"]))


def _truncated_run(cx: Ctx) -> Path:
    run = cx.copy_run()
    rep = run / "report.json"
    rep.write_bytes(rep.read_bytes()[: rep.stat().st_size // 2])
    cx.watch(cx.shared["drive"])
    return run


@case("truncated report.json: roadsurf report", "9")
def _trunc_report(cx: Ctx) -> Verdict:
    run = _truncated_run(cx)
    return classify(cx.cli("report", run), accept={"error"})


@case("truncated report.json: roadsurf view --save", "9")
def _trunc_view(cx: Ctx) -> Verdict:
    run = _truncated_run(cx)
    return classify(cx.cli("view", run, "--save", cx.dir / "run.rrd"), accept={"error"})


def model(cx: Ctx) -> tuple[Path, Path]:
    """A labelled dataset of the base run and a one-epoch model trained on it (built once)."""
    if "model" not in cx.shared:
        root = cx.shared["work"] / "base"
        ds, m = root / "dataset", root / "model"
        for p in (
            cx.cli("label", cx.shared["drive"], "--run", cx.shared["run"], "--out", ds),
            cx.cli("train", ds, "--out", m, "--epochs", "1", "--input-size", "32"),
        ):
            if p.rc != 0:
                raise RuntimeError(f"model for the battery failed: {p.stderr[-300:]}")
        cx.shared["model"] = (ds, m)
    return cx.shared["model"]


@case("bad checkpoint.pt for roadsurf train", "9")
def _bad_checkpoint(cx: Ctx) -> Verdict:
    ds, _ = model(cx)
    out = cx.dir / "model"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(b"not a torch checkpoint\n" * 40)
    p = cx.cli("train", cx.watch(ds), "--out", out, "--epochs", "1", "--input-size", "32")
    logged = [ln for ln in p.stderr.splitlines() if "WARNING" in ln]
    return classify(p, accept={"error", "warn"}, warn_re=r"(?i)checkpoint", warnings=logged)


@case("bad model file for run --classifier", "9")
def _bad_model(cx: Ctx) -> Verdict:
    _, m = model(cx)
    mine = cx.copy_run(m, "model")
    (mine / "model.safetensors").write_bytes(b"\x00garbage" * 100)
    p = cx.cli(
        "run", cx.drive(), "--out", cx.dir / "run", "--classifier", mine / "model.safetensors"
    )
    return classify(p, accept={"error"})


# --- item 8: signals ---------------------------------------------------------------------


def _n_pairs(run: Path) -> int:
    return len(list((run / "pairs").glob("*.npz"))) if (run / "pairs").is_dir() else 0


def _interrupted(cx: Ctx, when: Callable[[Path], bool], sig: int, stage: str) -> Verdict:
    d, run = cx.drive(), cx.dir / "run"
    group = sig == signal.SIGKILL
    p = cx.cli("run", d, "--out", run, when=lambda: when(run), sig=sig, group=group)
    if not p.signalled:
        return Verdict("skipped", p.rc, f"the run ended before {stage}; no signal sent", p.wall_s)
    if group:  # kill -9: nothing to print; only the drive must be intact
        if p.drive_lost:
            return classify(p, accept={"error"})
    elif bad := prelude(p, f"on {signal.Signals(sig).name}", {"error"}):
        return bad
    r = classify(cx.cli("run", d, "--out", run), accept={"ok"}, check=_resumed_right(cx, run))
    return Verdict(r.outcome, r.rc, f"resume: {r.message}", r.wall_s)


@case("SIGTERM during reconstruction, then resume", "8")
def _term_recon(cx: Ctx) -> Verdict:
    return _interrupted(cx, lambda r: _n_pairs(r) >= 3, signal.SIGTERM, "3 pairs")


@case("SIGTERM during mapping, then resume", "8")
def _term_map(cx: Ctx) -> Verdict:
    return _interrupted(cx, lambda r: (r / "poses.npz").exists(), signal.SIGTERM, "mapping")


@case("kill -9 during reconstruction, then resume", "8")
def _kill_recon(cx: Ctx) -> Verdict:
    return _interrupted(cx, lambda r: _n_pairs(r) >= 3, signal.SIGKILL, "3 pairs")


@case("kill -9 during mapping, then resume", "8")
def _kill_map(cx: Ctx) -> Verdict:
    return _interrupted(cx, lambda r: (r / "poses.npz").exists(), signal.SIGKILL, "mapping")


@case("SIGTERM with --classifier (CNN worker, temp folder)", "8")
def _term_classifier(cx: Ctx) -> Verdict:
    _, m = model(cx)
    screen = lambda: any(cx.tmp.glob("roadsurf-screen-*"))  # noqa: E731
    run = cx.dir / "run"
    p = cx.cli(
        "run", cx.drive(), "--out", run, "--classifier", m / "model.safetensors", when=screen
    )
    if not p.signalled:
        return Verdict("skipped", p.rc, "the CNN screening ended before the signal", p.wall_s)
    left = sorted(x.name for x in cx.tmp.iterdir())
    v = classify(p, accept={"error"})
    if v.outcome == "error ok" and left:
        return Verdict("SILENT WRONG", p.rc, f"left in TMPDIR: {', '.join(left[:3])}", p.wall_s)
    return v


def _serve(cx: Ctx, run: Path) -> tuple:
    out = cx.dir / f"cmd{cx._n + 1}.stdout"  # the next command's stdout
    ready = lambda: out.exists() and "Web viewer:" in out.read_text(errors="replace")  # noqa: E731
    cx.watch(cx.shared["drive"])
    return cx.cli(
        "view", run, "--serve", "--web-port", "0", "--grpc-port", "0", when=ready, timeout=150
    )


@case("view --serve with an existing run.rrd", "8")
def _serve_existing(cx: Ctx) -> Verdict:
    run = cx.copy_run()
    rrd = run / "run.rrd"
    rrd.write_bytes(b"an earlier recording")
    p = _serve(cx, run)
    kept = rrd.exists() and rrd.read_bytes() == b"an earlier recording"
    if not p.signalled:  # refused (or failed) before serving
        return classify(p, accept={"error"})
    v = classify(p, accept={"error"})
    if v.outcome != "error ok":
        return v
    msg = "served without touching run.rrd" if kept else "run.rrd overwritten without --overwrite"
    return Verdict("ok" if kept else "SILENT WRONG", p.rc, msg, p.wall_s)


@case("SIGTERM stops view --serve and its Rerun server", "8")
def _serve_term(cx: Ctx) -> Verdict:
    p = _serve(cx, cx.copy_run())
    if not p.signalled:
        return classify(p, accept={"error"}) if p.rc else Verdict("skipped", p.rc, "never served")
    return classify(p, accept={"error"})
