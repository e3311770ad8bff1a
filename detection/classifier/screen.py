"""CNN screening of a drive: p_defect for every frame, in batches (dissertation Fig. 5.6)."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from roadsurf.core.errors import RoadsurfError
from roadsurf.core.imagemask import ImageMask
from roadsurf.core.parallel import ordered_map
from roadsurf.detection.classifier.config import ClassifierConfig
from roadsurf.detection.classifier.dataset import thumbnail, to_input
from roadsurf.detection.classifier.modelfile import load_model
from roadsurf.detection.classifier.network import pick_device
from roadsurf.io.drive import Drive, Frame, load_drive, read_image

log = logging.getLogger(__name__)


def screen_drive(
    model_path: str | Path,
    drive: Drive | str | Path,
    cfg: ClassifierConfig | None = None,
    *,
    progress: bool = True,
) -> dict[str, float]:
    """p_defect in [0, 1] for every readable frame of ``drive`` -> {filename: p_defect}.

    Frames that cannot be read are left out (the loader reports them). Images go through the same
    ``thumbnail``/``to_input`` preprocessing as the training set, at the model's own sizes.
    Raises ``ModelFileError`` when the model file is missing, corrupt or incompatible.
    """

    src = drive

    def loaded() -> Drive:  # after the model: a bad model file is reported first
        nonlocal src
        if not isinstance(src, Drive):
            src = load_drive(src)
        return src

    return screen_frames(
        model_path, lambda: loaded().frames, cfg, progress=progress,
        mask=lambda: loaded().camera.mask,
    )  # fmt: skip


def screen_frames(
    model_path: str | Path,
    frames: Sequence[Frame] | Callable[[], Sequence[Frame]],
    cfg: ClassifierConfig | None = None,
    *,
    progress: bool = True,
    mask: ImageMask | Callable[[], ImageMask | None] | None = None,
) -> dict[str, float]:
    """``screen_drive`` on frames in capture order -> {filename: p_defect}. ``frames`` may be
    a callable, called once the model is loaded (the screening worker process loads the model
    while its parent is still reading the drive); so may the camera's image ``mask``
    (``thumbnail``), called after ``frames``."""
    cfg = cfg or ClassifierConfig()
    threads = screen_threads(cfg)
    before = torch.get_num_threads()
    if threads > 0:
        torch.set_num_threads(threads)
    try:
        return _screen(model_path, frames, cfg, progress, mask)
    finally:
        torch.set_num_threads(before)


def screen_threads(cfg: ClassifierConfig) -> int:
    """torch threads for screening: ``screen_num_threads`` capped at the usable cores, else
    ``num_threads`` (0 = torch's default)."""
    if cfg.screen_num_threads > 0:
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            cores = os.cpu_count() or 1
        return max(1, min(int(cfg.screen_num_threads), cores))
    return max(0, int(cfg.num_threads))


def _screen(
    model_path: str | Path,
    frames_or_get: Sequence[Frame] | Callable[[], Sequence[Frame]],
    cfg: ClassifierConfig,
    progress: bool,
    mask_or_get: ImageMask | Callable[[], ImageMask | None] | None,
) -> dict[str, float]:
    device = pick_device(cfg.device)
    net, meta = load_model(model_path, device)
    frames = list(frames_or_get() if callable(frames_or_get) else frames_or_get)
    mask = mask_or_get() if callable(mask_or_get) else mask_or_get
    store = int(meta.get("store_size_px", cfg.store_size_px))
    side = int(meta["input_size_px"])
    t0 = time.perf_counter()
    out: dict[str, float] = {}
    names: list[str] = []
    batch: list[np.ndarray] = []

    def flush() -> None:
        if not batch:
            return
        x = torch.from_numpy(np.stack(batch)).unsqueeze(1).to(device)
        with torch.no_grad():
            p = net.predict_proba(x)[:, 1].float().cpu().numpy()
        out.update(zip(names, (float(v) for v in p), strict=True))
        names.clear()
        batch.clear()

    def prepare(fr: Frame) -> np.ndarray | RoadsurfError:
        try:
            return to_input(thumbnail(read_image(fr), store, mask), side)
        except RoadsurfError as e:
            return e

    # frames are decoded and thumbnailed by worker threads (OpenCV releases the GIL) up to two
    # batches ahead of the network, so decoding overlaps inference; memory stays bounded
    workers = max(1, screen_threads(cfg))
    ahead = 2 * max(1, cfg.screen_batch_size)
    bar = tqdm(total=len(frames), desc="CNN screening", unit="frame", disable=not progress)
    with bar:
        for fr, x in zip(frames, ordered_map(prepare, frames, workers, ahead), strict=True):
            bar.update(1)
            if isinstance(x, RoadsurfError):
                log.warning("%s: not screened (%s)", fr.path, x)
                continue
            batch.append(x)
            names.append(fr.filename)
            if len(batch) >= cfg.screen_batch_size:
                flush()
    flush()
    dt = time.perf_counter() - t0
    log.info(
        "screened %d frames in %.2f s (%.1f ms/frame) with %s",
        len(out),
        dt,
        1e3 * dt / max(1, len(out)),
        model_path,
    )
    return out
