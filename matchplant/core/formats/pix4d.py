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
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from matchplant.core.formats.camera_set import CameraSet, Photo, check_rotation, make_shots
from matchplant.core.geometry.frame_camera import FrameCamera
from matchplant.core.geometry.frames import OffsetFrame, parse_crs
from matchplant.core.geometry.shot import Shot
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
    """The params folder of a Pix4D project folder, params folder or camera-parameters file; None if none."""
    path = Path(path)
    if path.is_file() and path.name.endswith(SUFFIX):
        return path.parent
    for folder in (path, path / PARAMS):
        if folder.is_dir() and any(p.name.endswith(SUFFIX) for p in folder.iterdir()):
            return folder
    return None


def read_pix4d(path: str | Path) -> CameraSet:
    """Read a Pix4D project's ``params/`` files into a :class:`CameraSet` (module docstring)."""
    path = Path(path)
    folder = params_folder(path)
    if folder is None:
        raise InputError(f"no *{SUFFIX} in this folder or in its {PARAMS}/", path=path, fix=EXPORT)
    names = sorted(p.name[: -len(SUFFIX)] for p in folder.iterdir() if p.name.endswith(SUFFIX))
    if path.is_file():
        names = [path.name[: -len(SUFFIX)]]
    if len(names) > 1:
        raise InputError(
            f"{len(names)} Pix4D projects' parameters in one folder ({', '.join(names)})",
            path=folder,
            fix="point at the camera-parameters file of the one to read",
        )
    name = names[0]
    ccp = folder / f"{name}{SUFFIX}"
    offset_file, prj = folder / f"{name}_offset.xyz", folder / f"{name}_wkt.prj"
    for needed, what in ((offset_file, "the offset the camera positions are given from"), (prj, "the output CRS")):
        if not needed.is_file():
            raise InputError(f"the Pix4D project lacks {needed.name} ({what})", path=needed, fix=EXPORT)
    offset = _numbers(read_text(offset_file, what="Pix4D offset file"), offset_file)
    if offset.size != 3:
        raise InputError(f"{offset_file.name} holds {offset.size} numbers, not 'x y z'", path=offset_file, fix=EXPORT)
    crs = parse_crs(read_text(prj, what="Pix4D .prj file").strip(), source=prj)
    if not crs.is_projected:
        raise InputError(
            f"the output CRS {crs.name!r} is not projected; Pix4D's camera positions are then not in metres",
            path=prj,
            fix="set a projected output coordinate system (e.g. UTM) in Pix4D and run step 1 again",
        )
    photos = _photos(ccp)
    frame = OffsetFrame(crs=crs, offset=offset)
    sensors = {p.camera.id: p.camera for p in photos.values()}
    files = [ccp, offset_file, prj] + [
        p for p in (folder / f"{name}_pmatrix.txt", *folder.glob(f"{name}*calibrated_internal_camera_parameters.cam"))
        if p.is_file()
    ]  # fmt: skip
    log.info(
        "Pix4D project %r: %d calibrated photos, %d cameras, %s", name, len(photos), len(sensors), frame.describe()
    )
    return CameraSet("pix4d", path, files, frame, photos, sensors)


def _numbers(text: str, path: Path) -> np.ndarray:
    """Every number of a text, or an error naming the file."""
    try:
        return np.array(text.split(), dtype=float)
    except ValueError as exc:
        raise InputError(f"{path.name} holds something that is not a number ({exc})", path=path, fix=EXPORT) from None


def _photos(ccp: Path) -> dict[str, Photo]:
    """Every photo block of ``calibrated_camera_parameters.txt`` (10 lines each after the header)."""
    lines = [ln.strip() for ln in read_text(ccp, what="Pix4D camera parameters").splitlines()]
    if not lines or not lines[0].lower().startswith("filename"):
        raise InputError(
            "not a Pix4D calibrated_camera_parameters file (its first line is not 'fileName imageWidth imageHeight')",
            path=ccp,
            fix=EXPORT,
        )
    start = next((i + 1 for i, ln in enumerate(lines) if ln.lower().startswith("camera model")), None)
    body = [ln for ln in lines[start or 1 :] if ln]
    if len(body) % 10 or not body:
        raise InputError(
            f"{ccp.name} is truncated: {len(body)} lines after the header, not 10 per photo",
            path=ccp,
            fix=EXPORT,
        )
    heads = body[0::10]
    try:
        values = np.array(" ".join(ln for i, ln in enumerate(body) if i % 10).split(), dtype=float).reshape(-1, 26)
    except ValueError:
        raise InputError(f"{ccp.name} has a photo block that is not 26 numbers", path=ccp, fix=EXPORT) from None
    photos: dict[str, Photo] = {}
    cameras: dict[tuple, FrameCamera] = {}
    rows = []
    for head, v in zip(heads, values):
        parts = head.rsplit(maxsplit=2)
        try:
            name, w, h = parts[0], int(parts[1]), int(parts[2])
        except (IndexError, ValueError):
            raise InputError(f"photo line {head!r} is not 'name width height'", path=ccp, fix=EXPORT) from None
        K, dist, t, R = v[:9].reshape(3, 3), v[9:14], v[14:17], v[17:26].reshape(3, 3)
        if not check_rotation(R, tol=1e-5) or K[0, 0] <= 0 or K[1, 1] <= 0 or not np.all(np.isfinite(v)):
            raise InputError(f"photo {name!r}: its rotation or camera matrix is not valid", path=ccp, fix=EXPORT)
        key = (w, h, *np.round(K.ravel(), 9), *np.round(dist, 12))
        if key not in cameras:
            s = float(max(w, h))
            cameras[key] = FrameCamera(
                id=f"camera {len(cameras) + 1} ({w}x{h})", projection_type="brown", width=w, height=h,
                focal_x=K[0, 0] / s, focal_y=K[1, 1] / s, skew=K[0, 1] / s, c_x=(K[0, 2] - w / 2) / s,
                c_y=(K[1, 2] - h / 2) / s, k1=dist[0], k2=dist[1], k3=dist[2], p1=dist[3], p2=dist[4],
            )  # fmt: skip
        cam = cameras[key]
        if name in photos:
            raise InputError(f"photo {name!r} appears twice", path=ccp, fix=EXPORT)
        photos[name] = Photo(name, name, cam.id, cam, None)
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
