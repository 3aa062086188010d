"""The statistics table: one row per plant of every trait of every date, from the polygons and the rasters.

Each date's rasters come as layers (``date_sets``: anything with ``date`` and ``layers()``, as the settings'
:class:`~matchplant.spatial_stat_extractor.config.RasterSet`), each layer is read window by window
(:mod:`~matchplant.spatial_stat_extractor.inputs.rasters`) under the polygons, reprojected to the raster's CRS
where they differ, and measured exactly (:mod:`~matchplant.spatial_stat_extractor.zonal.engine`): ``mode: center``
equals rasterstats (pixel centres inside), ``mode: coverage`` equals exactextract (pixels weighted by covered
fraction). Wide layout: columns ``<trait>_<stat>[_<date>]``; long: one row per plant and date. What went wrong
where (plants outside a raster, plants with only nodata) goes into the report.

Library use::

    plants = read_polygons("plants.gpkg")  # inputs.polygons
    table, report = extract_stats(plants, [RasterSet(date="w3", dsm="dsm.tif", dtm="dtm.tif")])
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import rasterio
import shapely

from matchplant.core.formats.csv_table import write_table
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.io import atomic_open
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.spatial_stat_extractor.inputs import open_layer
from matchplant.spatial_stat_extractor.zonal.engine import zonal_stats
from matchplant.spatial_stat_extractor.zonal.names import DEFAULT_STATS

log = get_logger("spatial_stat_extractor")


# --------------------------------------------------------------------------------------------------
# extraction


def polygons_in(gdf, crs, layer_label: str, report: dict):
    """The polygons in the raster's CRS (reprojected when they differ)."""
    if crs is None:
        if gdf.crs is not None:
            log.warning("%s has no CRS; assuming it is in the polygons' CRS %s", layer_label, gdf.crs.to_string())
        return gdf.geometry.values
    if gdf.crs is None:
        log.warning(
            "the polygons have no CRS; assuming they are in the raster's CRS %s (set polygons_crs if not)",
            crs.to_string(),
        )
        return gdf.geometry.values
    if gdf.crs.equals(crs):
        return gdf.geometry.values
    log.info(
        "%s is in %s, the polygons in %s: reprojecting the polygons", layer_label, crs.to_string(), gdf.crs.to_string()
    )
    report["reprojected_from"] = gdf.crs.to_string()
    return gdf.to_crs(crs).geometry.values


