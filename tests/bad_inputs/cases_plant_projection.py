"""Module 8 (plant_projection): predictions of the wrong shape or with impossible values, nothing to project
(min_score above every score, unknown image names, a DSM elsewhere), broken project pieces, and inputs that
must work (names that differ from the shot ids by extension or case, non-ASCII paths, BOM/CRLF JSON, a plain
results list with images_from, one image ODM did not place: a warning and unprojected_boxes.csv)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import rasterio
from affine import Affine
from cases_odm_runner import COORDS, DSM, UND_RECON, edit_json, first_camera, project, rewrite_raster, truncate
from harness import Case, Work

REPORT = ("unprojected_boxes.csv",)


def preds(w: Work) -> dict:
    return json.loads((w.artifacts / "predictions.json").read_text())


def write_preds(w: Work, data, name: str = "predictions.json") -> Path:
    path = w.inputs / name
    path.write_text(json.dumps(data))
    return path


def args(w: Work, proj: Path, predictions: Path, *extra: str) -> list[str]:
    a = ["--set", f"project={proj}", "--set", f"predictions={predictions}", "--set", f"output_dir={w.out}"]
    for e in extra:
        a += ["--set", e]
    return a


def changed_preds(change, *extra: str):
    """A case preparer: the project as it is, the predictions changed by ``change(data)``."""

    def prepare(w: Work) -> list[str]:
        data = preds(w)
        data = change(data) or data
        return args(w, project(w), write_preds(w, data), *extra)

    return prepare


def broken_project(change, *extra: str):
    def prepare(w: Work) -> list[str]:
        proj = project(w)
        change(proj)
        return args(w, proj, w.copy("predictions.json"), *extra)

    return prepare


def set_first(key: str, value):
    return lambda d: d["predictions"][0].update({key: value})


def rename_images(rule):
    def change(d):
        for im in d["images"]:
            im["file_name"] = rule(im["file_name"])
            im.pop("shot_id", None)

    return change


def coco_dataset(d):
    return {"images": d["images"], "categories": d["categories"], "annotations": d["predictions"]}


def all_scores(value: float):
    def change(d):
        for p in d["predictions"]:
            p["score"] = value

    return change


def in_percent(d):
    for p in d["predictions"]:
        p["score"] = round(100 * p["score"])


def dsm_elsewhere(w: Work) -> list[str]:
    """A DSM of another field: the same heights 2 km east."""
    path = w.inputs / "dsm other field.tif"
    with rasterio.open(w.artifacts / "field" / DSM) as src:
        profile, data = src.profile, src.read()
    profile["transform"] = Affine.translation(2000, 0) @ profile["transform"]
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data)
    return args(w, project(w), w.copy("predictions.json"), f"dsm={path}")


def dsm_key_empty(w: Work) -> list[str]:
    path = w.copy("field/" + DSM, "dsm_filled.tif")
    rewrite_raster(path, data=-9999, nodata=-9999)
    return args(w, project(w), w.copy("predictions.json"), f"dsm={path}")


def results_list(w: Work, with_images: bool) -> list[str]:
    path = write_preds(
        w,
        [{k: p[k] for k in ("image_id", "category_id", "bbox", "score")} for p in preds(w)["predictions"]],
        "results.json",
    )
    extra = [f"images_from={w.copy('field/truth/boxes_undistorted.json')}"] if with_images else []
    return args(w, project(w), path, *extra)


def unicode_paths(w: Work) -> list[str]:
    return args(
        w,
        project(w, "parcela ñ 3 (año 2024)"),
        w.copy("predictions.json", "détections 1.json"),
        "output_dir=" + str(w.out),
    )


def bom_crlf(w: Work) -> list[str]:
    path = w.inputs / "predictions.json"
    path.write_bytes(b"\xef\xbb\xbf" + json.dumps(preds(w), indent=1).replace("\n", "\r\n").encode())
    return args(w, project(w), path)


def rerun_over_old_output(w: Work) -> list[str]:
    w.out.mkdir()
    (w.out / "plants.csv").write_text("stale\n")
    (w.out / "notes.txt").write_text("mine\n")
    return args(w, project(w), w.copy("predictions.json"))


def one_image_unknown(w: Work) -> list[str]:
    data = preds(w)
    data["images"][2]["file_name"] = "OTHER_0003.JPG.tif"
    return args(w, project(w), write_preds(w, data))


def evaluate(w: Work, reference: Path) -> list[str]:
    return [
        "--set",
        "mode=evaluate",
        "--set",
        f"evaluate.reference={reference}",
        "--set",
        f"evaluate.plants={w.copy('plants/plants.gpkg')}",
        "--set",
        f"output_dir={w.out}",
    ]


def reference_csv(w: Work, text_of=None, name: str = "reference.csv") -> list[str]:
    """The field's true map boxes as the reference, their text changed by ``text_of(text)``."""
    text = (w.artifacts / "field" / "truth" / "map_boxes.csv").read_text()
    path = w.inputs / name
    data = text_of(text) if text_of else text
    path.write_bytes(data if isinstance(data, bytes) else data.encode())
    return evaluate(w, path)


