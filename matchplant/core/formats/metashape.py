"""Agisoft Metashape projects: the "Export Cameras" XML, or the project file (``.psx``) itself (docs/DESIGN.md §3).

    cameras = read_metashape("cameras.xml")            # File > Export > Export Cameras... (Agisoft XML)
    cameras = read_metashape("field.psx")              # the project; its <name>.files/ folder beside it

Both hold one ``<chunk>``: ``<sensors>`` with their ``<calibration>`` (f, cx, cy as offsets from the image
centre, b1, b2, k1..k4, p1, p2 in pixels and Metashape's own convention), ``<cameras>`` with a ``<transform>``
(camera -> chunk, 4x4) when aligned, the chunk's (or, from Metashape 2, each component's) ``<transform>``
(rotation, translation, scale: chunk -> geocentric coordinates of the chunk's datum) and ``<reference>`` (the
chunk's CRS as WKT), and ``<markers>``. The conversion (docs/DESIGN.md §3, Metashape's manual, appendix "Camera
models"): our pixel = Metashape's pixel - 0.5; focal_x = (f + b1)/S, focal_y = f/S, skew = b2/S, c = (cx, cy)/S with
S = max(w, h); our p1 = Metashape's P2 and our p2 = its P1. Poses go exactly into an east-north-up frame on the
datum's ellipsoid (:class:`~matchplant.core.geometry.geodetic.DatumTopocentricFrame`) whose map CRS is the chunk's
CRS when projected, else the UTM zone of the cameras on the same datum.

Variants (docs/DESIGN.md §8, tests/test_metashape_variants.py): a multi-camera rig's secondary bands (cameras with
``master_id``) and disabled photos are left out and counted (:attr:`CameraSet.left_out`); PhotoScan's layout before
1.4 (``fx``, ``fy``, ``skew``) and an aligned sensor with only its initial calibration are refused by name.
"""

from __future__ import annotations

import re
import zipfile
from pathlib import Path
from xml.etree import ElementTree

import numpy as np

from matchplant.core.formats.camera_set import (
    CameraSet,
    Marker,
    Photo,
    check_rotation,
    file_name,
    make_shots,
    stored_path,
)
from matchplant.core.geometry.frame_camera import FrameCamera
from matchplant.core.geometry.frames import _proj, parse_crs, utm_crs_for
from matchplant.core.geometry.geodetic import (
    DatumTopocentricFrame,
    geocentric_to_geodetic,
)
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger

log = get_logger("cameras")

EXPORT = "in Metashape: File > Export > Export Cameras..., format 'Agisoft XML' (after Workflow > Align Photos)"
CALIBRATION_KEYS = ("f", "cx", "cy", "b1", "b2", "k1", "k2", "k3", "k4", "p1", "p2", "p3", "p4")


def read_metashape(path: str | Path, *, chunk: str | None = None) -> CameraSet:
    """Read a Metashape camera export (``.xml``) or project (``.psx``) into a :class:`CameraSet`.

    ``chunk`` chooses a chunk by label where the project holds several (otherwise refused, naming them)."""
    path = Path(path)
    if path.suffix.lower() == ".psx":
        element, frame_doc, files = _psx_chunk(path, chunk)
    else:
        root = _parse(path, path.read_bytes() if path.is_file() else None, "Metashape camera export")
        if root.tag == "chunk":
            element = root
        elif root.tag == "document":
            element = _one_chunk(root.findall("chunk"), path, chunk)
        else:
            raise InputError(
                f"not a Metashape camera export: the XML's root is <{root.tag}>, not <document> with a <chunk>",
                path=path,
                fix=f"export the cameras {EXPORT}",
            )
        frame_doc = element.find("frames/frame")
        files = [path]
    return _read_chunk(element, frame_doc, path, files)


def _parse(path: Path, data: bytes | None, what: str) -> ElementTree.Element:
    """Parse XML bytes; a missing, truncated or non-XML file is an error naming it."""
    if data is None:
        raise InputError(f"{what} not found", path=path, fix=f"export the cameras {EXPORT}")
    try:
        return ElementTree.fromstring(data)
    except ElementTree.ParseError as exc:
        raise InputError(
            f"{what} is not complete XML ({exc}): truncated, or not an XML file",
            path=path,
            fix=f"export it again {EXPORT}",
        ) from None


