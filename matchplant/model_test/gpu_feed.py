"""Module 7 on a CUDA GPU (issue 38): the photos decoded ahead of the GPU, the tiles cut from the photo on the GPU,
batches sized from its free memory, bf16 autocast where supported. On a CPU nothing here applies: detection reads,
cuts and predicts exactly as :mod:`matchplant.model_test.tiles` does there (the same boxes). Every part reads the
run's :class:`~matchplant.detection.gpu.Runtime` (a bare device is turned into one by the same chooser).

- :func:`decoded`: the photos as RGB arrays in order, decoded by a few threads ahead of the GPU (OpenCV's decoder
  releases the GIL), so the GPU does not wait on JPEG decoding of 20 MP photos;
- :class:`DevicePredictor`: one photo sent to the GPU once (pinned, non-blocking), its tiles taken as views of that
  tensor (the tiles :func:`~matchplant.model_test.tiles.detect_image` cuts are views of the photo: their place in it
  is read from their address), so a tile is never copied on the host;
- :func:`detections`: two photos in flight, so that one photo's merge (CPU) overlaps the next one's tiles on the GPU;
- :func:`detect_batch`: tiles per batch from the GPU's free memory when ``batch_size`` is left at its default.
"""

from __future__ import annotations

import dataclasses
import os
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from matchplant.core.formats.images import read_rgb8
from matchplant.core.runtime.log import get_logger
from matchplant.detection.gpu import Runtime, as_runtime
from matchplant.model_test.config import ModelTestConfig

log = get_logger("model_test")

# GPU memory per input pixel of a tile in inference (ResNet-50 FPN, mixed precision, activations and the RPN's
# proposals), generous: a batch of 1024 px tiles then takes about 0.4 GB per tile
BYTES_PER_INPUT_PIXEL = 400
MAX_BATCH = 32  # larger batches fill the GPU no more
MEMORY_SHARE = 0.5  # of the free memory, for the batch
DEFAULT_BATCH = next(f.default for f in dataclasses.fields(ModelTestConfig) if f.name == "batch_size")


def decoded(indices: Iterable[int], files: list[Path], runtime, read: Callable = read_rgb8) -> Iterator[tuple]:
    """``(index, RGB array)`` of ``files[index]`` for each index in order; decoded by threads, up to the runtime's
    ``decode_ahead`` photos ahead (CUDA: :data:`~matchplant.detection.gpu.AHEAD`); with none, one after another (as
    module 7 always did on a CPU)."""
    indices, ahead = list(indices), as_runtime(runtime).decode_ahead
    if not ahead:
        for i in indices:
            yield i, read(files[i])
        return
    workers = max(1, min(ahead, (os.cpu_count() or 2) - 1))
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="decode") as pool:
        pending: deque = deque()
        it = iter(indices)
        for i in it:
            pending.append((i, pool.submit(read, files[i])))
            if len(pending) >= ahead:
                break
        while pending:
            i, future = pending.popleft()
            nxt = next(it, None)
            if nxt is not None:
                pending.append((nxt, pool.submit(read, files[nxt])))
            yield i, future.result()


def detections(
    indices, files: list[Path], runtime, predictor, detect: Callable, *, threads: int | None = None, read=read_rgb8
):
    """``(index, photo, detect(photo, predictor, counts), counts)`` for each photo in order. The runtime's
    ``photos_in_flight`` (CUDA: two; ``threads`` overrules it) are detected at once by as many threads, so that one
    photo's merge of its tiles' boxes (CPU work) runs while the GPU detects on the next; with none, one after
    another, as module 7 always did on a CPU."""
    runtime = as_runtime(runtime)
    threads = runtime.photos_in_flight if threads is None else threads
    photos = decoded(indices, files, runtime, read)

    def one(img):
        counts: dict = {}
        if isinstance(predictor, DevicePredictor):
            predictor.use(img)  # the photo on the GPU once; its tiles are cut there
        return detect(img, predictor, counts), counts

    if not threads:
        for i, img in photos:
            yield (i, img, *one(img))
        return
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="detect") as pool:
        pending: deque = deque()
        for i, img in photos:
            pending.append((i, img, pool.submit(one, img)))
            if len(pending) >= threads:
                j, im, future = pending.popleft()
                yield (j, im, *future.result())
        while pending:
            j, im, future = pending.popleft()
            yield (j, im, *future.result())


