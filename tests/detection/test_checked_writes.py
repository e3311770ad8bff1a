"""Every image detection writes is atomic and checked: cv2.imwrite reports success on a full
disk after writing nothing, which must not leave a 0-byte mask under its final name."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from roadsurf.core.errors import OutputError
from roadsurf.detection.pairs import write_mask

MASK = np.zeros((8, 8), bool)
MASK[2:5, 3:6] = True


def test_mask_written_whole_under_its_final_name(tmp_path):
    path = tmp_path / "masks" / "f0001.png"
    write_mask(path, MASK)
    assert (cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 0).tolist() == MASK.tolist()
    assert sorted(p.name for p in path.parent.iterdir()) == ["f0001.png"]


@pytest.mark.parametrize("returns", [True, False])
def test_imwrite_that_writes_nothing_leaves_no_empty_mask(tmp_path, monkeypatch, returns):
    def full_disk_imwrite(filename, img, *args):  # what cv2 does on a full disk: no bytes
        open(filename, "wb").close()
        return returns

    monkeypatch.setattr(cv2, "imwrite", full_disk_imwrite)
    path = tmp_path / "masks" / "f0001.png"
    with pytest.raises(OutputError) as e:
        write_mask(path, MASK)
    msg = str(e.value)
    assert "\n" not in msg and "f0001.png" in msg
    assert not path.exists()
    assert list(path.parent.iterdir()) == []  # no temporary left either
