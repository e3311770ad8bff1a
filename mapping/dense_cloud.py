"""The dense ``cloud.ply``: one point per measured cell of the dense surface (issue 29), written
tile by tile while the rasters are (memory flat in the drive's length).

Points are the cells' centres in the export CRS (x, y of the grid; z = the local road height +
the cell's residual as an ellipsoidal height, ENU up + the reference's altitude + the tangent
plane's rise (``GridToEnu.height_lift``), as ``ExportFrame.utm_from_enu`` gives the sparse
points, or local ENU without GPS), the mosaic's colour and the same per-point properties as the
sparse cloud (``residual_m``, ``n_obs``: the pairs fused into the cell). The binary body goes to
a temporary file as the tiles come; ``close`` writes the PLY header (the vertex count is known
only then) and the body into place atomically, the same layout ``io.formats.write_ply`` writes.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from roadsurf.core.atomic import atomic_path

VERTEX = np.dtype(
    [
        ("x", "<f8"),
        ("y", "<f8"),
        ("z", "<f8"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
        ("residual_m", "<f4"),
        ("n_obs", "<i4"),
    ]
)
_PLY_TYPES = {("f", 8): "double", ("u", 1): "uchar", ("f", 4): "float", ("i", 4): "int"}


def cloud_stride(gsd_m: float, spacing_m: float) -> int:
    """Every how many cells (along rows and columns) a point is kept so that points are at
    most ``spacing_m`` apart (1: every cell; spacing 0 = every cell)."""
    if spacing_m <= 0 or gsd_m <= 0:
        return 1
    return max(1, int(np.floor(spacing_m / gsd_m + 1e-9)))


class DenseCloudWriter:
    """Appends points (``add``) and writes ``path`` on ``close`` (``abort`` drops them)."""

    def __init__(self, path: Path, comments: list[str]) -> None:
        self.path = Path(path)
        self.comments = list(comments)
        self.n = 0
        self._tmp = tempfile.NamedTemporaryFile(
            prefix=".cloud_body.", suffix=".tmp", dir=self.path.parent, delete=False
        )

    def add(
        self, xyz: np.ndarray, rgb: np.ndarray, residual_m: np.ndarray, n_obs: np.ndarray
    ) -> None:
        """xyz (N, 3) export coordinates (m), rgb (N, 3) uint8, residual_m (N,) m, n_obs (N,)."""
        n = len(xyz)
        if n == 0:
            return
        rec = np.empty(n, VERTEX)
        rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
        rec["residual_m"] = residual_m
        rec["n_obs"] = n_obs
        self._tmp.write(rec.tobytes())
        self.n += n

    def close(self) -> Path:
        self._tmp.close()
        body = Path(self._tmp.name)
        head = ["ply", "format binary_little_endian 1.0"]
        head += [f"comment {c}" for c in self.comments]
        head.append(f"element vertex {self.n}")
        for name in VERTEX.names:
            dt = VERTEX[name]
            head.append(f"property {_PLY_TYPES[(dt.kind, dt.itemsize)]} {name}")
        head.append("end_header")
        try:
            with atomic_path(self.path) as tmp, open(tmp, "wb") as f:
                f.write(("\n".join(head) + "\n").encode("ascii"))
                with open(body, "rb") as b:
                    shutil.copyfileobj(b, f, 1 << 22)
        finally:
            body.unlink(missing_ok=True)
        return self.path

    def abort(self) -> None:
        self._tmp.close()
        Path(self._tmp.name).unlink(missing_ok=True)
