"""The marks of a session (a GCP's pixel in one image): set, move, delete, undo, saved to gcp_list.txt.

Every change is saved at once in the GUI, so a crash or a closed window loses nothing; an existing
gcp_list.txt (ours or another tool's) is continued rather than overwritten. The same save writes the
Pix4D and Metashape files of ``formats`` beside it (:mod:`matchplant.core.formats.gcp_marks`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pyproj import Transformer

from matchplant.core.formats.gcp_list import Mark, crs_header, read_gcp_list
from matchplant.core.formats.gcp_marks import check_names, metashape_camera_id, read_metashape_cameras, write_marks
from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.log import get_logger
from matchplant.gcp_finder.candidates import Finder
from matchplant.gcp_finder.config import MIN_IMAGES_PER_GCP, GcpFinderConfig

log = get_logger("gcp_finder")


class MarkStore:
    """The marks of one session: set, move, delete, undo; every change is saved to gcp_list.txt."""

    def __init__(self, finder: Finder, path: Path, autosave: bool = True):
        self.finder = finder
        self.path = Path(path)
        self.autosave = autosave
        self.marks: dict[tuple[str, str], tuple[float, float]] = {}
        self.undo_stack: list[tuple[tuple[str, str], tuple[float, float] | None]] = []
        self.continued: Path | None = None  # the earlier gcp_list.txt this session continues
        self.formats: tuple[str, ...] = ("odm",)  # gcp_list.txt always: sessions continue from it
        self.camera_ids: dict[str, str] | None = None  # Metashape's camera ids by label (metashape_cameras)
        self.cameras_path: Path | None = None

    def load(self, path: Path) -> int:
        """Continue from an existing gcp_list.txt; returns the number of marks taken over."""
        _, crs, marks = read_gcp_list(path)
        t = None if crs.equals(self.finder.crs) else Transformer.from_crs(crs, self.finder.crs, always_xy=True)
        ids = list(self.finder.gcps)
        xy = np.array([[g.x, g.y] for g in self.finder.gcps.values()])
        flight = self.finder.flight or set(self.finder.images)
        foreign = sorted({m.image for m in marks if m.image not in flight})
        if foreign:
            log.warning(
                "%s: %d line(s) mark images that are not in this flight's folder and are dropped: %s",
                path,
                sum(m.image in foreign for m in marks),
                ", ".join(foreign),
            )
        outside = [m for m in marks if m.image in self.finder.images and not self._inside(m)]
        dropped = {id(m) for m in outside}
        if outside:
            log.warning(
                "%s: %d mark(s) lie outside their image and are dropped: %s",
                path,
                len(outside),
                ", ".join(f"{m.gcp or 'unnamed'} in {m.image} at ({m.u:g}, {m.v:g})" for m in outside[:5]),
            )
        n = 0
        for m in marks:
            if m.image in foreign or id(m) in dropped:
                continue
            gid = m.gcp if m.gcp in self.finder.gcps else None
            if gid is None:  # unnamed line: the surveyed GCP at its coordinates
                mx, my = t.transform(m.x, m.y) if t else (m.x, m.y)
                d = np.hypot(xy[:, 0] - mx, xy[:, 1] - my)
                if d.min() < 0.5:
                    gid = ids[int(np.argmin(d))]
            if gid is None:
                log.warning("gcp_list line for %s (%s) matches no surveyed GCP; dropped", m.image, m.gcp or "unnamed")
                continue
            self.marks[(gid, m.image)] = (m.u, m.v)
            n += 1
        return n

    def _inside(self, m: Mark) -> bool:
        info = self.finder.images[m.image]
        return -0.5 <= m.u <= info.width - 0.5 and -0.5 <= m.v <= info.height - 0.5

    def set(self, gcp: str, image: str, u: float, v: float, record: bool = True) -> None:
        """Mark ``gcp`` at pixel (u, v) of ``image``, recorded for undo unless ``record`` is False."""
        if record:
            self.undo_stack.append(((gcp, image), self.marks.get((gcp, image))))
        self.marks[(gcp, image)] = (float(u), float(v))
        self._changed()

    def delete(self, gcp: str, image: str) -> bool:
        """Remove the mark of ``gcp`` in ``image``; False when there was none."""
        if (gcp, image) not in self.marks:
            return False
        self.undo_stack.append(((gcp, image), self.marks.pop((gcp, image))))
        self._changed()
        return True

    def undo(self) -> tuple[str, str] | None:
        """Undo the last set or delete; the (GCP, image) it changed, or None when there is nothing to undo."""
        if not self.undo_stack:
            return None
        key, previous = self.undo_stack.pop()
        if previous is None:
            self.marks.pop(key, None)
        else:
            self.marks[key] = previous
        self._changed()
        return key

    def count(self, gcp: str) -> int:
        """Number of images ``gcp`` is marked in."""
        return sum(1 for g, _ in self.marks if g == gcp)

    def to_marks(self) -> list[Mark]:
        """The marks as gcp_list lines, in survey order of the GCPs, then by image name."""
        order = {gid: i for i, gid in enumerate(self.finder.gcps)}
        out = []
        for (gid, image), (u, v) in sorted(self.marks.items(), key=lambda kv: (order.get(kv[0][0], 1e9), kv[0][1])):
            g = self.finder.gcps[gid]
            out.append(Mark(g.x, g.y, g.z, u, v, image, gid))
        return out

    def save(self) -> Path:
        """Write every mark to the store's gcp_list.txt (and the formats' files beside it); its path."""
        write_marks(
            self.path.parent,
            crs_header(self.finder.crs),
            self.finder.crs,
            self.to_marks(),
            self.formats,
            self.camera_ids,
            self.cameras_path,
        )
        return self.path

    def _changed(self) -> None:
        if self.autosave:
            self.save()

    def warn_few(self) -> list[str]:
        """Warn about GCPs marked in fewer images than ODM needs; their ids."""
        unmarked = [gid for gid in self.finder.gcps if self.count(gid) == 0]
        if unmarked:
            log.warning("GCPs marked in no image, so in none of the written files: %s", ", ".join(unmarked))
        few = [gid for gid in self.finder.gcps if 0 < self.count(gid) < MIN_IMAGES_PER_GCP]
        if few:
            log.warning(
                "GCPs marked in fewer than %d images (ODM may ignore them): %s",
                MIN_IMAGES_PER_GCP,
                ", ".join(f"{g} ({self.count(g)})" for g in few),
            )
        return few


def store_for(cfg: GcpFinderConfig, finder: Finder, autosave: bool) -> MarkStore:
    """The session's store, continuing the configured (or the output folder's) gcp_list.txt if it exists."""
    out = Path(cfg.output_dir)
    store = MarkStore(finder, out / "gcp_list.txt", autosave=autosave)
    if cfg.gcp_list and not Path(cfg.gcp_list).is_file():
        raise ConfigError(
            "config key 'gcp_list': the list to continue is not found",
            path=cfg.gcp_list,
            fix="correct 'gcp_list', or leave it empty to start a new list",
        )
    existing = cfg.gcp_list or (out / "gcp_list.txt")
    if Path(existing).is_file():
        n = store.load(Path(existing))
        store.continued = Path(existing)
        log.info("continuing from %s (%d marks)", existing, n)
    set_formats(store, cfg)
    return store


def set_formats(store: MarkStore, cfg: GcpFinderConfig) -> None:
    """The files each save writes; labels and photo names checked now, so no save fails half-way later.

    Every photo a mark can land on (the candidates and the marks taken over) must be a camera of the
    Metashape chunk when ``metashape_cameras`` is given.
    """
    store.formats = tuple(dict.fromkeys(["odm", *cfg.formats]))
    g = store.finder.gcps
    markable = [
        Mark(g[gid].x, g[gid].y, g[gid].z, 0, 0, c.image, gid)
        for gid, lst in store.finder.candidates.items()
        for c in lst
    ]
    markable += store.to_marks()
    check_names(markable, cfg.survey, cfg.images, store.formats)
    if "metashape" in store.formats and cfg.metashape_cameras:
        store.cameras_path = Path(cfg.metashape_cameras)
        store.camera_ids = read_metashape_cameras(store.cameras_path)
        for image in sorted({m.image for m in markable}):
            metashape_camera_id(image, store.camera_ids, store.cameras_path)
    elif "metashape" in store.formats:
        log.info(
            "metashape: writing metashape_reference.csv only; set 'metashape_cameras' (the chunk's exported "
            "cameras XML) for metashape_markers.xml, the marks themselves"
        )