def shift_east(text: str) -> str:
    lines = text.splitlines()
    head = lines[0].split(",")
    out = [lines[0]]
    for ln in lines[1:]:
        vals = ln.split(",")
        out.append(",".join(str(float(v) + 1000) if head[k] in ("xmin", "xmax") else v for k, v in enumerate(vals)))
    return "\n".join(out) + "\n"


def excel_export(text: str) -> bytes:
    """Semicolons, decimal commas, BOM and CRLF, as a European spreadsheet saves a CSV."""
    rows = [ln.replace(",", ";").replace(".", ",") for ln in text.splitlines()]
    return b"\xef\xbb\xbf" + "\r\n".join(rows).encode() + b"\r\n"


def evaluated_well(w: Work) -> None:
    m = json.loads((w.out / "evaluation.json").read_text())
    assert m["reference_boxes"] > 0 and m["share_matched"] > 0.9, m


# -- checks --------------------------------------------------------------------------------------------------


def rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def same_plants(w: Work) -> None:
    """The plants of the untouched inputs (the session's module 8 run), none left unprojected."""
    got, ref = rows(w.out / "plants.csv"), rows(w.artifacts / "plants" / "plants.csv")
    assert len(got) == len(ref) > 0
    for a, b in zip(sorted(got, key=lambda r: float(r["xmin"])), sorted(ref, key=lambda r: float(r["xmin"]))):
        assert all(math.isclose(float(a[k]), float(b[k]), abs_tol=1e-3) for k in ("xmin", "ymin", "xmax", "ymax"))
    assert rows(w.out / "unprojected_boxes.csv") == []
    assert (w.out / "plants.gpkg").is_file()


def rerun_replaced(w: Work) -> None:
    same_plants(w)
    assert (w.out / "notes.txt").read_text() == "mine\n"


