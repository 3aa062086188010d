"""Pix4Dmapper projects: the ``params/`` folder of step 1 (docs/DESIGN.md §3).

    cameras = read_pix4d("field")                  # the project folder (1_initial/params/ inside it)
    cameras = read_pix4d("field/1_initial/params")

Read: ``<name>_calibrated_camera_parameters.txt`` (per photo: file name and size, K, radial R1..R3, tangential T1,
T2, position t and world->camera rotation R with ``m = K [R | -R t] X``), ``<name>_offset.xyz`` (the offset the
positions are given from) and ``<name>_wkt.prj`` (the output CRS); ``<name>_pmatrix.txt`` where present
(:func:`read_pmatrix`). Pix4D's camera axes are OpenCV's (x right, y down, z forward); its pixels have the origin
at the top-left corner of the image (the image centre is (w/2, h/2): the .cam file's principal point offset is
w/2 - cx), so our pixel = Pix4D's - 0.5; distortion is Brown's in OpenCV's order (T1 = p1, T2 = p2). The frame
is the output CRS minus the offset (an :class:`~matchplant.core.geometry.frames.OffsetFrame`): Pix4D adjusts
in it as a Cartesian frame.

The project is found from the params folder, the project folder, its ``<name>.p4d`` (Pix4D writes it beside the
project folder) or the folder holding that; the .p4d's image paths are used and its photos Pix4D did not calibrate
count as without a pose. Refused by name (docs/DESIGN.md §8): a fisheye or other non-perspective camera, a local,
geographic or non-metre output CRS, a damaged parameters file (by line), several projects in one folder.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import replace
from pathlib import Path

import numpy as np

from matchplant.core.formats.camera_set import (
    CameraSet,
    Photo,
    check_rotation,
    file_name,
    make_shots,
    only_camera,
    stored_path,
)
from matchplant.core.geometry.frame_camera import FrameCamera
from matchplant.core.geometry.frames import OffsetFrame, parse_crs
from matchplant.core.geometry.shot import Shot
from matchplant.core.geometry.units import not_metres
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import write_text
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.validate import read_text

log = get_logger("cameras")

SUFFIX = "_calibrated_camera_parameters.txt"
PARAMS = "1_initial/params"
EXPORT = (
    "in Pix4Dmapper: Processing Options > 1. Initial Processing > Calibration > Export: tick 'Camera Internals "
    "and Externals, AAT, BBA', then run step 1 again (it writes 1_initial/params/)"
)


def params_folder(path: str | Path) -> Path | None:
    """The params folder of a Pix4D project: given a camera-parameters file, a params folder, a project folder,
    the project's ``.p4d`` file or the folder holding ``<name>.p4d`` beside ``<name>/``; None if none."""
    path = Path(path)
    if path.is_file():
        if path.name.endswith(SUFFIX):
            return path.parent
        return _with_params(path.with_suffix("") / PARAMS) if path.suffix.lower() == ".p4d" else None
    for folder in (path, path / PARAMS):
        if _with_params(folder) is not None:
            return folder
    if not path.is_dir():
        return None
    hits = [p for p in sorted(path.glob("*.p4d")) if _with_params(p.with_suffix("") / PARAMS) is not None]
    if len(hits) > 1:
        raise InputError(
            f"{len(hits)} Pix4D projects in one folder ({', '.join(p.name for p in hits)})",
            path=path,
            fix="point at the .p4d file (or the project folder) of the one to read",
        )
    return hits[0].with_suffix("") / PARAMS if hits else None


def _with_params(folder: Path) -> Path | None:
    """``folder`` when it holds a camera-parameters file, else None."""
    return folder if folder.is_dir() and any(p.name.endswith(SUFFIX) for p in folder.iterdir()) else None


