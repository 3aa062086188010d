"""The ``split`` preset: a generated field rewritten as an ODM split-merge project (docs/DESIGN.md §6).

ODM's ``--split`` cuts a large flight into submodels, reconstructs each on its own (ClusterODM: on its own
machine), aligns them and merges the rasters. This rewrites a normal synthetic field the same way:

- the flight lines cut into ``submodels`` contiguous groups, each sharing one line with the previous group
  (the split overlap: those images are in two submodels, with two slightly different poses);
- ``submodels/submodel_NNNN/`` each with ``opensfm/reconstruction.json`` and ``opensfm/undistorted/``
  (``reconstruction.json`` and ``images/``) in its own topocentric frame (its own ``reference_lla``), its own
  ``odm_georeferencing/coords.txt`` (its own offset), and its own DSM, DTM and orthophoto (the merged
  rasters cropped to its part of the field), as ODM leaves them before the merge;
- a small rigid misalignment per submodel (a few centimetres, a hundredth of a degree about the vertical),
  as ODM's alignment of the submodels leaves: each submodel's poses and rasters are the truth moved by it;
- the merged DSM, DTM and orthophoto and ``coords.txt`` at the top; the top-level reconstruction removed.

The truth (plants on the map, boxes in every image) is unchanged; ``truth/split.json`` adds each
submodel's lines, images, frame and misalignment.
"""

from __future__ import annotations

import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from pyproj import CRS, Transformer
from rasterio.windows import Window, from_bounds
from scipy.ndimage import affine_transform

from matchplant.core.formats.odm import OUTPUTS, SUBMODELS_DIR, ODMProject
from matchplant.core.formats.reconstruction import Reconstruction, write_reconstruction
from matchplant.core.geometry.frames import TopocentricFrame, write_coords_txt
from matchplant.core.geometry.shot import Shot
from matchplant.core.runtime.io import read_json, write_json
from matchplant.core.runtime.log import get_logger
from matchplant.simfield.layout import FieldPaths

log = get_logger("simfield")

MISALIGNMENT_M = 0.015  # horizontal shift of each submodel, metres; neighbours shifted opposite ways are about
# twice this apart (ODM's aligned submodels: a few centimetres)
MISALIGNMENT_DEG = 0.01  # rotation of each submodel about the vertical, degrees
RASTERS = ("dsm", "dtm", "orthophoto")


def split_lines(lines: int, submodels: int) -> list[list[int]]:
    """Contiguous groups of flight lines, each but the first also holding the previous group's last line."""
    n = max(1, min(submodels, max(1, lines - 1)))
    chunks = [list(map(int, c)) for c in np.array_split(np.arange(lines), n)]
    return [chunks[0]] + [[chunks[k - 1][-1]] + chunks[k] for k in range(1, n)]


def _link(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        dst.unlink()
    try:
        os.link(src, dst)  # no second copy of every image
    except OSError:
        shutil.copy2(src, dst)


def _moved(points: np.ndarray, pivot: np.ndarray, t: np.ndarray, theta: float) -> np.ndarray:
    """Map points (N, 3) rotated by ``theta`` (radians) about the vertical through ``pivot``, then shifted by t."""
    c, s = math.cos(theta), math.sin(theta)
    p = np.asarray(points, dtype=float) - pivot
    out = np.column_stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]])
    return out + pivot + t


def _moved_raster(
    data: np.ndarray, tr: Affine, pivot: np.ndarray, t: np.ndarray, theta: float, elevation: bool
) -> np.ndarray:
    """A north-up raster (bands, rows, cols) of the world moved by :func:`_moved`, on the same grid."""

    def to_map(rc):
        return np.column_stack([tr.c + (rc[:, 1] + 0.5) * tr.a, tr.f + (rc[:, 0] + 0.5) * tr.e])

    rc = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    q = to_map(rc) - t[:2] - pivot[:2]  # back to the unmoved world: undo the shift, then the rotation
    c, s_ = math.cos(-theta), math.sin(-theta)
    src = np.column_stack([c * q[:, 0] - s_ * q[:, 1], s_ * q[:, 0] + c * q[:, 1]]) + pivot[:2]
    idx = np.column_stack([(src[:, 1] - tr.f) / tr.e - 0.5, (src[:, 0] - tr.c) / tr.a - 0.5])
    matrix = np.column_stack([idx[1] - idx[0], idx[2] - idx[0]])
    out = np.empty_like(data)
    for b in range(data.shape[0]):
        band = affine_transform(data[b].astype(np.float32), matrix, offset=idx[0], order=1, mode="nearest")
        if elevation:
            band = band + np.float32(t[2])
        out[b] = np.round(band) if np.issubdtype(data.dtype, np.integer) else band
    return out


