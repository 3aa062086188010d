"""The GCP marks of step 1 in the import formats of ODM, Pix4Dmapper and Agisoft Metashape (docs/DESIGN.md §3).

    write_marks(folder, header, crs, marks, ["odm", "pix4d", "metashape"], metashape_cameras="cameras.xml")

Our marks (:class:`~matchplant.core.formats.gcp_list.Mark`) hold a GCP's label, its map coordinates and its
pixel in one original photo, with the centre of the top-left pixel at (0, 0). Pix4D and Metashape put (0, 0)
at the top-left corner of the image instead, so their pixel is ours + 0.5. Files written (sources in
1_gcp_finder/README.md):

- ``odm``: ``gcp_list.txt`` (:mod:`matchplant.core.formats.gcp_list`).
- ``pix4d``: ``pix4d_gcps.csv`` (``label,coordinate1,coordinate2,z``, the coordinates in the CRS's own axis
  order, no header) and ``pix4d_marks.csv`` (``image name,label,x,y``, no header): Pix4D's "Import GCPs" and
  "Import Marks" files.
- ``metashape``: ``metashape_reference.csv`` (``label,x,y,z`` with x the easting, no header; the Reference
  pane's import) and, given the camera ids of the user's chunk (its "Export Cameras" XML),
  ``metashape_markers.xml``: the markers and their pinned projections in the XML that "Import Markers" reads.
"""

from __future__ import annotations

from pathlib import Path
from xml.etree import ElementTree

from matchplant.core.formats.gcp_list import Mark, write_gcp_list
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import atomic_open

FORMATS = ("odm", "metashape", "pix4d")
PIXEL_SHIFT = 0.5  # Pix4D's and Metashape's pixel = ours + 0.5 (their origin is the image's corner)
WHITESPACE, CSV_BREAKERS = " \t\r\n", ',"'  # gcp_list.txt is split on whitespace; the others on commas


def check_names(
    marks: list[Mark],
    survey: Path | str | None = None,
    images: Path | str | None = None,
    formats: list[str] | tuple[str, ...] = FORMATS,
) -> None:
    """Refuse labels and photo names that ``formats`` cannot hold (empty, whitespace; commas and quotes but for ODM)."""
    forbidden = WHITESPACE + (CSV_BREAKERS if set(formats) - {"odm"} else "")
    for m in marks:
        if not m.gcp or any(c in forbidden for c in m.gcp):
            raise InputError(
                f"the GCP label {m.gcp!r} (marked in {m.image}) is empty or holds a space, comma or quote, "
                "which gcp_list.txt and the Pix4D and Metashape files cannot hold",
                path=survey,
                fix="give the GCP a one-word label in the survey, e.g. GCP01",
            )
        if any(c in forbidden for c in m.image):
            raise InputError(
                f"the photo name {m.image!r} holds a space, comma or quote, which the GCP files cannot hold",
                path=images,
                fix="rename the photo (e.g. spaces to underscores) in the images folder and in your project",
            )


def read_metashape_cameras(path: str | Path) -> dict[str, str]:
    """The camera ids of a Metashape "Export Cameras" XML (or a project's chunk doc.xml) by camera label."""
    path = Path(path)
    fix = "in Metashape: File > Export > Export Cameras..., format Agisoft XML, of the chunk with these photos"
    if not path.is_file():
        raise InputError("Metashape cameras file not found", path=path, fix=fix)
    try:
        root = ElementTree.parse(path).getroot()
    except ElementTree.ParseError as e:
        raise InputError(f"not a Metashape cameras XML ({e})", path=path, fix=fix) from None
    chunks = [root] if root.tag == "chunk" else root.findall("chunk")
    if len(chunks) != 1:
        raise InputError(f"the file holds {len(chunks)} chunks, not one", path=path, fix=fix)
    ids: dict[str, str] = {}
    for cam in chunks[0].iter("camera"):
        label, cid = cam.get("label"), cam.get("id")
        if label is None or cid is None:
            continue
        if label in ids:
            raise InputError(f"two cameras are labelled {label!r}", path=path, fix="rename one photo in Metashape")
        ids[label] = cid
    if not ids:
        raise InputError("no <camera id=... label=...> in the file", path=path, fix=fix)
    return ids


def metashape_camera_id(image: str, ids: dict[str, str], path: Path | str | None = None) -> str:
    """The id of ``image`` in a Metashape chunk; Metashape labels a camera by its photo's name without extension."""
    cid = ids.get(image, ids.get(Path(image).stem))
    if cid is None:
        raise InputError(
            f"the photo {image} is not a camera of the Metashape chunk, so its marks cannot be written for it",
            path=path,
            fix="add the photo to the chunk and export its cameras again, or take it out of the images folder",
        )
    return cid


