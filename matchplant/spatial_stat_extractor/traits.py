"""The canopy stage of module 9: outlines on every date, canopy-only statistics, growth between dates.

For each date with a CHM, the CHM's ground noise is measured and checked, and ``canopy.min_height`` /
``min_top`` left at ``auto`` follow from it (:mod:`~matchplant.spatial_stat_extractor.canopy.ground`); a later date's
offset against the date before is measured (:mod:`~matchplant.spatial_stat_extractor.canopy.dates`): beyond
``canopy.max_shift`` an error, or with ``canopy.register`` the boxes are moved by it. Every plant is then
outlined (:mod:`~matchplant.spatial_stat_extractor.canopy.outlines`);
on later dates, with ``canopy.recentre``, each plant is first re-centred on the local maximum nearest to
its earlier top moved by the median shift of the plants around (within ``canopy.max_shift``), and the
shift is reported. Then the CHM's canopy
percentiles, canopy pixels, area and volume, and every index (or the traits listed in
``canopy.traits``) over the canopy pixels (:mod:`~matchplant.spatial_stat_extractor.canopy.stats`).

Columns (``_<date>`` appended when there are several dates): ``canopy_pixels``, ``canopy_area_m2``,
``canopy_volume_m3``, ``top_x``, ``top_y``, ``top_height``, the tightened box ``tight_xmin`` ...
``tight_ymax``, ``outline_from`` (``chm`` or ``box``),
``outline_flag``, ``canopy_box_ratio`` and ``fills_box`` (an outline covering 90 % of its box or more: most
likely its soil), ``shift_x``/``shift_y``/``shift_m`` (later dates), ``chm_canopy_max``,
``chm_canopy_pNN``, ``<trait>_canopy_<stat>``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import shapely

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger
from matchplant.spatial_stat_extractor.canopy import (
    DEFAULT_MEMORY,
    GroundSample,
    Measure,
    Outlines,
    SegmentSettings,
    Thresholds,
    check_chm,
    measure_ground,
    measure_offset,
    outline_field,
    templates,
    thresholds,
)
from matchplant.spatial_stat_extractor.config import CanopyConfig, RasterSet
from matchplant.spatial_stat_extractor.inputs import chm_keys, open_layer
from matchplant.spatial_stat_extractor.zonal import polygons_in

log = get_logger("spatial_stat_extractor")

GUARD = 0.05  # m beyond each box plus margin before the ground sample starts (smoothed plant edges)


FILLS_BOX = 0.9  # an outline covering this share of its box or more is most likely the box's soil
UNCLAIMED = ["x", "y", "height", "pixels"]  # columns of unclaimed_canopies.csv (plus faint)


def settings_from(cfg: CanopyConfig, th: Thresholds | None = None) -> SegmentSettings:
    """The segmentation settings; ``th``: the thresholds resolved for one CHM (``auto`` ones from its noise)."""
    if th is None:
        th = thresholds(
            cfg.min_height, cfg.min_top, GroundSample(), None if cfg.ndvi_threshold == "auto" else cfg.ndvi_threshold
        )
    return SegmentSettings(
        margin=cfg.margin,
        relative=cfg.relative,
        min_height=th.min_height,
        min_top=th.min_top,
        min_pixels=cfg.min_pixels,
        max_shift=cfg.max_shift,
        mask_threshold=th.ndvi_threshold,
        mask_soil=th.ndvi_soil,
        unclaimed_min_top=th.unclaimed_min_top,
        noise_sd=th.noise_sd,
    )


def resolve_thresholds(chm, geoms, cfg: CanopyConfig, rs: RasterSet, first: bool, entry: dict, ndvi=None) -> Thresholds:
    """The CHM's ground noise measured (and ``ndvi``'s, a layer on the CHM's grid), the canopy thresholds
    resolved from it, the CHM checked; logged and reported in ``entry``."""
    noise = measure_ground(chm, geoms, guard_m=cfg.margin + GUARD, ndvi=ndvi)
    th = thresholds(cfg.min_height, cfg.min_top, noise, cfg.ndvi_threshold if ndvi is not None else None)
    files = ", ".join(Path(p).name for p in ((rs.chm,) if rs.chm is not None else (rs.dsm, rs.dtm)))
    check_chm(noise, th, cfg.max_height, files, chm_keys(rs, first))
    if noise.measured:
        log.info(
            "date '%s': CHM ground noise p50 %.3f m, p95 %.3f m, SD %.3f m (%d pixels between the plants%s, "
            "%d windows; %s)",
            rs.date,
            noise.p50,
            noise.p95,
            noise.sd,
            noise.pixels,
            "" if noise.guarded else f", just outside the boxes: none lies {cfg.margin + GUARD:g} m from every box",
            noise.windows,
            noise.excluded_text(),
        )
    else:
        log.warning(
            "date '%s': too little bare ground between the plants (%d pixels) to measure the CHM's noise",
            rs.date,
            noise.pixels,
        )
    if ndvi is not None:
        log.info(
            "date '%s': canopy.ndvi_threshold %s: %s",
            rs.date,
            "none" if th.ndvi_threshold is None else f"{th.ndvi_threshold:.3f}",
            th.source["ndvi_threshold"],
        )
    log.info(
        "date '%s': canopy.min_height %.3f m: %s; canopy.min_top %.3f m: %s; canopies no box claims need a top "
        "of %.3f m",
        rs.date,
        th.min_height,
        th.source["min_height"],
        th.min_top,
        th.source["min_top"],
        th.unclaimed_min_top,
    )
    entry.update(
        ground_noise=noise.report(),
        min_height=round(th.min_height, 4),
        min_top=round(th.min_top, 4),
        unclaimed_min_top=round(th.unclaimed_min_top, 4),
        thresholds_from=th.source,
        ndvi_threshold=None if th.ndvi_threshold is None else round(th.ndvi_threshold, 4),
    )
    return th


def date_offset(earlier, chm, cfg: CanopyConfig, rs: RasterSet, entry: dict) -> np.ndarray:
    """The offset (m) to move this date's boxes by: zero within ``canopy.max_shift``; beyond it an error,
    or with ``canopy.register`` the measured offset (:mod:`~matchplant.spatial_stat_extractor.canopy.dates`)."""
    date, crs, tmpl = earlier
    if tmpl is None:
        return np.zeros(2)
    if crs is not None and chm.crs is not None and not crs.equals(chm.crs):
        log.info("date '%s': its CHM is in another CRS than date '%s'; its offset is not measured", rs.date, date)
        return np.zeros(2)
    off = measure_offset(tmpl, chm, cfg.max_shift)
    entry["offset_to_" + (date or "previous")] = off.report()
    # a shift clearly beyond max_shift: the peak well above the best correlation near no shift
    beyond = (
        off.windows > 0
        and off.distance > cfg.max_shift + tmpl.resolution
        and off.score >= 0.3
        and off.score > off.near + 0.05
    )
    if not beyond:
        log.info(
            "date '%s': its CHM is %.3f m off date '%s' (east %+.3f m, north %+.3f m; correlation %.2f)",
            rs.date,
            off.distance,
            date,
            off.dx,
            off.dy,
            off.score,
        )
        return np.zeros(2)
    files = ", ".join(Path(p).name for p in ((rs.chm,) if rs.chm is not None else (rs.dsm, rs.dtm)))
    if not cfg.register:
        raise InputError(
            f"date '{rs.date}': its CHM ({files}) is shifted {off.distance:.2f} m (east {off.dx:+.2f} m, "
            f"north {off.dy:+.2f} m; correlation {off.score:.2f}, {off.near:.2f} without the shift) "
            f"against date '{date}', beyond canopy.max_shift = {cfg.max_shift:g} m: the two flights are "
            "georeferenced differently (one without GCPs?), and the boxes would measure the wrong "
            "plants",
            path=rs.chm if rs.chm is not None else rs.dsm,
            fix="georeference both flights with the same GCPs, or set canopy.register: true to move "
            f"date '{rs.date}' by the measured offset (raise canopy.max_shift only if the plants "
            "themselves moved that far)",
        )
    log.warning(
        "date '%s': its CHM is shifted %.2f m (east %+.3f m, north %+.3f m) against date '%s'; moved back "
        "by that offset (canopy.register); its box statistics are still over the unmoved boxes, its canopy "
        "columns are over the moved ones",
        rs.date,
        off.distance,
        off.dx,
        off.dy,
        date,
    )
    entry["registered"] = {"dx": round(off.dx, 3), "dy": round(off.dy, 3)}
    return np.array([off.dx, off.dy])


def outline_columns(o: Outlines, previous: Outlines | None, geoms=None) -> dict[str, np.ndarray]:
    """The outline columns of the plant table: canopy size, top, tight box, flag (and shift from ``previous``)."""
    cols = {
        "canopy_pixels": o.pixels,
        "canopy_area_m2": o.area,
        "canopy_volume_m3": o.volume,
        "top_x": o.top[:, 0],
        "top_y": o.top[:, 1],
        "top_height": o.top[:, 2],
        "tight_xmin": o.tight_box[:, 0],
        "tight_ymin": o.tight_box[:, 1],
        "tight_xmax": o.tight_box[:, 2],
        "tight_ymax": o.tight_box[:, 3],
        "outline_from": np.where(o.from_box, "box", "chm"),
        "outline_flag": o.flag.astype(str),
    }
    if geoms is not None:  # an outline that fills its box has most likely taken the box's soil for leaves
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.where(o.from_box, np.nan, o.area / shapely.area(np.asarray(geoms, dtype=object)))
        cols.update(canopy_box_ratio=ratio, fills_box=np.nan_to_num(ratio) >= FILLS_BOX)
    if previous is not None:
        d = o.top[:, :2] - previous.top[:, :2]
        cols.update(shift_x=d[:, 0], shift_y=d[:, 1], shift_m=np.hypot(d[:, 0], d[:, 1]))
    return cols


def _ndvi_mask(layers, chm, cfg: CanopyConfig, date: str, stack: contextlib.ExitStack, nodata):
    """The NDVI layer that masks the canopy (opened) and its layer, or ``None, None`` without
    ``canopy.ndvi_threshold`` or an NDVI on the CHM's grid."""
    mask = mask_layer = None
    if cfg.ndvi_threshold is not None:
        mask_layer = next((la for la in layers if la.kind == "ndvi"), None)
        mask = open_layer(mask_layer, stack, nodata) if mask_layer is not None else None
        if mask is None or (mask.width, mask.height) != (chm.width, chm.height):
            (log.info if cfg.ndvi_threshold == "auto" else log.warning)(
                "canopy.ndvi_threshold not used on date '%s': no multispectral raster on the CHM's grid "
                "(outlines from the CHM alone)",
                date,
            )
            mask = mask_layer = None
    return mask, mask_layer


