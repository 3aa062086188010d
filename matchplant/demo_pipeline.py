"""The demo's pipeline: every module, each reading the files the one before wrote (``pipeline_spec``), and
modules 8 and 9 again on the realistic field (``noisy_spec``); written with the comments of ``STEP_NOTES`` by
:func:`matchplant.pipeline.write.write_pipeline`. The chain itself, shared with ``matchplant init``, is
:func:`matchplant.pipeline.chain.season_chain`."""

from __future__ import annotations

from pathlib import Path

from matchplant.core.runtime.readers import read_record
from matchplant.pipeline.chain import geotag_steps, season_chain
from matchplant.pipeline.chain import map_steps as chain_map_steps

HELD_OUT = "heldout_images"  # the photos the detector never saw, linked for module 7
NOISY = "noisy"  # modules 8 and 9 on the realistic field, under <out>/noisy

# what each step does and the keys a user typically changes: the comments of the demo's pipeline.yaml
STEP_NOTES = {
    "0_gps": "module 0: GNSS positions from the drone's log into the photos' EXIF. Change images, gnss_log, log_crs.",
    "1_gcp": "module 1: ground control points found in the photos; gcp_list.txt for ODM. Change survey, survey_crs.",
    "2_odm": "module 2: OpenDroneMap's outputs checked (check_only); without it ODM runs in Docker.",
    "3_select": "module 3: the fewest photos that cover the field (to annotate). Change project_dir.",
    "4_annotate": "module 4: plant boxes on those photos; here imported from a COCO file (import_coco), in a "
    "season drawn with `matchplant bbox_drawer --gui`.",
    "5_tiles": "module 5: tiles for training and the train/val/test split. Change tile_size and overlap "
    "(`matchplant inspect annotations.json` recommends them).",
    "6_train": "module 6: the detector. This demo fixes its recipe (MobileNetV3, SGD 0.02, 2 epochs) so that every "
    "machine trains the same model;\nfor a season leave model.architecture: auto and set max_minutes (module 6's "
    "README). A re-run after Ctrl-C continues the training.",
    "7_detect": "module 7: test-set AP and detection on the photos (detect.images). Change "
    "detect.score_threshold, detect.images.",
    "8_plants": "module 8: the detected plants on the map (plants.gpkg). Change project, predictions, min_score.",
    "9_stats": "module 9: per-plant height, NDVI and plot statistics. Change rasters (dsm, dtm, multispectral with "
    "red_band/nir_band) and plots.",
}


RECORD_FIX = "delete it; running the demo again writes it again"


def demo_record(path: Path) -> dict:
    """A file an earlier demo run wrote, read back (empty when there is none); a damaged one is named."""
    return read_record(path, what="a file of an earlier demo run", fix=RECORD_FIX, default={})


def pipeline_spec(
    field: Path, crs: str, *, epochs: int, minutes: float, pretrained: str, tile: int, threads: int = 0
) -> dict:
    """The demo's pipeline: every module, each reading the files the one before wrote."""
    net = int(round(tile * 2.5))
    cpu = {"threads": threads} if threads else {}  # absent when automatic, so earlier runs' steps stay finished
    # small plants (about 20 px) need the tiles enlarged 2.5x for MobileNet's coarse feature maps; anchors
    # are in the enlarged pixels. A 128 px tile holds at most ~40 plants: far fewer proposals than
    # torchvision's defaults (2000/1000) keep the box head cheap on a CPU
    model = {
        "architecture": "fasterrcnn_mobilenet_v3_large_fpn",
        "pretrained": pretrained,
        "min_size": net,
        "max_size": net,
        "anchor_sizes": [[net // 8, net // 4, net // 2]] * 3,
        "rpn": {
            "pre_nms_top_n_train": 1000,
            "post_nms_top_n_train": 400,
            "pre_nms_top_n_test": 300,
            "post_nms_top_n_test": 100,
        },
        "roi": {"batch_size_per_image": 64},
    }
    train = {
        "model": model,
        "epochs": epochs,
        "max_minutes": minutes,
        "batch_size": 4,
        "num_workers": 0,
        "warmup_iters": 20,
        "step_size": 20,
        "save_every": 0,
        **cpu,
        "lr": {"backbone": 0.02, "fpn": 0.02, "rpn": 0.02, "roi_heads": 0.02},
    }
    steps = [
        *geotag_steps(
            "${field}/images_nogps",
            "${field}/gnss/events.txt",
            "${crs}",
            "${field}/gcp/gcp_survey.csv",
            "${crs}",
            auto=True,
        ),
        *season_chain(
            "${field}",
            "${3_select.output_dir}/images",
            annotations="${field}/truth/boxes_undistorted.json",
            annotate={"min_score": 0.0},
            tiles={"tile_size": tile, "overlap": tile // 4, "negative_share": 0.2, "split": [0.55, 0.15, 0.3]},
            train=train,
            # detection on the photos the detector never saw (module 5's test split and module 3's unselected
            # photos): only they are projected and scored
            detect={
                "evaluate": {"dataset_json": "${5_tiles.output_dir}/test.json"},
                **cpu,
                "detect": {"images": "${held_out_images}", "tile_size": tile, "overlap": tile // 4},
            },
            **map_settings(field),
        ),
    ]
    return {"output_dir": ".", "field": field.name, "crs": crs, "held_out_images": HELD_OUT, "steps": steps}


def map_settings(field: Path, bands: tuple[int, int] | None = None) -> dict[str, dict]:
    """Modules 8 and 9's other keys on the demo's field: both projection modes scored against the truth, the
    rasters and the plot grid. ``bands``: red and NIR band numbers of the multispectral raster (None: the exact
    field's, 1 and 2)."""
    rasters = {
        "dsm": "${field}/odm_dem/dsm.tif",
        "dtm": "${field}/odm_dem/dtm.tif",
        "multispectral": "${field}/multispectral/multispectral.tif",
        "rgb": "${field}/odm_orthophoto/odm_orthophoto.tif",
    }
    if bands:
        rasters.update(red_band=bands[0], nir_band=bands[1])
    return {
        "plants": {"mode": "both", "evaluate": {"reference": "${field}/truth/map_boxes.csv"}},
        "stats": {"rasters": rasters, "plots": _plots_section(field)},
    }


def map_steps(field: Path, predictions: str, bands: tuple[int, int] | None = None) -> list[dict]:
    """Modules 8 and 9: the detections on the map, then per-plant and per-plot statistics (:func:`map_settings`)."""
    return chain_map_steps("${field}", predictions, **map_settings(field, bands))


def noisy_spec(field: Path, crs: str, predictions: Path) -> dict:
    """Modules 8 and 9 on the realistic field with the exact run's detections (the photos are the same);
    its 5-band raster holds red in band 3 and NIR in band 5 (simfield/noise.py)."""
    return {
        "output_dir": NOISY,
        "field": field.name,
        "crs": crs,
        "predictions": predictions.relative_to(field.parent).as_posix(),
        "steps": map_steps(field, "${predictions}", bands=(3, 5)),
    }


def _plots_section(field: Path) -> dict:
    """Module 9's plot grid: the field's corners, columns, ranges and spacing (as a breeder measures them),
    and the field book; read from the generator's plot layout."""
    grid = demo_record(field / "truth" / "plots.json")
    if not grid:
        return {}
    return {
        "corners": grid["corners"],
        "columns": grid["columns"],
        "ranges": grid["ranges"],
        "rows_per_plot": grid["rows_per_plot"],
        "plant_spacing": grid["plant_spacing"],
        "field_book": "${field}/truth/field_book.csv",
        "figure_trait": "ndvi_canopy_mean",
    }
