"""``matchplant crops`` and ``matchplant map`` from the command line, and their bad inputs."""

from __future__ import annotations

import json

import geopandas as gpd
import pandas as pd
import pytest
from project_exports import write_exports
from views_truth import true_plants

from matchplant import cli
from matchplant.core.runtime.config import load_config
from matchplant.spatial_stat_extractor import SpatialStatExtractorConfig
from matchplant.spatial_stat_extractor.run import extract_and_write


@pytest.fixture(scope="module")
def plants_file(tiny_field, tmp_path_factory):
    """The tiny field's true plant outlines with their traits, as a GeoJSON in WGS 84 (any CRS will do)."""
    gdf = true_plants(tiny_field).to_crs("EPSG:4326")
    path = tmp_path_factory.mktemp("plants") / "plants.geojson"
    gdf.to_file(path)
    return path


def test_crops_then_map_from_the_command_line(tiny_field, plants_file, tmp_path):
    out = tmp_path / "field"
    assert cli.main(["crops", "--polygons", str(plants_file), "--project", str(tiny_field.root), "--best", "2",
                     "--out", str(out / "crops")]) == 0  # fmt: skip
    index = pd.read_csv(out / "crops" / "index.csv")
    assert index.groupby("plant_id").size().max() == 2 and index.plant_id.nunique() == 46
    assert all((out / "crops" / c).is_file() for c in index.crop)
    html = out / "map.html"
    assert cli.main(["map", "--plants", str(plants_file), "--crops", str(out / "crops" / "index.csv"),
                     "--orthophoto", str(tiny_field.orthophoto), "--out", str(out)]) == 0  # fmt: skip
    text = html.read_text(encoding="utf-8")
    assert "const DATA = " in text and '"height"' in text and "crops/crops/" in text


def test_bad_inputs_name_the_file_and_the_fix(tiny_field, plants_file, tmp_path, capsys):
    missing = tmp_path / "nope.gpkg"
    assert cli.main(["crops", "--polygons", str(missing), "--project", str(tiny_field.root),
                     "--out", str(tmp_path / "a")]) == 2  # fmt: skip
    assert "nope.gpkg" in capsys.readouterr().err
    empty = tmp_path / "empty_project"
    empty.mkdir()
    assert cli.main(["crops", "--polygons", str(plants_file), "--project", str(empty),
                     "--out", str(tmp_path / "b")]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "reconstruction.json" in err and "Traceback" not in err
    no_photos = tmp_path / "photos"
    no_photos.mkdir()
    assert cli.main(["crops", "--polygons", str(plants_file), "--project", str(tiny_field.root),
                     "--set", f"photos={no_photos}", "--out", str(tmp_path / "c")]) == 2  # fmt: skip
    assert "photos" in capsys.readouterr().err
    elsewhere = gpd.read_file(plants_file)
    elsewhere.geometry = elsewhere.translate(0.01, 0.01)  # about a kilometre away: another field
    elsewhere.to_file(tmp_path / "elsewhere.geojson")
    assert cli.main(["crops", "--polygons", str(tmp_path / "elsewhere.geojson"), "--project", str(tiny_field.root),
                     "--out", str(tmp_path / "d")]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "does not overlap" in err and "dsm.tif" in err and "Traceback" not in err


def test_crops_from_metashape_and_pix4d_on_the_command_line(tiny_field, camera_exports, plants_file, tmp_path, capsys):
    """A Pix4D project folder named by --project-type gives the views ODM gives; a Metashape export with no DSM
    beside it, or a project of the other program, is refused with the fix (exit 2, no traceback)."""
    args = ["crops", "--polygons", str(plants_file), "--set", f"photos={tiny_field.images}", "--best", "2"]
    assert cli.main([*args, "--project", str(tiny_field.root), "--out", str(tmp_path / "odm")]) == 0
    assert cli.main([*args, "--project", str(camera_exports / "p4d"), "--project-type", "pix4d",
                     "--set", f"dsm={tiny_field.dsm}", "--out", str(tmp_path / "p4d")]) == 0  # fmt: skip
    odm, p4d = (pd.read_csv(tmp_path / k / "index.csv") for k in ("odm", "p4d"))
    assert set(zip(p4d.plant_id, p4d.photo)) == set(zip(odm.plant_id, odm.photo))
    capsys.readouterr()
    meta = camera_exports / "meta" / "cameras.xml"
    assert cli.main([*args, "--project", str(meta), "--out", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err
    assert "DSM not found" in err and "Export DEM" in err and "Traceback" not in err
    assert cli.main([*args, "--project", str(meta), "--project-type", "pix4d", "--out", str(tmp_path / "x")]) == 2
    assert "not a pix4d project" in capsys.readouterr().err


@pytest.mark.parametrize("program", ["odm", "pix4d"])
def test_module_9_writes_the_crops_and_the_map(tiny_field, tmp_path, program):
    """Module 9 with ``views.project``: the crops of its plants beside its statistics, and map.html with the
    plots and the project's orthophoto, reading only its own folder (the crops' relative paths). A Pix4D project
    folder (photos, DSM and mosaic where Pix4D puts them) with ``views.project_type``."""
    project = tiny_field.root if program == "odm" else write_exports(tiny_field.root, tmp_path / "exports")["pix4d"]
    grid = json.loads(tiny_field.plots_json.read_text())
    cfg = load_config(
        SpatialStatExtractorConfig,
        None,
        [
            f"polygons={tiny_field.map_boxes}",
            f"polygons_crs={grid['crs']}",
            f"output_dir={tmp_path / 'out'}",
            f"rasters.dsm={tiny_field.dsm}",
            f"rasters.dtm={tiny_field.dtm}",
            f"plots.corners={json.dumps(grid['corners'])}",
            f"plots.columns={grid['columns']}",
            f"plots.ranges={grid['ranges']}",
            f"plots.plant_spacing={grid['plant_spacing']}",
            f"views.project={project}",
            f"views.project_type={program}",
            "views.best=2",
        ],
    )
    _, table, _, written = extract_and_write(cfg)
    index = pd.read_csv(written["crops_index"])
    assert set(index.plant_id) <= set(table.plant_id) and index.groupby("plant_id").size().max() == 2
    assert all((tmp_path / "out" / "crops" / c).is_file() for c in index.crop)
    text = written["map"].read_text(encoding="utf-8")
    data = json.loads(text.split("const DATA = ", 1)[1].split(";</script>", 1)[0].replace("<\\/", "</"))
    assert len(data["plants"]["ids"]) == len(table) and len(data["plots"]["ids"]) == grid["columns"] * grid["ranges"]
    assert data["ortho"] is not None and all(c[0].startswith("crops/crops/") for v in data["crops"].values() for c in v)
