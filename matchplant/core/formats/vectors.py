"""Vector files out: the one place GeoPackages, shapefiles and GeoJSON files are written.

The driver follows the suffix (``.gpkg``, ``.shp``, ``.geojson``), so a step only chooses names and formats
(its ``vector_formats`` setting, one of :data:`VECTOR_FORMATS` each). Every file is written to a temporary
name and moved into place, so an interrupted run never leaves half a file that a later step would read.

A shapefile is several files and holds one layer, with field names of at most 10 characters: its files are
written in a temporary folder and each moved into place, the columns get the short names of
:data:`SHAPEFILE_NAMES` (GDAL cuts any other long name to 10 characters), and true/false columns become 0/1.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

from pandas.api.types import is_bool_dtype

from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.io import atomic_path, place

VECTOR_FORMATS = ("gpkg", "shp", "geojson")
DRIVERS = {".gpkg": "GPKG", ".shp": "ESRI Shapefile", ".geojson": "GeoJSON"}

# the short names a shapefile shows for the plants' longer column names
SHAPEFILE_NAMES = {
    "source_image": "src_image",
    "off_nadir_deg": "off_nadir",
    "category_id": "cat_id",
    "score_max": "score_max",
    "truth_plant_id": "truth_id",
}


def write_vector(
    gdf, path: str | Path, *, layer: str | None = None, shapefile_columns: Sequence[str] | None = None
) -> Path:
    """One layer to ``path``, the driver chosen by its suffix; ``layer`` names it in a GeoPackage or GeoJSON
    (default: the file's stem, not the temporary name's). ``shapefile_columns``: the only columns a shapefile
    keeps (default: all, with short names)."""
    path = Path(path)
    driver = DRIVERS.get(path.suffix.lower())
    if driver is None:
        raise ConfigError(
            f"cannot write a vector file named {path.name}", path=path, fix=f"name it with one of {', '.join(DRIVERS)}"
        )
    if driver == "ESRI Shapefile":
        return _write_shapefile(gdf, path, shapefile_columns)
    with atomic_path(path) as tmp:
        gdf.to_file(tmp, layer=layer or path.stem, driver=driver)
    return path


def write_layers(
    layers: Mapping[str, object], path: str | Path, *, shapefile_columns: Sequence[str] | None = None
) -> list[Path]:
    """Named layers: all in one GeoPackage; in a format of one layer per file, the first layer goes to
    ``path`` and each other one to ``<stem>_<layer><suffix>`` beside it. Returns the files written."""
    path = Path(path)
    if DRIVERS.get(path.suffix.lower()) == "GPKG" and len(layers) > 1:
        with atomic_path(path) as tmp:  # one rename: a reader never sees some of the layers
            for name, gdf in layers.items():
                gdf.to_file(tmp, layer=name, driver="GPKG")
        return [path]
    return [
        write_vector(
            gdf,
            path if k == 0 else path.with_name(f"{path.stem}_{name}{path.suffix}"),
            layer=name,
            shapefile_columns=shapefile_columns,
        )
        for k, (name, gdf) in enumerate(layers.items())
    ]


def write_formats(
    layers: Mapping[str, object],
    base: str | Path,
    formats: Sequence[str],
    *,
    shapefile_columns: Sequence[str] | None = None,
) -> dict[str, Path]:
    """The layers (:func:`write_layers`) in every format of ``formats`` (names from :data:`VECTOR_FORMATS`),
    as ``<base>.<format>``; returns ``{format: main file}``."""
    base = Path(base)
    return {
        fmt: write_layers(layers, base.with_name(f"{base.name}.{fmt}"), shapefile_columns=shapefile_columns)[0]
        for fmt in formats
    }


def _write_shapefile(gdf, path: Path, columns: Sequence[str] | None) -> Path:
    """A shapefile is several files: write them in a temporary folder, then move each into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if columns is not None:
        gdf = gdf[[*columns, gdf.geometry.name]]
    g = gdf.rename(columns=SHAPEFILE_NAMES)
    for c in g.columns:
        if is_bool_dtype(g[c].dtype):
            g[c] = g[c].astype(int)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.stem}_shp_", dir=path.parent))
    try:
        g.to_file(tmp / path.name, driver="ESRI Shapefile")
        for f in tmp.iterdir():
            place(f, path.parent / f.name)  # a rename over a regular file only (io.place)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path