def read_pix4d(path: str | Path) -> CameraSet:
    """Read a Pix4D project's ``params/`` files into a :class:`CameraSet` (module docstring)."""
    path = Path(path)
    folder = params_folder(path)
    if folder is None:
        raise InputError(f"no *{SUFFIX} in this folder or in its {PARAMS}/", path=path, fix=EXPORT)
    names = sorted(p.name[: -len(SUFFIX)] for p in folder.iterdir() if p.name.endswith(SUFFIX))
    if path.is_file() and path.name.endswith(SUFFIX):
        names = [path.name[: -len(SUFFIX)]]
    if len(names) > 1:
        raise InputError(
            f"{len(names)} Pix4D projects' parameters in one folder ({', '.join(names)})",
            path=folder,
            fix="point at the camera-parameters file of the one to read",
        )
    name = names[0]
    root = folder.parent.parent if (folder.name, folder.parent.name) == ("params", "1_initial") else folder
    p4d = path if path.suffix.lower() == ".p4d" else _p4d_file(root, name)
    ccp = folder / f"{name}{SUFFIX}"
    offset_file = folder / f"{name}_offset.xyz"
    frame = OffsetFrame(crs=_output_crs(folder / f"{name}_wkt.prj"), offset=_offset(offset_file))
    lens_files = _check_lens(folder, name, p4d)
    photos = _photos(ccp)
    external = folder / f"{name}_calibrated_external_camera_parameters.txt"
    if external.is_file():
        photos = _with_external(photos, external, frame, offset_file)
    if p4d is not None:
        photos = _with_p4d_images(photos, p4d)
    sensors = {p.camera.id: p.camera for p in photos.values() if p.shot is not None}
    files = [ccp, offset_file, folder / f"{name}_wkt.prj"] + [
        p for p in (folder / f"{name}_pmatrix.txt", external, *lens_files, p4d) if p is not None and p.is_file()
    ]
    posed = sum(p.shot is not None for p in photos.values())
    log.info(
        "Pix4D project %r: %d calibrated photos (%d not calibrated), %d cameras, %s",
        name, posed, len(photos) - posed, len(sensors), frame.describe(),
    )  # fmt: skip
    return CameraSet("pix4d", root, files, frame, photos, sensors)


def _p4d_file(root: Path, name: str) -> Path | None:
    """The project's ``<name>.p4d``: beside the project folder (Pix4D's layout) or inside it; None if neither."""
    hits = [p for p in (root.parent / f"{name}.p4d", root / f"{name}.p4d") if p.is_file()]
    return hits[0] if hits else None


def _offset(path: Path) -> np.ndarray:
    """``<name>_offset.xyz``: the three numbers the camera positions are given from."""
    if not path.is_file():
        raise InputError(
            f"the Pix4D project lacks {path.name} (the offset the camera positions are given from)",
            path=path,
            fix=EXPORT,
        )
    offset = _numbers(read_text(path, what="Pix4D offset file"), path)
    if offset.size != 3:
        raise InputError(f"{path.name} holds {offset.size} numbers, not 'x y z'", path=path, fix=EXPORT)
    return offset


def _output_crs(prj: Path):
    """The output CRS from ``<name>_wkt.prj``: projected, in metres; a compound CRS gives its projected part (the
    heights stay in its vertical datum, which the project's DSM shares)."""
    fix = f"set a projected output coordinate system in metres (e.g. UTM) in Pix4D and run step 1 again; {EXPORT}"
    if not prj.is_file():
        raise InputError(
            f"the Pix4D project lacks {prj.name} (the output CRS): Pix4D writes none for a project in an arbitrary "
            "(local) coordinate system, which MatchPlant cannot place on a map",
            path=prj,
            fix=fix,
        )
    text = read_text(prj, what="Pix4D .prj file").strip()
    if not text or text.upper().startswith(("LOCAL_CS", "ENGCRS", "ENGINEERINGCRS")):
        raise InputError(
            f"{prj.name} is {'empty' if not text else 'a local (arbitrary) coordinate system'}: the cameras are not "
            "on a map",
            path=prj,
            fix=fix,
        )
    crs = parse_crs(text, source=prj)
    if crs.is_engineering or not crs.is_projected:
        what = "local (arbitrary)" if crs.is_engineering else "not projected"
        raise InputError(
            f"the output CRS {crs.name!r} is {what}; Pix4D's camera positions are then not in metres on a map",
            path=prj,
            fix=fix,
        )
    feet = not_metres(crs)
    if feet:
        raise InputError(
            f"the output CRS {crs.name!r} has axes in {feet}: Pix4D's camera positions are then not in metres",
            path=prj,
            fix=fix,
        )
    if crs.is_compound:
        horizontal = next(c for c in crs.sub_crs_list if c.is_projected)
        log.info("Pix4D output CRS %s: cameras placed in %s, heights as the project gives them", crs.name,
                 horizontal.name)  # fmt: skip
        return horizontal
    return crs


