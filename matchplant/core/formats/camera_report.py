"""``matchplant cameras PROJECT``: what a project holds, and where map points fall in its original photos.

    matchplant cameras field.psx                          # program, photos with and without a pose, sensors, CRS
    matchplant cameras field --points gcps.csv --output -  # photo,u,v of every point in every photo that sees it

The summary works for ODM, Metashape and Pix4D projects alike (:func:`~matchplant.core.formats.projects.open_project`).
Pixels are in the original photo, our convention (docs/DESIGN.md §3: the top-left pixel's centre is (0, 0)).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from matchplant.core.formats.projects import PROJECT_TYPES, detect_project, open_project
from matchplant.core.geometry.frames import parse_crs
from matchplant.core.geometry.geodetic import map_transformer
from matchplant.core.runtime.config import param
from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.io import is_stream, write_text
from matchplant.core.runtime.validate import read_csv


@dataclass
class CamerasConfig:
    """Summarise a photogrammetry project's cameras; optionally find map points in its original photos."""

    project: Path | None = param(
        None,
        "the project: an ODM folder, a Metashape .xml export or .psx, a Pix4D project folder",
        path="exists",
        required=True,
    )
    project_type: str = param("auto", "which program made the project (auto: from its files)", choices=PROJECT_TYPES)
    points: Path | None = param(None, "a CSV of map points (columns x, y, z) to find in the photos", path="file")
    points_crs: str | None = param(None, "the CRS of the points' x, y, z (default: the project's CRS)")
    output: Path = param(Path("-"), "where the points' photo pixels go as CSV ('-': standard output)", path="out_file")

    def check(self) -> None:
        """Settings that cannot work together."""
        if self.points_crs is not None and self.points is None:
            raise ConfigError("points_crs is set without points", fix="give --points FILE.csv, or drop points_crs")


def summary(project) -> str:
    """A few lines: program, files, photos with and without a pose, sensors, CRS and the cameras' extent."""
    ids = sorted(project.shot_ids(undistorted=False) or project.shot_ids(undistorted=True))
    und = not project.shot_ids(undistorted=False)
    shots = [project.nominal_shot(i, undistorted=und) for i in ids]
    frame = project.frame()
    program = getattr(project, "program", "odm")
    lines = [f"program: {program}"]
    cameras = getattr(project, "cameras", None)
    if cameras is not None:
        lines.append("read: " + ", ".join(str(p) for p in cameras.files))
        unposed = cameras.unposed
        lines.append(f"photos: {len(cameras.photos)} ({len(ids)} with a pose, {len(unposed)} without)")
        if unposed:
            lines.append("  without a pose: " + ", ".join(unposed[:10]) + (" ..." if len(unposed) > 10 else ""))
        for why, labels in getattr(cameras, "left_out", {}).items():
            lines.append(f"  left out: {len(labels)} photos, {why}")
    else:
        lines.append(f"photos: {len(ids)} with a pose")
    sensors = {}
    for s in shots:
        sensors.setdefault(s.camera.id, [s.camera, 0])[1] += 1
    lines.append(f"sensors: {len(sensors)}")
    for cam, n in sensors.values():
        f = cam.focal_y * max(cam.width, cam.height)
        lines.append(f"  {cam.id}: {cam.width}x{cam.height} px, focal {f:.1f} px, {n} photos")
    lines.append(f"CRS: {frame.crs.name}" + (f" (EPSG:{frame.crs.to_epsg()})" if frame.crs.to_epsg() else ""))
    if shots:
        c = np.vstack([project.frame_of(i).to_map(s.center[None, :]) for i, s in zip(ids, shots)])
        lo, hi = c.min(axis=0), c.max(axis=0)
        lines.append(
            f"cameras' extent: x {lo[0]:.2f} .. {hi[0]:.2f}, y {lo[1]:.2f} .. {hi[1]:.2f}, z {lo[2]:.2f} .. {hi[2]:.2f}"
        )
    return "\n".join(lines) + "\n"


def point_pixels(project, xyz: np.ndarray, crs=None) -> list[tuple[int, str, float, float]]:
    """(point index, photo, u, v) for every point and every posed original photo whose image it falls in."""
    frame = project.frame()
    pts = np.asarray(xyz, dtype=float).reshape(-1, 3)
    if crs is not None and not crs.equals(frame.crs):
        tr = map_transformer(crs, frame.crs, what="the points' CRS to the project's")
        pts = np.stack(tr.transform(pts[:, 0], pts[:, 1], pts[:, 2]), axis=-1)
    und = not project.shot_ids(undistorted=False)
    rows = []
    for sid in sorted(project.shot_ids(undistorted=und)):
        shot = project.nominal_shot(sid, undistorted=und)
        uv = shot.project(project.frame_of(sid).from_map(pts))
        inside = np.isfinite(uv).all(axis=1) & shot.camera.in_image(uv)
        rows += [(int(k), sid, float(uv[k, 0]), float(uv[k, 1])) for k in np.flatnonzero(inside)]
    return sorted(rows)


def run_cameras(cfg: CamerasConfig) -> str:
    """Print the summary; with ``points``, write their photo pixels as CSV to ``output``."""
    cfg.check()
    detect_project(cfg.project, cfg.project_type)
    project = open_project(cfg.project, cfg.project_type)
    text = summary(project)
    if cfg.points is None:
        print(text, end="")
        return text
    table = read_csv(cfg.points, required=("x", "y", "z"), numeric=("x", "y", "z"), what="points CSV")
    xyz = np.stack([table.numbers[k] for k in ("x", "y", "z")], axis=1)
    crs = parse_crs(cfg.points_crs, key="points_crs") if cfg.points_crs else None
    rows = point_pixels(project, xyz, crs)
    buf = io.StringIO()
    buf.write("point,x,y,z,photo,u,v\n")
    for k, sid, u, v in rows:
        buf.write(f"{k},{float(xyz[k, 0])!r},{float(xyz[k, 1])!r},{float(xyz[k, 2])!r},{sid},{u:.3f},{v:.3f}\n")
    if not is_stream(cfg.output):  # the CSV alone on standard output
        print(text, end="")
    write_text(cfg.output, buf.getvalue())
    return text
