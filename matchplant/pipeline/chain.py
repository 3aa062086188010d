"""The season's chain of steps, built in one place for ``matchplant init`` (:mod:`matchplant.pipeline.season`) and
the demo (:mod:`matchplant.demo_pipeline`): each step's name and module, and the keys by which it reads what an
earlier step wrote (``${4_annotate.output_dir}/annotations.json``, ...). The caller gives what differs: where
the photos are and each step's other keys, in the order they are written."""

from __future__ import annotations

ANNOTATIONS = "${4_annotate.output_dir}/annotations.json"
TRAINED = "${6_train.output_dir}/checkpoints/best.pt"
PREDICTIONS = "${7_detect.output_dir}/predictions.json"
PLANTS = "${8_plants.output_dir}/plants.gpkg"


def step(name: str, module: str, **config) -> dict:
    """One step of a pipeline file: its name, its module and its settings."""
    return {"name": name, "module": module, "config": config}


def geotag_steps(images: str, gnss_log: str, log_crs: str, survey: str, survey_crs: str, **gcp) -> list[dict]:
    """Modules 0 and 1, before ODM: the log's positions into the photos, then the ground control points found in
    the geotagged copies (``gcp``: module 1's other keys)."""
    return [
        step("0_gps", "gps_embeder", images=images, gnss_log=gnss_log, log_crs=log_crs),
        step("1_gcp", "gcp_finder", images="${0_gps.output_dir}/images", survey=survey, survey_crs=survey_crs, **gcp),
    ]


def map_steps(project: str, predictions: str, *, plants: dict | None = None, stats: dict | None = None) -> list[dict]:
    """Modules 8 and 9: the detections on the map, then per-plant statistics of the plants module 8 wrote
    (``plants``, ``stats``: their other keys)."""
    return [
        step("8_plants", "plant_projection", project=project, predictions=predictions, **(plants or {})),
        step("9_stats", "spatial_stat_extractor", polygons=PLANTS, **(stats or {})),
    ]


def season_chain(
    project: str,
    photos: str,
    *,
    annotations: str | None = None,
    checkpoint: str | None = None,
    odm: bool = True,
    select: dict | None = None,
    annotate: dict | None = None,
    tiles: dict | None = None,
    train: dict | None = None,
    detect: dict | None = None,
    plants: dict | None = None,
    stats: dict | None = None,
) -> list[dict]:
    """The steps from module 2 on, each reading what the one before wrote.

    Module 2 when the project is ODM's (``odm``), module 3 always; with ``annotations`` (plant boxes on
    ``photos``) modules 4 to 6 train a detector and
    module 7 detects with it; with only a ``checkpoint`` module 7 detects with that; with neither the chain stops
    at module 3 (the photos to annotate). Modules 8 and 9 follow module 7. ``select``, ``annotate``, ``tiles``,
    ``train``, ``detect``, ``plants`` and ``stats`` are the other keys of modules 3 to 9.
    """
    steps = [step("2_odm", "odm_runner", project_dir=project, check_only=True)] if odm else []
    steps.append(step("3_select", "min_img_finder", project_dir=project, **(select or {})))
    if annotations is not None:
        steps += [
            step("4_annotate", "bbox_drawer", images=photos, import_coco=annotations, **(annotate or {})),
            step("5_tiles", "img_splitter", images=photos, annotations=ANNOTATIONS, **(tiles or {})),
            step(
                "6_train",
                "model_train",
                train_json="${5_tiles.output_dir}/train.json",
                val_json="${5_tiles.output_dir}/val.json",
                **(train or {}),
            ),
        ]
        checkpoint = TRAINED
    if checkpoint is None:
        return steps
    steps.append(step("7_detect", "model_test", checkpoint=checkpoint, **(detect or {})))
    return steps + map_steps(project, PREDICTIONS, plants=plants, stats=stats)
