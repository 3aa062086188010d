"""Module 9's canopy on the realistic (noisy) synthetic field, with and without NDVI telling leaves from soil
(issue 26): outline IoU with the true canopies, canopy NDVI r and height r against the truth, canopy/box
area of the plants under 1 m, flags and unclaimed canopies.

    python bench/bench_canopy_noisy.py                  # the small field, noise realistic, generated once
    python bench/bench_canopy_noisy.py --field DIR      # an existing field (vigour on; e.g. the demo's field_noisy)

The plants are the field's true map boxes (truth/map_boxes.csv), so the numbers measure the outlines, not
the detector; the demo (``python -m matchplant.demo --noise realistic``) gives them with its own detections.
Each setting is one whole module 9 run: ``canopy.ndvi_threshold`` auto (the default), null (the CHM alone),
and null with the CHM thresholds lowered by hand to what auto uses with NDVI (5 cm, 8 cm: lower thresholds
alone let the ground's bumps in).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import rasterio

from matchplant.core.runtime.config import load_config
from matchplant.simfield import generate_field
from matchplant.simfield.layout import FieldPaths
from matchplant.simfield.scoring import (
    match_to_truth,
    outline_ious,
    positions,
    trait_scores,
)
from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig
from matchplant.spatial_stat_extractor.run import run as run_stats


def noisy_field(given: str | None) -> Path:
    """The given field, else the small realistic field with vigour (generated once in the temp folder)."""
    if given:
        return Path(given)
    root = Path(tempfile.gettempdir()) / "matchplant_bench_fields" / "small_realistic_seed0"
    if not (root / "truth" / "traits.csv").is_file():
        generate_field(preset="small", seed=0, out=root, vigour=True, noise="realistic")
    return root


SETTINGS = {
    "auto": [],
    "null": ["canopy.ndvi_threshold=null"],
    "null, min_height 0.05, min_top 0.08": [
        "canopy.ndvi_threshold=null",
        "canopy.min_height=0.05",
        "canopy.min_top=0.08",
    ],
}


def module9(field: Path, out: Path, sets: list[str]) -> pd.DataFrame:
    """Run module 9 on the field's true map boxes with extra ``KEY=VALUE`` settings; its plant table."""
    ms = field / "multispectral" / "multispectral.tif"
    with rasterio.open(ms) as ds:
        red, nir = (3, 5) if ds.count == 5 else (1, 2)  # the realistic field's 5 bands, else red + NIR
    crs = json.loads((field / "truth" / "field.json").read_text())["crs"]
    cfg = load_config(
        SpatialStatExtractorConfig,
        None,
        [
            f"polygons={field / 'truth' / 'map_boxes.csv'}",
            f"polygons_crs={crs}",
            f"output_dir={out}",
            f"rasters.dsm={field / 'odm_dem' / 'dsm.tif'}",
            f"rasters.dtm={field / 'odm_dem' / 'dtm.tif'}",
            f"rasters.multispectral={ms}",
            f"rasters.red_band={red}",
            f"rasters.nir_band={nir}",
            "rasters.indices=[]",
            "vector_formats=[]",
            *sets,
        ],
    )
    run_stats(cfg)
    return pd.read_csv(out / "stats.csv")


def scores(field: Path, out: Path, table: pd.DataFrame) -> dict:
    """Score one module 9 run against the truth: outline IoU, NDVI and height r, canopy/box ratios, flags."""
    paths = FieldPaths(field)
    traits = trait_scores(table, paths)
    outlines = gpd.read_file(out / "outlines.gpkg").set_index("plant_id").reindex(table["plant_id"])
    iou = outline_ious(outlines.geometry.values, table, paths)
    truth = pd.read_csv(paths.traits_csv)
    m = match_to_truth(positions(table), truth[["x", "y"]].to_numpy(float))
    height = np.where(m >= 0, truth["height"].to_numpy()[np.maximum(m, 0)], np.nan)
    ratio = table["canopy_box_ratio"].to_numpy(float)[height < 1]
    true_area = np.where(m >= 0, truth["canopy_area_m2"].to_numpy()[np.maximum(m, 0)], np.nan)
    date = json.loads((out / "stats_report.json").read_text())["canopy"]["dates"][0]
    return {
        "canopy_ndvi_r": round(traits["ndvi_r"], 3),
        "height_r": round(traits["height_r"], 3),
        "outline_iou_median": round(float(np.nanmedian(iou)), 3),
        "outline_over_true_area_median": round(float(np.nanmedian(table["canopy_area_m2"] / true_area)), 3),
        "canopy_box_under_1m_median": round(float(np.nanmedian(ratio)), 3),
        "canopy_box_under_1m_max": round(float(np.nanmax(ratio)), 3),
        "invalid_outlines": int((~outlines.geometry.is_valid).sum()),
        "flags": table["outline_flag"].fillna("").value_counts().to_dict(),
        **{
            k: date.get(k)
            for k in ("min_height", "min_top", "ndvi_threshold", "unclaimed_canopies", "unclaimed_below_noise")
        },
    }


def main() -> None:
    """Parse the options and print the scores of each ``canopy.ndvi_threshold`` setting."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--field", help="a synthetic field generated with vigour (default: small, noise realistic)")
    args = ap.parse_args()
    field = noisy_field(args.field)
    with tempfile.TemporaryDirectory() as tmp:
        for k, (name, sets) in enumerate(SETTINGS.items()):
            out = Path(tmp) / str(k)
            print(f"canopy.ndvi_threshold {name}:", json.dumps(scores(field, out, module9(field, out, sets))))


if __name__ == "__main__":
    main()
