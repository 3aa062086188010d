"""Module 9's canopy part: outlines on every date, canopy-only statistics, growth between dates.

For each date with a CHM, every plant is outlined (:mod:`~matchplant.spatial_stat_extractor.outlines`);
on later dates, with ``canopy.recentre``, each plant is first re-centred on the local maximum nearest to
its earlier top moved by the median shift of the plants around (within ``canopy.max_shift``), and the
shift is reported. Then the CHM's canopy
percentiles, canopy pixels, area and volume, and every index (or the traits listed in
``canopy.traits``) over the canopy pixels (:mod:`~matchplant.spatial_stat_extractor.canopy`).

Columns (``_<date>`` appended when there are several dates): ``canopy_pixels``, ``canopy_area_m2``,
``canopy_volume_m3``, ``top_x``, ``top_y``, ``top_height``, the tightened box ``tight_xmin`` ...
``tight_ymax``, ``outline_from`` (``chm`` or ``box``),
``outline_flag``, ``shift_x``/``shift_y``/``shift_m`` (later dates), ``chm_canopy_max``,
``chm_canopy_pNN``, ``<trait>_canopy_<stat>``.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Sequence

import geopandas as gpd
import numpy as np
import pandas as pd
import shapely

from matchplant.core.runtime.log import get_logger
from matchplant.spatial_stat_extractor.config import CanopyConfig, RasterSet
from matchplant.spatial_stat_extractor.extract import polygons_in
from matchplant.spatial_stat_extractor.memory import DEFAULT_MEMORY
from matchplant.spatial_stat_extractor.outlines import Outlines, SegmentSettings
from matchplant.spatial_stat_extractor.rasters import open_layer
from matchplant.spatial_stat_extractor.strips import Measure, outline_field

log = get_logger("spatial_stat_extractor")


def settings_from(cfg: CanopyConfig) -> SegmentSettings:
    return SegmentSettings(margin=cfg.margin, relative=cfg.relative, min_height=cfg.min_height, min_top=cfg.min_top,
                           min_pixels=cfg.min_pixels, max_shift=cfg.max_shift, mask_threshold=cfg.ndvi_threshold)


def outline_columns(o: Outlines, previous: Outlines | None) -> dict[str, np.ndarray]:
    cols = {"canopy_pixels": o.pixels, "canopy_area_m2": o.area, "canopy_volume_m3": o.volume,
            "top_x": o.top[:, 0], "top_y": o.top[:, 1], "top_height": o.top[:, 2],
            "tight_xmin": o.tight_box[:, 0], "tight_ymin": o.tight_box[:, 1], "tight_xmax": o.tight_box[:, 2],
            "tight_ymax": o.tight_box[:, 3],
            "outline_from": np.where(o.from_box, "box", "chm"), "outline_flag": o.flag.astype(str)}
    if previous is not None:
        d = o.top[:, :2] - previous.top[:, :2]
        cols.update(shift_x=d[:, 0], shift_y=d[:, 1], shift_m=np.hypot(d[:, 0], d[:, 1]))
    return cols


def canopy_traits(polygons, date_sets: Sequence[RasterSet], cfg: CanopyConfig, stats: Sequence[str],
                  percentiles: Sequence[float], nodata: float | None = None, *, max_memory: int = DEFAULT_MEMORY,
                  workers: int = 0):
    """Returns ``(per-date columns {date: DataFrame}, outlines GeoDataFrame (all dates), the first date's
    canopies that no box claims (DataFrame x, y, height, pixels: plants the detector missed), report)``."""
    s = settings_from(cfg)
    ids = polygons["plant_id"].to_numpy()
    per_date: dict[str, pd.DataFrame] = {}
    frames = []
    report = {"dates": []}
    previous: Outlines | None = None
    unclaimed = pd.DataFrame(columns=["x", "y", "height", "pixels"])
    for rs in date_sets:
        layers = rs.layers()
        chm_layer = next((la for la in layers if la.elevation), None)
        if chm_layer is None:
            log.info("date '%s' has no CHM: no outlines or canopy statistics for it", rs.date)
            continue
        wanted = set(cfg.traits) if cfg.traits else {la.name for la in layers if la.index}
        with contextlib.ExitStack() as stack:
            chm = open_layer(chm_layer, stack, nodata)
            entry: dict = {"date": rs.date}
            geoms = polygons_in(polygons, chm.crs, f"CHM {Path(chm_layer.paths[0]).name}", entry)
            mask = mask_layer = None
            if cfg.ndvi_threshold is not None:
                mask_layer = next((la for la in layers if la.kind == "ndvi"), None)
                mask = open_layer(mask_layer, stack, nodata) if mask_layer is not None else None
                if mask is None or (mask.width, mask.height) != (chm.width, chm.height):
                    log.warning("canopy.ndvi_threshold ignored on date '%s': no multispectral raster on the "
                                "CHM's grid", rs.date)
                    mask = mask_layer = None
            seeds = None
            if previous is not None and cfg.recentre:
                seeds = previous.top[:, :2].copy()
                lost = ~np.isfinite(seeds).all(axis=1)  # no top earlier: start from the box centre
                centre = shapely.centroid(np.asarray(geoms, dtype=object)[lost])
                seeds[lost] = np.stack([shapely.get_x(centre), shapely.get_y(centre)], axis=1)
            # strip by strip within max_memory, only per-plant results kept (strips.py)
            measures = [Measure(f"{chm_layer.name}_canopy", chm_layer, ("max", "mean"), tuple(cfg.height_percentiles))]
            measures += [Measure(f"{la.name}_canopy", la, tuple(stats), tuple(percentiles)) for la in layers
                         if not la.elevation and la.name in wanted]
            o, measured = outline_field(geoms, chm_layer, mask_layer, measures, s, nodata=nodata, seeds=seeds,
                                        max_memory=max_memory, workers=workers)
            cols = outline_columns(o, previous if seeds is not None else None)
            cols.update(measured)
        flags = pd.Series(o.flag[o.flag != ""]).value_counts().to_dict()
        entry.update(outlined=int((o.flag == "").sum()), kept_box={str(k): int(v) for k, v in flags.items()},
                     unclaimed_canopies=int(len(o.unclaimed)))
        if previous is None:
            unclaimed = pd.DataFrame(o.unclaimed, columns=["x", "y", "height", "pixels"])
        if seeds is not None:
            entry["median_shift_m"] = float(np.nanmedian(cols["shift_m"]))
        log.info("date '%s': %d plants outlined from the CHM, %d kept their box %s", rs.date, entry["outlined"],
                 int(o.from_box.sum()), entry["kept_box"] or "")
        report["dates"].append(entry)
        table = pd.DataFrame({"plant_id": ids, **cols})
        per_date[rs.date] = table
        gdf = gpd.GeoDataFrame(table.assign(date=rs.date), geometry=list(o.geometry), crs=chm.crs)
        frames.append(gdf)
        previous = o
    outlines = pd.concat(frames, ignore_index=True) if frames else None
    return per_date, outlines, unclaimed, report


def merge_columns(table: pd.DataFrame, per_date: dict[str, pd.DataFrame], layout: str, n_dates: int) -> pd.DataFrame:
    """The box statistics table with the canopy columns added (same layout: wide or long)."""
    if not per_date:
        return table
    if layout == "long" and n_dates > 1:
        extra = pd.concat([t.assign(date=d) for d, t in per_date.items()], ignore_index=True)
        return table.merge(extra, on=["plant_id", "date"], how="left")
    out = table
    for date, t in per_date.items():
        suffix = f"_{date}" if n_dates > 1 else ""
        out = out.merge(t.set_index("plant_id").add_suffix(suffix), left_on="plant_id", right_index=True,
                        how="left")
    return out
