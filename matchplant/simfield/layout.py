"""Where the synthetic field puts each file: ODM's names for ODM's outputs, plus inputs and the truth.

This is the contract between the generator and every test, benchmark and the demo; keep the names.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class FieldPaths:
    root: Path

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))  # accept a str too

    # -- what ODM leaves behind (docs/DESIGN.md §2) -------------------------------------------------------
    @property
    def images(self) -> Path:  # raw distorted JPEGs with EXIF (GPS included), ODM's input
        return self.root / "images"

    @property
    def reconstruction(self) -> Path:
        return self.root / "opensfm" / "reconstruction.json"

    @property
    def topocentric_reconstruction(self) -> Path:
        return self.root / "opensfm" / "reconstruction.topocentric.json"

    @property
    def undistorted_reconstruction(self) -> Path:
        return self.root / "opensfm" / "undistorted" / "reconstruction.json"

    @property
    def undistorted_images(self) -> Path:  # <image name>.tif
        return self.root / "opensfm" / "undistorted" / "images"

    @property
    def dsm(self) -> Path:
        return self.root / "odm_dem" / "dsm.tif"

    @property
    def dtm(self) -> Path:
        return self.root / "odm_dem" / "dtm.tif"

    @property
    def orthophoto(self) -> Path:  # RGBA
        return self.root / "odm_orthophoto" / "odm_orthophoto.tif"

    @property
    def coords(self) -> Path:
        return self.root / "odm_georeferencing" / "coords.txt"

    # -- other inputs ------------------------------------------------------------------------------
    @property
    def multispectral(self) -> Path:  # exact: band 1 red, 2 NIR; realistic: blue, green, red, red edge, NIR
        return self.root / "multispectral" / "multispectral.tif"

    @property
    def images_nogps(self) -> Path:  # the raw images with the GPS IFD removed (module 0's input)
        return self.root / "images_nogps"

    @property
    def gnss_log(self) -> Path:  # paper's events.txt: TAB, header "Timestamp X Y Z", UTM
        return self.root / "gnss" / "events.txt"

    @property
    def gcp_survey(self) -> Path:  # id,x,y,z in the field CRS (EPSG in truth/field.json)
        return self.root / "gcp" / "gcp_survey.csv"

    # -- ground truth ------------------------------------------------------------------------------
    @property
    def truth(self) -> Path:
        return self.root / "truth"

    @property
    def field_json(self) -> Path:  # crs (EPSG), offset, clock offset, gsd, preset, seed, camera
        return self.truth / "field.json"

    @property
    def plants_csv(self) -> Path:  # id,x,y,z,height,radius (map CRS; z = ground height)
        return self.truth / "plants.csv"

    @property
    def boxes_raw(self) -> Path:  # COCO: every visible plant in every raw image
        return self.truth / "boxes_raw.json"

    @property
    def boxes_undistorted(self) -> Path:  # COCO: every visible plant in every undistorted image
        return self.truth / "boxes_undistorted.json"

    @property
    def map_boxes(self) -> Path:  # CSV: id,xmin,ymin,xmax,ymax (map CRS), plant's box on the map
        return self.truth / "map_boxes.csv"

    @property
    def gcp_pixels(self) -> Path:  # CSV: gcp_id,image,u,v (raw image pixels)
        return self.truth / "gcp_pixels.csv"

    # -- extra truth (added by the generator; not part of an ODM project) --------------------------
    @property
    def plant_ids(self) -> Path:  # GeoTIFF int32 on the DSM grid: plant id, 0 soil, -1 weed, -2 GCP
        return self.truth / "plant_ids.tif"

    @property
    def masks_raw(self) -> Path:  # <image name>.png: uint16 plant id of every rendered raw pixel
        return self.truth / "masks_raw"

    @property
    def masks_undistorted(self) -> Path:  # <image name>.png: uint16 plant id of every undistorted pixel
        return self.truth / "masks_undistorted"

    # -- noise: realistic (simfield/noise.py) ------------------------------------------------------
    @property
    def masks_antialiased(self) -> Path:  # <image name>.png: uint8 binary plant mask, anti-aliased edges
        return self.truth / "masks_antialiased"

    @property
    def masks_antialiased_jpg(self) -> Path:  # the same masks as JPEG
        return self.truth / "masks_antialiased_jpg"

    @property
    def masks_antialiased_gif(self) -> Path:  # the same masks as GIF
        return self.truth / "masks_antialiased_gif"

    @property
    def mask_objects(self) -> Path:  # image,plants,parts,pixels of each anti-aliased mask
        return self.truth / "mask_objects.csv"

    @property
    def noise_json(self) -> Path:  # the noise model and what was measured on the written rasters
        return self.truth / "noise.json"

    # -- traits and plots (simfield/traits.py) -----------------------------------------------------
    @property
    def traits_csv(self) -> Path:  # id,x,y,height,ndvi,canopy_pixels,canopy_area_m2 (true canopy)
        return self.truth / "traits.csv"

    @property
    def plots_json(self) -> Path:  # the plot grid: corners, columns, ranges, plot size, spacings
        return self.truth / "plots.json"

    @property
    def plots_csv(self) -> Path:  # plot_id,range,column,expected,stand_count,gaps,geometry (WKT)
        return self.truth / "plots.csv"

    @property
    def gaps_csv(self) -> Path:  # plot_id,row,x,y of every empty seed position
        return self.truth / "gaps.csv"

    @property
    def field_book(self) -> Path:  # plot_id,genotype,rep
        return self.truth / "field_book.csv"

    @property
    def later(self) -> FieldPaths:  # a second date (second_date: true): rasters and truth, same layout
        return FieldPaths(self.root / "date2")