def _one_chunk(chunks: list, path: Path, label: str | None):
    """The chunk to read: the only one, or the one labelled ``label``."""
    labels = [c.get("label", f"chunk {i}") for i, c in enumerate(chunks)]
    if not chunks:
        raise InputError("the Metashape file holds no <chunk>", path=path, fix=f"export the cameras {EXPORT}")
    if label is not None:
        if label not in labels:
            raise InputError(
                f"no chunk labelled {label!r} (chunks: {', '.join(labels)})", path=path, fix="name one of these"
            )
        return chunks[labels.index(label)]
    if len(chunks) > 1:
        raise InputError(
            f"the project holds {len(chunks)} chunks ({', '.join(labels)}); MatchPlant reads one",
            path=path,
            fix="export the cameras of one chunk (Export Cameras exports the active chunk) and point at that file",
        )
    return chunks[0]


def _psx_chunk(path: Path, label: str | None):
    """The chunk element and its frame document of a ``.psx`` project (``<name>.files/``: zipped XML)."""
    folder = path.with_suffix(".files")
    project = _zip_doc(folder / "project.zip", path)
    refs = project.findall("chunks/chunk")
    stubs = [(r, _zip_doc(folder / r.get("path", ""), path)) for r in refs]
    element = _one_chunk([doc for _, doc in stubs], path, label)
    chunk_dir = folder / Path([r for r, d in stubs if d is element][0].get("path", "")).parent
    files = [path, folder / "project.zip", chunk_dir / "chunk.zip"]
    frame_ref = element.find("frames/frame")
    frame_doc = None
    if frame_ref is not None and frame_ref.get("path"):
        files.append(chunk_dir / frame_ref.get("path"))
        frame_doc = _zip_doc(files[-1], path)
    return element, frame_doc, files


def _zip_doc(zpath: Path, project: Path) -> ElementTree.Element:
    """``doc.xml`` of one of a project's zip files."""
    fix = "open the project in Metashape and save it again, or use File > Export > Export Cameras"
    if not zpath.is_file():
        raise InputError(
            f"the Metashape project lacks {zpath.name} (its .files folder is incomplete)", path=zpath, fix=fix
        )
    try:
        with zipfile.ZipFile(zpath) as z:
            data = z.read("doc.xml")
    except (zipfile.BadZipFile, KeyError, OSError) as exc:
        raise InputError(
            f"unreadable part of the Metashape project {project.name} ({exc})", path=zpath, fix=fix
        ) from None
    return _parse(zpath, data, "Metashape project part")


def _floats(text: str | None, n: int, what: str, path: Path) -> np.ndarray:
    """``n`` numbers from an element's text, or an error naming the element."""
    try:
        values = np.array((text or "").split(), dtype=float)
    except ValueError:
        values = np.zeros(0)
    if values.size != n or not np.all(np.isfinite(values)):
        raise InputError(
            f"{what} is not {n} numbers: {(text or '').strip()[:80]!r}", path=path, fix=f"export again {EXPORT}"
        )
    return values


def _similarity(element, what: str, path: Path) -> tuple[np.ndarray, np.ndarray, float] | None:
    """A ``<transform>`` (rotation, translation, scale; or a 4x4 ``matrix``) as (R, t, s); None if absent."""
    if element is None:
        return None
    if element.find("matrix") is not None:
        m = _floats(element.findtext("matrix"), 16, f"{what} matrix", path).reshape(4, 4)
        s = float(np.cbrt(np.linalg.det(m[:3, :3])))
        if s <= 0 or not check_rotation(m[:3, :3] / s, tol=1e-5) or np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9:
            raise InputError(
                f"{what} matrix is not a rotation, translation and scale", path=path, fix=f"export again {EXPORT}"
            )
        return m[:3, :3] / s, m[:3, 3], s
    if element.find("rotation") is None:
        return None
    R = _floats(element.findtext("rotation"), 9, f"{what} rotation", path).reshape(3, 3)
    t = _floats(element.findtext("translation") or "0 0 0", 3, f"{what} translation", path)
    s = float(_floats(element.findtext("scale") or "1", 1, f"{what} scale", path)[0])
    if not check_rotation(R, tol=1e-5) or s <= 0:
        raise InputError(f"{what} is not a rotation and a positive scale", path=path, fix=f"export again {EXPORT}")
    return R, t, s