def _check_lens(folder: Path, name: str, p4d: Path | None) -> list[Path]:
    """Refuse a project whose camera model is not Pix4D's perspective lens (a fisheye's calibrated_camera_parameters
    would read as a pinhole): the .cam files, the camera.ssk and the .p4d's cameras say so. The files read."""
    files = sorted(folder.glob(f"{name}*internal_camera_parameters.cam"))
    ssk = folder / f"{name}_camera.ssk"
    # Pix4D's fisheye model: a polynomial in the angle and an affine map (support note "Camera Internals for
    # fisheye lens"); a perspective .cam names neither ("Odd-order Poly Coeffs" is its radial distortion)
    said = [f for f in files if re.search(r"fisheye|polynomial|affine", read_text(f, what="Pix4D .cam file"), re.I)]
    if ssk.is_file():
        files.append(ssk)
        for ln in read_text(ssk, what="Pix4D camera.ssk file").splitlines():
            key, _, value = ln.strip().partition(":")
            if key.strip().lower() == "camera_type" and value.strip().lower() not in ("frame", ""):
                said.append(ssk)
    if p4d is not None and "fisheye" in _p4d_cameras_text(p4d).lower():
        said.append(p4d)
    if said:
        raise InputError(
            f"the project's camera is not a perspective (frame) lens ({', '.join(sorted({f.name for f in said}))} "
            "say fisheye or another model): its parameters would be misread as a pinhole camera's",
            path=said[0],
            fix="MatchPlant reads Pix4D's perspective lens model only; process the photos with a perspective camera "
            "model, or use ODM (fisheye supported)",
        )
    return files


def _p4d_root(p4d: Path):
    """The parsed .p4d (XML), or an error naming it."""
    try:
        return ET.fromstring(read_text(p4d, what="Pix4D .p4d project file"))
    except ET.ParseError as exc:
        raise InputError(
            f"{p4d.name} is not a readable Pix4D project file ({exc})",
            path=p4d,
            fix="open and save the project in Pix4Dmapper, or move the .p4d away to read the params folder alone",
        ) from None


def _p4d_cameras_text(p4d: Path) -> str:
    """Everything the .p4d says of its camera models (tags, attributes and text of ``inputs/cameras``)."""
    out = []
    for cams in _p4d_root(p4d).iter("cameras"):
        for el in cams.iter():
            out += [el.tag, *el.attrib.values(), el.text or ""]
    return " ".join(out)


def _with_p4d_images(photos: dict[str, Photo], p4d: Path) -> dict[str, Photo]:
    """The calibrated photos with the paths the .p4d stores, plus its photos Pix4D did not calibrate (no pose)."""
    listed = {}
    for el in _p4d_root(p4d).iter("image"):
        stored = el.get("path")
        if stored and file_name(stored) in listed:
            raise InputError(
                f"two images named {file_name(stored)!r} in {p4d.name}: the camera parameters name photos by file "
                "name alone",
                path=p4d,
                fix="give the photos unique names and process the project again",
            )
        if stored:
            listed[file_name(stored)] = stored_path(stored, p4d.parent)
    if not listed:
        return photos
    known = {p.name for p in photos.values()}
    missing = sorted(known - set(listed))
    if len(missing) == len(known):
        raise InputError(
            f"none of the {len(known)} calibrated photos is among the {len(listed)} images of {p4d.name}",
            path=p4d,
            fix="the .p4d is another project's: move it away, or point at this project's params folder",
        )
    if missing:
        log.warning("%d calibrated photos are not in %s (e.g. %s)", len(missing), p4d.name, missing[0])
    out = {k: replace(p, path=listed.get(p.name) or p.path) for k, p in photos.items()}
    only = only_camera(photos.values())  # several cameras: which one is not known
    for fname, stored in listed.items():
        if fname not in known:
            out[fname] = Photo(fname, fname, only.id if only else "", only, None, stored)
    return out


def _with_external(photos: dict[str, Photo], external: Path, frame: OffsetFrame, offset_file: Path) -> dict:
    """Check the camera centres against ``calibrated_external_camera_parameters.txt`` (``imageName X Y Z Omega Phi
    Kappa``, X Y Z in the output CRS): a stale offset or a file from another run is refused; photos it lists that
    the camera-parameters file lacks are kept without a pose (a parameters file cut between two blocks)."""
    centres = {}
    for n, ln in enumerate(read_text(external, what="Pix4D external parameters").splitlines(), 1):
        parts = ln.split()
        if not parts or parts[0].lower() == "imagename":
            continue
        if len(parts) < 7:
            raise InputError(f"line {n} is not 'imageName X Y Z Omega Phi Kappa'", path=external, fix=EXPORT)
        centres[" ".join(parts[:-6])] = _numbers(" ".join(parts[-6:-3]), external)
    far = [
        (k, float(np.abs(frame.to_map(p.shot.center[None, :])[0] - centres[k]).max()))
        for k, p in photos.items()
        if k in centres
    ]
    worst = max(far, key=lambda kv: kv[1], default=("", 0.0))
    if worst[1] > 0.01:
        raise InputError(
            f"photo {worst[0]!r} is {worst[1]:.3f} m from where {external.name} puts it: {offset_file.name} or the "
            "camera parameters are from another run",
            path=external,
            fix=EXPORT,
        )
    lost = [k for k in centres if k not in photos]
    if lost:
        log.warning("%d photos in %s are not in the camera parameters (e.g. %s): read without a pose",
                    len(lost), external.name, lost[0])  # fmt: skip
    only = only_camera(photos.values())
    return photos | {k: Photo(k, file_name(k), only.id if only else "", only, None) for k in lost}