def _rewrite_rasters(project: ODMProject, subs: list[dict], root: Path) -> None:
    """Each submodel's rasters (its world moved by its misalignment, cropped to its part) and the merged ones at
    the top: each cell from the submodel whose cameras' centroid is nearest, as ODM's merge keeps each
    submodel's own surface away from the seams."""
    for r in RASTERS:
        if not project.has(r):
            continue
        path = project.path(r)
        with rasterio.open(path) as src:
            data, tr, profile = src.read(), src.transform, src.profile.copy()
        moved = [_moved_raster(data, tr, s["pivot"], s["t"], s["theta"], r != "orthophoto") for s in subs]
        rows, cols = data.shape[1:]
        xs = tr.c + (np.arange(cols) + 0.5) * tr.a
        ys = tr.f + (np.arange(rows) + 0.5) * tr.e
        d = np.stack([(xs[None, :] - s["pivot"][0]) ** 2 + (ys[:, None] - s["pivot"][1]) ** 2 for s in subs])
        nearest = d.argmin(axis=0)
        merged = np.choose(nearest[None], moved) if len(subs) > 1 else moved[0]
        with rasterio.open(path, "w", **profile) as dst:
            dst.write(merged.astype(data.dtype))
        for s, m in zip(subs, moved):
            b = s["bounds"]
            win = from_bounds(*b, transform=tr).round_offsets().round_lengths().intersection(Window(0, 0, cols, rows))
            r0, c0 = int(win.row_off), int(win.col_off)
            part = m[:, r0 : r0 + int(win.height), c0 : c0 + int(win.width)]
            prof = dict(
                profile, width=part.shape[2], height=part.shape[1], transform=rasterio.windows.transform(win, tr)
            )
            out = root / SUBMODELS_DIR / s["name"] / OUTPUTS[r].relpath
            out.parent.mkdir(parents=True, exist_ok=True)
            with rasterio.open(out, "w", **prof) as dst:
                dst.write(part.astype(data.dtype))


@dataclass(frozen=True)
class _Move:
    """How one submodel's world is moved against the field's (its misalignment), and its own frame."""

    pivot: np.ndarray
    t: np.ndarray
    theta: float
    rz: np.ndarray
    topo: TopocentricFrame
    ref: dict


def _convert(src: Reconstruction, ids: list[str], centres: dict, frame, move: _Move) -> Reconstruction:
    """The submodel's reconstruction: its shots ``ids`` and the points, moved and put in its own frame."""
    topo, pivot, t, theta = move.topo, move.pivot, move.t, move.theta
    shots = {}
    for sid in ids:
        sh = src.shots[sid]
        centre = topo.from_map(_moved(centres[sid][None, :], pivot, t, theta))[0]
        R = sh.R @ move.rz.T @ topo.rotation_from_map(centre)  # the camera turned with the submodel's world
        gps = tuple(float(v) for v in topo.from_map(centres[sid][None, :])[0])
        shots[sid] = Shot.from_center(
            sid, sh.camera, R, centre, capture_time=sh.capture_time, gps_position=gps, extra=dict(sh.extra)
        )
    pts = frame.to_map(src.points) if len(src.points) else src.points
    pts = topo.from_map(_moved(pts, pivot, t, theta)) if len(pts) else pts
    return Reconstruction(
        cameras=dict(src.cameras), shots=shots, point_ids=list(src.point_ids), points=pts, reference_lla=dict(move.ref)
    )