def _sensor(el, path: Path) -> tuple[FrameCamera | None, bool]:
    """One ``<sensor>`` as our camera, converted exactly (module docstring), and whether its calibration is the
    one the alignment used (adjusted, or a fixed initial one); None where it has no ``<calibration>``."""
    sid, label = el.get("id"), el.get("label", el.get("id"))
    where = f"sensor {label!r} (id {sid})"
    kind = el.get("type", "frame")
    if kind != "frame":
        raise InputError(
            f"{where} is a {kind!r} camera; MatchPlant reads frame cameras only",
            path=path,
            fix="set the camera type to 'Frame' in Tools > Camera Calibration, or process these photos apart",
        )
    cal, used = _calibration(el, where, path)
    if cal is None:  # a sensor none of whose photos was aligned
        return None, False
    res = cal.find("resolution") if cal.find("resolution") is not None else el.find("resolution")
    try:
        w, h = int(res.get("width")), int(res.get("height"))
    except (AttributeError, TypeError, ValueError):
        raise InputError(f"{where} has no image <resolution>", path=path, fix=f"export again {EXPORT}") from None
    v = {
        k: float(_floats(cal.findtext(k), 1, f"{where} <{k}>", path)[0]) if cal.find(k) is not None else 0.0
        for k in CALIBRATION_KEYS
    }
    if v["p3"] or v["p4"]:
        raise InputError(
            f"{where} uses p3/p4, which MatchPlant does not model", path=path, fix="calibrate without p3 and p4"
        )
    if v["f"] <= 0:
        raise InputError(
            f"{where} has focal length {v['f']:g} px", path=path, fix=f"align the photos, then export {EXPORT}"
        )
    s = float(max(w, h))
    return FrameCamera(
        id=label, projection_type="brown", width=w, height=h, focal_x=(v["f"] + v["b1"]) / s, focal_y=v["f"] / s,
        c_x=v["cx"] / s, c_y=v["cy"] / s, k1=v["k1"], k2=v["k2"], k3=v["k3"], k4=v["k4"], p1=v["p2"], p2=v["p1"],
        skew=v["b2"] / s,
    ), used  # fmt: skip


def _calibration(el, where: str, path: Path):
    """The sensor's ``<calibration>`` in the layout MatchPlant reads, and whether the alignment used it.

    Metashape keeps the ``adjusted`` calibration (what Align Photos estimated) beside the ``initial`` one; an
    initial calibration alone is what the alignment used only where the sensor's calibration is fixed.
    PhotoScan before 1.4 wrote another layout (``fx``, ``fy``, ``cx``/``cy`` from the image's corner, ``skew``),
    whose pixel origin and tangential order no public document pins down for that file: refused by name."""
    cals = el.findall("calibration")
    if not cals:
        return None, False
    adjusted = [c for c in cals if c.get("class", "adjusted") == "adjusted"]
    cal = adjusted[0] if adjusted else cals[0]
    fixed = any(p.get("name") == "fixed" and p.get("value", "").lower() == "true" for p in el.findall("property"))
    if cal.find("f") is None:
        old = [k for k in ("fx", "fy", "skew") if cal.find(k) is not None]
        problem = (
            f"{where}'s calibration is in PhotoScan's layout from before version 1.4 (<{'>, <'.join(old)}>), "
            "which MatchPlant does not read"
            if old
            else f"{where}'s calibration has no focal length <f>"
        )
        raise InputError(
            problem,
            path=path,
            fix="open the project in Metashape 1.4 or later and export the cameras again "
            f"({EXPORT}): that writes f, cx, cy, b1, b2, which MatchPlant reads exactly",
        )
    return cal, bool(adjusted) or fixed


