"""Settings of the synthetic field: a preset (tiny, small, large) plus optional overrides.

Every override left at ``null`` takes the preset's value; :func:`resolve` merges both into the plain
:class:`Settings` the generator uses.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass, fields, replace
from pathlib import Path

from matchplant.core.runtime.config import param, validate
from matchplant.core.runtime.errors import ConfigError

# Field site: near Lincoln, Nebraska (UTM zone 14N). The south-west corner of the rasters lies here.
SITE_LON, SITE_LAT = -96.6, 40.85
GROUND_ALTITUDE = 350.0  # m, ellipsoidal height of the terrain at the site


@dataclass(frozen=True)
class Settings:
    """Everything that shapes one field (a preset after overrides)."""

    image_width: int
    aspect: float  # height / width
    focal: float  # normalised focal length (OpenSfM: focal / max(width, height))
    altitude: float  # flight height above the ground, m
    field_width: float  # plant area across the rows (east), m
    field_length: float  # plant area along the rows (north), m
    raster_res: float  # ground sampling of the rasters, m (about half the image GSD)
    n_gcps: int
    slope_pct: float
    undulation: float  # amplitude of the terrain waves, m
    overlap_front: float = 0.85
    overlap_side: float = 0.85
    tilt_deg: float = 0.0
    attitude_noise_deg: float = 0.7
    height_min: float = 0.10
    height_max: float = 0.60
    weeds: bool = True
    shadows: bool = True
    jpeg_quality: int = 92
    plot_skew_deg: float = 0.0  # ranges' edges off the perpendicular to the rows (a parallelogram plot grid)

    @property
    def image_height(self) -> int:
        """Image height in pixels, from the width and the aspect ratio."""
        return int(round(self.image_width * self.aspect))

    @property
    def gsd(self) -> float:
        """Nominal ground sampling distance at nadir, m/pixel."""
        return self.altitude / (self.focal * max(self.image_width, self.image_height))


PRESETS: dict[str, Settings] = {
    # nine 400x300 images over ~50 plants: unit tests (seconds)
    "tiny": Settings(
        image_width=400,
        aspect=0.75,
        focal=1.0,
        altitude=3.0,
        field_width=3.9,
        field_length=2.9,
        raster_res=0.004,
        n_gcps=4,
        slope_pct=2.0,
        undulation=0.03,
    ),
    # 40 images 1000 px wide over ~1300 plants: the demo (about a minute on 4 cores)
    "small": Settings(
        image_width=1000,
        aspect=0.75,
        focal=0.85,
        altitude=8.5,
        field_width=15.0,
        field_length=15.0,
        raster_res=0.005,
        n_gcps=5,
        slope_pct=2.0,
        undulation=0.08,
    ),
    # ~210 images over ~21000 plants (70 x 50 m): benchmarks
    "large": Settings(
        image_width=1000,
        aspect=0.75,
        focal=0.85,
        altitude=20.0,
        field_width=70.0,
        field_length=50.0,
        raster_res=0.01,
        n_gcps=9,
        slope_pct=1.5,
        undulation=0.15,
    ),
    # 4 DJI Mavic 2 Pro-like 5472x3648 (20 MP) photos at 20 m, 85 % overlap, ~2,500 plants per photo:
    # annotation and detection at real size (bench_bbox_drawer_gui, detection speed)
    "realistic": Settings(
        image_width=5472,
        aspect=2 / 3,
        focal=0.777,
        altitude=20.0,
        field_width=28.0,
        field_length=19.0,
        raster_res=0.005,
        n_gcps=5,
        slope_pct=1.5,
        undulation=0.1,
    ),
}
PRESETS["split"] = PRESETS["small"]  # the small field written as an ODM split-merge project (simfield/split.py)


@dataclass
class SimFieldConfig:
    """Generate a synthetic ODM project of an early-season maize field, with exact ground truth."""

    preset: str = param(
        "tiny",
        "size of the field and flight: tiny (9 images, ~50 plants, 20 MB, ~10 s), small (40 "
        "images, ~1,300 plants, 320 MB, ~2 min), large (210 images, ~21,000 plants, 1.3 GB, "
        "~9 min), realistic (4 photos of 20 MP, ~2,500 plants each: GBs, minutes), split (small "
        "as an ODM split-merge project); times on 2 busy cores, noise: realistic adds ~10 % "
        "time and makes the field about 1.8x larger",
        choices=tuple(PRESETS),
    )
    seed: int = param(0, "random seed: the same seed and settings give the same files", min=0)
    output_dir: Path = param(Path("runs/simfield"), "folder to write the project into", path="out")
    altitude: float | None = param(None, "flight height above ground, m (null: the preset's)", min=0.5, max=500)
    tilt_deg: float = param(0.0, "camera pitch off nadir, degrees (forward, for oblique flights)", min=0, max=45)
    slope_pct: float | None = param(None, "terrain slope, percent (null: the preset's)", min=0, max=30)
    image_width: int | None = param(
        None, "image width in pixels; height is 3/4 of it (null: the preset's)", min=64, max=8000
    )
    overlap: float | None = param(
        None, "front and side overlap of the images, 0..1 (null: 0.85 as in the paper)", min=0.0, max=0.95
    )
    field_width: float | None = param(None, "planted area across the rows, m (null: the preset's)", min=1, max=1000)
    field_length: float | None = param(None, "planted area along the rows, m (null: the preset's)", min=1, max=1000)
    weeds: bool = param(True, "scatter small weeds between the rows")
    shadows: bool = param(True, "cast plant shadows on the soil")
    vigour: bool = param(
        False, "give each plant's leaves its own NDVI (vigour; truth/traits.csv); off: every leaf has NDVI 0.8"
    )
    second_date: bool = param(False, "also write a later date with grown plants and a shifted map (date2/)")
    attitude_noise_deg: float | None = param(None, "standard deviation of roll/pitch/yaw noise, degrees", min=0, max=10)
    noise: str = param(
        "exact",
        "what ODM leaves imperfect: 'exact' (DSM/DTM, masks and rasters exact) or "
        "'realistic' (photogrammetric DSM/DTM noise, smoothed tops and holes, a 5-band "
        "multispectral raster labelled as generic writers label it, anti-aliased masks; "
        "simfield/noise.py)",
        choices=("exact", "realistic"),
    )
    plot_skew_deg: float = param(
        0.0,
        "skew of the plot grid, degrees: each crop row starts further along than "
        "the one before (a parallelogram field, as plot_grid builds from 4 corners)",
        min=0,
        max=30,
    )
    workers: int | None = param(
        None,
        "processes rendering images in parallel (0: one per CPU core, at most 8; "
        "null: 1 for tiny, 0 otherwise); the files do not depend on it",
        min=0,
        max=64,
    )


def resolve(cfg: SimFieldConfig) -> Settings:
    """The preset with the config's non-null overrides applied."""
    if cfg.preset not in PRESETS:
        raise ConfigError(f"unknown preset '{cfg.preset}'", fix=f"use one of {', '.join(PRESETS)}")
    s = PRESETS[cfg.preset]
    changes = {}
    for name in ("altitude", "slope_pct", "image_width", "field_width", "field_length", "attitude_noise_deg"):
        v = getattr(cfg, name)
        if v is not None:
            changes[name] = v
    if cfg.overlap is not None:
        changes.update(overlap_front=cfg.overlap, overlap_side=cfg.overlap)
    changes.update(tilt_deg=cfg.tilt_deg, weeds=cfg.weeds, shadows=cfg.shadows, plot_skew_deg=cfg.plot_skew_deg)
    return replace(s, **changes)


def config_from(preset: str = "tiny", seed: int = 0, out: str | Path = "simfield_out", **overrides) -> SimFieldConfig:
    """A validated :class:`SimFieldConfig` from a preset, a seed, an output folder and named overrides."""
    names = {f.name for f in fields(SimFieldConfig)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        hints = [difflib.get_close_matches(u, names, n=1) for u in unknown]
        hint = "; ".join(f"'{u}'" + (f" (did you mean '{h[0]}'?)" if h else "") for u, h in zip(unknown, hints))
        raise ConfigError(f"unknown simfield setting {hint}", fix=f"valid settings: {', '.join(sorted(names))}")
    cfg = SimFieldConfig(preset=preset, seed=int(seed), output_dir=Path(out), **overrides)
    validate(cfg, source="generate_field()")
    return cfg
