"""Module 3: the fewest undistorted images that cover the field, and the part of the field each one owns.

1. **Footprints.** Each undistorted image's true ground footprint: rays through points along its border
   (``border_samples`` per side, corners included) are intersected with the DSM
   (:func:`~matchplant.core.geometry.ground.pixels_to_ground`), giving a polygon in the map CRS that follows the relief
   - not the bounding box of an orthorectified image, and without ODM's slow orthorectification.
2. **Area of interest (AOI).** The orthophoto's valid-data area, read at reduced resolution and
   polygonised (``rasterio.features.shapes``), or a polygon file from the user.
3. **Selection: greedy weighted set cover with an overlap penalty and an overlap cap.** The AOI is cut into
   a grid of cells (each weighted by its area). Starting from nothing, the image adding the most uncovered
   area, minus ``overlap_penalty`` times the area it covers twice, is taken, among images whose overlap
   with every image already taken is at most ``max_overlap`` (the paper's overlap limit, so the same
   plants are not labelled many times); this repeats until the uncovered share of the AOI is at most
   ``uncovered_threshold`` (the paper's control). If the cap makes that impossible it is relaxed, with a
   warning. It is also started from each corner of the area (from every image on small flights), and each
   run is pruned of images the coverage no longer needs and improved by swaps. Greedy set cover is within a
   factor ln(n) of the optimum in theory and close to it on survey grids; ``method: milp`` solves the same
   problem exactly as an integer program (scipy's HiGHS ``milp``) for small flights.
4. **Owned areas.** Every covered point of the AOI is given to exactly one selected image: the one whose
   footprint centre is nearest (a Voronoi partition) when that image sees it, otherwise the selected image
   that sees most of the leftover piece. Each owned area is also mapped into its image's pixels
   (:func:`~matchplant.core.geometry.ground.ground_to_pixels` through the DSM), so module 4 can show the annotator which
   part of each photo to label: every plant is then labelled exactly once.

Where it lives: footprints in :mod:`matchplant.core.formats.footprints`; the AOI and its grid in
:mod:`~matchplant.min_img_finder.aoi`; the set-cover solvers (pure arrays) in
:mod:`~matchplant.min_img_finder.setcover`; owned areas in :mod:`~matchplant.min_img_finder.owned`; the
outputs in :mod:`~matchplant.min_img_finder.output`. This module loads a project once and ties them together
(the CLI and the GUI share it).

Outputs (``output_dir``): ``selected_images.csv``, the selected undistorted images (copied, hard-linked or
only listed), ``coverage.png``, ``footprints.gpkg`` (layers ``footprints``, ``owned``, ``aoi``,
``uncovered``), ``owned_areas.json`` (``{image file name: [[u, v], ...]}`` in that image's pixels) and
``selection.json`` (settings and results); ``skipped_images.csv`` when reconstructed images got no footprint
(no undistorted image file, or a border that misses the DSM), with the reason for each. An area of interest
that no image sees, or a selection of 0 images, is an error; a failed run writes nothing.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon

from matchplant.core.formats.footprints import Footprint, compute_footprints, open_dsm, polygon_to_pixels
from matchplant.core.formats.odm import ODMProject
from matchplant.core.formats.projects import open_project
from matchplant.core.formats.split_check import check_split
from matchplant.core.geometry.frames import parse_crs
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.validate_gis import check_raster
from matchplant.min_img_finder.aoi import aoi_from_mask, build_grid, orthophoto_preview, read_aoi_file
from matchplant.min_img_finder.config import MinImgFinderConfig
from matchplant.min_img_finder.output import save_selection
from matchplant.min_img_finder.owned import largest_polygon, owned_areas
from matchplant.min_img_finder.setcover import Selection, reachable_coverage, select_greedy, select_milp

log = get_logger("min_img_finder")


@dataclass
class Result:
    """A selection evaluated: what the outputs and the GUI show."""

    selection: Selection
    footprints: list[Footprint]
    owned: dict[str, Polygon | MultiPolygon]  # shot id -> owned ground area
    owned_pixels: dict[str, np.ndarray]  # shot id -> (N, 2) pixels in its undistorted image
    exact_coverage: float  # union of the selected footprints / AOI area (polygons)
    uncovered: Polygon | MultiPolygon

    @property
    def selected(self) -> list[Footprint]:
        """Footprints of the selected images, in selection order."""
        return [self.footprints[i] for i in self.selection.indices]


class MinImageFinder:
    """Loads a project once (footprints, AOI, grid); selects, evaluates and saves many times (GUI)."""

    def __init__(self, cfg: MinImgFinderConfig):
        self.cfg = cfg
        t0 = time.perf_counter()
        self.project = open_project(cfg.project_dir, cfg.project_type)
        check_split(self.project)  # a failed or foreign submodel: named, not skipped
        if isinstance(self.project, ODMProject):
            self.project.require("undistorted_reconstruction", "undistorted_images", "dsm")
        else:  # Metashape, Pix4D: the original photos (on disk: their footprints are copied)
            self.project.require("dsm")
        self.frame = self.project.frame()
        check_raster(self.project.path("dsm"), bands=1, what="DSM")
        self.surface = open_dsm(self.project.path("dsm"), cfg.dsm_resolution)
        if (
            self.surface.crs is not None
            and getattr(self.frame, "crs", None) is not None
            and not _same_crs(self.surface.crs, self.frame.crs)
        ):
            raise InputError(
                f"the DSM's CRS ({self.surface.crs}) differs from the reconstruction's ({self.frame.crs.to_string()})",
                path=self.project.path("dsm"),
                fix="use the DSM of this ODM run, or reproject it to the reconstruction's CRS",
            )
        self.preview = None
        if self.project.has("orthophoto"):
            ortho = self.project.path("orthophoto")
            check_raster(ortho, bands=1, require_crs=cfg.aoi_file is None, allow_empty=True, what="orthophoto")
            self.preview = orthophoto_preview(ortho, cfg.preview_size)
        if cfg.aoi_file is not None:
            self.aoi = read_aoi_file(Path(cfg.aoi_file), self.frame.crs)
        elif self.preview is not None:
            self.aoi = aoi_from_mask(self.preview[1], self.preview[2], self.project.path("orthophoto"))
        else:
            raise InputError(
                "no area of interest: the orthophoto is missing and no aoi_file is set",
                path=self.project.path("orthophoto"),
                fix="set aoi_file to a polygon file, or run ODM with the orthophoto step",
            )
        self.footprints = compute_footprints(self.project, self.frame, self.surface, cfg.border_samples)
        self.skipped = skipped_images(self.project, self.footprints)
        self.footprint_seconds = time.perf_counter() - t0
        self.grid = build_grid(self.aoi, [f.polygon for f in self.footprints], cfg.cell_size)
        if reachable_coverage(self.grid) <= 0:
            raise self._aoi_misses()
        log.info(
            "%d footprints on the DSM; area of interest %.1f m^2 in %d cells of %.3f m",
            len(self.footprints),
            self.aoi.area,
            self.grid.A.shape[1],
            self.grid.cell,
        )

    def _aoi_misses(self) -> InputError:
        """The error for an area of interest that no image sees: where each lies, and what to change."""
        fps = shapely.union_all([f.polygon for f in self.footprints])
        gap = self.aoi.distance(fps)
        a, b = self.aoi.bounds, fps.bounds
        where = (
            f"the area of interest ({a[0]:.0f}..{a[2]:.0f} E, {a[1]:.0f}..{a[3]:.0f} N) lies {gap:.0f} m from "
            f"the images' footprints ({b[0]:.0f}..{b[2]:.0f} E, {b[1]:.0f}..{b[3]:.0f} N, {self.frame.crs.name})"
        )
        if self.cfg.aoi_file is not None:
            return InputError(
                f"no image covers any of the area of interest: {where}; 0 images would be selected",
                path=self.cfg.aoi_file,
                fix="draw the AOI over this field, check its CRS, or leave "
                "aoi_file empty to cover the orthophoto's area",
            )
        return InputError(
            f"no image covers any of the orthophoto's valid area: {where}",
            path=self.project.path("orthophoto"),
            fix="use the orthophoto of this ODM run, or set aoi_file to the field's boundary",
        )

    @property
    def reachable(self) -> float:
        """The share of the area every image together covers: the most any selection can reach."""
        return reachable_coverage(self.grid)

    @property
    def names(self) -> list[str]:
        """Image names of all footprints, in footprint order."""
        return [f.name for f in self.footprints]

    def select(self) -> Selection:
        """Choose few images covering the AOI up to the configured uncovered threshold, with the configured method."""
        cfg = self.cfg
        target = 1.0 - cfg.uncovered_threshold / 100.0
        reach = self.reachable
        if reach < target - 1e-9:
            log.warning("all images together cover only %.1f%% of the area; selecting for that", 100 * reach)
        if cfg.method == "milp":
            sel = select_milp(self.grid, target, cfg.max_overlap / 100.0, cfg.milp_time_limit)
        else:
            sel = select_greedy(self.grid, target, cfg.max_overlap / 100.0, cfg.overlap_penalty)
        # the grid approximates the AOI: add images until the exact (polygon) coverage reaches the target too
        goal = min(target, reach)
        for _ in range(len(self.footprints)):
            if self.exact_coverage(sel.indices) >= goal - 1e-6:
                break
            extra = self._best_addition(sel.indices)
            if extra is None:
                break
            sel.indices.append(extra)
            sel.coverage = self.grid.coverage(sel.indices)
        if sel.relaxed:
            log.warning(
                "max_overlap %.0f%% could not reach the coverage; some selected images overlap more", cfg.max_overlap
            )
        return sel

    def _best_addition(self, chosen: Sequence[int]) -> int | None:
        covered = (
            np.asarray(self.grid.A[list(chosen)].sum(axis=0)).ravel() > 0
            if chosen
            else np.zeros(self.grid.A.shape[1], bool)
        )
        gain = self.grid.A.astype(float) @ np.where(covered, 0.0, self.grid.weights)
        gain[list(chosen)] = -1
        return int(np.argmax(gain)) if gain.max() > 0 else None

    def exact_coverage(self, indices: Sequence[int]) -> float:
        """Fraction of the AOI the union of these images' footprint polygons covers."""
        if not indices:
            return 0.0
        union = shapely.union_all([self.footprints[i].polygon for i in indices])
        return float(union.intersection(self.aoi).area / self.aoi.area)

    def evaluate(self, selection: Selection) -> Result:
        """Owned areas (map and pixels), exact coverage and the uncovered area of a selection."""
        chosen = [self.footprints[i] for i in selection.indices]
        owned = owned_areas(self.aoi, [f.polygon for f in chosen])
        step = max(self.grid.cell, self.surface.pixel_size)
        pix = {}
        for fp, area in zip(chosen, owned):
            main = largest_polygon(area)
            if area.area - main.area > 0.01 * max(area.area, 1e-9):
                log.warning(
                    "%s owns %d separate pieces; owned_areas.json holds its largest",
                    fp.name,
                    len(getattr(area, "geoms", [area])),
                )
            pix[fp.name] = polygon_to_pixels(main, fp.shot, fp.frame or self.frame, self.surface, step)
        union = shapely.union_all([f.polygon for f in chosen]) if chosen else Polygon()
        uncovered = self.aoi.difference(union)
        exact = float(self.aoi.intersection(union).area / self.aoi.area) if chosen else 0.0
        return Result(
            selection=selection,
            footprints=self.footprints,
            owned={f.name: a for f, a in zip(chosen, owned)},
            owned_pixels=pix,
            exact_coverage=exact,
            uncovered=uncovered,
        )

    def with_indices(self, indices: Sequence[int], method: str = "manual") -> Selection:
        """A selection of the given images, e.g. one picked by hand in the GUI."""
        target = 1.0 - self.cfg.uncovered_threshold / 100.0
        return Selection(indices=list(indices), coverage=self.grid.coverage(indices), target=target, method=method)


