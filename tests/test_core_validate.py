"""The shared input checks (matchplant.core.runtime.validate): each reader on good input and on each kind of damage,
with the message naming the file, the line or key, and a fix."""

from __future__ import annotations

import json

import geopandas as gpd
import numpy as np
import pytest
import rasterio
from affine import Affine
from PIL import Image
from shapely.geometry import box

from matchplant.core.runtime import validate_gis
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.validate import (
    check_coordinates,
    check_jpeg,
    check_path,
    check_range,
    did_you_mean,
    match_name,
    match_names,
    name_key,
    read_csv,
    read_json,
    read_text,
    read_yaml,
)
from matchplant.core.runtime.validate_gis import check_raster, check_vector


def fails(call, *texts, exc=InputError) -> str:
    with pytest.raises(exc) as info:
        call()
    message = str(info.value)
    for t in texts:
        assert t in message, f"{t!r} not in {message!r}"
    assert "fix:" in message or "did you mean" in message
    return message


# -- names ------------------------------------------------------------------------------------------------------


def test_did_you_mean_and_name_matching():
    assert did_you_mean("tile_sise", ["tile_size", "overlap"]) == "did you mean 'tile_size'?"
    assert did_you_mean("ZZZ", ["tile_size"]) == ""
    assert did_you_mean("PLANTS", ["plants", "boxes"]) == "did you mean 'plants'?"
    assert name_key("a/b/IMG_1.JPG") == name_key("img_1.tif") == name_key("IMG_1") == "img_1"
    matched, unmatched = match_names(
        ["IMG_1.tif", "IMG_2.jpg", "IMG_3.JPG", "other.JPG"], ["IMG_1", "IMG_2.JPG", "IMG_3.JPG"]
    )
    assert matched == {"IMG_1.tif": "IMG_1", "IMG_2.jpg": "IMG_2.JPG", "IMG_3.JPG": "IMG_3.JPG"}
    assert unmatched == ["other.JPG"]
    # ambiguous loose matches are not guessed
    assert match_names(["a.jpg"], ["A.JPG", "a.tif"]) == ({}, ["a.jpg"])
    assert match_name("IMG_1.tif", ["IMG_1.JPG"], what="image") == "IMG_1.JPG"
    fails(
        lambda: match_name("IMG_7.JPG", ["IMG_1.JPG", "IMG_2.JPG"], what="image", path="rec.json"),
        "image 'IMG_7.JPG' not found",
        "did you mean",
        "rec.json",
    )
    fails(
        lambda: match_name("plnts", ["plants", "boxes"], what="layer", error=ConfigError),
        "did you mean 'plants'",
        exc=ConfigError,
    )


# -- text, JSON, YAML -------------------------------------------------------------------------------------------


def test_read_text_accepts_windows_encodings(tmp_path):
    for name, data in [
        ("bom.txt", b"\xef\xbb\xbfa,b\r\n1,2\r\n"),
        ("u16.txt", "a,b\r\n1,2\r\n".encode("utf-16")),
        ("plain.txt", b"a,b\n1,2\n"),
    ]:
        (tmp_path / name).write_bytes(data)
        assert read_text(tmp_path / name) == "a,b\n1,2\n"
    (tmp_path / "latin.txt").write_bytes("champ é\n".encode("cp1252"))
    assert read_text(tmp_path / "latin.txt") == "champ é\n"
    (tmp_path / "bin.dat").write_bytes(b"\x00\xff\xfe\x00" * 10)
    fails(lambda: read_text(tmp_path / "bin.dat"), "binary")
    fails(lambda: read_text(tmp_path / "none.txt"), "not found", "none.txt")
    fails(lambda: read_text(tmp_path), "is a folder")


def test_read_json(tmp_path):
    p = tmp_path / "coco.json"
    p.write_text(json.dumps({"images": [1, 2], "annotations": []}))
    assert read_json(p, expect=dict, required=["images"])["images"] == [1, 2]
    p.write_text(json.dumps({"images": [1, 2], "annotations": []})[:20])
    fails(lambda: read_json(p), "ends early", "truncated", "coco.json")
    p.write_text('{"images": [1, 2],\n "x": oops, "y": 1}')
    fails(lambda: read_json(p), "not valid JSON: line 2, column 7")
    p.write_text("[1, 2]")
    fails(lambda: read_json(p, expect=dict), "holds a list [...], expected an object")
    p.write_text('{"image": []}')
    fails(lambda: read_json(p, required=["images"]), "has no 'images'; did you mean 'image'?")
    p.write_text("  \n")
    fails(lambda: read_json(p), "is empty")
    p.write_bytes(b'\xef\xbb\xbf{"a": 1}\r\n')
    assert read_json(p) == {"a": 1}