def _numbers(text: str, path: Path) -> np.ndarray:
    """Every number of a text, or an error naming the file."""
    try:
        return np.array(text.split(), dtype=float)
    except ValueError as exc:
        raise InputError(f"{path.name} holds something that is not a number ({exc})", path=path, fix=EXPORT) from None


# numbers on each line of a photo's block after its 'name width height' line: K (3 rows), radial R1..R3,
# tangential T1 T2, position t, rotation R (3 rows)
BLOCK = ((3, "K"), (3, "K"), (3, "K"), (3, "radial distortion"), (2, "tangential distortion"),
         (3, "camera position"), (3, "rotation"), (3, "rotation"), (3, "rotation"))  # fmt: skip


def _blocks(ccp: Path) -> list[tuple[int, str, list[str]]]:
    """Each photo's block of ``calibrated_camera_parameters.txt``: (line number, head line, its 9 number lines),
    each line's count checked so a missing or extra line is named where it is."""
    text = read_text(ccp, what="Pix4D camera parameters")
    lines = [(n, ln.strip()) for n, ln in enumerate(text.splitlines(), 1)]
    first = next((ln for _, ln in lines if ln), "")
    if not first:
        raise InputError(f"{ccp.name} is empty (Pix4D stopped while writing it?)", path=ccp, fix=EXPORT)
    if not first.lower().startswith("filename"):
        raise InputError(
            "not a Pix4D calibrated_camera_parameters file (its first line is not 'fileName imageWidth imageHeight')",
            path=ccp,
            fix=EXPORT,
        )
    start = next((i + 1 for i, (_, ln) in enumerate(lines) if ln.lower().startswith("camera model")), None)
    body = [(n, ln) for n, ln in lines[start or 1 :] if ln]
    if not body:
        raise InputError(f"{ccp.name} lists no calibrated photo", path=ccp, fix="calibrate the project: " + EXPORT)
    out = []
    for b in range(0, len(body), 10):
        block = body[b : b + 10]
        n, head = block[0]
        if len(block) < 10:
            raise InputError(
                f"{ccp.name} is truncated: the last photo's block (line {n}, {head[:40]!r}) has {len(block)} of 10 "
                "lines",
                path=ccp,
                fix=EXPORT,
            )
        for (m, ln), (count, what) in zip(block[1:], BLOCK):
            if len(ln.split()) != count:
                raise InputError(
                    f"{ccp.name} line {m} (photo {head[:40]!r}: {what}) holds {len(ln.split())} values, not {count}: "
                    "a line is missing or extra, or the file is truncated",
                    path=ccp,
                    fix=EXPORT,
                )
        out.append((n, head, [ln for _, ln in block[1:]]))
    return out


def _photos(ccp: Path) -> dict[str, Photo]:
    """Every photo of ``calibrated_camera_parameters.txt`` (:func:`_blocks`) with its camera and pose."""
    blocks = _blocks(ccp)
    values = _numbers(" ".join(" ".join(rows) for _, _, rows in blocks), ccp).reshape(-1, 26)
    photos: dict[str, Photo] = {}
    cameras: dict[tuple, FrameCamera] = {}
    rows = []
    for (n, head, _), v in zip(blocks, values):
        parts = head.rsplit(maxsplit=2)
        try:
            label, w, h = parts[0], int(parts[1]), int(parts[2])
        except (IndexError, ValueError):
            raise InputError(f"line {n}: {head!r} is not 'name width height'", path=ccp, fix=EXPORT) from None
        K, dist, t, R = v[:9].reshape(3, 3), v[9:14], v[14:17], v[17:26].reshape(3, 3)
        if not check_rotation(R, tol=1e-5) or K[0, 0] <= 0 or K[1, 1] <= 0 or not np.all(np.isfinite(v)):
            raise InputError(f"photo {label!r}: its rotation or camera matrix is not valid", path=ccp, fix=EXPORT)
        key = (w, h, *np.round(K.ravel(), 9), *np.round(dist, 12))
        if key not in cameras:
            s = float(max(w, h))
            cameras[key] = FrameCamera(
                id=f"camera {len(cameras) + 1} ({w}x{h})", projection_type="brown", width=w, height=h,
                focal_x=K[0, 0] / s, focal_y=K[1, 1] / s, skew=K[0, 1] / s, c_x=(K[0, 2] - w / 2) / s,
                c_y=(K[1, 2] - h / 2) / s, k1=dist[0], k2=dist[1], k3=dist[2], p1=dist[3], p2=dist[4],
            )  # fmt: skip
        cam = cameras[key]
        if label in photos:
            raise InputError(f"photo {label!r} appears twice", path=ccp, fix=EXPORT)
        name = file_name(label)  # Pix4D writes file names; a path keeps its folders as the photo's path
        photos[label] = Photo(label, name, cam.id, cam, None, label if name != label else None)
        rows.append((cam, R, t))
    shots = make_shots(
        list(photos), [r[0] for r in rows], np.array([r[1] for r in rows]), np.array([r[2] for r in rows])
    )
    return {k: replace(p, shot=s) for (k, p), s in zip(photos.items(), shots)}


