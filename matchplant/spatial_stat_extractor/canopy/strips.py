"""Outlines and canopy statistics of a whole field in bounded memory: strip by strip, in parallel.

:func:`~matchplant.spatial_stat_extractor.canopy.segmentation.segment` reads the CHM in strips of rows across the
whole field; each strip's window costs about :data:`BYTES_PER_PIXEL` bytes per pixel while it is
outlined (the CHM as float64, its filtered copies, label images) and each canopy pixel then costs as much
again while its statistics are gathered. Here the strip height comes from the memory budget (``max_memory``
divided among the worker processes), and each strip runs as one band: outlined, every trait measured over
its plants' canopy pixels, and only the per-plant results kept (a few numbers and an outline per plant).
The pixels of a strip are freed before the next, so memory depends on the setting and the field's width,
never on its length or its number of plants.

Strips are independent (each reads its own window with the boxes that cross its edges, and every plant near
it competes for the canopy as in one pass over the field), so they run in a process pool when more cores
are available, with the same results as one process. A process pool rather than threads: the labelling,
watershed and polygon tracing hold the GIL for much of their time; rather than Dask: each strip is one
whole job with its own raster reads, there is no array graph to schedule, and a pool needs no new
dependency. A plant whose box is a second box of a plant in another strip (``duplicate``) takes that
plant's outline and canopy values afterwards, as in one pass.
"""

from __future__ import annotations

import contextlib
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
import rasterio
import shapely

from matchplant.core.runtime.cores import usable_cores
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.spatial_stat_extractor.canopy.grid import STRIP_ROWS, home_strip, plant_windows
from matchplant.spatial_stat_extractor.canopy.memory import format_memory, gdal_cache_bytes
from matchplant.spatial_stat_extractor.canopy.outlines import Outlines, SegmentSettings
from matchplant.spatial_stat_extractor.canopy.segmentation import segment
from matchplant.spatial_stat_extractor.canopy.stats import gather, grouped_stats
from matchplant.spatial_stat_extractor.inputs import Layer, open_layer
from matchplant.spatial_stat_extractor.zonal import zonal_stats

log = get_logger("spatial_stat_extractor.strips")

# peak bytes per pixel of a strip's window (its rows and the halo of a box's height above and below), outlining
# and measuring together, from /proc's high-water mark over one band: 24 B for the CHM alone (the survey bench,
# 713 MB over 30 Mpx at 30,000 px wide); 46 B with an NDVI mask and the demo's multispectral and RGB layers
# measured on the canopy (its noisy field, 505 MB over 10.9 Mpx). The rest of max_memory (the plants, tables,
# GDAL's cache: about 1 GB for 100,000 plants) must fit beside the strips, so 64 keeps a masked survey within
# its budget. Every strip repeats its halo's work, so strips as tall as the budget allows (at most
# MAX_STRIP_ROWS) cost least: 764-row strips across 30,000 px outlined 1.26x the pixels they own.
BYTES_PER_PIXEL = 64
STRIP_SHARE = 0.75  # of max_memory for the strips in flight; the rest: polygons, tables, outlines, GDAL cache
# (the survey bench's whole module peaked at 1.8 GB of max_memory 3GB with half of it for the strips)
MIN_STRIP_ROWS = 64
MAX_STRIP_ROWS = 4 * STRIP_ROWS


@dataclass
class Measure:
    """One trait measured over every plant's canopy: columns ``<prefix>_<stat>``."""

    prefix: str
    layer: Layer
    stats: tuple
    percentiles: tuple


@dataclass
class _Job:
    geoms: np.ndarray
    chm: Layer
    mask: Layer | None
    nodata: float | None
    settings: SegmentSettings
    seeds: np.ndarray | None
    measures: list
    strip_rows: int
    gdal_cache_bytes: int
    windows: np.ndarray | None = None  # each plant's window (grid.plant_windows), found once for every band