def write_marks(
    folder: str | Path,
    header: str,
    crs,
    marks: list[Mark],
    formats: list[str] | tuple[str, ...] = ("odm",),
    metashape_cameras: dict[str, str] | None = None,
    cameras_path: Path | str | None = None,
) -> list[Path]:
    """Write ``marks`` in each of ``formats`` into ``folder``; the files written.

    Parameters
    ----------
    folder : path
        Output folder (exists).
    header : str
        Line 1 of gcp_list.txt (the CRS, e.g. ``EPSG:32614``).
    crs : pyproj.CRS
        The CRS of the marks' coordinates (x easting, y northing).
    marks : list of Mark
        Each GCP's pixel in one original photo (centre of the top-left pixel = 0, 0); names the formats
        cannot hold are refused (:func:`check_names`) before anything is written.
    formats : list of str
        Any of ``odm``, ``metashape``, ``pix4d``.
    metashape_cameras : dict, optional
        Camera ids by label (:func:`read_metashape_cameras`); without it Metashape gets only the reference CSV.
    cameras_path : path, optional
        The file the ids came from, named in errors.

    Returns
    -------
    list of Path
        The files written.
    """
    folder = Path(folder)
    check_names(marks, formats=formats)
    if "metashape" in formats and metashape_cameras is not None:
        for m in marks:  # every photo checked before any file is written
            metashape_camera_id(m.image, metashape_cameras, cameras_path)
    out = []
    if "odm" in formats:
        out.append(write_gcp_list(folder / "gcp_list.txt", header, marks))
    if "pix4d" in formats:
        out += [
            write_pix4d_gcps(folder / "pix4d_gcps.csv", crs, marks),
            write_pix4d_marks(folder / "pix4d_marks.csv", marks),
        ]
    if "metashape" in formats:
        out.append(write_metashape_reference(folder / "metashape_reference.csv", marks))
        if metashape_cameras is not None:
            out.append(
                write_metashape_markers(folder / "metashape_markers.xml", marks, metashape_cameras, cameras_path)
            )
    return out


def _gcps(marks: list[Mark]) -> dict[str, Mark]:
    """The first mark of each GCP label, in the marks' order (its coordinates are the GCP's)."""
    first: dict[str, Mark] = {}
    for m in marks:
        first.setdefault(m.gcp, m)
    return first


def write_pix4d_gcps(path: str | Path, crs, marks: list[Mark]) -> Path:
    """Pix4D's GCP file: ``label,coordinate1,coordinate2,z`` in the CRS's axis order (e.g. easting first for UTM)."""
    north_first = crs.axis_info[0].direction.lower() in ("north", "south")
    with atomic_open(path, "w") as fh:
        for label, m in _gcps(marks).items():
            a, b = (m.y, m.x) if north_first else (m.x, m.y)
            fh.write(f"{label},{a:.4f},{b:.4f},{m.z:.4f}\n")
    return Path(path)


def write_pix4d_marks(path: str | Path, marks: list[Mark]) -> Path:
    """Pix4D's image marks file: ``image name,label,x,y`` in pixels from the image's top-left corner."""
    with atomic_open(path, "w") as fh:
        for m in marks:
            fh.write(f"{m.image},{m.gcp},{m.u + PIXEL_SHIFT:.3f},{m.v + PIXEL_SHIFT:.3f}\n")
    return Path(path)


def write_metashape_reference(path: str | Path, marks: list[Mark]) -> Path:
    """Metashape's reference CSV for markers: ``label,x,y,z`` (x easting, y northing, as its Reference pane)."""
    with atomic_open(path, "w") as fh:
        for label, m in _gcps(marks).items():
            fh.write(f"{label},{m.x:.4f},{m.y:.4f},{m.z:.4f}\n")
    return Path(path)


def write_metashape_markers(
    path: str | Path, marks: list[Mark], camera_ids: dict[str, str], cameras_path: Path | str | None = None
) -> Path:
    """Metashape's markers XML: each GCP a marker, each mark a pinned projection on the chunk's camera id.

    No reference coordinates: the XML has no CRS of its own, so they come from the reference CSV.
    """
    labels = list(_gcps(marks))
    index = {label: i for i, label in enumerate(labels)}
    located = [(index[m.gcp], metashape_camera_id(m.image, camera_ids, cameras_path), m) for m in marks]
    root = ElementTree.Element("document", version="1.2.0")
    chunk = ElementTree.SubElement(root, "chunk")
    markers = ElementTree.SubElement(chunk, "markers", next_id=str(len(labels)), next_group_id="0")
    for i, label in enumerate(labels):
        ElementTree.SubElement(markers, "marker", id=str(i), label=label)
    frames = ElementTree.SubElement(chunk, "frames", next_id="1")
    frame_markers = ElementTree.SubElement(ElementTree.SubElement(frames, "frame", id="0"), "markers")
    for i in range(len(labels)):
        marker = ElementTree.SubElement(frame_markers, "marker", marker_id=str(i))
        for j, cid, m in located:
            if j == i:
                x, y = f"{m.u + PIXEL_SHIFT:.3f}", f"{m.v + PIXEL_SHIFT:.3f}"
                ElementTree.SubElement(marker, "location", camera_id=cid, pinned="true", x=x, y=y)
    ElementTree.indent(root)
    with atomic_open(path, "w") as fh:
        fh.write('<?xml version="1.0" encoding="UTF-8"?>\n')
        fh.write(ElementTree.tostring(root, encoding="unicode") + "\n")
    return Path(path)