def detect_batch(batch_size: int, runtime, tile: int, model_config: dict) -> int:
    """``batch_size`` as set; at its default where the runtime sizes it from memory (CUDA), as many tiles as
    :data:`MEMORY_SHARE` of the free memory holds (at most :data:`MAX_BATCH`), logged."""
    runtime = as_runtime(runtime)
    if not runtime.batch_from_memory or batch_size != DEFAULT_BATCH:
        return batch_size
    device = runtime.device
    import torch  # lazy: PyTorch is heavy; configs load without it

    min_size, max_size = int(model_config.get("min_size", 800)), int(model_config.get("max_size", 1333))
    free, _ = torch.cuda.mem_get_info(device)
    side = max(min_size, min(tile * max(min_size / tile, 1.0), max_size))
    per_tile = BYTES_PER_INPUT_PIXEL * side * side
    batch = int(max(1, min(MAX_BATCH, MEMORY_SHARE * free // per_tile)))
    log.info("batch_size: %d tiles (%.0f GB free on %s)", batch, free / 1e9, device)
    return batch


def device_predictor(model, runtime: Runtime) -> DevicePredictor | None:
    """Where the runtime cuts tiles on the device (CUDA), its predictor (bf16 where supported; warmed up, so that the
    estimate times the model and not cuDNN's first choices); None elsewhere (module 7's own predictor then)."""
    if not runtime.tiles_on_device:
        return None
    predictor = DevicePredictor(model, runtime, runtime.amp, runtime.amp_dtype)
    predictor([np.zeros((64, 64, 3), np.uint8)])
    return predictor


class DevicePredictor:
    """The module's predictor on CUDA: ``(boxes, scores, labels)`` per tile, the tiles cut from the photo on the
    GPU. Call :meth:`use` with each photo before detecting on it. ``runtime``: the run's
    :class:`~matchplant.detection.gpu.Runtime` (or a bare device); ``amp``, ``dtype``: its autocast."""

    def __init__(self, model, runtime, amp: bool, dtype):
        self.runtime = as_runtime(runtime, amp)
        self.model, self.device, self.amp, self.dtype = model, self.runtime.device, amp, dtype
        self._photo = threading.local()  # each detecting thread has its photo (:func:`detections`)

    @property
    def image(self) -> np.ndarray | None:
        """The photo in use by this thread (None before :meth:`use`)."""
        return getattr(self._photo, "image", None)

    def use(self, image: np.ndarray) -> None:
        """Send ``image`` to the device once; the tiles this thread detects next are cut from it there."""
        import torch  # lazy: PyTorch is heavy; configs load without it

        self._photo.image = image
        host = torch.from_numpy(image)
        if self.runtime.pin_memory:  # pinned: the copy runs while the host goes on
            host = host.pin_memory()
        self._photo.on_device = host.to(self.device, non_blocking=True).permute(2, 0, 1)  # 3 x H x W uint8

    def _place(self, tile: np.ndarray) -> tuple[int, int] | None:
        """Where ``tile`` lies in the photo in use (row, column), or None when it is not a view of it."""
        base = self.image
        if base is None or tile.base is None or not base.flags.c_contiguous or tile.dtype != base.dtype:
            return None
        offset = tile.ctypes.data - base.ctypes.data
        if offset < 0 or offset >= base.nbytes or tile.strides != base.strides:
            return None
        return offset // base.strides[0], (offset % base.strides[0]) // base.strides[1]

    def _tensor(self, tile: np.ndarray):
        """``tile`` as a 3 x H x W uint8 tensor on the device: a view of the photo there, or sent on its own."""
        import torch  # lazy: PyTorch is heavy; configs load without it

        place = self._place(tile)
        if place is None:  # not a view of the photo in use (the estimate's probe tile): sent on its own
            return torch.from_numpy(np.ascontiguousarray(tile)).to(self.device).permute(2, 0, 1)
        (y0, x0), (h, w) = place, tile.shape[:2]
        return self._photo.on_device[:, y0 : y0 + h, x0 : x0 + w]

    def __call__(self, tiles: list[np.ndarray]):
        """``(boxes xyxy, scores, labels)`` per tile, on the host."""
        import torch  # lazy: PyTorch is heavy; configs load without it

        batch = [self._tensor(t).float().div_(255.0) for t in tiles]
        with (
            torch.inference_mode(),
            torch.autocast(device_type=self.runtime.kind, enabled=self.amp, dtype=self.dtype),
        ):
            outputs = self.model(batch)
        return [
            (o["boxes"].float().cpu().numpy(), o["scores"].float().cpu().numpy(), o["labels"].cpu().numpy())
            for o in outputs
        ]
