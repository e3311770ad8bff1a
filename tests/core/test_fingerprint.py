"""The stage fingerprint is stable, order-sensitive and sees content changes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from roadsurf.core.fingerprint import Fingerprint


def test_same_inputs_same_digest_and_changes_show(tmp_path: Path) -> None:
    def fp(gsd: float, arr: np.ndarray) -> str:
        return Fingerprint().add_json({"gsd_m": gsd, "b": [1, 2]}).add_array(arr).hexdigest(16)

    a = np.arange(6.0)
    assert fp(0.005, a) == fp(0.005, a.copy())
    assert fp(0.005, a) != fp(0.004, a)
    b = a.copy()
    b[3] += 1e-12
    assert fp(0.005, a) != fp(0.005, b)
    assert len(fp(0.005, a)) == 16 and len(Fingerprint().hexdigest()) == 64
    f = tmp_path / "x.bin"
    assert Fingerprint().add_file_stat(f).hexdigest() == Fingerprint().hexdigest()  # missing
    f.write_bytes(b"abc")
    assert Fingerprint().add_file_stat(f).hexdigest() != Fingerprint().hexdigest()
    assert Fingerprint().add_text("ab").add_text("c").hexdigest() == (
        Fingerprint().add_text("abc").hexdigest()
    )
