"""``noise: realistic``: the synthetic field's ODM outputs made imperfect the way a real survey's are.

The images are rendered from the exact scene either way (so the photos, boxes and detections of an exact
and a realistic field of the same seed are the same); what changes is what photogrammetry and generic
tools make of it:

* **DSM/DTM** as OpenDroneMap grids them: the canopy smoothed (a median filter, ODM's DEM smoothing, then
  a small Gaussian, the point cloud's gridding radius), so that thin leaves and tips are lost and tops
  rounded; correlated ground noise on the DSM so that the bare-ground CHM (DSM - DTM) has the quantiles of
  a real photogrammetric CHM (p50 about 1.6 cm, p95 about 7 cm: 45 % of bare ground above 2 cm), from a
  fine grain (soil clods) and 5-15 cm bumps (what a canopy finder can mistake for small plants); a smooth
  DTM error (interpolated ground) shared by both; small nodata holes in the DSM (low texture).
* **Multispectral**: 5 bands, blue, green, red, red edge, near-infrared reflectance (float32), slightly
  blurred with sensor noise, written as generic writers write it: TIFF photometric RGB plus two extra
  samples and no band descriptions, so GDAL labels bands 1-3 red, green, blue (band 1 is blue).
* **Masks**: ``truth/masks_antialiased{,_jpg,_gif}/<image>.<ext>``, a binary plant mask of every
  undistorted image with anti-aliased edges (grey levels at the edges), as PNG, JPEG and GIF.

``truth/noise.json`` records the model and what was measured on the written rasters (bare-ground CHM
quantiles, hole share, band order).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from matchplant.simfield.scene import Rasters, _noise

BAND_ORDER = ("blue", "green", "red", "rededge", "nir")


@dataclass(frozen=True)
class NoiseModel:
    """Parameters of the realistic noise: DEM smoothing, ground noise, holes, multispectral and mask blur."""

    chm_p50: float = 0.016  # m, median of the bare-ground CHM
    chm_p95: float = 0.070  # m, its 95th percentile (a Gaussian: sigma = (p95 - p50) / 1.645)
    grain_m: float = 0.02  # feature size of the fine ground noise, m
    bump_m: float = 0.12  # feature size of the ground bumps, m
    bump_weight: float = 0.8  # share of the ground noise's variance in the bumps
    dtm_sigma: float = 0.01  # m, smooth error of the interpolated DTM (shared by the DSM)
    dtm_scale_m: float = 1.5  # its feature size, m
    median_m: float = 0.025  # ODM's median smoothing of the DEM: window side, m (odd pixels, >= 3)
    blur_m: float = 0.005  # the gridding's Gaussian, sigma in m
    hole_share: float = 0.004  # share of DSM cells that are nodata holes
    hole_m: float = 0.03  # feature size of the holes, m
    ms_blur_m: float = 0.005  # multispectral blur, sigma in m
    ms_noise: float = 0.015  # multiplicative sensor noise of each band (SD)
    mask_blur_px: float = 0.7  # anti-aliasing of the masks: Gaussian sigma, image pixels
    mask_jpeg_quality: int = 90


REALISTIC = NoiseModel()


def _standard(a: np.ndarray) -> np.ndarray:
    a = a - a.mean()
    return a / max(float(a.std()), 1e-12)


def _odd(m: float, res: float, least: int = 3) -> int:
    k = max(least, round(m / res))
    return k + 1 - k % 2


@dataclass
class NoisyDEM:
    """The DSM and DTM as offsets from the true terrain, and the DSM's nodata holes."""

    dsm: np.ndarray  # float32, DSM minus the true terrain (smoothed canopy + ground noise + DTM error)
    dtm: np.ndarray  # float32, DTM minus the true terrain
    holes: np.ndarray  # bool, DSM cells written as nodata


