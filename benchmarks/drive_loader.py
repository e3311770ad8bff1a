"""Benchmark: how long ``load_drive`` takes, with and without the image check.

A long drive is made by repeating a short one's frames (copies with new names and times) in a
temporary folder, so the figure for e.g. 600 frames needs no 600-frame render.
"""

from __future__ import annotations

import shutil
import statistics
import tempfile
import time
from pathlib import Path

from roadsurf.io.drive import load_drive


def _repeated_drive(src: Path, dst: Path, repeat: int) -> int:
    """Write a drive whose frames are ``src``'s frames repeated ``repeat`` times. Returns count."""
    drive = load_drive(src, check_images=False)
    (dst / "frames").mkdir(parents=True)
    shutil.copy2(src / "camera.yaml", dst / "camera.yaml")
    dt = 1.0 / drive.camera.fps
    rows = ["filename,timestamp_s"]
    k = 0
    for r in range(repeat):
        for f in drive.frames:
            name = f"r{r:03d}_{Path(f.filename).name}"
            shutil.copyfile(f.path, dst / "frames" / name)
            rows.append(f"{name},{k * dt:.6f}")
            k += 1
    (dst / "frames.csv").write_text("\n".join(rows) + "\n")
    return k


def bench_loader(drive: str | Path, repeat: int = 12, runs: int = 3) -> str:
    """Median wall time of ``load_drive`` (check_images True and False) as a markdown table."""
    drive = Path(drive)
    with tempfile.TemporaryDirectory(prefix="roadsurf_bench_loader_") as tmp:
        root = Path(tmp) / "drive"
        n = _repeated_drive(drive, root, repeat)
        load_drive(root)  # warm the page cache: we time decoding, not the first disk read
        rows = []
        for check in (True, False):
            times = []
            for _ in range(runs):
                t = time.perf_counter()
                d = load_drive(root, check_images=check)
                times.append(time.perf_counter() - t)
            med = statistics.median(times)
            rows.append(
                f"| {n} | {check} | {len(d.frames)} | {med:.2f} s | {1000 * med / n:.2f} ms |"
            )
    return "\n".join(
        [
            f"load_drive on {drive} repeated {repeat}x (median of {runs} runs)",
            "",
            "| frames | check_images | loaded | wall | per frame |",
            "|---|---|---|---|---|",
            *rows,
        ]
    )


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.drive_loader [DRIVE] [--repeat N]`` (``make bench-drive_loader``)."""
    import argparse

    from benchmarks._result import write_result

    ap = argparse.ArgumentParser(description="Time load_drive on a long drive made by repetition.")
    ap.add_argument("drive", nargs="?", default="data_samples/drive", type=Path)
    ap.add_argument("--repeat", type=int, default=12, help="repeat the frames this many times")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    table = bench_loader(a.drive, repeat=a.repeat)
    print(table)
    write_result(a.json, "drive_loader", {"markdown": table})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
