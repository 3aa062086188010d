"""Plant crops from the raw photos: every polygon, cut from every photo that sees it whole (or its best few).

    survey = survey_cameras("odm_project")                      # the cameras, the map CRS, the DSM
    result = cut_crops(plants, survey, "crops_out", CropSettings(best=3))

``plants`` is a GeoDataFrame with a ``plant_id`` column (module 9's reader gives one from any polygon file, in
any CRS). Out: ``crops/<photo>/<plant>.jpg`` (the crop from the original photo, with a margin), ``index.csv``
(one row per crop: the view and the plant's outline in the crop's pixels, as WKT) and ``index.gpkg`` (the same
rows on the plants' polygons). Every photo is decoded once; its crops appear together (:mod:`.cut`), so a run
stopped by Ctrl-C resumes where it stopped when started again with the same settings.
"""

from __future__ import annotations

import json
import re
import shutil
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from matchplant.core.formats.vectors import write_vector
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.io import atomic_open, write_json
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.core.runtime.readers import read_record
from matchplant.views.cameras import Survey
from matchplant.views.config import CropSettings
from matchplant.views.cut import COLUMNS, PARTIAL, ROWS_FILE, crop_box, cut_photo, decode
from matchplant.views.outlines import drape
from matchplant.views.plan import all_views, best_views

log = get_logger("views")

CROPS_DIR = "crops"
INDEX_CSV = "index.csv"
INDEX_GPKG = "index.gpkg"
SETTINGS_FILE = "crops.json"


@dataclass
class CropResult:
    """What a run wrote."""

    index_csv: Path
    index_gpkg: Path
    crops: int
    photos: int
    plants_seen: int
    plants: int


def file_names(ids) -> list[str]:
    """A file name per plant id (characters a file system may refuse replaced; made unique with the row)."""
    names = [re.sub(r"[^A-Za-z0-9_.-]", "_", str(i)) or "_" for i in ids]
    if len(set(n.lower() for n in names)) < len(names):
        names = [f"{k:06d}_{n}" for k, n in enumerate(names)]
    return names


def cut_crops(plants, survey: Survey, out: str | Path, settings: CropSettings | None = None) -> CropResult:
    """Cut every plant of ``plants`` (GeoDataFrame with ``plant_id``) from the survey's photos into ``out``."""
    out = Path(out)
    settings = settings or CropSettings()
    if plants.crs is None:
        raise InputError(
            "the plant polygons have no CRS", path=plants.attrs.get("source"), fix="give polygons_crs (e.g. EPSG:32614)"
        )
    plants = plants.to_crs(survey.crs).reset_index(drop=True)
    _check_settings(out, plants, survey, settings)
    outlines = drape(plants.geometry.values, survey.dsm, settings.levels)
    views = best_views(all_views(survey.cameras, outlines), settings.best)
    if len(views.plant) == 0:
        raise InputError(
            f"no photo sees any of the {len(plants)} polygons whole",
            path=plants.attrs.get("source"),
            fix="check that the polygons are of this project's field (their CRS, or polygons_crs for a CSV)",
        )
    first = np.r_[True, views.plant[1:] != views.plant[:-1]]
    rank = np.arange(len(views.plant)) - np.maximum.accumulate(np.where(first, np.arange(len(views.plant)), 0)) + 1
    ids = plants["plant_id"].astype(str).tolist()
    names = file_names(ids)
    folder = out / CROPS_DIR
    for stale in folder.glob(PARTIAL + "*"):  # a photo interrupted last time: cut again
        shutil.rmtree(stale, ignore_errors=True)
    todo = np.unique(views.camera)
    log.info(
        "%d crops of %d of %d plants from %d photos (%s)",
        len(views.plant),
        len(np.unique(views.plant)),
        len(plants),
        len(todo),
        f"best {settings.best} views" if settings.best else "every whole view",
    )
    pending = [k for k in todo if not (folder / survey.cameras[k].name).is_dir()]
    if len(pending) < len(todo):
        log.info("%d of %d photos were cut by an earlier run", len(todo) - len(pending), len(todo))
    plan = _Plan(views, rank, ids, names, outlines, settings)
    by_camera = np.argsort(views.camera, kind="stable")  # each photo's views, in plant order
    bounds = np.searchsorted(views.camera[by_camera], [todo, todo + 1])
    # the next photo is decoded in a thread while this one is cut (OpenCV lets go of the GIL): two photos in memory
    with ThreadPoolExecutor(max_workers=1) as pool:
        ahead = pool.submit(decode, survey.cameras[pending[0]]) if pending else None
        for n, k in enumerate(progress(pending, desc="crops", unit="photo")):
            img = ahead.result()
            ahead = pool.submit(decode, survey.cameras[pending[n + 1]]) if n + 1 < len(pending) else None
            j = int(np.searchsorted(todo, k))
            _cut(survey.cameras[k], img, by_camera[bounds[0, j] : bounds[1, j]], plan, folder)
            del img
    return _write_index(out, plants, [survey.cameras[k].name for k in todo], len(np.unique(views.plant)))