def test_read_yaml(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_bytes(b"\xef\xbb\xbfa: 1\r\nb: [x, y]\r\n")
    assert read_yaml(p) == {"a": 1, "b": ["x", "y"]}
    p.write_text("a: 1\nb:\n\t- x\n")
    fails(lambda: read_yaml(p), "line 3 is indented with a tab", "c.yaml", exc=ConfigError)
    p.write_text("a: 1\nb: [x\nc: 2\n")
    fails(lambda: read_yaml(p), "not valid YAML at line", exc=ConfigError)
    p.write_text("a: 1\nb: 2\na: 3\n")
    fails(lambda: read_yaml(p), "the key 'a' is given twice, at lines 1 and 3", exc=ConfigError)
    p.write_text("# only a comment\n\n")
    fails(lambda: read_yaml(p), "is empty", exc=ConfigError)
    p.write_text("- a\n- b\n")
    fails(lambda: read_yaml(p), "holds a list", exc=ConfigError)
    assert read_yaml(p, expect=list) == ["a", "b"]
    fails(lambda: read_yaml(p, expect=dict, error=InputError), "holds a list")


# -- CSV --------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "text",
    [
        "id,x,y,z\nA,1.5,2,3\nB,4,5,6\n",
        "\ufeffid;x;y;z\r\nA;1,5;2;3\r\nB;4;5;6\r\n",  # Excel in a comma-decimal locale
        "ID\tX\tY\tZ\nA\t1.5\t2\t3\nB\t4\t5\t6\n",
        "id x y z\nA 1.5 2 3\nB 4 5 6\n",
        "# survey of 2024\nid, x, y, z\n\nA, 1.5, 2, 3\nB, 4, 5, 6\n",
    ],
)
def test_read_csv_accepts_the_usual_dialects(tmp_path, text):
    p = tmp_path / "gcp.csv"
    p.write_bytes(text.encode("utf-8"))
    t = read_csv(p, required=["id"], numeric=["x", "y", "z"])
    assert len(t) == 2 and t.column("id") == ["A", "B"]
    np.testing.assert_allclose(t.numbers["x"], [1.5, 4])
    np.testing.assert_allclose(t.numbers["z"], [3, 6])


def test_read_csv_errors_name_the_line_and_column(tmp_path):
    p = tmp_path / "gcp.csv"
    p.write_text("id,easting,y,z\nA,1,2,3\n")
    fails(lambda: read_csv(p, numeric=["x", "y"]), "no column 'x'", "columns: id, easting, y, z", "gcp.csv")
    assert read_csv(p, numeric=["x"], aliases={"x": ["easting"]}).numbers["x"][0] == 1
    p.write_text("name,lat,lon\nA,1,2\n")
    fails(lambda: read_csv(p, required=["nme"]), "did you mean 'name'")
    p.write_text("id,x,y\nA,1,2\nB,3,abc\nC,4,5\n")
    fails(lambda: read_csv(p, numeric=["x", "y"]), "line 3: column 'y' is 'abc', not a number")
    p.write_text("id,x,y\nA,1,2\nB,,2\n")
    fails(lambda: read_csv(p, numeric=["x"]), "line 3: column 'x' is empty")
    p.write_text("id,x,y\nA,1,nan\n")
    fails(lambda: read_csv(p, numeric=["y"]), "line 2: column 'y' is 'nan'")
    p.write_text("id,x,y\nA,1,2\nB,3\n")
    fails(lambda: read_csv(p), "line 3: 2 values, but the header has 3 columns")
    p.write_text("A,1,2\nB,3,4\n")
    fails(lambda: read_csv(p, numeric=["x"]), "no header line")
    p.write_text("id,x,x\nA,1,2\n")
    fails(lambda: read_csv(p), "column 'x' appears twice")
    p.write_text("id,x\n")
    fails(lambda: read_csv(p), "no data rows")
    assert len(read_csv(p, allow_empty=True)) == 0
    p.write_text("")
    fails(lambda: read_csv(p, required=["id"]), "is empty")


# -- values and units -------------------------------------------------------------------------------------------


def test_check_range():
    check_range([0.1, 0.5, 1.0], lo=0, hi=1, what="score")
    fails(
        lambda: check_range([0.1, 1.5, 2], lo=0, hi=1, what="score", lines=[2, 3, 4], path="p.json"),
        "line 3: score = 1.5 is outside [0, 1] (2 of 3 values)",
        "p.json",
    )
    fails(lambda: check_range([1, np.nan], what="height"), "height = nan")
    fails(lambda: check_range([-1], lo=0, what="width", unit="px"), "outside [0, ] px")


