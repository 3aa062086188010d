"""GCP image marks in the import formats of Metashape and Pix4D (module 1; ODM's is ``gcp_list.py``).

* Metashape: ``metashape_markers.xml``, Agisoft XML as File > Import > Import Markers reads it: a ``<chunk>``
  with the photos (``<cameras>`` by label), the markers with their reference coordinates and the chunk's
  ``<reference>`` CRS, and each mark as a pinned ``<location>`` in Metashape's pixels (the top-left pixel's
  centre at 0.5, 0.5: ours + 0.5). The same coordinates as ``metashape_gcps.csv`` (label, x, y, z) for the
  Reference pane's Import, where the CRS is chosen.
* Pix4D: ``pix4d_gcps.csv`` (label, x, y, z in the project's projected CRS: Project > GCP/MTP Manager > Import
  GCPs) and ``pix4d_marks.csv`` (image, GCP label, x, y, accuracy in pixels, origin at the image's top-left
  corner: ours + 0.5; GCP/MTP Manager > Import Marks, "PIX4D marks file").
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from xml.sax.saxutils import escape, quoteattr

from matchplant.core.formats.gcp_list import Mark
from matchplant.core.runtime.io import write_text

MARK_ACCURACY_PX = 1.0  # a mark found by module 1: about a pixel


def _gcps(marks: list[Mark]) -> dict[str, tuple[float, float, float]]:
    """Each GCP's map coordinates (the first mark's: every mark of a GCP carries the same)."""
    out: dict[str, tuple[float, float, float]] = {}
    for m in marks:
        out.setdefault(m.gcp or f"gcp{len(out) + 1}", (float(m.x), float(m.y), float(m.z)))
    return out


def _coords_csv(marks: list[Mark]) -> str:
    """``label,x,y,z`` lines of every GCP."""
    return "".join(f"{k},{x!r},{y!r},{z!r}\n" for k, (x, y, z) in _gcps(marks).items())


def write_metashape_markers(folder: str | Path, marks: list[Mark], crs) -> list[Path]:
    """Write ``metashape_markers.xml`` and ``metashape_gcps.csv`` into ``folder`` (module docstring)."""
    folder = Path(folder)
    gcps = _gcps(marks)
    ids = {k: i for i, k in enumerate(gcps)}
    photos = {name: i for i, name in enumerate(sorted({m.image for m in marks}))}
    by_gcp: dict[str, list[Mark]] = defaultdict(list)
    for m in marks:
        by_gcp[m.gcp or next(iter(gcps))].append(m)
    cams = "".join(f'<camera id="{i}" label={quoteattr(n)}/>' for n, i in photos.items())
    refs = "".join(
        f'<marker id="{ids[k]}" label={quoteattr(k)}><reference x="{x!r}" y="{y!r}" z="{z!r}" enabled="true"/></marker>'
        for k, (x, y, z) in gcps.items()
    )
    locs = "".join(
        f'<marker marker_id="{ids[k]}">'
        + "".join(
            f'<location camera_id="{photos[m.image]}" pinned="true" x="{float(m.u) + 0.5!r}" y="{float(m.v) + 0.5!r}"/>'
            for m in ms
        )
        + "</marker>"
        for k, ms in by_gcp.items()
    )
    text = (
        '<?xml version="1.0" encoding="UTF-8"?>\n<document version="1.5.0"><chunk label="MatchPlant GCPs">'
        f"<cameras>{cams}</cameras><markers>{refs}</markers><frames><frame><markers>{locs}</markers></frame>"
        f"</frames><reference>{escape(crs.to_wkt('WKT1_GDAL'))}</reference></chunk></document>\n"
    )
    return [
        write_text(folder / "metashape_markers.xml", text),
        write_text(folder / "metashape_gcps.csv", _coords_csv(marks)),
    ]


def write_pix4d_marks(folder: str | Path, marks: list[Mark]) -> list[Path]:
    """Write ``pix4d_gcps.csv`` and ``pix4d_marks.csv`` into ``folder`` (module docstring)."""
    folder = Path(folder)
    gcps = _gcps(marks)
    first = next(iter(gcps), "")
    rows = "".join(
        f"{m.image},{m.gcp or first},{float(m.u) + 0.5!r},{float(m.v) + 0.5!r},{MARK_ACCURACY_PX!r}\n" for m in marks
    )
    return [write_text(folder / "pix4d_gcps.csv", _coords_csv(marks)), write_text(folder / "pix4d_marks.csv", rows)]
