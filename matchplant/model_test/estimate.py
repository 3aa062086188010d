"""How long detection will take, before it starts (issue 29): from the actual tiles of every photo and the
network input size of each tile, timed on this device.

A tile of ``t`` px is resized by the detector to its ``min_size`` (short side; long side at most ``max_size``)
before the network sees it, so its cost grows with the *input* pixels, not the photo's: 128 px tiles enlarged
to 800 px cost ~39x their own pixels, and a 1000 x 750 photo cut into 128 px tiles costs about 12x the same photo
in 1024 px tiles. :func:`plan` counts each photo's tiles (module 7's own grid) and their input pixels; one
timed pass of the model on a real tile of the first photo gives this device's seconds per input megapixel
(:func:`probe`; on a GPU a warm pass of the run's batch of tiles); the estimate is their product. A warning comes before
any work that will take longer than :data:`WARN_AFTER_S`.
"""

from __future__ import annotations

import math
import time

import numpy as np

from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import duration
from matchplant.detection.gpu import as_runtime
from matchplant.detection.objects import input_scale

log = get_logger("model_test")

WARN_AFTER_S = 180.0  # "more than a few minutes"
PAD = 32  # torchvision batches images padded to a multiple of 32 px


def _starts(length: int, tile: int, overlap: int) -> int:
    """How many tile origins module 7's grid has along one axis (``tiles.tile_starts``)."""
    return 1 if length <= tile else math.ceil((length - tile) / (tile - overlap)) + 1


def input_pixels(tw: int, th: int, min_size: int, max_size: int) -> float:
    """Pixels the network sees for a ``tw`` x ``th`` tile (resized, then padded to a multiple of 32)."""
    s = input_scale(tw, th, min_size, max_size)
    return math.ceil(tw * s / PAD) * PAD * math.ceil(th * s / PAD) * PAD


def plan(sizes: list[tuple[int, int]], tile: int, overlap: int, model_config: dict) -> dict:
    """Tiles and network input megapixels per photo and in all (``sizes``: width, height per photo)."""
    lo, hi = int(model_config.get("min_size", 800)), int(model_config.get("max_size", 1333))
    tiles, mpx = [], []
    for w, h in sizes:
        n = _starts(w, tile, overlap) * _starts(h, tile, overlap)
        tiles.append(n)
        mpx.append(n * input_pixels(min(tile, w), min(tile, h), lo, hi) / 1e6)
    photo_mpx = sum(w * h for w, h in sizes) / 1e6
    return {
        "photos": len(sizes),
        "tiles": int(sum(tiles)),
        "input_megapixels": float(sum(mpx)),
        "photo_megapixels": photo_mpx,
        "tiles_per_photo": [int(min(tiles)), int(max(tiles))],
        "input_per_photo_pixel": float(sum(mpx) / photo_mpx) if photo_mpx else 0.0,
    }


def probe(predictor, image: np.ndarray, tile: int, model_config: dict, batch: int = 1) -> float:
    """Seconds per network input megapixel on this device: one timed pass on the first tile of ``image``. With
    ``batch`` > 1 (a GPU, which detects many tiles per pass), a pass of ``batch`` copies of it after one untimed
    pass of the same shape: a GPU at one tile per pass is mostly idle, and its first pass at a new batch pays
    for memory and kernel choices, so one cold tile would overstate the time several-fold. On a CPU one tile's
    pass is what every tile costs, and a second pass of a large model would add seconds to minutes."""
    th, tw = min(tile, image.shape[0]), min(tile, image.shape[1])
    tiles = [np.ascontiguousarray(image[:th, :tw])] * max(batch, 1)
    if batch > 1:
        predictor(tiles)  # untimed: the first pass at this batch
    t0 = time.perf_counter()
    predictor(tiles)  # returns boxes on the host: the device's work is finished when it returns
    seconds = (time.perf_counter() - t0) / len(tiles)
    return seconds / (
        input_pixels(tw, th, int(model_config.get("min_size", 800)), int(model_config.get("max_size", 1333))) / 1e6
    )


def estimate(
    predictor,
    first_image: np.ndarray,
    sizes: list[tuple[int, int]],
    tile: int,
    overlap: int,
    model_config: dict,
    device,
    processes: int = 1,
    warn_after_s: float = WARN_AFTER_S,
    every: list[tuple[int, int]] | None = None,
    batch: int = 1,
) -> dict:
    """The plan, the probe and the estimated seconds (``processes``: a torchrun job shares the photos); logged,
    and a warning before a run longer than ``warn_after_s``. ``every``: the sizes of every photo when ``sizes``
    are a cover's (``detect.cover``): both estimates are logged side by side (``p["every_photo"]``). ``batch``: the
    tiles per pass the run will use where that changes the time per tile (a GPU; :func:`probe`)."""
    p = plan(sizes, tile, overlap, model_config)
    rate = probe(predictor, first_image, tile, model_config, batch)
    seconds = rate * p["input_megapixels"] / max(processes, 1)
    runtime = as_runtime(device)
    p.update(seconds_per_input_megapixel=rate, seconds=seconds, device=str(runtime.device))
    if every is not None:
        whole = plan(every, tile, overlap, model_config)
        whole["seconds"] = rate * whole["input_megapixels"] / max(processes, 1)
        p["every_photo"] = {k: whole[k] for k in ("photos", "tiles", "input_megapixels", "seconds")}
        log.info(
            "detection estimate: the cover's %d photo(s) about %s; every one of the %d photos about %s (%.0f %% of it)",
            p["photos"],
            duration(seconds),
            whole["photos"],
            duration(whole["seconds"]),
            100 * seconds / whole["seconds"] if whole["seconds"] else 100.0,
        )
    lo = int(model_config.get("min_size", 800))
    what = (
        f"{p['photos']} photo(s), {p['tiles']} tiles of {tile} px ({p['tiles_per_photo'][0]}"
        f"{'-' + str(p['tiles_per_photo'][1]) if p['tiles_per_photo'][1] != p['tiles_per_photo'][0] else ''} "
        f"per photo), each resized to the network's {lo} px input: {p['input_megapixels']:.1f} MP for the network, "
        f"{p['input_per_photo_pixel']:.1f}x the photos' own pixels; {rate:.2f} s per MP measured on {runtime.device}"
    )
    if seconds >= warn_after_s:
        hint = (
            " Larger tiles cost less: the enlargement of small tiles is paid quadratically (module 7 detects at "
            "the training scale; train on larger tiles, or a lower model.min_size, to detect faster)."
            if p["input_per_photo_pixel"] > 4
            else ""
        )
        gpu = " A CUDA GPU (device: auto picks it) is much faster." if runtime.on_cpu else ""
        log.warning("detection will take about %s: %s.%s%s", duration(seconds), what, hint, gpu)
    else:
        log.info("detection estimate: about %s (%s)", duration(seconds), what)
    return p
