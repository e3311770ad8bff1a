"""The one stage fingerprint: a SHA-256 over what produced an artifact.

A stage stores the fingerprint of its inputs beside its outputs (or in a cache file's name) and
reuses the outputs only when the fingerprint of the current inputs matches, so a resumed run
never trusts artifacts made from other inputs. Every piece is fed in a fixed, documented byte
form, so the digest is stable across processes and machines.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np


class Fingerprint:
    """Incremental SHA-256 of a stage's inputs.

    >>> fp = Fingerprint()
    >>> fp.add_json({"gsd_m": 0.005}).add_text("pairs").hexdigest(16)  # doctest: +SKIP
    """

    def __init__(self) -> None:
        self._h = hashlib.sha256()

    def add_bytes(self, data: bytes) -> Fingerprint:
        self._h.update(data)
        return self

    def add_text(self, text: str) -> Fingerprint:
        """UTF-8 bytes of ``text``."""
        return self.add_bytes(text.encode())

    def add_json(self, obj: Any, *, default_str: bool = True) -> Fingerprint:
        """``json.dumps(obj, sort_keys=True)``; with ``default_str`` non-JSON values (paths,
        tuples inside sets...) are written with ``str``."""
        return self.add_text(json.dumps(obj, sort_keys=True, default=str if default_str else None))

    def add_repr(self, obj: Any) -> Fingerprint:
        """``repr(obj)``: for tuples of numbers and strings, whose repr is canonical."""
        return self.add_text(repr(obj))

    def add_array(
        self, a: Any, dtype: Any = np.float64, max_bytes: int | None = None
    ) -> Fingerprint:
        """The C-contiguous bytes of ``a`` as ``dtype`` (the first ``max_bytes`` if given)."""
        b = np.ascontiguousarray(a, dtype=dtype).tobytes()
        return self.add_bytes(b if max_bytes is None else b[:max_bytes])

    def add_file_bytes(self, path: str | Path) -> Fingerprint:
        """The whole content of a file (small files: labels, configs)."""
        return self.add_bytes(Path(path).read_bytes())

    def add_file_stat(self, path: str | Path, label: str | None = None) -> Fingerprint:
        """A cheap file identity: ``label|size|mtime_ns`` (nothing if the file is missing)."""
        p = Path(path)
        if p.exists():
            st = p.stat()
            self.add_text(f"{label or p.name}|{st.st_size}|{st.st_mtime_ns}")
        return self

    def hexdigest(self, n: int | None = None) -> str:
        """The hex digest, truncated to ``n`` characters if given."""
        d = self._h.hexdigest()
        return d if n is None else d[:n]