def extract_stats(
    polygons,
    date_sets: Sequence,
    stats: Sequence[str] = DEFAULT_STATS,
    percentiles: Sequence[float] = (95,),
    mode: str = "center",
    *,
    nodata: float | None = None,
    layout: str = "wide",
    on_progress: Callable[[float, str], None] | None = None,
) -> tuple[pd.DataFrame, dict]:
    """Per-plant statistics of every trait of every date; returns the table and a report.

    ``polygons``: from :func:`read_polygons`. Wide layout: one row per plant, columns
    ``<trait>_<stat>`` (``_<date>`` appended when there are several dates); long: one row per plant and
    date with a ``date`` column. ``on_progress(fraction, message)`` is called as work proceeds.
    """
    jobs = [(s, layer) for s in date_sets for layer in s.layers()]
    if not jobs:
        raise ConfigError("no raster given", fix="set a CHM, a DSM + DTM, a multispectral raster or bands")
    several = len(date_sets) > 1
    ids = polygons["plant_id"].to_numpy()
    per_date: dict[str, pd.DataFrame] = {}
    report = {"plants": int(len(ids)), "mode": mode, "layers": []}
    bar = progress(None, desc="statistics", total=len(jobs), unit="raster")
    try:
        for k, (s, layer) in enumerate(jobs):
            label = f"{layer.name}" + (f" ({s.date})" if s.date else "")
            entry = {"date": s.date, "trait": layer.name, "kind": layer.kind, "files": [str(p) for p in layer.paths]}

            def step(done, total, k=k, label=label):
                if on_progress is not None:
                    on_progress((k + done / max(total, 1)) / len(jobs), f"{label}: batch {done}/{total}")

            with contextlib.ExitStack() as stack:
                src = open_layer(layer, stack, nodata, warp=False)  # degrees: the polygons reprojected, exact
                geoms = polygons_in(polygons, src.crs, f"raster {Path(layer.paths[0]).name}", entry)
                try:
                    res = zonal_stats(geoms, src, stats, percentiles, mode=mode, on_progress=step)
                except rasterio.errors.RasterioIOError as exc:  # a block past the end of a cut-off file
                    raise InputError(
                        f"{label}: a raster cannot be read part-way (truncated file?): {exc}",
                        path=", ".join(entry["files"]),
                        fix="copy or regenerate the raster (an interrupted copy or run)",
                    ) from exc
            _report_problems(entry, res, ids, label, polygons.attrs.get("source"))
            report["layers"].append(entry)
            table = per_date.setdefault(s.date, pd.DataFrame({"plant_id": ids}))
            for c in res.columns:
                table[f"{layer.name}_{c}"] = res.stats[c]
            bar.update(1)
    finally:
        bar.close()
    centroids = shapely.centroid(polygons.geometry.values)
    xy = pd.DataFrame({"x": shapely.get_x(centroids), "y": shapely.get_y(centroids)})
    if layout == "long" and several:
        frames = []
        for date, t in per_date.items():
            t = t.copy()
            t.insert(1, "date", date)
            frames.append(pd.concat([t.iloc[:, :2], xy, t.iloc[:, 2:]], axis=1))
        table = pd.concat(frames, ignore_index=True)
    else:
        table = pd.concat([pd.DataFrame({"plant_id": ids}), xy], axis=1)
        for date, t in per_date.items():
            suffix = f"_{date}" if several else ""
            table = pd.concat([table, t.drop(columns="plant_id").add_suffix(suffix)], axis=1)
    if on_progress is not None:
        on_progress(1.0, "done")
    return table, report


def _report_problems(entry: dict, res, ids: np.ndarray, label: str, source: str | None = None) -> None:
    def listed(mask):
        return [v.item() if hasattr(v, "item") else v for v in ids[mask][:50]]

    entry.update(
        outside=int(res.outside.sum()),
        outside_ids=listed(res.outside),
        partly_outside=int(res.partial.sum()),
        partly_outside_ids=listed(res.partial),
        only_nodata=int(res.no_valid.sum()),
        only_nodata_ids=listed(res.no_valid),
    )
    n = len(ids)
    of = f" (polygons: {Path(source).name})" if source else ""
    if res.outside.all():
        raise InputError(
            f"none of the {n} plants overlaps the raster of {label} "
            f"({', '.join(Path(f).name for f in entry['files'])}){of}: 0 plants with values",
            path=entry["files"][0],
            fix="check that the raster is of the same field, and the CRS of the polygons "
            "(polygons_crs) and of the raster",
        )
    if (res.outside | res.no_valid).all():
        raise InputError(
            f"0 of the {n} plants have values in the raster of {label} "
            f"({', '.join(Path(f).name for f in entry['files'])}){of}: every plant is on nodata pixels "
            f"({int(res.outside.sum())} outside the raster)",
            path=entry["files"][0],
            fix="check that the rasters cover the plants (a DTM or nodata value of another field?)",
        )
    if res.outside.any():
        log.warning(
            "%s: %d of %d plants are outside the raster (e.g. ids %s); their statistics are empty",
            label,
            res.outside.sum(),
            n,
            entry["outside_ids"][:5],
        )
    if res.partial.any():
        log.info("%s: %d plants are only partly on the raster", label, res.partial.sum())
    if res.no_valid.any():
        log.warning(
            "%s: %d plants cover only nodata pixels (e.g. ids %s)",
            label,
            res.no_valid.sum(),
            entry["only_nodata_ids"][:5],
        )


def write_csv(df: pd.DataFrame, path: Path) -> Path:
    """Write ``df`` to ``path`` whole or not at all (the project's CSV format); the path."""
    with atomic_open(path) as fh:
        write_table(df, fh)
    return Path(path)
