"""Headless Chromium helpers: screenshots of report.html and of the Rerun web viewer.

Used by the tests and by ``roadsurf view --screenshot`` (docs/img). Everything binds to
127.0.0.1 and the browser runs with networking extras disabled; nothing is downloaded.
"""

from __future__ import annotations

import http.server
import logging
import shutil
import subprocess
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from roadsurf.core.errors import RoadsurfError

log = logging.getLogger(__name__)

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    # WebGL through the CPU (SwiftShader) so the Rerun web viewer renders without a GPU
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
)


def find_chromium() -> str | None:
    """Path of a Chromium/Chrome executable, or None (install Debian's `chromium`)."""
    for name in CHROMIUM_NAMES:
        p = shutil.which(name)
        if p:
            return p
    return None


@dataclass
class ShotResult:
    path: Path
    console: str  # browser console/log output (stderr), for load checks


def screenshot(
    url: str,
    out_png: str | Path,
    *,
    size: tuple[int, int] = (1400, 900),
    wait_s: float = 0.0,
    wait_for: str | None = None,
    settle_s: float = 3.0,
    timeout_s: float = 180.0,
) -> ShotResult:
    """Screenshot ``url`` with headless Chromium into ``out_png``.

    ``wait_s`` > 0 keeps the page loading up to that long before the shot (for apps that draw
    after the load event, like the Rerun web viewer): the URL is shown in a full-window iframe
    of a local page whose load event is held back by a delayed resource. With ``wait_for``, the
    hold ends ``settle_s`` after that text appears in the browser console (adaptive on a busy
    machine), and at the latest after ``wait_s``.
    """
    exe = find_chromium()
    if exe is None:
        raise RoadsurfError(
            "Chromium not found. Install it (Debian: `apt-get install chromium`, or "
            "`make browser-deps`) to take screenshots."
        )
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    release = threading.Event()
    lines: list[str] = []
    with (
        _delayed_page(url, wait_s, release) as page_url,
        tempfile.TemporaryDirectory() as profile,
    ):
        cmd = [
            exe,
            *CHROMIUM_FLAGS,
            f"--user-data-dir={profile}",
            f"--window-size={size[0]},{size[1]}",
            "--enable-logging=stderr",
            "--v=0",
            f"--screenshot={out_png}",
            page_url,
        ]
        proc = subprocess.Popen(
            cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, errors="replace"
        )

        def pump() -> None:  # read the console as it comes, to release the hold early
            for line in proc.stderr or ():
                lines.append(line)
                if wait_for and wait_for in line and not release.is_set():
                    threading.Timer(settle_s, release.set).start()

        reader = threading.Thread(target=pump, daemon=True)
        reader.start()
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired as e:
            proc.kill()
            proc.wait()
            raise RoadsurfError(f"Chromium did not finish within {timeout_s:.0f} s on {url}") from e
        finally:
            release.set()
        reader.join(timeout=5)
    console = "".join(lines)
    if not out_png.exists():
        raise RoadsurfError(
            f"Chromium wrote no screenshot of {url} (exit {proc.returncode}): " + console[-800:]
        )
    return ShotResult(out_png, console)


@contextmanager
def _delayed_page(url: str, wait_s: float, release: threading.Event) -> Iterator[str]:
    if wait_s <= 0:
        yield url
        return
    # the URL comes from our own code (localhost viewer); still keep quotes out of the attribute
    src = url.replace('"', "%22")
    body = (
        '<!doctype html><html><body style="margin:0;background:#000;overflow:hidden">'
        f'<iframe src="{src}" style="border:0;width:100vw;height:100vh"></iframe>'
        '<img src="/delay" style="display:none"></body></html>'
    ).encode()
    done = release

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - http.server API
            if self.path.startswith("/delay"):
                done.wait(wait_s)
                payload, ctype = b"GIF89a\x01\x00\x01\x00\x00\x00\x00;", "image/gif"
            else:
                payload, ctype = body, "text/html"
            self.send_response(200)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(payload)))
            self.end_headers()
            self.wfile.write(payload)

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        done.set()
        server.shutdown()
        server.server_close()


def is_blank(png: str | Path, min_std: float = 4.0) -> bool:
    """True when an image is (nearly) one flat colour."""
    import cv2
    import numpy as np

    img = cv2.imread(str(png), cv2.IMREAD_COLOR)
    if img is None:
        return True
    return bool(float(np.std(img.astype(float))) < min_std)