def test_check_coordinates_units():
    check_coordinates([-96.1, -96.2], [41.1, 41.2], geographic=True)
    check_coordinates([500100.0, 500200.0], [4550000.0, 4550100.0], geographic=False)
    fails(
        lambda: check_coordinates(
            [500100.0, 500200.0], [4550000.0, 4550100.0], geographic=True, path="log.csv", lines=[2, 3]
        ),
        "line 2: coordinates (500100, 4.55e+06) are not degrees",
        "projected metres",
        "log.csv",
    )
    fails(lambda: check_coordinates([41.1, 41.2], [-96.1, -96.2], geographic=True), "look swapped")
    fails(lambda: check_coordinates([-96.1, -96.2], [41.1, 41.2], geographic=False), "look like degrees")
    fails(lambda: check_coordinates([1.0, np.inf], [1.0, 2.0], geographic=True), "coordinates x = inf")


def test_check_path(tmp_path):
    (tmp_path / "f.txt").write_text("x")
    check_path(tmp_path / "f.txt", "file", key="survey")
    check_path(tmp_path, "dir", key="images")
    check_path(tmp_path, "exists", key="annotations")
    fails(lambda: check_path(tmp_path / "no.txt", "file", key="survey"), "'survey': file not found", exc=ConfigError)
    fails(lambda: check_path(tmp_path, "file", key="survey"), "must be a file, but this is a folder", exc=ConfigError)
    fails(
        lambda: check_path(tmp_path / "f.txt", "dir", key="images"),
        "must be a folder, but this is a file",
        exc=ConfigError,
    )


# -- rasters, vectors, JPEG ---------------------------------------------------------------------------------------


UTM_10CM = Affine(0.1, 0, 500000, 0, -0.1, 4500000)


def write_raster(path, data, crs="EPSG:32614", nodata=None, transform=UTM_10CM):
    data = np.atleast_3d(data).transpose(2, 0, 1) if data.ndim == 2 else data
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=data.shape[2],
        height=data.shape[1],
        count=data.shape[0],
        dtype=data.dtype,
        crs=crs,
        transform=transform,
        nodata=nodata,
    ) as ds:
        ds.write(data)
    return path


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
def test_check_raster(tmp_path):
    good = np.full((3, 40, 50), np.nan, dtype="float32")
    good[:, 17, 23] = 1.0  # one valid pixel, missed by a decimated look on a big raster, found by the scan
    info = check_raster(write_raster(tmp_path / "ms.tif", good), bands=[1, 3])
    assert (info.count, info.width, info.height) == (3, 50, 40)
    fails(lambda: check_raster(tmp_path / "ms.tif", bands=[4]), "has 3 band(s), band 4 is needed", "ms.tif")
    fails(lambda: check_raster(tmp_path / "ms.tif", bands=5), "band 5 is needed")
    write_raster(tmp_path / "nan.tif", np.full((20, 20), np.nan, dtype="float32"))
    fails(lambda: check_raster(tmp_path / "nan.tif"), "band 1 holds no valid data", "nan.tif")
    check_raster(tmp_path / "nan.tif", allow_empty=True)
    write_raster(tmp_path / "nodata.tif", np.full((20, 20), -9999, dtype="int16"), nodata=-9999)
    fails(lambda: check_raster(tmp_path / "nodata.tif", what="DSM"), "DSM: band 1 holds no valid data")
    write_raster(tmp_path / "nocrs.tif", np.ones((20, 20), dtype="uint8"), crs=None)
    fails(lambda: check_raster(tmp_path / "nocrs.tif"), "has no CRS")
    write_raster(tmp_path / "nogeo.tif", np.ones((20, 20), dtype="uint8"), transform=Affine.identity())
    fails(lambda: check_raster(tmp_path / "nogeo.tif"), "has no georeferencing")
    check_raster(tmp_path / "nocrs.tif", require_crs=False)
    (tmp_path / "cut.tif").write_bytes((tmp_path / "ms.tif").read_bytes()[:300])
    fails(lambda: check_raster(tmp_path / "cut.tif"), "cut.tif")
    fails(lambda: check_raster(tmp_path / "none.tif"), "not found")


def test_check_raster_scans_a_big_raster_in_strips(tmp_path):
    data = np.zeros((2100, 2100), dtype="uint8")
    data[1001, 1001] = 7  # not on the decimated grid (every third pixel, from 0)
    write_raster(tmp_path / "big.tif", data, nodata=0)
    check_raster(tmp_path / "big.tif")
    write_raster(tmp_path / "big0.tif", np.zeros((2100, 2100), dtype="uint8"), nodata=0)
    fails(lambda: check_raster(tmp_path / "big0.tif"), "holds no valid data")