def _reference_crs(element, path: Path):
    """The chunk's CRS (``<reference>`` WKT); a local (unreferenced) chunk is refused."""
    text = (element.findtext("reference") or "").strip()
    if not text or text.upper().startswith(("LOCAL_CS", "LOCAL_CRS", "ENGCRS", "ENGINEERING")):
        raise InputError(
            "the chunk is in a local coordinate system (not georeferenced), so its cameras cannot be placed on a map",
            path=path,
            fix="in Metashape, set the chunk's coordinate system in the Reference pane (camera GPS or markers), "
            "click Update, then export the cameras again",
        )
    return parse_crs(_authority(text), source=path)


def _authority(text: str) -> str:
    """Metashape's short form of an authority code (``EPSG::32615``, as its Python API writes it) as PROJ's."""
    m = re.fullmatch(r"\s*([A-Za-z]+)::(\d+)\s*", text)
    return f"{m.group(1)}:{m.group(2)}" if m else text


def _map_crs(crs, lon: float, lat: float):
    """The map CRS: the chunk's when projected, else the UTM zone of (lon, lat) on the chunk's datum."""
    if crs.is_projected or (crs.is_compound and crs.sub_crs_list[0].is_projected):
        return crs
    if crs.ellipsoid is not None and crs.ellipsoid.name == "WGS 84" and not crs.is_compound:
        utm = utm_crs_for(lon, lat)
        log.info("the chunk's CRS %s is geographic: the map is %s", crs.name, utm.name)
        return utm
    pyproj = _proj()  # pyproj on first use (docs: frames._proj); its submodules with it
    from pyproj.aoi import AreaOfInterest
    from pyproj.database import query_utm_crs_info

    datum = crs.geodetic_crs.datum.name if crs.geodetic_crs is not None else "WGS 84"
    found = query_utm_crs_info(datum_name=datum, area_of_interest=AreaOfInterest(lon, lat, lon, lat))
    if not found:
        found = query_utm_crs_info(datum_name="WGS 84", area_of_interest=AreaOfInterest(lon, lat, lon, lat))
    utm = pyproj.CRS.from_authority(found[0].auth_name, found[0].code)
    log.info("the chunk's CRS %s is geographic: the map is %s", crs.name, utm.name)
    return utm


def _read_chunk(element, frame_doc, path: Path, files: list[Path]) -> CameraSet:
    """Cameras, sensors and markers of one chunk element in one frame."""
    read = {el.get("id"): _sensor(el, path) for el in element.findall("sensors/sensor")}
    sensors = {k: cam for k, (cam, _) in read.items()}
    cameras = element.findall("cameras/camera") + element.findall("cameras/group/camera")
    if not cameras or not sensors:
        raise InputError(
            f"no {'cameras' if sensors else 'sensors'} in the Metashape chunk: not a camera export",
            path=path,
            fix=f"export the cameras {EXPORT}",
        )
    crs = _reference_crs(element, path)
    rows, unposed, left_out = _camera_rows(element, cameras, sensors, path)
    if not rows:
        raise InputError(
            f"none of the {len(cameras)} photos is aligned and placed (no camera has a <transform> MatchPlant can "
            "use" + (f"; left out: {'; '.join(left_out)}" if left_out else "") + ")",
            path=path,
            fix="run Workflow > Align Photos in Metashape, then export the cameras again",
        )
    bare = sorted({r[4] for r in rows if sensors[r[4]] is None})
    if bare:
        raise InputError(
            f"sensor {bare[0]} has no <calibration>, yet photos of it are aligned",
            path=path,
            fix=f"align the photos, then export {EXPORT}",
        )
    rough = sorted({sensors[r[4]].id for r in rows if not read[r[4]][1]})
    if rough:
        raise InputError(
            f'sensor {rough[0]!r} holds only its initial calibration (class="initial"), not the adjusted one '
            "its aligned photos were posed with",
            path=path,
            fix=f"export the cameras again after Align Photos {EXPORT}, or fix the sensor's calibration "
            "(Tools > Camera Calibration, 'Fix calibration') before aligning",
        )
    paths = {}
    if frame_doc is not None:
        # a .psx writes each photo's path relative to its frame document (frame.zip), e.g. ../../../photos/x.JPG
        base = files[-1].parent if files[-1].suffix.lower() == ".zip" else path.parent
        paths = {
            c.get("camera_id"): stored_path(c.find("photo").get("path"), base)
            for c in frame_doc.findall("cameras/camera")
            if c.find("photo") is not None and c.find("photo").get("path")
        }
    frame, shots = _shots(rows, sensors, crs, path)
    photos = {}
    for (cid, label, _, _, sid), shot in zip(rows, shots):
        camera = sensors[sid]
        name = file_name(paths.get(cid) or label)
        photos[label] = Photo(label=label, name=name, sensor=camera.id, camera=camera, shot=shot, path=paths.get(cid))
    for cid, label, sid in unposed:
        camera = sensors[sid]
        if camera is None:  # never aligned, never calibrated: said in the log, left out
            left_out.setdefault("not aligned, of a sensor without a calibration", []).append(label)
            continue
        name = file_name(paths.get(cid) or label)
        photos[label] = Photo(label=label, name=name, sensor=camera.id, camera=camera, shot=None, path=paths.get(cid))
    if len(photos) < len(rows) + len(unposed) - len(left_out.get("not aligned, of a sensor without a calibration", [])):
        raise InputError(
            "two cameras share a label; MatchPlant names photos by label",
            path=path,
            fix="rename the photos in Metashape",
        )
    markers = _markers(element, frame_doc, {c.get("id"): c.get("label", c.get("id")) for c in cameras}, crs, path)
    log.info(
        "Metashape chunk %r: %d photos (%d aligned), %d sensors, %s%s",
        element.get("label", ""), len(photos), len(rows), len(sensors), frame.describe(),
        "".join(f"; left out: {len(v)} photos, {k}" for k, v in left_out.items()),
    )  # fmt: skip
    sensor_set = {s.id: s for s in sensors.values() if s is not None}
    return CameraSet("metashape", path, files, frame, photos, sensor_set, markers, left_out)


