"""Where the synthetic field puts each file: ODM's names for ODM's outputs, plus inputs and the truth.

This is the contract between the generator and every test, benchmark and the demo; keep the names.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class FieldPaths:
    """The path of every file of one synthetic field, under its root folder."""

    root: Path

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))  # accept a str too

    # -- what ODM leaves behind (docs/DESIGN.md §2) -------------------------------------------------------
    @property
    def images(self) -> Path:
        """Folder of the raw distorted JPEGs with EXIF (GPS included), ODM's input."""
        return self.root / "images"

    @property
    def reconstruction(self) -> Path:
        """OpenSfM's reconstruction.json (cameras and shots, geographic reference)."""
        return self.root / "opensfm" / "reconstruction.json"

    @property
    def topocentric_reconstruction(self) -> Path:
        """OpenSfM's reconstruction in local topocentric coordinates (reconstruction.topocentric.json)."""
        return self.root / "opensfm" / "reconstruction.topocentric.json"

    @property
    def undistorted_reconstruction(self) -> Path:
        """The reconstruction of the undistorted images."""
        return self.root / "opensfm" / "undistorted" / "reconstruction.json"

    @property
    def undistorted_images(self) -> Path:
        """Folder of the undistorted images, one ``<image name>.tif`` each."""
        return self.root / "opensfm" / "undistorted" / "images"

    @property
    def dsm(self) -> Path:
        """The digital surface model (DSM) GeoTIFF."""
        return self.root / "odm_dem" / "dsm.tif"

    @property
    def dtm(self) -> Path:
        """The digital terrain model (DTM, bare ground) GeoTIFF."""
        return self.root / "odm_dem" / "dtm.tif"

    @property
    def orthophoto(self) -> Path:
        """The RGBA orthophoto GeoTIFF."""
        return self.root / "odm_orthophoto" / "odm_orthophoto.tif"

    @property
    def coords(self) -> Path:
        """ODM's coords.txt: the field's CRS and the offset of the reconstruction's origin."""
        return self.root / "odm_georeferencing" / "coords.txt"

    # -- other inputs ------------------------------------------------------------------------------
    @property
    def multispectral(self) -> Path:
        """Multispectral GeoTIFF (exact: band 1 red, 2 NIR; realistic: blue, green, red, red edge, NIR)."""
        return self.root / "multispectral" / "multispectral.tif"

    @property
    def images_nogps(self) -> Path:
        """Folder of the raw images with the GPS IFD removed (module 0's input)."""
        return self.root / "images_nogps"

    @property
    def gnss_log(self) -> Path:
        """GNSS event log (the paper's events.txt: TAB, header "Timestamp X Y Z", UTM)."""
        return self.root / "gnss" / "events.txt"

    @property
    def gcp_survey(self) -> Path:
        """Surveyed GCP positions: id,x,y,z in the field CRS (EPSG in truth/field.json)."""
        return self.root / "gcp" / "gcp_survey.csv"

    # -- ground truth ------------------------------------------------------------------------------
    @property
    def truth(self) -> Path:
        """Folder of the ground truth."""
        return self.root / "truth"

    @property
    def field_json(self) -> Path:
        """Field facts: CRS (EPSG), offset, clock offset, GSD, preset, seed, camera."""
        return self.truth / "field.json"

    @property
    def plants_csv(self) -> Path:
        """Every plant: id,x,y,z,height,radius (map CRS; z = ground height)."""
        return self.truth / "plants.csv"

    @property
    def boxes_raw(self) -> Path:
        """COCO boxes of every visible plant in every raw image."""
        return self.truth / "boxes_raw.json"

    @property
    def boxes_undistorted(self) -> Path:
        """COCO boxes of every visible plant in every undistorted image."""
        return self.truth / "boxes_undistorted.json"

    @property
    def map_boxes(self) -> Path:
        """Each plant's box on the map: CSV id,xmin,ymin,xmax,ymax (map CRS)."""
        return self.truth / "map_boxes.csv"

    @property
    def gcp_pixels(self) -> Path:
        """Where each GCP shows in the raw images: CSV gcp_id,image,u,v (raw pixels)."""
        return self.truth / "gcp_pixels.csv"

    # -- extra truth (added by the generator; not part of an ODM project) --------------------------
    @property
    def plant_ids(self) -> Path:
        """int32 GeoTIFF on the DSM grid: plant id, 0 soil, -1 weed, -2 GCP."""
        return self.truth / "plant_ids.tif"

    @property
    def masks_raw(self) -> Path:
        """Folder of ``<image name>.png`` masks: uint16 plant id of every rendered raw pixel."""
        return self.truth / "masks_raw"

    @property
    def masks_undistorted(self) -> Path:
        """Folder of ``<image name>.png`` masks: uint16 plant id of every undistorted pixel."""
        return self.truth / "masks_undistorted"

    # -- noise: realistic (simfield/noise.py) ------------------------------------------------------
    @property
    def masks_antialiased(self) -> Path:
        """Folder of ``<image name>.png`` uint8 binary plant masks with anti-aliased edges."""
        return self.truth / "masks_antialiased"

    @property
    def masks_antialiased_jpg(self) -> Path:
        """Folder of the anti-aliased masks as JPEG."""
        return self.truth / "masks_antialiased_jpg"

    @property
    def masks_antialiased_gif(self) -> Path:
        """Folder of the anti-aliased masks as GIF."""
        return self.truth / "masks_antialiased_gif"

    @property
    def mask_objects(self) -> Path:
        """CSV image,plants,parts,pixels of each anti-aliased mask."""
        return self.truth / "mask_objects.csv"

    @property
    def noise_json(self) -> Path:
        """The noise model and what was measured on the written rasters (JSON)."""
        return self.truth / "noise.json"

    # -- traits and plots (simfield/traits.py) -----------------------------------------------------
    @property
    def traits_csv(self) -> Path:
        """True traits per plant: id,x,y,height,ndvi,canopy_pixels,canopy_area_m2."""
        return self.truth / "traits.csv"

    @property
    def plots_json(self) -> Path:
        """The plot grid (JSON): corners, columns, ranges, plot size, spacings."""
        return self.truth / "plots.json"

    @property
    def plots_csv(self) -> Path:
        """Every plot: plot_id,range,column,expected,stand_count,gaps,geometry (WKT)."""
        return self.truth / "plots.csv"

    @property
    def gaps_csv(self) -> Path:
        """Every empty seed position: plot_id,row,x,y."""
        return self.truth / "gaps.csv"

    @property
    def field_book(self) -> Path:
        """The field book: plot_id,genotype,rep."""
        return self.truth / "field_book.csv"

    @property
    def later(self) -> FieldPaths:
        """The second date's field (second_date: true): its rasters and truth in the same layout."""
        return FieldPaths(self.root / "date2")
