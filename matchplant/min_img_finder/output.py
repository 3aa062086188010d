"""Step 3's outputs: what the annotator (step 4) and the user get from a selection.

``selected_images.csv``, the selected images (copied, hard-linked or only listed), ``owned_areas.json``
(the shared format of :mod:`matchplant.core.formats.owned_areas`), ``footprints.gpkg`` for GIS (the formats of
``vector_formats``), ``coverage.png``
and ``selection.json`` (settings and results, so a run can be traced). The coverage map is drawn by
:func:`draw_coverage`, shared by the figure and the GUI. ``finder`` below is a loaded
:class:`~matchplant.min_img_finder.run.MinImageFinder` and ``result`` its
:class:`~matchplant.min_img_finder.run.Result` (not imported here: the finder writes through this module).
"""

from __future__ import annotations

import csv
import os
import shutil
from pathlib import Path

import geopandas as gpd
import numpy as np
import shapely
from matplotlib import colormaps
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, PathPatch
from matplotlib.path import Path as MPath
from shapely.geometry import MultiPolygon, Polygon

from matchplant.core.formats.owned_areas import write_owned_areas
from matchplant.core.formats.vectors import write_formats
from matchplant.core.runtime.guard import staged_outputs
from matchplant.core.runtime.gui import figure
from matchplant.core.runtime.io import atomic_open, atomic_path, output_target, write_json
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress

log = get_logger("min_img_finder")


def save_selection(finder, result, skipped: list[dict] | None = None) -> dict[str, Path]:
    """Write a selection's outputs into ``output_dir`` whole or not at all (through a staging folder), then
    remove the images of an earlier selection there that this one does not hold. The command line and the
    GUI both save through here, so a re-run (greedy then milp, the GUI after the command) leaves nothing stale."""
    out = Path(finder.cfg.output_dir)
    previous = previous_images(out)
    with staged_outputs(out) as stage:
        paths = write_outputs(finder, result, stage)
        if skipped:
            write_rows(stage / "skipped_images.csv", skipped)
    kept = {fp.file.name for fp in result.selected} if finder.cfg.copy_images != "none" else set()
    remove_stale(out, previous, kept)
    return {k: out / Path(v).relative_to(stage) for k, v in paths.items()}