def dsm_hole(x0: float, x1: float):
    """A case preparer: the project with a nodata hole over the columns ``x0``-``x1`` (shares of the DSM's width)
    and the middle four fifths of its rows, far larger than fill_holes (a field's flooded corner, a failed
    match over low texture)."""

    def prepare(w: Work) -> list[str]:
        proj = project(w)
        with rasterio.open(proj / DSM) as src:
            z = src.read(1)
        h, wd = z.shape
        z[h // 10 : h - h // 10, int(x0 * wd) : int(x1 * wd)] = -9999
        rewrite_raster(proj / DSM, data=z, nodata=-9999)
        return args(w, proj, w.copy("predictions.json"))

    return prepare


def lost_to_the_hole(w: Work) -> None:
    """Boxes lost in the hole are listed with their reason, the others projected."""
    left = rows(w.out / "unprojected_boxes.csv")
    assert left and all("nodata" in r["reason"] for r in left), left
    assert len(rows(w.out / "plants.csv")) > len(left) / 4


def one_image_reported(w: Work) -> None:
    on_third = sum(p["image_id"] == preds(w)["images"][2]["id"] for p in preds(w)["predictions"])
    left = rows(w.out / "unprojected_boxes.csv")
    assert len(left) == on_third > 0 and all(r["source_image"] == "OTHER_0003.JPG.tif" for r in left), left
    assert all("not in the reconstruction" in r["reason"] for r in left)
    assert rows(w.out / "plants.csv")


CASES = [
    Case(
        "m8-undistorted-reconstruction-truncated",
        "plant_projection",
        broken_project(lambda p: truncate(p / UND_RECON)),
        mentions=("undistorted/reconstruction.json", "truncated"),
    ),
    Case(
        "m8-reconstruction-no-shots",
        "plant_projection",
        broken_project(lambda p: edit_json(p / UND_RECON, lambda d: d[0].update(shots={}))),
        mentions=("reconstruction.json", "no images"),
    ),
    Case(
        "m8-unknown-camera-model",
        "plant_projection",
        broken_project(
            lambda p: edit_json(p / UND_RECON, lambda d: first_camera(d).update(projection_type="equirect"))
        ),
        mentions=("reconstruction.json", "equirect", "not support"),
    ),
    Case(
        "m8-dsm-all-nodata",
        "plant_projection",
        broken_project(lambda p: rewrite_raster(p / DSM, data=-9999, nodata=-9999)),
        mentions=("dsm.tif", "no valid"),
    ),
    Case(
        "m8-dsm-without-crs",
        "plant_projection",
        broken_project(lambda p: rewrite_raster(p / DSM, crs=None)),
        mentions=("dsm.tif", "CRS"),
    ),
    Case("m8-dsm-key-all-nodata", "plant_projection", dsm_key_empty, mentions=("dsm_filled.tif", "'dsm'")),
    Case(
        "m8-dsm-hole-over-most-plants",
        "plant_projection",
        dsm_hole(0.05, 0.95),
        mentions=("dsm.tif", "fill_holes = 0.1 m", "m across", "set fill_holes", "--dem-gapfill-steps"),
        outputs_allowed=REPORT,
    ),
    Case("m8-dsm-hole-over-some-plants", "plant_projection", dsm_hole(0.4, 0.55), expect="ok", check=lost_to_the_hole),
    Case(
        "m8-dsm-of-another-field",
        "plant_projection",
        dsm_elsewhere,
        mentions=("dsm other field.tif", "none of"),
        outputs_allowed=REPORT,
    ),
    Case(
        "m8-coords-garbled",
        "plant_projection",
        broken_project(lambda p: (p / COORDS).write_text("WGS84 UTM 14N\n")),
        mentions=("coords.txt", "line"),
    ),
    Case(
        "m8-coco-dataset-as-predictions",
        "plant_projection",
        changed_preds(coco_dataset),
        mentions=("predictions.json", "COCO dataset"),
    ),
    Case(
        "m8-results-list-without-images-from",
        "plant_projection",
        lambda w: results_list(w, False),
        mentions=("results.json", "images_from"),
    ),
    Case(
        "m8-bbox-nan",
        "plant_projection",
        changed_preds(set_first("bbox", [10, float("nan"), 5, 5])),
        mentions=("predictions.json", "predictions[0]", "bbox"),
    ),
    Case(
        "m8-bbox-three-numbers",
        "plant_projection",
        changed_preds(set_first("bbox", [10, 20, 5])),
        mentions=("predictions.json", "predictions[0]"),
    ),
    Case(
        "m8-bbox-negative-size",
        "plant_projection",
        changed_preds(set_first("bbox", [50, 60, -12, 8])),
        mentions=("predictions.json", "predictions[0]", "negative"),
    ),
    Case(
        "m8-score-above-one",
        "plant_projection",
        changed_preds(set_first("score", 1.7)),
        mentions=("predictions.json", "score", "[0, 1]"),
    ),
    Case("m8-scores-in-percent", "plant_projection", changed_preds(in_percent), mentions=("score", "percentage")),
    Case(
        "m8-min-score-above-every-score",
        "plant_projection",
        changed_preds(all_scores(0.3), "min_score=0.8"),
        mentions=("min_score", "0 of"),
    ),
    Case(
        "m8-no-detections",
        "plant_projection",
        changed_preds(lambda d: d.update(predictions=[])),
        mentions=("predictions.json", "no detections"),
    ),
    Case(
        "m8-image-names-of-another-flight",
        "plant_projection",
        changed_preds(rename_images(lambda n: n.replace("SIM_", "DJI_2024_"))),
        mentions=("predictions.json", "not in the reconstruction", "DJI_2024_0001"),
        outputs_allowed=REPORT,
    ),
    Case(
        "m8-tile-offset-not-a-number",
        "plant_projection",
        changed_preds(lambda d: d["images"][1].update(x0="left", y0=0)),
        mentions=("predictions.json", "x0"),
    ),
    Case(
        "m8-bbox-as-text",
        "plant_projection",
        changed_preds(set_first("bbox", ["10", "20", "5", "5"])),
        mentions=("predictions.json", "predictions[0]", "numbers"),
    ),
    Case(
        "m8-image-type-original-for-undistorted-boxes",
        "plant_projection",
        changed_preds(lambda d: None, "image_type=original"),
        mentions=("predictions.json", "image_type"),
        outputs_allowed=REPORT,
    ),
    Case(
        "m8-undistorted-reconstruction-missing",
        "plant_projection",
        broken_project(lambda p: (p / UND_RECON).unlink()),
        mentions=("undistorted/reconstruction.json",),
    ),
    Case(
        "m8-predictions-truncated",
        "plant_projection",
        lambda w: args(w, project(w), (lambda p: (truncate(p, 0.6), p)[1])(w.copy("predictions.json"))),
        mentions=("predictions.json", "line"),
    ),
    Case(
        "m8-predictions-missing",
        "plant_projection",
        lambda w: args(w, project(w), w.inputs / "preds.json"),
        mentions=("predictions", "preds.json"),
    ),
    Case(
        "m8-evaluate-reference-column-renamed",
        "plant_projection",
        lambda w: reference_csv(w, lambda t: t.replace("xmin", "x_min", 1)),
        mentions=("reference.csv", "xmin"),
    ),
    Case(
        "m8-evaluate-reference-of-another-field",
        "plant_projection",
        lambda w: reference_csv(w, shift_east),
        mentions=("reference.csv", "none of"),
    ),
    Case(
        "m8-evaluate-reference-excel-export",
        "plant_projection",
        lambda w: reference_csv(w, excel_export, "référence plantes.csv"),
        expect="ok",
        check=evaluated_well,
    ),
    Case(
        "m8-names-without-original-extension",
        "plant_projection",
        changed_preds(rename_images(lambda n: n.replace(".JPG.tif", ".tif"))),
        expect="ok",
        check=same_plants,
    ),
    Case(
        "m8-names-lower-case-extension",
        "plant_projection",
        changed_preds(rename_images(lambda n: n.replace(".JPG", ".jpg"))),
        expect="ok",
        check=same_plants,
    ),
    Case("m8-unicode-space-paths", "plant_projection", unicode_paths, expect="ok", check=same_plants),
    Case("m8-predictions-bom-crlf", "plant_projection", bom_crlf, expect="ok", check=same_plants),
    Case(
        "m8-results-list-with-images-from",
        "plant_projection",
        lambda w: results_list(w, True),
        expect="ok",
        check=same_plants,
    ),
    Case("m8-rerun-over-old-output", "plant_projection", rerun_over_old_output, expect="ok", check=rerun_replaced),
    Case(
        "m8-one-image-not-in-reconstruction",
        "plant_projection",
        one_image_unknown,
        expect="ok",
        check=one_image_reported,
    ),
]
