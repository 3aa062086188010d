"""Settings of the crops and the field map: the commands ``matchplant crops`` and ``matchplant map``, and module
9's ``views`` section (both written by module 9 after its statistics)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from matchplant.core.formats.projects import PROJECT_TYPES
from matchplant.core.runtime.config import param

LEVELS = 8  # flat rings of a draped polygon (outlines.py): the silhouette's error shrinks with their spacing


@dataclass(frozen=True)
class CropSettings:
    """How crops are chosen and cut."""

    best: int = 0  # each plant's best N views by off-nadir angle; 0: every view that sees it whole
    margin: float = 0.25  # added on each side, as a share of the plant's larger side in the photo
    margin_px: int = 8  # at least this many pixels on each side
    quality: int = 92  # JPEG quality of the crops
    levels: int = LEVELS  # flat rings of the draped polygon (see outlines.py)


_DEFAULT = CropSettings()
PROJECT = (
    "the project whose original photos and poses give the crops: an ODM folder (opensfm/reconstruction.json, "
    "images/, odm_dem/dsm.tif), a Metashape camera export (.xml) or project (.psx), or a Pix4D project folder"
)
PHOTOS = "folder of the original photos (null: ODM's images/; the paths a Metashape/Pix4D project stores)"
PROJECT_TYPE = "which program made the project (auto: from its files, named in the log)"


@dataclass
class ViewsSection:
    """Module 9's crops of every plant from the raw photos and its interactive field map (map.html)."""

    project: Path | None = param(None, PROJECT + "; null = no crops", path="exists")
    project_type: Literal["auto", "odm", "metashape", "pix4d"] = param("auto", PROJECT_TYPE, choices=PROJECT_TYPES)
    photos: Path | None = param(None, PHOTOS, path="dir")
    best: int = param(3, "each plant's best N views by off-nadir angle; 0 = every photo that sees it whole", min=0)
    field_map: bool = param(True, "write map.html: the plants coloured by any statistic, the plots, the crops")
    orthophoto: Path | None = param(
        None, "orthophoto under the plants on the map (null: the project's, if any)", path="file"
    )


@dataclass
class CropsConfig:
    """Crops of every plant (or plot) polygon from the raw photos that see it whole, with an index."""

    polygons: Path = param(
        None,
        "plant or plot polygons: module 8's plants.gpkg, module 9's stats.gpkg, any GeoPackage, shapefile, "
        "GeoJSON or CSV with WKT (any CRS)",
        path="file",
        required=True,
    )
    id_column: str = param("auto", "column holding the id ('auto': plant_id, id or fid; 'number': 1..n)")
    layer: str = param("", "layer of a GeoPackage ('' = the first)")
    polygons_crs: str = param("", "CRS of the polygons when the file has none (a CSV), e.g. EPSG:32615")
    project: Path = param(None, PROJECT, path="exists", required=True)
    project_type: Literal["auto", "odm", "metashape", "pix4d"] = param("auto", PROJECT_TYPE, choices=PROJECT_TYPES)
    photos: Path | None = param(None, PHOTOS, path="dir")
    dsm: Path | None = param(
        None,
        "DSM the polygons are draped on (null: the project's: ODM's odm_dem/dsm.tif, the DSM GeoTIFF beside a "
        "Metashape export, Pix4D's 3_dsm_ortho/1_dsm/)",
        path="file",
    )
    best: int = param(0, "each plant's best N views by off-nadir angle; 0 = every photo that sees it whole", min=0)
    margin: float = param(_DEFAULT.margin, "margin around the plant, as a share of its larger side", min=0, max=5)
    margin_px: int = param(_DEFAULT.margin_px, "margin of at least this many pixels", min=0, max=10000)
    quality: int = param(_DEFAULT.quality, "JPEG quality of the crops", min=10, max=100)
    output_dir: Path = param(Path("runs/crops"), "output folder: crops/, index.csv, index.gpkg", path="out")

    def settings(self) -> CropSettings:
        """The cutting settings of this config."""
        return CropSettings(best=self.best, margin=self.margin, margin_px=self.margin_px, quality=self.quality)


@dataclass
class FieldMapConfig:
    """An interactive field map in one HTML file that opens with no network."""

    plants: Path = param(
        None,
        "plant polygons with their traits: module 9's stats.gpkg (or any polygon file with numeric columns)",
        path="file",
        required=True,
    )
    id_column: str = param("auto", "column holding the plant id ('auto': plant_id, id or fid)")
    layer: str = param("", "layer of a GeoPackage ('' = the first)")
    polygons_crs: str = param("", "CRS of the plants when the file has none (a CSV)")
    plots: Path | None = param(
        None, "plot polygons with their statistics (module 9's plots.gpkg); null = none", path="file"
    )
    plot_id_column: str = param("plot_id", "column of the plot id in the plots file")
    orthophoto: Path | None = param(None, "orthophoto under the plants, downsampled into the file", path="file")
    crops: Path | None = param(
        None,
        "index.csv of the plants' crops (matchplant crops); keep the crops inside the map's folder",
        path="file",
    )
    trait: str = param("", "the trait the map opens with ('' = the first numeric column)")
    title: str = param("MatchPlant field map", "the page's title")
    output_dir: Path = param(
        Path("runs/map"),
        "output folder: map.html (keep the crops inside it: the page reads only its folder)",
        path="out",
    )