def write_outputs(finder, result, output_dir: Path | None = None) -> dict[str, Path]:
    """Write the CSV, images, figure, GeoPackage, owned-area JSON and summary; return their paths."""
    cfg = finder.cfg
    out = Path(output_dir or cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    sel = result.selected
    frac = finder.grid.overlap_fraction()
    idx = result.selection.indices
    # copies first, so the CSV and JSON name files that exist
    if cfg.copy_images != "none":
        folder = out / "images"
        folder.mkdir(exist_ok=True)
        for fp in progress(sel, desc=f"{cfg.copy_images} images", unit="image"):
            place_image(fp.file, folder / fp.file.name, cfg.copy_images)
        paths["images"] = folder
    covered = np.zeros(finder.grid.A.shape[1], bool)
    with atomic_open(out / "selected_images.csv", "w") as fh:
        wr = csv.writer(fh)
        wr.writerow(
            [
                "order",
                "image",
                "file",
                "footprint_area_m2",
                "owned_area_m2",
                "new_area_m2",
                "cumulative_coverage_pct",
                "centroid_x",
                "centroid_y",
                "max_overlap_pct",
                "map_number",
            ]
        )
        for k, (i, fp) in enumerate(zip(idx, sel), start=1):
            cells = finder.grid.A[i].indices
            new = float(finder.grid.weights[cells[~covered[cells]]].sum())
            covered[cells] = True
            row = frac[i]
            others = [row[0, j] for j in idx if j != i]
            cx, cy = fp.centroid
            wr.writerow(
                [
                    k,
                    fp.name,
                    fp.file.name,
                    f"{fp.polygon.intersection(finder.aoi).area:.4f}",
                    f"{result.owned[fp.name].area:.4f}",
                    f"{new:.4f}",
                    f"{100 * finder.grid.weights[covered].sum() / finder.grid.total:.3f}",
                    f"{cx:.3f}",
                    f"{cy:.3f}",
                    f"{100 * max(others, default=0.0):.2f}",
                    i + 1,
                ]
            )
    paths["csv"] = out / "selected_images.csv"
    write_owned_areas(out / "owned_areas.json", {fp.file.name: result.owned_pixels[fp.name] for fp in sel})
    paths["owned_areas"] = out / "owned_areas.json"
    paths.update(write_vectors(finder, result, out / "footprints", cfg.vector_formats))
    paths["figure"] = coverage_figure(finder, result, out / "coverage.png")
    s = result.selection
    write_json(
        out / "selection.json",
        {
            "project_dir": str(cfg.project_dir),
            "images_total": len(finder.footprints),
            "images_selected": len(idx),
            "selected": [fp.name for fp in sel],
            "method": s.method,
            "optimal": s.optimal,
            "overlap_cap_relaxed": s.relaxed,
            "requested_coverage_pct": 100 * s.target,
            "coverage_pct": 100 * result.exact_coverage,
            "grid_coverage_pct": 100 * s.coverage,
            "aoi_area_m2": finder.aoi.area,
            "cell_size_m": finder.grid.cell,
            "crs": finder.frame.crs.to_string(),
            "settings": {
                k: getattr(cfg, k)
                for k in ("uncovered_threshold", "max_overlap", "overlap_penalty", "border_samples", "dsm_resolution")
            },
            "selection_seconds": round(s.seconds, 4),
            "footprint_seconds": round(finder.footprint_seconds, 3),
        },
    )
    paths["summary"] = out / "selection.json"
    return paths


def previous_images(out: Path) -> set[str]:
    """The image files an earlier run placed in ``out/images`` (its ``selected_images.csv``, column ``file``)."""
    path = out / "selected_images.csv"
    if not path.is_file():
        return set()
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            return {Path(row["file"]).name for row in csv.DictReader(fh) if row.get("file")}
    except (OSError, UnicodeError, KeyError, csv.Error):
        return set()


def remove_stale(out: Path, previous: set[str], kept: set[str]) -> None:
    """Remove the images an earlier run placed that this selection does not hold, so ``images/`` holds
    exactly the selection (step 4 opens, and step 5 tiles, whatever is there). Only files the earlier run
    listed are removed: anything else a user put in the folder stays."""
    stale = sorted(name for name in previous - kept if (out / "images" / name).is_file())
    for name in stale:
        (out / "images" / name).unlink()
    if stale:
        log.info(
            "removed %d image(s) of the previous selection from %s: %s",
            len(stale),
            out / "images",
            ", ".join(stale[:5]) + (" ..." if len(stale) > 5 else ""),
        )


def write_rows(path: Path, rows: list[dict]) -> Path:
    """A small CSV of dicts (their keys as the header), written atomically."""
    with atomic_open(path, "w") as fh:
        wr = csv.DictWriter(fh, fieldnames=list(rows[0]))
        wr.writeheader()
        wr.writerows(rows)
    return path


def place_image(src: Path, dst: Path, mode: str) -> None:
    """Copy or hard-link an image into place (a hard link falls back to a copy across drives)."""
    if dst.exists() and dst.stat().st_size == src.stat().st_size and mode == "link" and os.path.samefile(src, dst):
        return
    if mode == "link" and output_target(dst) == ("file", dst):  # a link or a device at dst: written through
        tmp = dst.with_name(f".{dst.name}.link")
        try:
            if tmp.exists():
                tmp.unlink()
            os.link(src, tmp)
            os.replace(tmp, dst)
            return
        except OSError:
            log.debug("hard link failed for %s; copying", src)
    with atomic_path(dst) as tmp:
        shutil.copy2(src, tmp)


def write_vectors(finder, result, base: Path, formats) -> dict[str, Path]:
    """Footprints, owned areas, AOI and uncovered parts as layers in each of ``formats`` (``base.gpkg``, ...),
    to check a selection in a GIS."""
    crs = finder.frame.crs
    order = {i: k for k, i in enumerate(result.selection.indices, start=1)}
    fps = gpd.GeoDataFrame(
        {
            "image": finder.names,
            "selected": [i in order for i in range(len(finder.footprints))],
            "order": [order.get(i, 0) for i in range(len(finder.footprints))],
            "area_m2": [f.polygon.area for f in finder.footprints],
        },
        geometry=[f.polygon for f in finder.footprints],
        crs=crs,
    )
    sel = result.selected
    owned = gpd.GeoDataFrame(
        {
            "image": [f.name for f in sel],
            "file": [f.file.name for f in sel],
            "order": list(range(1, len(sel) + 1)),
            "area_m2": [result.owned[f.name].area for f in sel],
        },
        geometry=[_multi(result.owned[f.name]) for f in sel],
        crs=crs,
    )
    aoi = gpd.GeoDataFrame({"area_m2": [finder.aoi.area]}, geometry=[_multi(finder.aoi)], crs=crs)
    unc = gpd.GeoDataFrame({"area_m2": [result.uncovered.area]}, geometry=[_multi(result.uncovered)], crs=crs)
    return write_formats({"footprints": fps, "owned": owned, "aoi": aoi, "uncovered": unc}, base, formats)


def _multi(geom):
    """Polygon or MultiPolygon only (GeoPackage layers want one geometry type)."""
    polys = [g for g in shapely.get_parts(geom) if isinstance(g, Polygon) and not g.is_empty]
    return MultiPolygon(polys) if polys else MultiPolygon()


def draw_coverage(ax, finder, result, *, numbers: bool = True) -> None:
    """The coverage map: orthophoto, AOI, every footprint (grey), selected ones numbered with their owned
    areas, uncovered areas in red, and a legend saying so. Used by the figure and the GUI."""
    ax.clear()
    if finder.preview is not None:
        rgb, mask, t, _ = finder.preview
        h, w = mask.shape
        ext = (t.c, t.c + w * t.a, t.f + h * t.e, t.f)
        ax.imshow(np.dstack([rgb, (mask * 255).astype(np.uint8)]), extent=ext, interpolation="nearest")
    for f in finder.footprints:
        x, y = f.polygon.exterior.xy
        ax.plot(x, y, color="0.55", lw=0.5, alpha=0.6)
    # number and colour follow the image (its place among all the flight's images), not the order of
    # selection: removing one image in the GUI leaves every other image's number and colour as it was
    palette = _palette(len(finder.footprints))
    colors = [palette[i] for i in result.selection.indices]
    numbers_of = [i + 1 for i in result.selection.indices]
    for k, fp in enumerate(result.selected):
        area = result.owned[fp.name]
        for part in shapely.get_parts(area):
            if isinstance(part, Polygon) and not part.is_empty:
                ax.add_patch(PathPatch(_mpl_path(part), facecolor=colors[k], alpha=0.28, lw=0))
        x, y = fp.polygon.exterior.xy
        ax.plot(x, y, color=colors[k], lw=1.6)
        if numbers:
            cx, cy = fp.centroid
            ax.text(
                cx,
                cy,
                str(numbers_of[k]),
                ha="center",
                va="center",
                fontsize=10,
                weight="bold",
                color="black",
                bbox=dict(boxstyle="circle,pad=0.2", fc="white", ec=colors[k], alpha=0.85),
            )
    for part in shapely.get_parts(result.uncovered):
        if isinstance(part, Polygon) and part.area > 0:
            ax.add_patch(PathPatch(_mpl_path(part), facecolor="red", alpha=0.45, lw=0, hatch="//"))
    for part in shapely.get_parts(finder.aoi):
        if isinstance(part, Polygon):
            x, y = part.exterior.xy
            ax.plot(x, y, color="yellow", lw=1.2, ls="--")
    xmin, ymin, xmax, ymax = shapely.union_all([finder.aoi] + [f.polygon for f in finder.footprints]).bounds
    pad = 0.03 * max(xmax - xmin, ymax - ymin)
    ax.set_xlim(xmin - pad, xmax + pad)
    ax.set_ylim(ymin - pad, ymax + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("easting (m)")
    ax.set_ylabel("northing (m)")
    s = result.selection
    ax.set_title(
        f"{len(s.indices)} of {len(finder.footprints)} images cover {100 * result.exact_coverage:.1f}% "
        f"of the area (asked {100 * s.target:.0f}%)",
        fontsize=11,
    )
    ax.ticklabel_format(useOffset=False, style="plain")
    _legend(ax, colors[0] if colors else "tab:blue", numbers)


def _legend(ax, colour, numbers: bool) -> None:
    """What each mark on the coverage map means (proxies, so the legend does not depend on the data)."""
    handles = [
        Line2D([], [], color="0.55", lw=0.8, label="footprint of an image (all images)"),
        Line2D(
            [],
            [],
            color=colour,
            lw=1.6,
            marker="o" if numbers else None,
            mfc="white",
            mec=colour,
            label="selected image (number: its map_number in selected_images.csv)" if numbers else "selected image",
        ),
        Patch(facecolor=colour, alpha=0.28, lw=0, label="area that image owns (its plants)"),
        Patch(facecolor="red", alpha=0.45, hatch="//", lw=0, label="not covered by the selection"),
        Line2D([], [], color="yellow", lw=1.2, ls="--", label="area to cover (AOI)"),
    ]
    ax.legend(handles=handles, loc="upper right", fontsize=8, framealpha=0.85)


def _mpl_path(poly: Polygon) -> MPath:
    verts, codes = [], []
    for ring in [poly.exterior, *poly.interiors]:
        xy = np.asarray(ring.coords)[:, :2]
        verts.append(xy)
        codes += [MPath.MOVETO] + [MPath.LINETO] * (len(xy) - 2) + [MPath.CLOSEPOLY]
    return MPath(np.concatenate(verts), codes)


def _palette(n: int):
    cmap = colormaps["tab20"]
    return [cmap(i % 20) for i in range(n)]


def coverage_figure(finder, result, path: Path) -> Path:
    """Save the coverage map of a selection as a PNG at ``path``; the path."""
    fig = figure(headless=True, figsize=(9, 8), dpi=110)
    ax = fig.add_subplot(111)
    draw_coverage(ax, finder, result)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
