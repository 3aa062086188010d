"""The one vector writer (core/formats/vectors.py): every suffix round-trips, and nothing else writes vectors."""

from __future__ import annotations

import re
from pathlib import Path

import geopandas as gpd
import numpy as np
import pyogrio
import pytest
import shapely

from matchplant.core.formats.vectors import DRIVERS, write_formats, write_layers, write_vector
from matchplant.core.runtime.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
WRITER = ROOT / "matchplant" / "core" / "formats" / "vectors.py"
# a vector write: GeoPandas' to_file, or a vector driver named as text (rasterio's "GTiff" is a raster)
VECTOR_WRITE = re.compile(r"\.to_file\(|write_dataframe\(|\b(GPKG|ESRI Shapefile|GeoJSON)\b[\"']")


def plants(crs="EPSG:32615"):
    x = 500000.0 + 2 * np.arange(3)
    boxes = shapely.box(x, 4e6, x + 1, 4e6 + 1)
    return gpd.GeoDataFrame(
        {
            "plant_id": [1, 2, 3],
            "source_image": ["a.JPG", "b.JPG", "c.JPG"],
            "cut": [True, False, True],
            "score": [0.5, 0.25, 0.125],
        },
        geometry=boxes,
        crs=crs,
    )


def test_only_the_writer_writes_vector_files():
    found = []
    for folder in ("matchplant", "bench"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            if path == WRITER:
                continue
            for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
                if VECTOR_WRITE.search(line):
                    found.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not found, "vector files are written only by core/formats/vectors.py:\n" + "\n".join(found)


@pytest.mark.parametrize("suffix", sorted(DRIVERS))
def test_round_trip(tmp_path, suffix):
    gdf = plants()
    path = write_vector(gdf, tmp_path / f"plants{suffix}", layer="plants")
    back = gpd.read_file(path)
    assert back.crs == gdf.crs
    assert shapely.equals(back.geometry.values, gdf.geometry.values).all()
    assert back["plant_id"].tolist() == [1, 2, 3] and back["score"].tolist() == [0.5, 0.25, 0.125]
    if suffix == ".shp":  # short names, 0/1 for true/false
        assert list(back.columns) == ["plant_id", "src_image", "cut", "score", "geometry"]
        assert back["cut"].tolist() == [1, 0, 1]
    else:
        assert list(back.columns) == list(gdf.columns)
        assert back["cut"].tolist() == [True, False, True]
        assert pyogrio.list_layers(path)[0][0] == "plants"
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # no temporaries left


def test_shapefile_columns_and_layers(tmp_path):
    gdf = plants()
    shp = write_vector(gdf, tmp_path / "ids.shp", shapefile_columns=["plant_id"])
    assert list(gpd.read_file(shp).columns) == ["plant_id", "geometry"]
    layers = {"plants": gdf, "first": gdf.iloc[:1]}
    assert write_layers(layers, tmp_path / "two.gpkg") == [tmp_path / "two.gpkg"]
    assert [name for name, _ in pyogrio.list_layers(tmp_path / "two.gpkg")] == ["plants", "first"]
    assert write_layers(layers, tmp_path / "two.geojson") == [tmp_path / "two.geojson", tmp_path / "two_first.geojson"]
    assert len(gpd.read_file(tmp_path / "two_first.geojson")) == 1
    written = write_formats({"plants": gdf}, tmp_path / "out" / "p", ["gpkg", "shp", "geojson"])
    assert {k: v.name for k, v in written.items()} == {"gpkg": "p.gpkg", "shp": "p.shp", "geojson": "p.geojson"}
    assert {p.suffix for p in (tmp_path / "out").iterdir()} >= {".gpkg", ".shp", ".dbf", ".prj", ".geojson"}
    with pytest.raises(ConfigError, match="plants.kml"):
        write_vector(gdf, tmp_path / "plants.kml")