def _same_crs(a, b) -> bool:
    try:
        return parse_crs(a) == parse_crs(b)
    except Exception:  # noqa: BLE001 - undecidable: do not block the run
        return True


def skipped_images(project: ODMProject, footprints: Sequence[Footprint]) -> list[dict]:
    """The reconstructed images that got no footprint, each with the reason (for ``skipped_images.csv``)."""
    placed = {f.name for f in footprints}
    if not isinstance(project, ODMProject):  # Metashape, Pix4D: every posed photo is on disk (checked on reading)
        return [
            {"image": sid, "reason": "its border rays miss the DSM (it does not look at the mapped ground)"}
            for sid in sorted(project.shot_ids(undistorted=False) - placed)
        ]
    files = project.undistorted_images()
    return [
        {
            "image": sid,
            "reason": f"no undistorted image file (expected {sid}.tif in opensfm/undistorted/images)"
            if sid not in files
            else "its border rays miss the DSM (it does not look at the mapped ground)",
        }
        for sid in sorted(project.shot_ids(undistorted=True) - placed)
    ]


def run(cfg: MinImgFinderConfig) -> Result:
    """Step 3 from the command line: load, select, evaluate, write.

    All or nothing: a failed run leaves ``output_dir`` as it was.

    Parameters
    ----------
    cfg : MinImgFinderConfig
        The step's settings, as loaded from its YAML config (``3_min_img_finder/config.yaml``) or built in Python.

    Returns
    -------
    Result
        The selection evaluated: the selected images, the ground area each owns, the coverage and the uncovered
        area.
    """
    finder = MinImageFinder(cfg)
    selection = finder.select()
    if not selection.indices:
        raise InputError(
            f"0 of {len(finder.footprints)} images selected: none covers the area of interest",
            path=cfg.aoi_file or cfg.project_dir,
            fix="check the area of interest (aoi_file) and uncovered_threshold",
        )
    result = finder.evaluate(selection)
    out = Path(cfg.output_dir)
    save_selection(finder, result, finder.skipped)
    if finder.skipped:
        log.warning(
            "%d of %d reconstructed images could not be used (%s); see %s",
            len(finder.skipped),
            len(finder.skipped) + len(finder.footprints),
            "; ".join(f"{n} x {r}" for r, n in Counter(s["reason"] for s in finder.skipped).items()),
            out / "skipped_images.csv",
        )
    log.info(
        "selected %d of %d images (%s, %.3f s) covering %.1f%% of the area; outputs in %s",
        len(selection.indices),
        len(finder.footprints),
        selection.method,
        selection.seconds,
        100 * result.exact_coverage,
        out,
    )
    return result
