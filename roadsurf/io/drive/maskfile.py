"""camera.yaml's ``mask``: read and check the image of pixels that never show the road.

The file is an image of the camera's size (PNG recommended: JPEG blurs its edges); pixels of
value 0 are ignored by every stage, any other value is usable (COLMAP's and OpenSfM's
convention; a colour image counts a pixel usable when any colour channel is nonzero, and with
an alpha channel only where it is not fully transparent: a mask painted black on an opaque
layer and one cut out as transparency both work). Errors name camera.yaml's line and say what
to do. An empty value (``mask:``) means no mask."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from roadsurf.core.errors import DriveFormatError
from roadsurf.core.imagemask import ImageMask

# Below this share of usable pixels a mask leaves too little road to reconstruct (a 640 x 480
# frame keeps 31,000 px): almost certainly an inverted mask (0 = road)
MIN_USABLE_SHARE = 0.1
# Above this share masked the run goes on with a warning (a bonnet and a stamp hide 10-25 %)
WARN_MASKED_SHARE = 0.5


def load_mask(
    value: object, yaml_path: Path, where: str, width: int, height: int
) -> ImageMask | None:
    """The ``mask`` value of camera.yaml ``yaml_path`` (``where``: its file:line) as an
    ImageMask of the camera's ``width`` x ``height``; None for an empty value. Raises
    DriveFormatError."""
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    if not isinstance(value, str):
        raise DriveFormatError(
            f"{where}: camera.yaml 'mask' must be the path of an image (relative to camera.yaml's "
            f"folder), got {value!r}. Its 0 pixels are ignored (a burned-in stamp, the bonnet)."
        )
    path = Path(value.strip())
    if not path.is_absolute():
        path = yaml_path.parent / path
    if not path.is_file():
        what = "a folder, not an image file" if path.is_dir() else "does not exist"
        raise DriveFormatError(
            f"{where}: camera.yaml 'mask' names {path}, which {what}. Put the mask image "
            "there (same size as the frames, 0 = ignore) or remove the key."
        )
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DriveFormatError(
            f"{where}: camera.yaml 'mask' {path} cannot be read as an image. Save it as an 8-bit "
            "PNG of the frames' size (0 = ignore, 255 = road)."
        )
    if img.ndim == 3 and img.shape[2] == 4:  # colour any nonzero, and not transparent
        usable = np.asarray(img[..., :3].any(axis=2) & (img[..., 3] > 0), bool)
    elif img.ndim == 3:
        usable = np.asarray(img.any(axis=2), bool)
    else:
        usable = np.asarray(img != 0, bool)
    if usable.shape != (height, width):
        raise DriveFormatError(
            f"{where}: camera.yaml 'mask' {path} is {usable.shape[1]} x {usable.shape[0]} px, the "
            f"camera's images are {width} x {height}. The mask must be the frames' size (masks "
            "of a resized or rotated image do not carry over)."
        )
    share = float(usable.mean())
    if share < MIN_USABLE_SHARE:
        raise DriveFormatError(
            f"{where}: camera.yaml 'mask' {path} leaves {share:.1%} of the image usable. Pixels "
            "of value 0 are IGNORED and all others used: is the mask inverted (0 = road)?"
        )
    return ImageMask(usable, str(path))


def mask_warning(mask: ImageMask) -> str | None:
    """A drive warning for a mask that hides most of the image, else None."""
    if mask.masked_share <= WARN_MASKED_SHARE:
        return None
    return (
        f"{mask.source}: the camera's mask hides {mask.masked_share:.0%} of every image; the "
        "road is measured only in the rest. Check that 0 marks what is NOT road."
    )
