"""Module 9's window (the paper's Fig. 9): choose the files (a "..." file picker beside each path), the statistics and
percentiles, look at the plants over the raster,
run in the background with a progress bar, and save. A thin layer over :mod:`matchplant.spatial_stat_extractor.run`.

The preview reads the raster at reduced resolution (overviews or decimated reads), never the full
raster. The work runs in a thread; a timer on the window moves the progress bar and shows errors.
"""

from __future__ import annotations

import re
import threading
from pathlib import Path

import numpy as np
import shapely
from matplotlib.collections import LineCollection
from matplotlib.widgets import Button, CheckButtons, RadioButtons

from matchplant.core.runtime.config import save_config, set_value, validate
from matchplant.core.runtime.errors import ConfigError, MatchPlantError
from matchplant.core.runtime.gui import figure, fit_to_axes, is_headless, require_display, show
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.widgets import QuietTextBox, ask_path
from matchplant.spatial_stat_extractor.config import RasterSet, SpatialStatExtractorConfig
from matchplant.spatial_stat_extractor.inputs import preview_layer, read_polygons
from matchplant.spatial_stat_extractor.plots import describe, unit_of
from matchplant.spatial_stat_extractor.run import extract_and_write
from matchplant.spatial_stat_extractor.zonal import BASIC_STATS, MODES

log = get_logger("spatial_stat_extractor")

TEXT_FIELDS = [  # (config key, label)
    ("polygons", "Polygons"),
    ("rasters.chm", "CHM"),
    ("rasters.dsm", "DSM"),
    ("rasters.dtm", "DTM"),
    ("rasters.multispectral", "Multispectral"),
    ("rasters.red_band", "Red band"),
    ("rasters.nir_band", "NIR band"),
    ("rasters.rgb", "RGB orthophoto"),
    ("plots.polygons", "Plots"),
    ("plots.field_book", "Field book"),
    (LATER_CHM := "later_chm", "Later-date CHM"),
    ("polygons_crs", "Polygons CRS"),
    ("percentiles", "Percentiles"),
    ("output_dir", "Output folder"),
]
# keys with a file picker ("..." beside the box: Tk's dialogs)
PICKERS = {
    "polygons": "file",
    "rasters.chm": "file",
    "rasters.dsm": "file",
    "rasters.dtm": "file",
    "rasters.multispectral": "file",
    "rasters.rgb": "file",
    "plots.polygons": "file",
    "plots.field_book": "file",
    LATER_CHM: "file",
    "output_dir": "folder",
}
# the later-date CHM box fills this one entry of more_dates (a config file can list any number of dates)
LATER_DATE = "later"
ERROR_COLOR = "#c62828"


def _get(cfg, key: str):
    if key == LATER_CHM:
        return next((d.chm for d in cfg.more_dates if d.date == LATER_DATE), None)
    for part in key.split("."):
        cfg = getattr(cfg, part)
    return cfg


def set_later_chm(cfg, path: str | None) -> None:
    """The window's one later date: a CHM of a second flight over the same plants (growth per plant)."""
    cfg.more_dates = [d for d in cfg.more_dates if d.date != LATER_DATE]
    if path:
        cfg.more_dates.append(RasterSet(date=LATER_DATE, chm=Path(path)))
        if not cfg.rasters.date:
            cfg.rasters.date = "first"


def _as_text(value) -> str:
    if value is None:
        return ""
    if isinstance(value, (list, tuple)):
        return ", ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in value)
    return str(value)


# what the map is coloured by after a run, the first present: a height, then a vegetation index, then any mean
COLOUR_BY = (
    r"^chm_max",
    r"^chm_(canopy_)?(max|p9\d|mean)",
    r"^(ndvi|ndre|gndvi|exg|vari|gli)_(canopy_)?mean",
    r"_mean$",
)


def colour_column(columns: list[str]) -> str:
    """The statistic the map is coloured by: a plant's height, else an index's mean, else any mean (not a
    minimum such as exg_min, which says little about a plant), else the first column."""
    for pattern in COLOUR_BY:
        found = next((c for c in columns if re.search(pattern, c)), None)
        if found:
            return found
    return columns[0]


