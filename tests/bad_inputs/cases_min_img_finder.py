"""Module 3 (min_img_finder): areas of interest that miss the field, lack a CRS or are in another one,
broken project pieces (DSM, orthophoto, reconstruction, coords.txt), and inputs that must work (an AOI in
WGS84, non-ASCII paths, junk files and names that differ by extension in the undistorted images folder, one
image missing: a warning and skipped_images.csv)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import geopandas as gpd
import rasterio
from cases_odm_runner import COORDS, DSM, UND_RECON, edit_json, project, rewrite_raster, truncate
from harness import Case, Work
from shapely.geometry import Point, box

ORTHO = "odm_orthophoto/odm_orthophoto.tif"
UND_IMAGES = "opensfm/undistorted/images"


def args(w: Work, proj: Path, *extra: str) -> list[str]:
    a = ["--set", f"project_dir={proj}", "--set", f"output_dir={w.out}"]
    for e in extra:
        a += ["--set", e]
    return a


def field_box(w: Work, dx: float = 0.0, shrink: float = 0.1):
    """The orthophoto's extent (shrunk by ``shrink`` of its size, moved ``dx`` metres east) and its CRS."""
    with rasterio.open(w.artifacts / "field" / ORTHO) as src:
        b, crs = src.bounds, src.crs
    mx, my = shrink * (b.right - b.left), shrink * (b.top - b.bottom)
    return box(b.left + mx + dx, b.bottom + my, b.right - mx + dx, b.top - my), crs


def write_aoi(w: Work, name: str, geom, crs, to_crs=None, driver: str | None = None) -> Path:
    gdf = gpd.GeoDataFrame({"name": ["field"]}, geometry=[geom], crs=crs)
    if to_crs is not None:
        gdf = gdf.to_crs(to_crs)
    path = w.inputs / name
    gdf.to_file(path, driver=driver) if driver else gdf.to_file(path)
    return path


def with_aoi(name: str, dx: float = 0.0, to_crs=None, folder: str = "project"):
    def prepare(w: Work) -> list[str]:
        proj = project(w, folder)
        geom, crs = field_box(w, dx)
        return args(w, proj, f"aoi_file={write_aoi(w, name, geom, crs, to_crs)}")

    return prepare


def aoi_shapefile_without_prj(w: Work) -> list[str]:
    geom, crs = field_box(w)
    path = write_aoi(w, "field.shp", geom, crs)
    path.with_suffix(".prj").unlink()
    return args(w, project(w), f"aoi_file={path}")


def aoi_geojson_in_metres(w: Work) -> list[str]:
    """A GeoJSON with UTM coordinates and no 'crs' member: by the standard it is WGS84 degrees."""
    geom, _ = field_box(w)
    path = w.inputs / "aoi.geojson"
    path.write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "features": [{"type": "Feature", "properties": {}, "geometry": geom.__geo_interface__}],
            }
        )
    )
    return args(w, project(w), f"aoi_file={path}")


def aoi_points(w: Work) -> list[str]:
    geom, crs = field_box(w)
    path = write_aoi(w, "aoi.gpkg", Point(geom.centroid), crs)
    return args(w, project(w), f"aoi_file={path}")


def aoi_two_layers(polygons_twice: bool):
    """A GeoPackage with a second layer: plot points (the polygon layer is the area), or another polygon layer
    (which one is meant cannot be told)."""

    def prepare(w: Work) -> list[str]:
        geom, crs = field_box(w)
        path = write_aoi(w, "layers.gpkg", geom, crs)
        other = geom.buffer(-0.5) if polygons_twice else Point(geom.centroid)
        gpd.GeoDataFrame({"name": ["x"]}, geometry=[other], crs=crs).to_file(path, layer="extra")
        return args(w, project(w), f"aoi_file={path}")

    return prepare


def aoi_not_vector(w: Work) -> list[str]:
    path = w.inputs / "aoi.gpkg"
    path.write_text("this is not a GeoPackage\n")
    return args(w, project(w), f"aoi_file={path}")


def aoi_missing(w: Work) -> list[str]:
    return args(w, project(w), f"aoi_file={w.inputs / 'boundary.gpkg'}")


def broken(change):
    def prepare(w: Work) -> list[str]:
        proj = project(w)
        change(proj)
        return args(w, proj)

    return prepare


def junk_in_undistorted(p: Path) -> None:
    (p / UND_IMAGES / "Thumbs.db").write_bytes(b"\x00junk")
    (p / UND_IMAGES / "._SIM_0001.JPG.tif").write_bytes(b"\x00\x05\x16\x07 resource fork")
    (p / UND_IMAGES / "desktop.ini").write_text("[.ShellClassInfo]\r\n")


def names_without_original_extension(p: Path) -> None:
    for f in (p / UND_IMAGES).glob("*.JPG.tif"):
        f.rename(f.with_name(f.name.replace(".JPG.tif", ".tif")))  # SIM_0001.JPG.tif -> SIM_0001.tif


def names_lower_case_extension(p: Path) -> None:
    for f in (p / UND_IMAGES).glob("*.JPG.tif"):
        f.rename(f.with_name(f.name.replace(".JPG.tif", ".jpg.tif")))


# -- checks --------------------------------------------------------------------------------------------------