def _enabled(el) -> bool:
    """A Metashape ``enabled`` attribute (absent: enabled)."""
    return el.get("enabled", "true").strip().lower() not in ("false", "0")


def _camera_rows(element, cameras: list, sensors: dict, path: Path):
    """(id, label, camera->chunk 4x4, chunk->geocentric similarity, sensor id) of each posed camera, (id, label,
    sensor id) of each camera without a usable pose, and the photos left out, by why."""
    chunk_tf = _similarity(element.find("transform"), "the chunk's <transform>", path)
    comps = element.find("components")
    components = {
        c.get("id"): _similarity(c.find("transform"), f"component {c.get('id')}'s <transform>", path)
        for c in element.findall("components/component")
    }
    if comps is not None and comps.get("active_id") in components and components[comps.get("active_id")] is None:
        components[comps.get("active_id")] = chunk_tf  # the chunk's transform is its active component's
    slaves, disabled, unplaced = [], [], {}
    rows, unposed, rolling = [], [], 0
    for cam in cameras:
        cid, label, sid = cam.get("id"), cam.get("label", cam.get("id")), cam.get("sensor_id")
        if sid not in sensors:
            raise InputError(
                f"camera {label!r} names sensor {sid}, which is not in <sensors>",
                path=path,
                fix=f"export again {EXPORT}",
            )
        if cam.get("master_id") not in (None, cid):  # a band of a multi-camera rig: posed through its master
            slaves.append(label)
            continue
        if not _enabled(cam):
            disabled.append(label)
            continue
        if cam.findtext("orientation", "1").strip() not in ("1", ""):
            raise InputError(
                f"photo {label!r} is rotated by its EXIF orientation ({cam.findtext('orientation')}); MatchPlant's "
                "pixels are those of the stored image",
                path=path,
                fix="store the photos unrotated (orientation 1), re-align and export again",
            )
        rolling += cam.find("rolling_shutter") is not None
        tf = (cam.findtext("transform") or "").strip()
        comp = cam.get("component_id")
        sim = components.get(comp) if comp is not None and components else chunk_tf
        if comp is not None and components and comp not in components:
            raise InputError(
                f"camera {label!r} names component {comp}, which is not in <components>",
                path=path,
                fix=f"export again {EXPORT}",
            )
        if not tf:
            unposed.append((cid, label, sid))
        elif sim is None and comp is not None and components:
            unplaced.setdefault(comp, []).append(label)
            unposed.append((cid, label, sid))
        elif sim is None:
            raise InputError(
                "the chunk has no <transform> to geocentric coordinates (a local chunk)", path=path,
                fix="georeference the chunk in Metashape (Reference pane, Update), then export the cameras again",
            )  # fmt: skip
        else:
            rows.append((cid, label, _floats(tf, 16, f"camera {label!r} <transform>", path).reshape(4, 4), sim, sid))
    if rolling:
        log.warning("%d photos carry rolling-shutter corrections, which MatchPlant does not apply (%s)", rolling, path)
    return rows, unposed, _left_out(slaves, disabled, unplaced, cameras, sensors, path)


