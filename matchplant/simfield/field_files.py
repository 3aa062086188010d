"""The field's own files: the rasters ODM would make (DTM, DSM, orthophoto, multispectral, plant ids) and the
truth tables (plants, traits, plots, gaps, field book)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from pyproj import CRS
from rasterio.enums import ColorInterp
from rasterio.windows import Window

from matchplant.core.runtime.io import atomic_open, atomic_path, write_json
from matchplant.simfield.layout import FieldPaths
from matchplant.simfield.noise import BAND_ORDER, REALISTIC, five_bands, noise_summary, photogrammetric_dem
from matchplant.simfield.scene import Grid, Plants, Rasters, Terrain
from matchplant.simfield.traits import plot_truth, traits_rows

NODATA = -9999.0


def write_csv(path: Path, header: list[str], rows: list) -> None:
    """Write a CSV file whole (header, then rows), or nothing if it fails."""
    with atomic_open(path, "w") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(header)
        w.writerows(rows)


def write_plants(paths: FieldPaths, plants: Plants, rasters: Rasters, res: float, offset: np.ndarray) -> None:
    """Write the true plants (plants.csv) and their true traits (traits.csv) in map coordinates."""
    radius = plants.radius()
    write_csv(
        paths.plants_csv,
        ["id", "x", "y", "z", "height", "radius", "row"],
        [
            [int(i), f"{x + offset[0]:.4f}", f"{y + offset[1]:.4f}", f"{z:.4f}", f"{h:.4f}", f"{r:.4f}", int(row)]
            for i, x, y, z, h, r, row in zip(
                plants.ids, plants.x, plants.y, plants.z, plants.height, radius, plants.row
            )
        ],
    )
    write_csv(
        paths.traits_csv,
        ["id", "x", "y", "height", "ndvi", "canopy_pixels", "canopy_area_m2"],
        traits_rows(plants, rasters.label, res, offset),
    )


def write_plot_truth(paths: FieldPaths, s, plants: Plants, offset: np.ndarray, crs: str) -> None:
    """Write the plot grid, the plots, the seed gaps and the field book of the truth."""
    t = plot_truth(s, plants, offset, crs)
    write_json(paths.plots_json, t["grid"])
    write_csv(
        paths.plots_csv, ["plot_id", "range", "column", "expected", "stand_count", "gaps", "geometry"], t["plots"]
    )
    write_csv(paths.gaps_csv, ["plot_id", "row", "x", "y"], t["gaps"])
    write_csv(paths.field_book, ["plot_id", "genotype", "rep"], t["field_book"])


def write_rasters(
    paths: FieldPaths,
    grid: Grid,
    rasters: Rasters,
    terrain: Terrain,
    offset: np.ndarray,
    crs: CRS,
    noise_rng: np.random.Generator | None = None,
) -> dict | None:
    """DTM, DSM, orthophoto, multispectral and plant ids. With ``noise_rng`` (noise: realistic) the DSM and
    DTM are photogrammetric and the multispectral raster has 5 bands (simfield/noise.py); returns what was
    measured on them."""
    transform = Affine(grid.res, 0.0, grid.x0 + offset[0], 0.0, -grid.res, grid.y1 + offset[1])
    block = 512
    dem = photogrammetric_dem(rasters, noise_rng) if noise_rng is not None else None

    def ground(rows: slice) -> np.ndarray:
        x, y = grid.centres(rows)
        return terrain.height(x, y)

    def dsm(rows: slice) -> np.ndarray:
        if dem is None:
            return (ground(rows) + rasters.canopy[rows])[None]
        return np.where(dem.holes[rows], NODATA, ground(rows) + dem.dsm[rows])[None]

    def dtm(rows: slice) -> np.ndarray:
        return (ground(rows) + (0.0 if dem is None else dem.dtm[rows]))[None]

    outputs = [
        (paths.dtm, 1, "float32", NODATA, dtm),
        (paths.dsm, 1, "float32", NODATA, dsm),
        (
            paths.orthophoto,
            4,
            "uint8",
            0,
            lambda r: np.concatenate(
                [np.moveaxis(rasters.albedo[r], 2, 0), np.full((1,) + rasters.label[r].shape, 255, np.uint8)]
            ),
        ),
        (paths.plant_ids, 1, "int32", -9999, lambda r: rasters.label[r][None]),
    ]
    if dem is None:
        outputs.insert(
            3, (paths.multispectral, 2, "float32", NODATA, lambda r: np.stack([rasters.red[r], rasters.nir[r]]))
        )
    for path, count, dtype, nodata, fn in outputs:
        profile = raster_profile(grid, count, dtype, crs, transform, nodata)
        if count == 4:
            profile["photometric"] = "RGB"
            profile["alpha"] = "YES"
        with atomic_path(path) as tmp:
            with rasterio.open(tmp, "w", **profile) as dst:
                for r0 in range(0, grid.height, block):
                    rows = slice(r0, min(r0 + block, grid.height))
                    dst.write(fn(rows).astype(dtype), window=Window(0, r0, grid.width, rows.stop - r0))
                if count == 4:
                    dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]
                elif count == 2:
                    dst.set_band_description(1, "red reflectance")
                    dst.set_band_description(2, "near-infrared reflectance")
    if dem is None:
        return None
    # 5 bands as a generic writer leaves them: photometric RGB + 2 extra samples, no descriptions, no nodata
    profile = raster_profile(grid, len(BAND_ORDER), "float32", crs, transform, None)
    profile["photometric"] = "RGB"
    with atomic_path(paths.multispectral) as tmp, rasterio.open(tmp, "w", **profile) as dst:
        for b, band in enumerate(five_bands(rasters, noise_rng), start=1):
            dst.write(band, b)
    return noise_summary(REALISTIC, dem, rasters)


def raster_profile(grid: Grid, count: int, dtype: str, crs: CRS, transform: Affine, nodata) -> dict:
    """Rasterio profile of a tiled, deflate-compressed GeoTIFF on the grid."""
    return dict(
        driver="GTiff",
        width=grid.width,
        height=grid.height,
        count=count,
        dtype=dtype,
        crs=crs,
        transform=transform,
        nodata=nodata,
        tiled=True,
        blockxsize=256,
        blockysize=256,
        compress="deflate",
        zlevel=1,
        BIGTIFF="IF_SAFER",
    )