def plan_strips(
    geoms, transform, width: int, height: int, margin: float, *, budget: int, workers: int
) -> tuple[int, int]:
    """Rows per strip and the number of strips for a per-process share of ``budget`` bytes."""
    res = float(np.sqrt(abs(transform.a * transform.e - transform.b * transform.d)))
    b = shapely.bounds(np.asarray(geoms, dtype=object))
    tall = np.nan_to_num((b[:, 3] - b[:, 1]) / res, nan=0.0)
    pad = int(np.ceil(tall.max() + 2 * margin / res)) + 2 if len(tall) else 0
    per_process = budget * STRIP_SHARE / max(workers, 1)
    # a strip reads its rows plus a box's height above and below (the boxes crossing its edges)
    rows = int(per_process / (BYTES_PER_PIXEL * max(width, 1))) - 2 * pad
    rows = int(np.clip(rows, MIN_STRIP_ROWS, MAX_STRIP_ROWS))
    return rows, max(1, -(-height // rows))


def _measure(o: Outlines, rows: np.ndarray, src, m: Measure) -> dict[str, np.ndarray]:
    """Statistics of ``src`` over the canopies of plants ``rows`` (pixels on the CHM's grid, else the outline
    polygons: pixel centres inside)."""
    if o.same_grid(src):  # one window: the band's own (the CHM's is kept: _LastWindow)
        got = grouped_stats(gather(o, src, strip_rows=o.height), o.start, list(m.stats), list(m.percentiles))
        return {f"{m.prefix}_{k}": v[rows] for k, v in got.items()}
    res = zonal_stats(o.geometry[rows], src, list(m.stats), list(m.percentiles), mode="center")
    return {f"{m.prefix}_{c}": res.stats[c] for c in res.columns}


def _open_all(job: _Job, stack: contextlib.ExitStack) -> tuple:
    """The CHM, the mask and each measure's source (one per measure, in order)."""
    chm = open_layer(job.chm, stack, job.nodata)
    mask = open_layer(job.mask, stack, job.nodata) if job.mask is not None else None
    return chm, mask, [chm if m.layer == job.chm else open_layer(m.layer, stack, job.nodata) for m in job.measures]


class _LastWindow:
    """A raster source that keeps its last window: the CHM of one band, read once for the outlines, then serves
    the canopy statistics' reads inside that window (decompressing the strip again cost a tenth of the
    outlining time). The array is shared, not copied: neither the outlining nor the gathering writes into it."""

    def __init__(self, source):
        self.source = source
        self.transform, self.width, self.height = source.transform, source.width, source.height
        self.crs = getattr(source, "crs", None)
        self._bounds: tuple[int, int, int, int] | None = None
        self._data: np.ndarray | None = None

    def read(self, row0: int, row1: int, col0: int, col1: int) -> np.ndarray:
        b = self._bounds
        if b is not None and b[0] <= row0 and row1 <= b[1] and b[2] <= col0 and col1 <= b[3]:
            return self._data[row0 - b[0] : row1 - b[0], col0 - b[2] : col1 - b[2]]
        self._data, self._bounds = self.source.read(row0, row1, col0, col1), (row0, row1, col0, col1)
        return self._data


def band_plants(win_i: np.ndarray, height: int, band: tuple[int, int], strip_rows: int) -> np.ndarray:
    """The plants a band of strips needs, in their order: those at home in it (off the raster too), and every
    plant whose window comes within two windows' height of it, a superset of the neighbours that compete
    for its canopy (a strip reads its home plants' windows plus the tallest one's height around them). A band
    that handled the whole field's plants cost time with the field's plant count in every band: 74 bands of
    100,000 plants on the survey bench."""
    tall = int(max(0, (win_i[:, 3] - win_i[:, 1]).max(initial=0)))
    r0, r1 = band[0] * strip_rows - 2 * tall, band[1] * strip_rows + 2 * tall
    home = home_strip(win_i, height, strip_rows)
    return np.flatnonzero(((home >= band[0]) & (home < band[1])) | ((win_i[:, 3] > r0) & (win_i[:, 1] < r1)))


def _run_band(job: _Job, band: tuple[int, int] | None, sources: tuple) -> dict:
    """Outline one band of strips and measure its plants; only per-plant results come back."""
    chm, mask, measured = sources
    kept = _LastWindow(chm)  # for this band only: its window is freed with it
    chm, measured = kept, [kept if src is chm else src for src in measured]
    sub = np.arange(len(job.geoms)) if band is None else band_plants(job.windows, chm.height, band, job.strip_rows)
    o = segment(
        job.geoms[sub],
        chm,
        job.settings,
        mask_source=mask,
        seeds=None if job.seeds is None else job.seeds[sub],
        strip_rows=job.strip_rows,
        band=band,
    )
    rows = np.flatnonzero(o.flag != "skipped")
    cols: dict[str, np.ndarray] = {}
    if len(rows):
        for m, src in zip(job.measures, measured):
            cols.update(_measure(o, rows, src, m))
    of = o.duplicate_of[rows]
    return {
        "rows": sub[rows],
        "geometry": o.geometry[rows],
        "tight_box": o.tight_box[rows],
        "top": o.top[rows],
        "pixels": o.pixels[rows],
        "area": o.area[rows],
        "volume": o.volume[rows],
        "flag": o.flag[rows],
        "duplicate_of": np.where(of >= 0, sub[np.maximum(of, 0)], -1),
        "unclaimed": o.unclaimed,
        "faint": o.faint,
        "noise_bumps": o.noise_bumps,
        "cols": cols,
        "transform": o.transform,
        "width": o.width,
        "height": o.height,
        "crs": o.crs,
    }


_worker: dict = {}


def _init_worker(job: _Job) -> None:
    # once per worker process: the job, and the rasters opened for the life of the process
    stack = contextlib.ExitStack()
    stack.enter_context(rasterio.Env(GDAL_CACHEMAX=job.gdal_cache_bytes))
    _worker.update(job=job, stack=stack, sources=_open_all(job, stack))


def _worker_band(band: tuple[int, int]) -> dict:
    return _run_band(_worker["job"], band, _worker["sources"])


def outline_field(
    geoms,
    chm_layer: Layer,
    mask_layer: Layer | None,
    measures: list[Measure],
    s: SegmentSettings,
    *,
    nodata: float | None,
    seeds: np.ndarray | None,
    max_memory: int,
    workers: int = 0,
) -> tuple[Outlines, dict[str, np.ndarray]]:
    """Outlines of every plant and its canopy statistics (``measures``), strip by strip within ``max_memory``
    bytes, with ``workers`` processes (0: one per core). Returns a compact :class:`Outlines` (no canopy
    pixels kept) and the columns ``<measure prefix>_<stat>``."""
    geoms = np.asarray(geoms, dtype=object)
    with contextlib.ExitStack() as stack:
        base = _Job(geoms, chm_layer, mask_layer, nodata, s, seeds, measures, 0, 0)
        return _outline_field(base, _open_all(base, stack), max_memory, workers)


def _outline_field(base: _Job, local: tuple, max_memory: int, workers: int) -> tuple[Outlines, dict[str, np.ndarray]]:
    """:func:`outline_field` with its rasters open (``local``): plan the strips, then run them here or in
    worker processes."""
    geoms, s = base.geoms, base.settings
    n = len(geoms)
    chm = local[0]
    cores = usable_cores()[0]
    want = cores if workers == 0 else workers
    rows, count = plan_strips(geoms, chm.transform, chm.width, chm.height, s.margin, budget=max_memory, workers=want)
    want = max(1, min(want, count))
    if want > 1:  # fewer processes when each would get too thin a strip
        rows, count = plan_strips(
            geoms, chm.transform, chm.width, chm.height, s.margin, budget=max_memory, workers=want
        )
    job = replace(
        base,
        strip_rows=rows,
        gdal_cache_bytes=gdal_cache_bytes(max_memory // want),
        windows=plant_windows(geoms, chm.transform, s, base.seeds)[1],
    )
    log.info(
        "outlines: %d strip(s) of %d rows across %d columns (max_memory %s: ~%s per strip), %d worker "
        "process(es) of %d core(s)",
        count,
        rows,
        chm.width,
        format_memory(max_memory),
        format_memory(BYTES_PER_PIXEL * chm.width * rows),
        want,
        cores,
    )
    bands = [(k, k + 1) for k in range(count)]
    bar = progress(None, desc="outlines + canopy statistics", total=count, unit="strip")
    try:
        if want == 1:
            parts = []
            for band in bands:
                parts.append(_run_band(job, band if count > 1 else None, local))
                bar.update(1)
        else:
            # spawn: a clean interpreter per worker (forking a process holding GDAL and numba threads is unsafe)
            ctx = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(
                max_workers=want, mp_context=ctx, initializer=_init_worker, initargs=(job,)
            ) as pool:
                parts = []
                for part in pool.map(_worker_band, bands):
                    parts.append(part)
                    bar.update(1)
    finally:
        bar.close()
    return _merge(parts, n, geoms)


def _merge(parts: list[dict], n: int, geoms: np.ndarray) -> tuple[Outlines, dict[str, np.ndarray]]:
    """One :class:`Outlines` and one set of columns from the strips' results (a plant's values come from the
    strip it belongs to; a plant off the raster is in every strip, with the same values)."""
    first = parts[0]
    geometry = geoms.copy()
    tight, top = np.full((n, 4), np.nan), np.full((n, 3), np.nan)
    pixels, area, volume = np.zeros(n, np.int64), np.zeros(n), np.full(n, np.nan)
    flag = np.full(n, "outside", dtype=object)
    of = np.full(n, -1, np.int64)
    cols = {k: np.full(n, np.nan) for p in parts for k in p["cols"]}
    for p in parts:
        r = p["rows"]
        geometry[r], tight[r], top[r], pixels[r], area[r], volume[r], flag[r] = (
            p["geometry"],
            p["tight_box"],
            p["top"],
            p["pixels"],
            p["area"],
            p["volume"],
            p["flag"],
        )
        of[r] = p["duplicate_of"]
        for k, v in p["cols"].items():
            cols[k][r] = v
    # a second box of a plant homed in another strip: that plant's outline and canopy (as in one pass)
    d = np.flatnonzero((flag == "duplicate") & (of >= 0))
    o = of[d]
    d, o = d[flag[o] == ""], o[flag[o] == ""]
    if len(d):
        geometry[d], tight[d], pixels[d], area[d], volume[d] = geometry[o], tight[o], pixels[o], area[o], volume[o]
        for v in cols.values():
            v[d] = v[o]
    unclaimed = np.concatenate([p["unclaimed"] for p in parts]) if parts else np.zeros((0, 4))
    faint = np.concatenate([p["faint"] for p in parts]) if parts else np.zeros((0, 4))
    out = Outlines(
        geometry=geometry,
        tight_box=tight,
        top=top,
        pixels=pixels,
        area=area,
        volume=volume,
        flag=flag,
        pix=np.zeros(0, np.int64),
        start=np.zeros(n + 1, np.int64),
        transform=first["transform"],
        width=first["width"],
        height=first["height"],
        crs=first["crs"],
        unclaimed=unclaimed,
        faint=faint,
        noise_bumps=sum(p["noise_bumps"] for p in parts),
        duplicate_of=of,
    )
    return out, cols
