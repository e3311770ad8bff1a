"""Screening input without torch: frames -> network inputs, prepared by threads ahead of the net.

``FramePrefetch`` decodes and thumbnails frames on background threads (OpenCV releases the GIL)
and hands them over in capture order. ``screen`` uses it to overlap decoding with inference. The
screening worker process (``screen_job``) starts one before it imports torch, so the 200 frames
of a long drive are ready when the 1.3-2 s import ends, and the net runs on inputs at once.
"""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from detection.classifier.config import ClassifierConfig
from detection.classifier.dataset import thumbnail, to_input
from roadsurf.drive import Frame, read_image
from roadsurf.errors import RoadsurfError
from roadsurf.parallel import ordered_map

Prepared = tuple[Frame, "np.ndarray | RoadsurfError"]
_END = object()


def screen_threads(cfg: ClassifierConfig) -> int:
    """Threads for screening (torch's, and the frame decoders'): ``screen_num_threads`` capped
    at the usable cores, else ``num_threads`` (0 = torch's default)."""
    if cfg.screen_num_threads > 0:
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            cores = os.cpu_count() or 1
        return max(1, min(int(cfg.screen_num_threads), cores))
    return max(0, int(cfg.num_threads))


def model_input_sizes(meta: Mapping[str, Any], cfg: ClassifierConfig) -> tuple[int, int]:
    """(thumbnail side, network input side) in px of a model from its metadata."""
    return int(meta.get("store_size_px", cfg.store_size_px)), int(meta["input_size_px"])


def frame_input(frame: Frame, store_px: int, side_px: int) -> np.ndarray | RoadsurfError:
    """One frame -> its (side_px, side_px) uint8 network input, through the training set's
    ``thumbnail``/``to_input``; an unreadable frame gives its error instead."""
    try:
        return to_input(thumbnail(read_image(frame), store_px), side_px)
    except RoadsurfError as e:
        return e


class FramePrefetch:
    """Prepares the network inputs of ``frames`` (a sequence, or a callable returning one,
    called on the background thread) in capture order, at most ``ahead`` frames ahead of the
    consumer. ``frames()`` waits for the frame list; iterating yields (frame, input or error).
    An error in getting the frames is raised to the consumer. ``close`` stops the threads."""

    def __init__(
        self,
        frames: Sequence[Frame] | Callable[[], Sequence[Frame]],
        store_px: int,
        side_px: int,
        workers: int,
        ahead: int,
    ) -> None:
        self.sizes = (int(store_px), int(side_px))
        self._q: queue.Queue[Any] = queue.Queue(maxsize=max(1, ahead))
        self._frames: list[Frame] | None = None
        self._error: BaseException | None = None
        self._listed = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, args=(frames, max(1, workers), max(1, ahead)), daemon=True
        )
        self._thread.start()

    def _run(self, frames: Any, workers: int, ahead: int) -> None:
        try:
            fl = list(frames() if callable(frames) else frames)
            self._frames = fl
            self._listed.set()
            store, side = self.sizes
            items = ordered_map(lambda f: frame_input(f, store, side), fl, workers, ahead)
            try:
                for fr, x in zip(fl, items, strict=True):
                    if not self._put((fr, x)):
                        return
            finally:
                items.close()  # cancels decodes not started yet
        except BaseException as e:  # noqa: BLE001 - handed to the consumer, which raises it
            self._error = e
        finally:
            self._listed.set()
            self._put(_END)

    def _put(self, item: Any) -> bool:
        while not self._stop.is_set():
            try:
                self._q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def frames(self) -> list[Frame]:
        """The frames, in capture order (waits until they are known)."""
        self._listed.wait()
        if self._frames is None:
            raise self._error if self._error is not None else RoadsurfError("no frames")
        return self._frames

    def __iter__(self) -> Iterator[Prepared]:
        while True:
            item = self._q.get()
            if item is _END:
                if self._error is not None:
                    raise self._error
                return
            yield item

    def close(self) -> None:
        self._stop.set()
        if self._listed.is_set():  # else the thread may wait on its frames (e.g. on stdin)
            self._thread.join()