def read_pmatrix(path: str | Path) -> dict[str, np.ndarray]:
    """``<name>_pmatrix.txt``: photo name -> its 3x4 matrix (offset coordinates to Pix4D's undistorted pixels)."""
    path = Path(path)
    out = {}
    for ln in read_text(path, what="Pix4D pmatrix file").splitlines():
        parts = ln.split()
        if not parts:
            continue
        if len(parts) < 13:
            raise InputError(f"line {ln[:60]!r} is not a name and 12 numbers", path=path, fix=EXPORT)
        out[" ".join(parts[:-12])] = _numbers(" ".join(parts[-12:]), path).reshape(3, 4)
    return out


def write_pix4d(folder: str | Path, name: str, shots: dict[str, Shot], frame: OffsetFrame) -> Path:
    """Write shots (pinhole cameras; poses in an offset frame) as a Pix4D ``params/`` folder: camera parameters,
    offset, .prj and P matrices, inverting the reader's conversion (module docstring)."""
    if not isinstance(frame, OffsetFrame):
        raise InputError(
            "Pix4D's parameters are in a projected CRS minus an offset; these poses are in another frame",
            fix="export from a project whose reconstruction is in map coordinates minus an offset (modern ODM)",
        )
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    head = (
        "fileName imageWidth imageHeight \ncamera matrix K [3x3]\nradial distortion [3x1]\ntangential distortion "
        "[2x1]\ncamera position t [3x1]\ncamera rotation R [3x3]\ncamera model m = K [R|-Rt] X\n\n"
    )
    blocks, pm = [], []
    for k in sorted(shots):
        shot = shots[k]
        cam = shot.camera
        if cam.projection_type not in ("perspective", "brown", "radial", "simple_radial"):
            raise InputError(
                f"camera '{cam.id}' ({cam.projection_type}) is not a pinhole camera", fix="export pinhole cameras"
            )
        K = _pixel_matrix(cam)
        rows = [
            f"{k} {cam.width} {cam.height}",
            *(" ".join(repr(float(v)) for v in r) for r in K),
            " ".join(repr(float(v)) for v in (cam.k1, cam.k2, cam.k3)),
            " ".join(repr(float(v)) for v in (cam.p1, cam.p2)),
            " ".join(repr(float(v)) for v in shot.center),
            *(" ".join(repr(float(v)) for v in r) for r in shot.R),
        ]
        blocks.append("\n".join(rows))
        P = K @ np.c_[shot.R, -shot.R @ shot.center]
        pm.append(f"{k} " + " ".join(f"{v:.6f}" for v in P.ravel()))
    write_text(folder / f"{name}{SUFFIX}", head + "\n".join(blocks) + "\n")
    write_text(folder / f"{name}_offset.xyz", " ".join(f"{v:.3f}" for v in frame.offset) + "\n")
    write_text(folder / f"{name}_wkt.prj", frame.crs.to_wkt("WKT1_ESRI") + "\n")
    write_text(folder / f"{name}_pmatrix.txt", "\n".join(pm) + "\n")
    return folder


def _pixel_matrix(cam) -> np.ndarray:
    """Pix4D's K (pixels, origin at the image's corner) of one of our cameras."""
    s = float(max(cam.width, cam.height))
    return np.array(
        [
            [cam.focal_x * s, getattr(cam, "skew", 0.0) * s, cam.c_x * s + cam.width / 2],
            [0.0, cam.focal_y * s, cam.c_y * s + cam.height / 2],
            [0.0, 0.0, 1.0],
        ]
    )