def _left_out(slaves: list, disabled: list, unplaced: dict, cameras: list, sensors: dict, path: Path) -> dict:
    """Why photos were left out (or left without a pose), said once each in the log; by reason."""
    out = {}
    if slaves:
        left = set(slaves)
        sids = {c.get("sensor_id") for c in cameras if c.get("label", c.get("id")) in left}
        bands = sorted(getattr(sensors[k], "id", k) for k in sids)
        why = (
            "secondary bands of a multi-camera rig (sensors "
            + ", ".join(repr(b) for b in bands)
            + "): Metashape stores their pose as the master band's plus the rig's offset, which MatchPlant does "
            "not apply; the master band's photos are read"
        )
        log.warning("%d photos left out, %s (%s)", len(slaves), why, path)
        out[why] = slaves
    if disabled:
        why = 'disabled in Metashape (enabled="false"; enable them in the Photos pane and export again to use them)'
        log.warning("%d photos left out, %s (%s)", len(disabled), why, path)
        out[why] = disabled
    for comp, labels in unplaced.items():
        why = f"aligned in component {comp}, which has no <transform> to the map (not georeferenced): no pose"
        log.warning("%d photos %s (%s)", len(labels), why, path)
        out[why] = labels
    return out


def _shots(rows: list, sensors: dict, crs, path: Path):
    """The east-north-up frame around the posed cameras and their shots in it (camera -> geocentric:
    X_geo = s R (R_c X_cam + t_c) + t)."""
    R_geo = np.array([sim[0] @ m[:3, :3] for _, _, m, sim, _ in rows])
    c_geo = np.array([sim[2] * sim[0] @ m[:3, 3] + sim[1] for _, _, m, sim, _ in rows])
    bad = [r[1] for r, Rg in zip(rows, R_geo) if not check_rotation(Rg, tol=1e-5)]
    if bad:
        raise InputError(
            f"camera {bad[0]!r}: its <transform> is not a rotation", path=path, fix=f"export again {EXPORT}"
        )
    lon, lat, _ = geocentric_to_geodetic(c_geo.mean(axis=0), crs)[0]
    frame = DatumTopocentricFrame(lat, lon, 0.0, crs.geodetic_crs or crs, _map_crs(crs, lon, lat))
    centres = frame.from_geocentric(c_geo)
    cams = [sensors[r[4]] for r in rows]
    return frame, make_shots([r[1] for r in rows], cams, np.transpose(frame.Q @ R_geo, (0, 2, 1)), centres)


def _markers(element, frame_doc, labels: dict, crs, path: Path) -> list[Marker]:
    """Markers with their reference coordinates and the pixels marked on each photo (our pixel convention)."""
    text = (element.findtext("marker_reference") or "").strip()
    mcrs = parse_crs(_authority(text), source=path) if text else crs
    marks: dict[str, dict] = {}
    source = frame_doc if frame_doc is not None else element
    for m in source.findall("markers/marker") + source.findall("markers/group/marker"):
        for loc in m.findall("location"):
            try:
                uv = (float(loc.get("x")) - 0.5, float(loc.get("y")) - 0.5)
            except (TypeError, ValueError):
                continue
            marks.setdefault(m.get("marker_id"), {})[labels.get(loc.get("camera_id"), loc.get("camera_id"))] = uv
    out = []
    for m in element.findall("markers/marker") + element.findall("markers/group/marker"):
        ref = m.find("reference")
        xyz = None
        if ref is not None and ref.get("x") is not None:
            xyz = np.array([float(ref.get(k, "nan")) for k in "xyz"])
        out.append(Marker(m.get("label", m.get("id")), xyz, mcrs, marks.get(m.get("id"), {})))
    return out