def test_check_raster_looks_at_a_few_blocks_before_any_scan(tmp_path, monkeypatch):
    """A big tiled raster is judged from at most 8 x 8 of its tiles (not a decimated read, which decompresses
    every tile of a raster without overviews); only a band that looks empty there is scanned in full."""
    path = tmp_path / "tiled.tif"
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=4096,
        height=4096,
        count=1,
        dtype="float32",
        nodata=-1,
        crs="EPSG:32615",
        transform=Affine(0.01, 0, 0, 0, -0.01, 0),
        tiled=True,
        blockxsize=256,
        blockysize=256,
        compress="deflate",
    ) as ds:
        ds.write(np.full((4096, 4096), -1, "float32"), 1)
        ds.write(np.ones((256, 256), "float32"), 1, window=rasterio.windows.Window(2304, 2304, 256, 256))
    with rasterio.open(path) as ds:
        windows = validate_gis._sampled_windows(ds, 1)
    assert len(windows) == 64 and all(w.width == w.height == 256 for w in windows)
    # a band valid in one tile the sample does not include is still found by the scan
    monkeypatch.setattr(validate_gis, "SAMPLED_BLOCKS", 2)
    check_raster(path)
    read = []
    real = rasterio.io.DatasetReader.read
    monkeypatch.setattr(rasterio.io.DatasetReader, "read", lambda self, *a, **k: read.append(k) or real(self, *a, **k))
    monkeypatch.setattr(validate_gis, "SAMPLED_BLOCKS", 8)
    check_raster(path)  # tile (9, 9) of 16 x 16 is among the 8 x 8 sampled: no scan
    assert 0 < len(read) <= 64 and all(k["window"].width == 256 for k in read)
    # a truncated copy fails: the sample holds the last tile, at the end of the file
    (tmp_path / "cut.tif").write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])
    fails(lambda: check_raster(tmp_path / "cut.tif"), "cannot be read", "cut.tif")


@pytest.mark.filterwarnings("ignore:'crs' was not provided")
def test_check_vector(tmp_path):
    gdf = gpd.GeoDataFrame({"plant_id": [1, 2]}, geometry=[box(0, 0, 1, 1), box(2, 2, 3, 3)], crs="EPSG:32614")
    path = tmp_path / "plants.gpkg"
    gdf.to_file(path, layer="plants")
    gdf.iloc[:0].to_file(path, layer="empty")
    assert check_vector(path, layer="plants") == "plants"
    fails(lambda: check_vector(path, layer="plnts"), "no layer 'plnts'; did you mean 'plants'?", "plants.gpkg")
    fails(lambda: check_vector(path), "has 2 layers")
    fails(lambda: check_vector(path, layer="empty"), "has no features")
    check_vector(path, layer="empty", allow_empty=True)
    nocrs = tmp_path / "nocrs.gpkg"
    gpd.GeoDataFrame({"a": [1]}, geometry=[box(0, 0, 1, 1)]).to_file(nocrs)
    fails(lambda: check_vector(nocrs), "has no CRS", "nocrs.gpkg")
    assert check_vector(nocrs, require_crs=False) == "nocrs"
    (tmp_path / "bad.gpkg").write_bytes(b"not a geopackage at all")
    fails(lambda: check_vector(tmp_path / "bad.gpkg"), "cannot be opened as vector data")
    fails(lambda: check_vector(tmp_path / "none.gpkg"), "not found")


def test_check_jpeg(tmp_path):
    rng = np.random.default_rng(0)
    path = tmp_path / "IMG_1.JPG"
    Image.fromarray(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)).save(path, quality=90)
    check_jpeg(path, decode=True)
    padded = tmp_path / "padded.jpg"
    padded.write_bytes(path.read_bytes() + b"\x00" * 64)
    check_jpeg(padded, decode=True)
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    fails(lambda: check_jpeg(cut), "truncated", "cut.jpg")
    # right markers around a damaged header: only decoding finds it
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(b"\xff\xd8" + bytes(range(256)) * 4 + b"\xff\xd9")
    check_jpeg(broken)  # markers only
    fails(lambda: check_jpeg(broken, decode=True), "cannot be decoded", "broken.jpg")
    (tmp_path / "png.jpg").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 20)
    fails(lambda: check_jpeg(tmp_path / "png.jpg"), "not a JPEG")