def photogrammetric_dem(rasters: Rasters, rng: np.random.Generator, m: NoiseModel = REALISTIC) -> NoisyDEM:
    """The DSM and DTM as offsets from the true terrain (see the module doc). Vectorised: a few filters
    over the whole grid."""
    res = rasters.grid.res
    canopy = rasters.canopy.astype(np.float32)
    # cv2's median of float32 takes windows up to 5 px: ODM's smoothing is a few pixels of its DEM anyway
    smooth = cv2.medianBlur(canopy, min(_odd(m.median_m, res), 5))
    smooth = cv2.GaussianBlur(smooth, (0, 0), max(m.blur_m / res, 0.3))
    shape = canopy.shape
    grain = _standard(_noise(shape, m.grain_m / res, rng))
    bumps = _standard(_noise(shape, m.bump_m / res, rng))
    ground = _standard(np.sqrt(1 - m.bump_weight) * grain + np.sqrt(m.bump_weight) * bumps)
    sigma = (m.chm_p95 - m.chm_p50) / 1.6449
    chm_noise = (m.chm_p50 + sigma * ground).astype(np.float32)
    dtm = (m.dtm_sigma * _standard(_noise(shape, m.dtm_scale_m / res, rng))).astype(np.float32)
    holes_field = _noise(shape, m.hole_m / res, rng)
    holes = holes_field > np.quantile(holes_field, 1 - m.hole_share) if m.hole_share > 0 else np.zeros(shape, bool)
    return NoisyDEM(dsm=smooth + chm_noise + dtm, dtm=dtm, holes=holes)


def five_bands(rasters: Rasters, rng: np.random.Generator, m: NoiseModel = REALISTIC):
    """Blue, green, red, red edge and NIR reflectance (float32), one band at a time (see the module doc).
    Red and NIR are the exact field's (leaf NDVI unchanged); blue and green follow the orthophoto's
    colours, red edge lies between red and NIR."""
    sigma = max(m.ms_blur_m / rasters.grid.res, 0.3)
    bands = {
        "blue": lambda: rasters.albedo[..., 2].astype(np.float32) / 255 * 0.45,
        "green": lambda: rasters.albedo[..., 1].astype(np.float32) / 255 * 0.45,
        "red": lambda: rasters.red,
        "rededge": lambda: 0.5 * (rasters.red + rasters.nir),
        "nir": lambda: rasters.nir,
    }
    for name in BAND_ORDER:
        band = cv2.GaussianBlur(bands[name]().astype(np.float32), (0, 0), sigma)
        band *= 1 + m.ms_noise * rng.standard_normal(band.shape, dtype=np.float32)
        yield np.clip(band, 0, 1)


def antialiased_mask(ids: np.ndarray, m: NoiseModel = REALISTIC) -> np.ndarray:
    """uint8 binary plant mask (255 plant, 0 else) with smooth edges, as masks saved through a resampling or
    an anti-aliasing tool are."""
    binary = (ids > 0).astype(np.float32)
    return np.clip(np.round(255 * cv2.GaussianBlur(binary, (0, 0), m.mask_blur_px)), 0, 255).astype(np.uint8)


def mask_objects(ids: np.ndarray) -> tuple[int, int, int]:
    """Truth of one mask: distinct plants in it, connected parts of its binary mask (8-connected: touching
    plants are one part), plant pixels."""
    binary = (ids > 0).astype(np.uint8)
    parts = cv2.connectedComponents(binary, connectivity=8)[0] - 1
    return len(np.unique(ids[ids > 0])), int(parts), int(binary.sum())


def bare_ground_chm(chm: np.ndarray, label: np.ndarray, valid: np.ndarray, res: float, clear_m: float = 0.05):
    """CHM values on soil at least ``clear_m`` from any plant, weed or target (what a real CHM's bare
    ground is measured on)."""
    busy = (label != 0).astype(np.uint8)
    k = 2 * int(np.ceil(clear_m / res)) + 1
    near = cv2.dilate(busy, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0
    return chm[(~near) & valid]


def noise_summary(m: NoiseModel, dem: NoisyDEM, rasters: Rasters) -> dict:
    """The noise model and what the written DEMs measure: bare-ground CHM quantiles and the share of holes."""
    chm = dem.dsm - dem.dtm
    ground = bare_ground_chm(chm, rasters.label, ~dem.holes, rasters.grid.res)
    q = np.percentile(ground, [5, 50, 95]) if len(ground) else [np.nan] * 3
    return {
        "model": asdict(m),
        "bare_ground_chm_m": {
            "p5": float(q[0]),
            "p50": float(q[1]),
            "p95": float(q[2]),
            "share_above_0.02": float(np.mean(ground > 0.02)) if len(ground) else None,
            "cells": len(ground),
            "meaning": "DSM - DTM on soil at least 5 cm from any plant, weed or target",
        },
        "dsm_holes": {"cells": int(dem.holes.sum()), "share": float(dem.holes.mean())},
    }
