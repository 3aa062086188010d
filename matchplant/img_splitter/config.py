"""Module 5's settings (the folder's config.yaml is generated from them)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from matchplant.core.runtime.config import param
from matchplant.core.runtime.errors import ConfigError


@dataclass
class ImgSplitterConfig:
    """Module 5 - tile annotated images, recompute their boxes and split the tiles into train/val/test."""

    images: Path | None = param(None, "folder of the annotated source images", path="dir", required=True)
    annotations: Path | None = param(
        None,
        "the boxes: module 4's COCO JSON (annotations.json), or a folder of YOLO labels with classes.txt",
        path="exists",
        required=True,
    )
    output_dir: Path = param(
        Path("runs/img_splitter"), "folder for the tiles, one COCO JSON per split and summary.json", path="out"
    )
    tile_size: int = param(1024, "tile side in pixels", min=32)
    overlap: int = param(
        100, "pixels shared by neighbouring tiles (so a plant cut by one tile is whole in the next)", min=0
    )
    min_visible: float = param(
        0.3,
        "smallest fraction of a box's area inside a tile for the box to be kept in that tile (the paper's 'IoU')",
        min=0.0,
        max=1.0,
    )
    iou: float | None = param(None, "the paper's name for min_visible; when set, it is used instead", min=0.0, max=1.0)
    min_box_side: float = param(
        10.0, "boxes whose part inside a tile is narrower or lower than this (px) are dropped from that tile", min=0.0
    )
    split: list[float] = param([0.7, 0.15, 0.15], "shares of source images for train, val, test", min=0.0)
    seed: int = param(0, "random seed of the split and of the choice of negative tiles")
    split_mode: Literal["random", "spatial"] = param(
        "random",
        "'random' split of the photos, or 'spatial': "
        "photos ordered along the field, val and test at its end "
        "(needs positions or GPS in EXIF)",
        choices=["random", "spatial"],
    )
    positions: Path | None = param(
        None, "CSV image,x,y of each photo for the spatial split (default: the images' EXIF GPS)", path="file"
    )
    negative_share: float = param(
        0.1,
        "share of the tiles without any plant that are kept as negative examples (0 = none, 1 = all)",
        min=0.0,
        max=1.0,
    )
    tile_format: Literal["auto", "png", "tif"] = param(
        "auto",
        "tile files: 'auto' keeps a PNG or TIFF source's format and writes PNG otherwise (always lossless)",
        choices=["auto", "png", "tif"],
    )
    min_region_share: float = param(
        0.25,
        "for images annotated only inside a region (module 4's "
        "annotated_region, e.g. the owned area): tiles with less of their "
        "area inside it are not written; pixels outside it are masked",
        min=0.0,
        max=1.0,
    )
    yolo: bool = param(False, "also write YOLO labels, classes.txt and data.yaml")
    workers: int = param(0, "parallel processes (0 = one per CPU core, up to 8)", min=0)

    def check(self) -> None:
        """Reject an overlap too large for the tiles and split shares that are not three fractions summing to 1."""
        if self.overlap >= self.tile_size:
            raise ConfigError(
                f"'overlap' ({self.overlap}) must be smaller than 'tile_size' ({self.tile_size})",
                fix="for example tile_size: 1024 with overlap: 100",
            )
        if self.overlap > 0.75 * self.tile_size:
            raise ConfigError(
                f"'overlap' ({self.overlap}) is more than 3/4 of 'tile_size' ({self.tile_size}): every "
                f"plant would be cut into {(self.tile_size // (self.tile_size - self.overlap)) ** 2}+ "
                "nearly equal tiles",
                fix="use an overlap of about one plant's size, e.g. tile_size: 1024 with overlap: 100",
            )
        if len(self.split) != 3:
            raise ConfigError(
                f"'split' must be three shares (train, val, test), got {self.split}",
                fix="for example split: [0.7, 0.15, 0.15]",
            )
        if abs(sum(self.split) - 1.0) > 1e-3:
            pct = " (percentages? write fractions)" if abs(sum(self.split) - 100) < 0.1 else ""
            raise ConfigError(
                f"'split' shares must add up to 1, but {' + '.join(f'{v:g}' for v in self.split)} = "
                f"{sum(self.split):g}{pct}",
                fix="give train, val and test shares that sum to 1, e.g. split: [0.7, 0.15, 0.15]",
            )

    @property
    def threshold(self) -> float:
        """Smallest visible share of a box for a tile to keep it: ``iou`` when set, else ``min_visible``."""
        return self.min_visible if self.iou is None else self.iou
