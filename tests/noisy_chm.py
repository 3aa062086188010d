"""A photogrammetric-looking canopy height model built with numpy, for module 9's canopy tests: star-shaped
plants under 1 m (a core and a few leaves, height ``H (1 - rho^2)``) in rows with gaps, smoothed as ODM's DSM
gridding smooths tops and edges, on bare ground with spatially correlated noise (median ~1.5 cm, SD ~3 cm,
p95 ~6.5 cm: the magnitude of a real ODM CHM) and small holes (nodata); and an NDVI raster on the same grid
(each plant's leaves their own NDVI, soil ~0.15, blurred by a pixel, with sensor noise; drawn from a stream
of its own, so the CHM is the same with or without it). The truth: each plant's footprint (its leaf pixels
before smoothing), height, leaf NDVI and centre; the ground noise's own percentiles."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from affine import Affine
from scipy import ndimage as ndi


@dataclass
class NoisyChm:
    chm: np.ndarray  # float, NaN holes
    transform: Affine
    boxes: np.ndarray  # shapely boxes, one per plant (the detector's: footprint bounds + slack)
    truth: np.ndarray  # int32 label image: plant k + 1 on its footprint (leaf pixels), 0 ground
    height: np.ndarray  # true top height per plant (before smoothing)
    centre: np.ndarray  # (n, 2) x, y
    ground_sd: float  # the noise's SD on bare ground
    ground_p50: float
    ground_p95: float
    ndvi: np.ndarray  # NDVI raster on the CHM's grid
    leaf_ndvi: np.ndarray  # true leaf NDVI per plant


def noisy_chm(
    seed: int = 0,
    res: float = 0.01,
    width_m: float = 6.0,
    length_m: float = 3.2,
    noise_sd: float = 0.03,
    bias: float = 0.015,
    smooth_m: float = 0.015,
    heights=(0.15, 0.9),
    spacing: float = 0.3,
) -> NoisyChm:
    rng = np.random.default_rng(seed)
    ny, nx = round(length_m / res), round(width_m / res)
    t = Affine(res, 0, 500000.0, 0, -res, 4500000.0 + length_m)
    xs = (np.arange(nx) + 0.5) * res
    ys = (np.arange(ny) + 0.5) * res  # from the top edge down
    plants = []
    for y in np.arange(0.4, length_m - 0.3, 0.75):  # rows across the field
        for x in np.arange(0.35, width_m - 0.3, spacing):
            if rng.random() < 0.1:  # a gap in the row
                continue
            plants.append((x + rng.normal(0, 0.02), y + rng.normal(0, 0.02)))
    plants = np.array(plants)
    n = len(plants)
    H = rng.uniform(*heights, n)
    R = 0.06 + 0.12 * (H - heights[0]) / (heights[1] - heights[0]) * rng.uniform(0.8, 1.0, n)
    surf = np.zeros((ny, nx))
    truth = np.zeros((ny, nx), np.int32)
    boxes = []
    for k, ((cx, cy), h, r) in enumerate(zip(plants, H, R)):
        c0, c1 = int((cx - r) / res) - 1, int((cx + r) / res) + 2
        r0, r1 = int((cy - r) / res) - 1, int((cy + r) / res) + 2
        dx = xs[c0:c1][None, :] - cx
        dy = ys[r0:r1][:, None] - cy
        rho = np.hypot(dx, dy) / r
        ang = np.arctan2(dy, dx)
        leaves = rng.uniform(0, 2 * np.pi, rng.integers(4, 8))
        # angular distance to the nearest leaf, as an arc length: leaves are ~0.3 r wide, tapering
        dang = np.min(np.abs(np.angle(np.exp(1j * (ang[..., None] - leaves)))), axis=-1)
        leaf = (dang * rho * r < 0.15 * r * (1.1 - rho)) | (rho < 0.3)
        inside = leaf & (rho < 1)
        hgt = np.where(inside, h * (1 - rho**2), 0)
        sub = surf[r0:r1, c0:c1]
        mine = inside & (hgt > sub)
        sub[mine] = hgt[mine]
        truth[r0:r1, c0:c1][mine] = k + 1
        rr, cc = np.nonzero(inside)
        slack = rng.uniform(0.0, 0.02, 4)  # the detector's box: the plant's extent, a little loose
        x0, x1 = xs[c0 + cc.min()] - res / 2 - slack[0], xs[c0 + cc.max()] + res / 2 + slack[1]
        y0, y1 = ys[r0 + rr.min()] - res / 2 - slack[2], ys[r0 + rr.max()] + res / 2 + slack[3]
        boxes.append(shapely.box(t.c + x0, t.f - y1, t.c + x1, t.f - y0))
    # ODM's gridding: tops and edges smoothed
    surf = ndi.gaussian_filter(surf, smooth_m / res)
    noise = ndi.gaussian_filter(rng.normal(0, 1, (ny, nx)), 2.0)
    noise = bias + noise_sd * noise / noise.std()
    chm = surf + noise
    # small holes where the matching failed
    holes = ndi.binary_dilation(rng.random((ny, nx)) < 0.002, iterations=1)
    chm[holes] = np.nan
    nrng = np.random.default_rng([seed, 1])
    leaf_ndvi = nrng.uniform(0.35, 0.85, n)  # pale plants (0.35) to green ones
    ndvi = np.where(truth > 0, leaf_ndvi[truth - 1], 0.15)
    ndvi = ndi.gaussian_filter(ndvi, 0.7) + nrng.normal(0, 0.015, (ny, nx))
    ground = noise[ndi.binary_dilation(truth > 0, iterations=int(0.1 / res)) == 0]
    return NoisyChm(
        chm=chm,
        transform=t,
        boxes=np.array(boxes, dtype=object),
        truth=truth,
        height=H,
        centre=np.column_stack([t.c + plants[:, 0], t.f - plants[:, 1]]),
        ground_sd=float(ground.std()),
        ground_p50=float(np.median(ground)),
        ground_p95=float(np.percentile(ground, 95)),
        ndvi=ndvi,
        leaf_ndvi=leaf_ndvi,
    )