@dataclass
class _Plan:
    """Everything the cutting of each photo reads: the views chosen, their ranks, the plants' ids, file names
    and rings, the settings."""

    views: object
    rank: np.ndarray
    ids: list
    names: list
    outlines: object
    settings: CropSettings


def _cut(cam, img, sel, plan: _Plan, folder: Path) -> None:
    """Cut the views ``sel`` (all of camera ``cam``) from its decoded photo into ``folder/<photo>``."""
    views, rank, ids, names, settings = plan.views, plan.rank, plan.ids, plan.names, plan.settings
    w, h = cam.shot.camera.width, cam.shot.camera.height
    boxes = crop_box(views.box[sel], w, h, settings.margin, settings.margin_px)
    rows = [
        {
            "plant_id": ids[p],
            "photo": cam.name,
            "crop": f"{CROPS_DIR}/{cam.name}/{names[p]}.jpg",
            "rank": int(rank[i]),
            "off_nadir_deg": round(float(views.off_nadir[i]), 3),
            "distance_m": round(float(views.distance[i]), 4),
            "gsd_cm": round(100 * float(views.gsd[i]), 4),
        }
        for i, p in zip(sel, views.plant[sel])
    ]
    plants = views.plant[sel]
    cut_photo(
        cam, img, plants, boxes, rows, plan.outlines, [names[p] for p in plants], folder / cam.name, settings.quality
    )


def _check_settings(out: Path, plants, survey: Survey, settings: CropSettings) -> None:
    """Refuse to mix crops of other settings or other plants into an earlier run's folder (resume needs the same)."""
    record = {
        "settings": asdict(settings),
        "plants": len(plants),
        "plant_ids": pd.util.hash_pandas_object(plants["plant_id"].astype(str), index=False).sum().item() % (1 << 61),
        "cameras": [c.name for c in survey.cameras],
        "source": survey.source,
    }
    path = out / SETTINGS_FILE
    earlier = read_record(
        path, what="the crops' settings record", fix="delete the output folder's crops.json, or choose another folder"
    )
    if earlier is not None:
        if json.dumps(earlier, sort_keys=True) != json.dumps(record, sort_keys=True):  # tuples and lists alike
            raise ConfigError(
                "the output folder holds crops of another run (other settings, plants or photos)",
                path=out,
                fix="choose another output folder, or delete this one to start again",
            )
        log.info("resuming the crops in %s", out)
        return
    out.mkdir(parents=True, exist_ok=True)
    write_json(path, record)


def _write_index(out: Path, plants, photos: list[str], seen: int) -> CropResult:
    """Gather every photo's rows into ``index.csv`` and ``index.gpkg`` (the rows on the plants' polygons)."""
    parts = [pd.read_csv(out / CROPS_DIR / name / ROWS_FILE, dtype={"plant_id": str, "photo": str}) for name in photos]
    table = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=list(COLUMNS))
    table = table.sort_values(["plant_id", "rank"], kind="stable").reset_index(drop=True)
    with atomic_open(out / INDEX_CSV, "w") as fh:
        table.to_csv(fh, index=False)
    shapes = plants[["plant_id", plants.geometry.name]].assign(plant_id=plants["plant_id"].astype(str))
    gdf = shapes.merge(table, on="plant_id", how="inner")
    write_vector(gdf, out / INDEX_GPKG, layer="crops")
    return CropResult(out / INDEX_CSV, out / INDEX_GPKG, len(table), len(photos), seen, len(plants))