def split_field(
    paths: FieldPaths,
    submodels: int = 2,
    seed: int = 0,
    misalignment: float = MISALIGNMENT_M,
    rotation_deg: float = MISALIGNMENT_DEG,
) -> FieldPaths:
    """Rewrite the generated field at ``paths`` (in place) as a split-merge project of ``submodels``."""
    root = paths.root
    project = ODMProject(root)
    frame = project.frame()
    crs = frame.crs
    rec, urec = project.reconstruction(), project.reconstruction(undistorted=True)
    field = read_json(paths.field_json)
    lines = {im["name"]: int(im["line"]) for im in field["images"]}
    groups = split_lines(int(field["flight"]["lines"]), submodels)
    gsd, cam = float(field["gsd"]), field["camera"]["opensfm"]
    half = 0.6 * gsd * max(float(cam["width"]), float(cam["height"]))  # beyond an image's half footprint
    rng = np.random.default_rng([seed, 1818])
    heading = rng.uniform(0, 2 * math.pi)
    centres = {sid: frame.to_map(sh.center[None, :])[0] for sid, sh in rec.shots.items()}
    z_ground = float(field["topocentric_reference_lla"]["altitude"])
    to_lla = Transformer.from_crs(crs.to_3d(), CRS.from_epsg(4979), always_xy=True)
    info, moves = [], []
    for k, group in enumerate(groups):
        name = f"submodel_{k:04d}"
        sub = root / SUBMODELS_DIR / name
        ids = sorted(sid for sid in rec.shots if lines.get(sid) in group)
        c = np.array([centres[sid] for sid in ids])
        pivot = np.r_[c[:, :2].mean(axis=0), z_ground]
        angle = heading + k * math.pi + rng.normal(0.0, 0.3)  # neighbours about twice the shift apart
        t = np.array(
            [misalignment * math.cos(angle), misalignment * math.sin(angle), rng.normal(0.0, misalignment / 3)]
        )
        theta = math.radians(rotation_deg) * (-1) ** k
        rz = np.array([[math.cos(theta), -math.sin(theta), 0], [math.sin(theta), math.cos(theta), 0], [0, 0, 1]])
        lon, lat, alt = to_lla.transform(*pivot)
        ref = {"latitude": float(lat), "longitude": float(lon), "altitude": float(alt)}
        topo = TopocentricFrame(ref["latitude"], ref["longitude"], ref["altitude"], crs)

        move = _Move(pivot, t, theta, rz, topo, ref)
        for source, key in ((rec, "reconstruction"), (urec, "undistorted_reconstruction")):
            write_reconstruction(sub / OUTPUTS[key].relpath, _convert(source, ids, centres, frame, move))
        for sid in ids:
            _link(project.undistorted_image_path(sid), sub / OUTPUTS["undistorted_images"].relpath / f"{sid}.tif")
            if (paths.images / sid).is_file():
                _link(paths.images / sid, sub / "images" / sid)
        offset = np.floor(c[:, :2].min(axis=0) - half)
        write_coords_txt(sub / OUTPUTS["coords"].relpath, crs, np.r_[offset, 0.0])
        bounds = (*(c[:, :2].min(axis=0) - half), *(c[:, :2].max(axis=0) + half))
        moves.append({"name": name, "pivot": pivot, "t": t, "theta": theta, "bounds": bounds})
        info.append(
            {
                "name": name,
                "lines": group,
                "images": ids,
                "reference_lla": ref,
                "coords_offset": [float(offset[0]), float(offset[1])],
                "misalignment": {
                    "translation_m": [float(v) for v in t],
                    "rotation_deg": math.degrees(theta),
                    "pivot": [float(v) for v in pivot],
                },
            }
        )
    _rewrite_rasters(project, moves, root)
    # the top keeps what ODM's merge stage leaves: merged rasters and coords.txt, no reconstruction
    for name in ("reconstruction", "topocentric_reconstruction", "undistorted_reconstruction"):
        project.path(name).unlink(missing_ok=True)
    shutil.rmtree(root / "opensfm" / "undistorted", ignore_errors=True)
    shared = {}
    for s in info:
        for sid in s["images"]:
            shared.setdefault(sid, []).append(s["name"])
    write_json(
        paths.truth / "split.json",
        {"submodels": info, "shared": {k: v for k, v in sorted(shared.items()) if len(v) > 1}},
    )
    log.info(
        "split into %d submodels (%s images each, %d in two)",
        len(info),
        "/".join(str(len(s["images"])) for s in info),
        sum(len(v) > 1 for v in shared.values()),
    )
    return paths