def _report_date(o: Outlines, cols: dict, entry: dict, date: str) -> None:
    """Into the date's report ``entry``: the plants outlined, those that kept their box (by flag), the canopies no
    box claims; a warning when outlines fill their box, a line on the noise bumps."""
    flags = pd.Series(o.flag[o.flag != ""]).value_counts().to_dict()
    entry.update(
        outlined=int((o.flag == "").sum()),
        kept_box={str(k): int(v) for k, v in flags.items()},
        unclaimed_canopies=int(len(o.unclaimed)),
        unclaimed_below_noise=o.noise_bumps,
        fills_box=int(cols["fills_box"].sum()),
    )
    if entry["fills_box"]:
        log.warning(
            "date '%s': %d of %d outlines fill their box (canopy >= %d %% of the box, column fills_box): "
            "the CHM's soil may reach canopy.min_height (%.3f m; raise it if these plants are smaller "
            "than their boxes), or the plants outgrew boxes drawn on an earlier date",
            date,
            entry["fills_box"],
            entry["outlined"],
            FILLS_BOX * 100,
            entry["min_height"],
        )
    if o.noise_bumps:
        log.info(
            "date '%s': %d canopies no box claims are ground-noise bumps (top below %.3f m), not plants; "
            "%d look like plants",
            date,
            o.noise_bumps,
            entry["unclaimed_min_top"],
            len(o.unclaimed),
        )