def selected(total: int = 9, coverage: float = 50.0):
    """Every image got a footprint, some were selected, they cover the area, and the files listed exist."""

    def check(w: Work) -> None:
        s = json.loads((w.out / "selection.json").read_text())
        assert s["images_total"] == total and s["images_selected"] >= 1, s
        assert s["coverage_pct"] >= coverage, s
        with open(w.out / "selected_images.csv", newline="") as fh:
            files = [r["file"] for r in csv.DictReader(fh)]
        assert len(files) == s["images_selected"] and all((w.out / "images" / f).is_file() for f in files)

    return check


def reprojected_and_said(w: Work) -> None:
    selected()(w)
    text = "".join(p.read_text() for p in (w.out / "logs").glob("*.log"))
    assert "reprojected to the project's" in text, text[-2000:]


def one_skipped(w: Work) -> None:
    selected(total=8)(w)
    with open(w.out / "skipped_images.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["image"] for r in rows] == ["SIM_0005.JPG"] and "undistorted image" in rows[0]["reason"], rows


CASES = [
    Case(
        "m3-aoi-misses-field",
        "min_img_finder",
        with_aoi("aoi.gpkg", dx=5000.0),
        mentions=("aoi.gpkg", "0 images", "CRS"),
    ),
    Case(
        "m3-aoi-beside-field",
        "min_img_finder",
        with_aoi("next field.gpkg", dx=6.0),
        mentions=("next field.gpkg", "m from"),
    ),
    Case(
        "m3-aoi-shapefile-without-prj",
        "min_img_finder",
        aoi_shapefile_without_prj,
        mentions=("field.shp", "coordinate system"),
    ),
    Case("m3-aoi-geojson-in-metres", "min_img_finder", aoi_geojson_in_metres, mentions=("aoi.geojson", "degrees")),
    Case("m3-aoi-points-only", "min_img_finder", aoi_points, mentions=("aoi.gpkg", "no polygon", "Point")),
    Case("m3-aoi-two-polygon-layers", "min_img_finder", aoi_two_layers(True), mentions=("layers.gpkg", "layers")),
    Case("m3-aoi-polygon-and-point-layers", "min_img_finder", aoi_two_layers(False), expect="ok", check=selected()),
    Case("m3-aoi-not-a-vector-file", "min_img_finder", aoi_not_vector, mentions=("aoi.gpkg",)),
    Case("m3-aoi-missing", "min_img_finder", aoi_missing, mentions=("aoi_file", "boundary.gpkg")),
    Case(
        "m3-dsm-all-nodata",
        "min_img_finder",
        broken(lambda p: rewrite_raster(p / DSM, data=-9999, nodata=-9999)),
        mentions=("dsm.tif", "no valid data"),
    ),
    Case(
        "m3-dsm-without-crs",
        "min_img_finder",
        broken(lambda p: rewrite_raster(p / DSM, crs=None)),
        mentions=("dsm.tif", "CRS"),
    ),
    Case(
        "m3-orthophoto-empty",
        "min_img_finder",
        broken(lambda p: rewrite_raster(p / ORTHO, data=0, nodata=0)),
        mentions=("odm_orthophoto.tif", "aoi_file"),
    ),
    Case(
        "m3-truncated-reconstruction",
        "min_img_finder",
        broken(lambda p: truncate(p / UND_RECON, 0.7)),
        mentions=("undistorted/reconstruction.json", "truncated"),
    ),
    Case(
        "m3-reconstruction-without-shots",
        "min_img_finder",
        broken(lambda p: edit_json(p / UND_RECON, lambda d: d[0].update(shots={}))),
        mentions=("reconstruction.json", "no images"),
    ),
    Case(
        "m3-coords-garbled",
        "min_img_finder",
        broken(lambda p: (p / COORDS).write_text("WGS84 UTM 14N\n702309.0 north\n")),
        mentions=("coords.txt", "line 2"),
    ),
    Case(
        "m3-undistorted-images-deleted",
        "min_img_finder",
        broken(lambda p: [f.unlink() for f in (p / UND_IMAGES).iterdir()]),
        mentions=("opensfm/undistorted/images", "optimize-disk-space"),
    ),
    Case(
        "m3-aoi-in-wgs84",
        "min_img_finder",
        with_aoi("aoi.geojson", to_crs="EPSG:4326"),
        expect="ok",
        check=reprojected_and_said,
    ),
    Case(
        "m3-unicode-space-paths",
        "min_img_finder",
        with_aoi("zone d'intérêt ñ.gpkg", folder="champ d'essai 2024"),
        expect="ok",
        check=selected(),
    ),
    Case(
        "m3-aoi-half-outside",
        "min_img_finder",
        with_aoi("aoi.gpkg", dx=2.0),
        expect="ok",
        check=selected(coverage=30.0),
    ),
    Case("m3-junk-in-undistorted-folder", "min_img_finder", broken(junk_in_undistorted), expect="ok", check=selected()),
    Case(
        "m3-names-without-original-extension",
        "min_img_finder",
        broken(names_without_original_extension),
        expect="ok",
        check=selected(),
    ),
    Case(
        "m3-names-lower-case-extension",
        "min_img_finder",
        broken(names_lower_case_extension),
        expect="ok",
        check=selected(),
    ),
    Case(
        "m3-one-undistorted-image-missing",
        "min_img_finder",
        broken(lambda p: (p / UND_IMAGES / "SIM_0005.JPG.tif").unlink()),
        expect="ok",
        check=one_skipped,
    ),
]
