"""One builder for the small ODM projects that tests make from first principles.

A test describes its scene (a DSM array, cameras and poses, optionally an orthophoto); this writes it in
the layout ODM leaves behind (docs/DESIGN.md §2): ``odm_georeferencing/coords.txt``,
``opensfm/reconstruction.json`` (and ``reconstruction.topocentric.json``), the undistorted
reconstruction and images, ``odm_dem/dsm.tif`` and ``odm_orthophoto/odm_orthophoto.tif``. The larger
synthetic field with exact truth is ``matchplant.simfield``; this one is for scenes a test controls pixel
by pixel.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from PIL import Image
from pyproj import CRS

from matchplant.core.formats.reconstruction import Reconstruction, write_reconstruction
from matchplant.core.geometry.frames import write_coords_txt
from matchplant.core.geometry.shot import Shot


@dataclass
class Raster:
    """A georeferenced array: (rows, cols) or (bands, rows, cols), with its map transform."""

    data: np.ndarray
    transform: Affine


def write_raster(path: Path, raster: Raster, crs: CRS, nodata: float | None = None) -> None:
    data = raster.data if raster.data.ndim == 3 else raster.data[None]
    path.parent.mkdir(parents=True, exist_ok=True)
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=data.shape[2],
        height=data.shape[1],
        count=data.shape[0],
        dtype=data.dtype,
        crs=crs,
        transform=raster.transform,
        nodata=nodata,
    ) as dst:
        dst.write(data)


def _reconstruction(shots: dict[str, Shot], reference_lla: dict) -> Reconstruction:
    cameras = {shot.camera.id: shot.camera for shot in shots.values()}
    return Reconstruction(cameras=cameras, shots=shots, reference_lla=reference_lla)


def write_odm_project(
    root: Path,
    *,
    crs: CRS,
    offset,
    reference_lla: dict,
    shots: dict[str, Shot],
    dsm: Raster,
    undistorted_shots: dict[str, Shot] | None = None,
    orthophoto: Raster | None = None,
    topocentric_copy: bool = False,
    image_color: tuple[int, int, int] = (90, 120, 60),
) -> Path:
    """Write an ODM project under ``root`` and return ``root``.

    ``shots`` are the poses in the raw photos' cameras; ``undistorted_shots`` (default: the same) those of
    the undistorted images, which are written as plain ``<name>.tif`` of ``image_color`` at their camera's
    size. ``offset`` is the UTM offset of ``coords.txt`` (x, y[, z]); the DSM is float32 with nodata −9999.
    """
    root = Path(root)
    undistorted_shots = shots if undistorted_shots is None else undistorted_shots
    write_coords_txt(root / "odm_georeferencing" / "coords.txt", crs, np.array([*np.asarray(offset)[:2], 0.0]))
    osfm = root / "opensfm"
    write_reconstruction(osfm / "reconstruction.json", _reconstruction(shots, reference_lla))
    if topocentric_copy:
        write_reconstruction(osfm / "reconstruction.topocentric.json", _reconstruction(shots, reference_lla))
    write_reconstruction(
        osfm / "undistorted" / "reconstruction.json", _reconstruction(undistorted_shots, reference_lla)
    )
    images = osfm / "undistorted" / "images"
    images.mkdir(parents=True, exist_ok=True)
    for name, shot in undistorted_shots.items():
        Image.new("RGB", (shot.camera.width, shot.camera.height), image_color).save(images / f"{name}.tif")
    write_raster(root / "odm_dem" / "dsm.tif", Raster(dsm.data.astype("float32"), dsm.transform), crs, nodata=-9999)
    if orthophoto is not None:
        write_raster(root / "odm_orthophoto" / "odm_orthophoto.tif", orthophoto, crs)
    return root
