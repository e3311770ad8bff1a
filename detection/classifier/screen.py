"""CNN screening of a drive: p_defect for every frame, in batches (dissertation Fig. 5.6)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from detection.classifier.config import ClassifierConfig
from detection.classifier.modelfile import load_model
from detection.classifier.network import pick_device
from detection.classifier.screen_input import FramePrefetch, model_input_sizes, screen_threads
from roadsurf.drive import Drive, Frame, load_drive
from roadsurf.errors import RoadsurfError

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

    def frames() -> Sequence[Frame]:  # after the model: a bad model file is reported first
        return (drive if isinstance(drive, Drive) else load_drive(drive)).frames

    return screen_frames(model_path, frames, cfg, progress=progress)


def screen_frames(
    model_path: str | Path,
    frames: Sequence[Frame] | Callable[[], Sequence[Frame]] | FramePrefetch,
    cfg: ClassifierConfig | None = None,
    *,
    progress: bool = True,
) -> dict[str, float]:
    """``screen_drive`` on frames in capture order -> {filename: p_defect}. ``frames`` may be
    a callable, called once the model is loaded, or a ``FramePrefetch`` already preparing them
    (the screening worker process starts one before it imports torch)."""
    cfg = cfg or ClassifierConfig()
    threads = screen_threads(cfg)
    before = torch.get_num_threads()
    if threads > 0:
        torch.set_num_threads(threads)
    try:
        return _screen(model_path, frames, cfg, progress)
    finally:
        torch.set_num_threads(before)


def _screen(
    model_path: str | Path,
    frames_in: Sequence[Frame] | Callable[[], Sequence[Frame]] | FramePrefetch,
    cfg: ClassifierConfig,
    progress: bool,
) -> dict[str, float]:
    device = pick_device(cfg.device)
    net, meta = load_model(model_path, device)
    sizes = model_input_sizes(meta, cfg)
    pre = frames_in if isinstance(frames_in, FramePrefetch) else None
    if pre is not None and pre.sizes != sizes:  # the model file changed since it was started
        log.warning("screening: the model's input sizes changed; preparing the frames again")
        pre.close()
        pre = None
        frames_in = frames_in.frames()
    if pre is None:
        # frames are decoded and thumbnailed by threads (OpenCV releases the GIL) up to two
        # batches ahead of the network, so decoding overlaps inference; memory stays bounded
        pre = FramePrefetch(
            frames_in,  # type: ignore[arg-type]
            *sizes,
            workers=max(1, screen_threads(cfg)),
            ahead=2 * max(1, cfg.screen_batch_size),
        )
    try:
        return _run_net(net, pre, device, cfg, progress, model_path)
    finally:
        pre.close()


def _run_net(
    net: Any,
    pre: FramePrefetch,
    device: Any,
    cfg: ClassifierConfig,
    progress: bool,
    model_path: str | Path,
) -> dict[str, float]:
    frames = pre.frames()
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

    bar = tqdm(total=len(frames), desc="CNN screening", unit="frame", disable=not progress)
    with bar:
        for fr, x in pre:
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