def _faint(o: Outlines) -> pd.DataFrame:
    """The canopies no box claims below the ground noise's highest bumps whose pixels are leaves by NDVI."""
    return pd.DataFrame(o.faint, columns=UNCLAIMED).assign(faint=True)


def canopy_traits(
    polygons,
    date_sets: Sequence[RasterSet],
    cfg: CanopyConfig,
    stats: Sequence[str],
    percentiles: Sequence[float],
    nodata: float | None = None,
    *,
    max_memory: int = DEFAULT_MEMORY,
    workers: int = 0,
):
    """Returns ``(per-date columns {date: DataFrame}, outlines GeoDataFrame (all dates), the first date's
    canopies that no box claims (DataFrame x, y, height, pixels: plants the detector missed), report)``."""
    ids = polygons["plant_id"].to_numpy()
    per_date: dict[str, pd.DataFrame] = {}
    frames = []
    report = {"dates": []}
    previous: Outlines | None = None
    earlier = None  # (date, crs, Templates) of the last date with a CHM
    moved = np.zeros(2)  # m: the registration of the current date against the first
    unclaimed = pd.DataFrame(columns=[*UNCLAIMED, "faint"])
    for i, rs in enumerate(date_sets):
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
            mask, mask_layer = _ndvi_mask(layers, chm, cfg, rs.date, stack, nodata)
            step = np.zeros(2)
            if earlier is not None:
                step = date_offset(earlier, chm, cfg, rs, entry)
                moved = moved + step
            if moved.any():  # registered: the boxes onto this date's map
                geoms = shapely.transform(np.asarray(geoms, dtype=object), lambda c, d=moved: c + d)
            seeds = None
            if previous is not None and cfg.recentre:
                seeds = previous.top[:, :2] + step
                lost = ~np.isfinite(seeds).all(axis=1)  # no top earlier: start from the box centre
                centre = shapely.centroid(np.asarray(geoms, dtype=object)[lost])
                seeds[lost] = np.stack([shapely.get_x(centre), shapely.get_y(centre)], axis=1)
            th = resolve_thresholds(chm, geoms, cfg, rs, i == 0, entry, mask)
            if th.ndvi_threshold is None:
                mask_layer = None
            # strip by strip within max_memory, only per-plant results kept (canopy/strips.py)
            measures = [Measure(f"{chm_layer.name}_canopy", chm_layer, ("max", "mean"), tuple(cfg.height_percentiles))]
            measures += [
                Measure(f"{la.name}_canopy", la, tuple(stats), tuple(percentiles))
                for la in layers
                if not la.elevation and la.name in wanted
            ]
            o, measured = outline_field(
                geoms,
                chm_layer,
                mask_layer,
                measures,
                settings_from(cfg, th),
                nodata=nodata,
                seeds=seeds,
                max_memory=max_memory,
                workers=workers,
            )
            if i < len(date_sets) - 1:  # windows of this CHM, to measure the next date's offset against
                earlier = (rs.date, chm.crs, templates(chm, geoms, cfg.max_shift))
            cols = outline_columns(o, previous if seeds is not None else None, geoms)
            cols.update(measured)
        _report_date(o, cols, entry, rs.date)
        if previous is None:
            # the faint ones too (below the ground noise's highest bumps): plots count them only at an empty
            # seed position, where the detector missed a plant too small to rise above the noise (plots/table.py)
            unclaimed = pd.concat(
                [pd.DataFrame(o.unclaimed, columns=UNCLAIMED).assign(faint=False), _faint(o)], ignore_index=True
            )
        if seeds is not None:
            entry["median_shift_m"] = float(np.nanmedian(cols["shift_m"]))
        log.info(
            "date '%s': %d plants outlined from the CHM, %d kept their box %s",
            rs.date,
            entry["outlined"],
            int(o.from_box.sum()),
            entry["kept_box"] or "",
        )
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
        out = out.merge(t.set_index("plant_id").add_suffix(suffix), left_on="plant_id", right_index=True, how="left")
    return out