class SpatialStatExtractorGUI:
    """The window over a :class:`~matchplant.spatial_stat_extractor.config.SpatialStatExtractorConfig`.
    ``headless=True``
    (tests) draws on a figure of its own, without a window."""

    def __init__(
        self,
        cfg: SpatialStatExtractorConfig,
        config_path: Path | None = None,
        headless: bool | None = None,
        chooser=None,
    ):
        self.cfg = cfg
        self.chooser = chooser  # replaces Tk's dialog (tests): chooser(kind, title, initial) -> path or None
        self.config_path = Path(config_path) if config_path else None
        self.headless = is_headless(headless)
        self.fig = fig = figure(self.headless, figsize=(13, 8), title="9 Spatial statistics")
        if self.headless:  # Agg draws at once on every widget event; nobody looks until savefig (which still draws)
            self.fig.canvas.draw_idle = self.fig.canvas.draw = lambda *args, **kwargs: None
        self.ax = fig.add_axes([0.06, 0.13, 0.46, 0.80])
        self.cbar_ax = fig.add_axes([0.535, 0.13, 0.012, 0.80])  # the map's colour bar, shown with a result
        self.cbar_ax.set_visible(False)
        self.ax.set_title("Preview: load the files and press Preview", fontsize=10)
        self.ax.set_aspect("equal")
        self.boxes: dict = {}
        self.pickers: dict = {}
        y = 0.955
        for key, label in TEXT_FIELDS:
            width = 0.225 if key in PICKERS else 0.26
            box = QuietTextBox(fig.add_axes([0.72, y, width, 0.03]), label + " ", initial=_as_text(_get(cfg, key)))
            box.on_submit(lambda text, key=key: self._set(key, text))
            self.boxes[key] = box
            if key in PICKERS:
                self.pickers[key] = Button(fig.add_axes([0.948, y, 0.032, 0.03]), "...")
                self.pickers[key].on_clicked(lambda _e, key=key: self.browse(key))
            y -= 0.036
        self.crs_text = fig.text(0.62, y + 0.005, "CRS: -", fontsize=9, family="monospace")
        fig.text(0.62, y - 0.03, "Statistics", fontsize=10, weight="bold")
        self.stat_checks = CheckButtons(
            fig.add_axes([0.62, y - 0.25, 0.17, 0.21]), list(BASIC_STATS), [s in cfg.stats for s in BASIC_STATS]
        )
        self.stat_checks.on_clicked(lambda _label: self._set_stats())
        fig.text(0.81, y - 0.03, "Pixels", fontsize=10, weight="bold")
        self.mode_radio = RadioButtons(
            fig.add_axes([0.81, y - 0.13, 0.17, 0.09]), list(MODES), active=list(MODES).index(cfg.mode)
        )
        self.mode_radio.on_clicked(lambda label: self._set("mode", label))
        by = 0.13
        self.btn_preview = Button(fig.add_axes([0.62, by, 0.11, 0.05]), "Preview")
        self.btn_run = Button(fig.add_axes([0.745, by, 0.11, 0.05]), "Run + save")
        self.btn_save = Button(fig.add_axes([0.87, by, 0.11, 0.05]), "Save config")
        self.btn_preview.on_clicked(lambda _e: self.preview())
        self.btn_run.on_clicked(lambda _e: self.run())
        self.btn_save.on_clicked(lambda _e: self.save_config())
        self.bar_ax = fig.add_axes([0.62, 0.075, 0.36, 0.03])
        self.bar_ax.set_xlim(0, 1)
        self.bar_ax.set_ylim(0, 1)
        self.bar_ax.set_xticks([])
        self.bar_ax.set_yticks([])
        self.bar = self.bar_ax.barh(0.5, 0.0, height=1.0, color="#2e7d32")[0]
        self.status = fit_to_axes(fig.text(0.04, 0.03, "", fontsize=9, family="monospace"))  # in the window
        # background work: the thread writes these, the timer (main thread) draws them
        self.fraction = 0.0
        self.message = ""
        self.error: str | None = None
        self.result = None
        self.thread: threading.Thread | None = None
        self.timer = fig.canvas.new_timer(interval=150)
        self.timer.add_callback(self.poll)
        self.poly_artist = None
        self.image_artist = None
        self.colorbar = None
        self.set_status("Set the files (press Enter in a box), then Preview or Run + save.")

    # ---------------------------------------------------------------------------------------------
    # settings

    def set_status(self, text: str, error: bool = False) -> None:
        """Show ``text`` in the status line (red for an error)."""
        self.status.set_text(text)
        self.status.set_color(ERROR_COLOR if error else "black")
        self.fig.canvas.draw_idle()

    def _set(self, key: str, text: str) -> bool:
        text = text.strip()
        try:
            if key == "percentiles":
                value = [float(v) for v in text.replace(";", ",").split(",") if v.strip()]
            elif text == "" and key not in ("polygons_crs",):
                value = None
            else:
                value = text
            if value is None and key in ("polygons", "output_dir"):
                raise ConfigError(f"'{key}' cannot be empty", fix="type a value and press Enter")
            if key == LATER_CHM:
                set_later_chm(self.cfg, value)
            else:  # an empty red/NIR band: from the raster's band names or band_order
                set_value(self.cfg, key, value, source="window")
        except ValueError:
            self.set_status(f"error: percentiles must be numbers separated by commas, got {text!r}", error=True)
            return False
        except MatchPlantError as exc:
            self.set_status(f"error: {exc}", error=True)
            return False
        self.set_status(f"{key} = {_as_text(_get(self.cfg, key))}")
        return True

    def browse(self, key: str) -> str | None:
        """Tk's file (or folder) dialog for ``key``; the choice goes into its box and the config."""
        label = dict(TEXT_FIELDS)[key]
        current = self.boxes[key].text.strip() or None
        try:
            if self.chooser is not None:
                chosen = self.chooser(PICKERS[key], f"Choose the {label.lower()}", current)
            else:
                widget = getattr(self.fig.canvas, "get_tk_widget", None)
                chosen = ask_path(
                    PICKERS[key],
                    f"Choose the {label.lower()}",
                    current,
                    parent=widget() if widget is not None else None,
                )
        except MatchPlantError as exc:
            self.set_status(f"error: {exc}", error=True)
            return None
        if chosen:
            self.boxes[key].set_val(chosen)
            self._set(key, chosen)
        return chosen

    def _set_stats(self) -> None:
        chosen = [s for s, on in zip(BASIC_STATS, self.stat_checks.get_status()) if on]
        self.cfg.stats = chosen
        self.set_status("statistics: " + (", ".join(chosen) or "none (only percentiles)"))

    def sync(self) -> bool:
        """Take every text box's current text (also those not confirmed with Enter)."""
        return all(
            self._set(key, box.text) for key, box in self.boxes.items() if box.text != _as_text(_get(self.cfg, key))
        )

    def _validate(self) -> bool:
        if not self.sync():
            return False
        try:
            validate(self.cfg, source="window")
        except MatchPlantError as exc:
            self.set_status(f"error: {exc}", error=True)
            return False
        return True

    # ---------------------------------------------------------------------------------------------
    # preview

    def preview(self) -> bool:
        """Polygons over the first raster, read at reduced resolution."""
        if not self._validate():
            return False
        try:
            layer = self.cfg.date_sets()[0].layers()[0]
            arr, extent, rcrs = preview_layer(layer, nodata=self.cfg.nodata)
            polys = read_polygons(self.cfg.polygons, self.cfg.id_column, self.cfg.layer, self.cfg.polygons_crs)
        except MatchPlantError as exc:
            self.set_status(f"error: {exc}", error=True)
            return False
        note = ""
        if rcrs is not None and polys.crs is not None and not polys.crs.equals(rcrs):
            polys = polys.to_crs(rcrs)
            note = "  (polygons reprojected to the raster's CRS)"
        pcrs = polys.crs.to_string() if polys.crs is not None else "none"
        self.crs_text.set_text(f"CRS: raster {rcrs.to_string() if rcrs else 'none'}, polygons {pcrs}")
        self.ax.clear()
        finite = arr[np.isfinite(arr)]
        vmin, vmax = np.percentile(finite, [2, 98]) if finite.size else (0, 1)
        self.image_artist = self.ax.imshow(
            arr, extent=extent, cmap="viridis", vmin=vmin, vmax=vmax, interpolation="nearest"
        )
        rings = shapely.get_exterior_ring(shapely.get_parts(polys.geometry.values))
        coords, idx = shapely.get_coordinates(rings, return_index=True)
        segments = np.split(coords, np.flatnonzero(np.diff(idx)) + 1) if len(coords) else []
        self.segments = segments
        self.poly_artist = LineCollection(segments, colors="#ff3df2", linewidths=0.8)
        self.ax.add_collection(self.poly_artist)
        self.ax.ticklabel_format(useOffset=False, style="plain")
        self.ax.tick_params(labelsize=8)
        self.ax.tick_params(axis="y", labelrotation=90)
        self.ax.set_xlim(extent[0], extent[1])
        self.ax.set_ylim(extent[2], extent[3])
        self.ax.set_title(
            f"{layer.name} ({arr.shape[1]} x {arr.shape[0]} preview) and {len(polys)} plants", fontsize=10
        )
        self.preview_polygons = polys
        self.set_status(f"preview of {Path(layer.paths[0]).name}: {len(polys)} plants{note}")
        return True

    # ---------------------------------------------------------------------------------------------
    # background run

    @property
    def busy(self) -> bool:
        """Whether a run is in progress."""
        return self.thread is not None and self.thread.is_alive()

    def run(self) -> bool:
        """Start the statistics in a background thread; the timer shows progress."""
        if self.busy:
            self.set_status("already running")
            return False
        if not self._validate():
            return False
        self.fraction, self.message, self.error, self.result = 0.0, "starting", None, None
        self.bar.set_width(0.0)
        self.thread = threading.Thread(target=self._work, daemon=True)
        self.thread.start()
        self.timer.start()
        self.set_status("running ...")
        return True

    def _progress(self, fraction: float, message: str) -> None:
        self.fraction, self.message = fraction, message

    def _work(self) -> None:
        try:
            polygons, table, _, written = extract_and_write(self.cfg, on_progress=self._progress)
            self.result = (polygons, table, written)
        except MatchPlantError as exc:
            self.error = f"error: {exc}"
        except Exception as exc:  # noqa: BLE001 - shown in the window instead of a lost traceback
            log.debug("internal error", exc_info=True)
            self.error = f"internal error: {type(exc).__name__}: {exc}"
        finally:
            self.fraction = 1.0 if self.error is None else self.fraction

    def poll(self) -> None:
        """Draw the worker's progress; when it has finished, its result or error."""
        self.bar.set_width(self.fraction)
        if self.busy:
            self.set_status(f"running: {self.message} ({100 * self.fraction:.0f} %)")
            return
        self.timer.stop()
        if self.error:
            self.bar.set_color(ERROR_COLOR)
            self.set_status(self.error, error=True)
        elif self.result is not None:
            self.bar.set_color("#2e7d32")
            polygons, table, written = self.result
            self._show_result(polygons, table)
            polygon_files = "".join(f", {p.name}" for k, p in written.items() if k.startswith("polygons_"))
            self.set_status(f"done: {len(table)} rows -> {written['stats_csv']} (and stats.gpkg{polygon_files})")

    def _show_result(self, polygons, table) -> None:
        """Colour the plants by their first statistic (e.g. chm_max) on the preview."""
        cols = [c for c in table.columns if c not in ("plant_id", "date", "x", "y") and not c.endswith("_count")]
        if not cols or self.poly_artist is None or len(table) != len(polygons):
            return
        col = colour_column(cols)
        values = table[col].to_numpy(float)
        _, owner = shapely.get_parts(self.preview_polygons.geometry.values, return_index=True)
        self.poly_artist.remove()
        self.poly_artist = LineCollection(self.segments, array=values[owner], cmap="autumn", linewidths=1.6)
        self.ax.add_collection(self.poly_artist)
        if self.colorbar is not None:
            self.colorbar.remove()
        # the colour bar in the map's own column, left of the form (given the map's axes, Matplotlib put it over
        # the form's labels)
        self.colorbar = self.fig.colorbar(self.poly_artist, cax=self.cbar_ax)
        self.cbar_ax.set_visible(True)
        self.colorbar.set_label(f"{col} ({unit_of(col)})", fontsize=9)
        self.colorbar.ax.tick_params(labelsize=8)
        self.ax.set_title(
            f"plants coloured by {describe(col)} ({np.nanmin(values):.3g} .. {np.nanmax(values):.3g} {unit_of(col)})",
            fontsize=10,
        )

    def wait(self, timeout: float = 60) -> None:
        """Wait for the background work and draw its outcome (tests and scripts)."""
        if self.thread is not None:
            self.thread.join(timeout)
        self.poll()

    def save_config(self) -> Path | None:
        """Write the settings shown to the config file (else ``stat_extractor.yaml`` in the output); None: not saved."""
        if not self.sync():
            return None
        path = self.config_path or Path(self.cfg.output_dir) / "stat_extractor.yaml"
        save_config(self.cfg, path)
        self.set_status(f"settings saved to {path}")
        return path


def launch(
    cfg: SpatialStatExtractorConfig, config_path: Path | None = None, headless: bool | None = None, chooser=None
) -> SpatialStatExtractorGUI:
    """The window (the paper's Fig. 9); blocks until it is closed."""
    if not headless:
        require_display(
            "python 9_spatial_stat_extractor/spatial_stat_extractor.py --polygons FILE --dsm FILE --dtm FILE"
        )
    gui = SpatialStatExtractorGUI(cfg, config_path, headless=headless, chooser=chooser)
    try:
        named = (
            [cfg.polygons] + [p for layer in cfg.date_sets()[0].layers() for p in layer.paths]
            if cfg.polygons is not None and cfg.date_sets()
            else []
        )
    except MatchPlantError as exc:
        gui.set_status(f"error: {exc}", error=True)
        named = []
    # the folder's config names where the previous modules write; before they ran, that is no error yet
    if named and all(Path(p).exists() for p in named):
        gui.preview()
    elif named:
        gui.set_status("choose the plant polygons (module 8's plants.gpkg) and the rasters, then Preview")
    show(gui.fig)
    return gui
