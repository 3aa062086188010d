"""Which images see each GCP, and where: the survey and the images' metadata in, ranked candidates out.

An image is a candidate for a GCP when the predicted pixel lies inside it and within
``max_center_distance`` of its centre; candidates are ranked by that distance (the centre has the least
distortion and relief error), so the user marks the best images first.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib.patches import Polygon

from matchplant.core.formats.images import EXIF_SUFFIXES, list_images
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.gui import figure
from matchplant.core.runtime.io import atomic_open, atomic_path
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.gcp_finder.config import MIN_IMAGES_PER_GCP, GcpFinderConfig
from matchplant.gcp_finder.metadata import ImageInfo, focal_ratio, read_image_info
from matchplant.gcp_finder.pose import camera_heights, camera_positions, footprint, image_yaw, predict_pixels, track_yaw
from matchplant.gcp_finder.survey import GCP, read_survey

log = get_logger("gcp_finder")


@dataclass
class Candidate:
    """An image predicted to see a GCP, with the predicted pixel (the GUI opens zoomed there)."""

    gcp: str
    image: str
    u: float  # predicted pixel
    v: float
    center_distance: float  # 0 at the centre, 1 at a corner
    rank: int = 0


@dataclass
class Finder:
    """Everything the GUI and auto mode need: GCPs, image metadata and ranked candidates."""

    gcps: dict[str, GCP]
    crs: object
    images: dict[str, ImageInfo]
    candidates: dict[str, list[Candidate]]  # per GCP, best first
    ratio: dict[str, float]
    yaw: dict[str, float]
    pitch: dict[str, float]
    height: dict[tuple[str, str], float]  # (gcp, image) -> camera height above the GCP
    flight: set[str] = field(default_factory=set)  # every image of the folder, with GPS or not

    def gsd(self, gcp: str, image: str) -> float:
        """Metres per pixel at the GCP in that image: the target's expected size in pixels follows."""
        info = self.images[image]
        return self.height[(gcp, image)] / (self.ratio[image] * max(info.width, info.height))


def find_candidates(cfg: GcpFinderConfig) -> Finder:
    """Read the survey and every image's metadata; predict each GCP's pixel in each image; rank."""
    gcps, crs = read_survey(cfg.survey, cfg.survey_crs, cfg.output_crs)
    files, infos, notes = _read_flight(cfg)
    camera_positions(infos, crs)
    infos.sort(key=lambda i: (i.time if i.time is not None else 0.0, i.name))
    track = track_yaw(np.array([i.xyz[:2] for i in infos]))
    pts = np.array([[g.x, g.y, g.z] for g in gcps])
    ground = float(np.median(pts[:, 2]))
    cands: dict[str, list[Candidate]] = {g.id: [] for g in gcps}
    ratio, yaw, pitch, height = {}, {}, {}, {}
    for k, info in enumerate(infos):
        ratio[info.name] = focal_ratio(info, cfg.sensor_width_mm, cfg.focal_length_mm)
        yaw[info.name] = image_yaw(info, cfg, track[k])
        pitch[info.name] = info.pitch if info.pitch is not None else -90.0
        cam_z, hs = camera_heights(info, cfg, pts, ground)
        for g, z in zip(gcps, cam_z):
            height[(g.id, info.name)] = float(z - g.z)
        if not 0 < float(np.median(cam_z - pts[:, 2])) < 2000:
            notes.append(
                f"{info.name}: the camera is {float(np.median(cam_z - pts[:, 2])):.0f} m above the GCPs "
                f"({hs} height); check 'height_source' and 'altitude_offset_m'"
            )
        uv = predict_pixels(info, ratio[info.name], yaw[info.name], pitch[info.name], cam_z, pts)
        ok, dist = _in_view(info, uv, cam_z - pts[:, 2], cfg)
        for gi in np.flatnonzero(ok):
            cands[gcps[gi].id].append(
                Candidate(gcps[gi].id, info.name, float(uv[gi, 0]), float(uv[gi, 1]), float(dist[gi]))
            )
    _rank(cands, cfg.max_images_per_gcp)
    unseen = [gid for gid, lst in cands.items() if not lst]
    if len(unseen) == len(gcps):
        heights = next((f"; {n}" for n in notes if "above the GCPs" in n), "")
        raise InputError(
            f"none of the {len(gcps)} GCPs falls inside any of the {len(infos)} images{heights}",
            path=cfg.survey,
            fix="check 'survey_crs' (x = easting/longitude, y = northing/latitude) and that the survey "
            "belongs to this flight; or raise 'max_center_distance'",
        )
    for note in notes:
        log.warning("%s", note)
    if unseen:
        log.warning(
            "%d of %d GCPs fall outside every image and get no candidates (check their coordinates): %s",
            len(unseen),
            len(gcps),
            ", ".join(unseen),
        )
    return Finder(
        {g.id: g for g in gcps},
        crs,
        {i.name: i for i in infos},
        cands,
        ratio,
        yaw,
        pitch,
        height,
        {p.name for p in files},
    )


def _read_flight(cfg: GcpFinderConfig) -> tuple[list[Path], list[ImageInfo], list[str]]:
    """``(every image file, the images with a GPS position, notes)``: each image's EXIF read; damaged images or
    none with a position are an error."""
    infos, skipped, damaged = [], [], []
    files = list_images(
        cfg.images, EXIF_SUFFIXES, key="images", fix="point 'images' at the folder of the flight's images"
    )
    for p in progress(files, desc="reading EXIF", unit="img"):
        try:
            info = read_image_info(p)
        except InputError as exc:
            damaged.append(f"{p.name}: {exc.problem}")
            continue
        (infos if info.lat is not None else skipped).append(info)
    if damaged:
        more = f" (and {len(damaged) - 5} more)" if len(damaged) > 5 else ""
        raise InputError(
            f"{len(damaged)} damaged image(s) in the flight's folder: {'; '.join(damaged[:5])}{more}",
            path=cfg.images,
            fix="copy those images again from the camera's card, or move them out of the folder",
        )
    if not infos:
        raise InputError(
            f"none of the {len(skipped)} images has a GPS position in its EXIF",
            path=cfg.images,
            fix="write the positions with module 0 (gps_embeder) first, and point 'images' at its "
            "output images/ folder",
        )
    notes = []  # warnings, printed once no error can follow
    if skipped:
        notes.append(
            f"{len(skipped)} of {len(files)} images have no GPS position in EXIF and are skipped "
            f"(e.g. {skipped[0].name}); module 0 writes it"
        )
    return files, infos, notes


def _in_view(info: ImageInfo, uv: np.ndarray, above: np.ndarray, cfg: GcpFinderConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(whether each GCP's predicted pixel is a usable candidate, its distance from the image centre as a share of
    the half-diagonal)``: inside the edge margin, near enough the centre, and below the camera (``above``: the
    camera's height above each GCP)."""
    m = cfg.edge_margin_px
    cx, cy = (info.width - 1) / 2.0, (info.height - 1) / 2.0
    dist = np.hypot(uv[:, 0] - cx, uv[:, 1] - cy) / math.hypot(cx, cy)
    ok = (
        (uv[:, 0] >= m)
        & (uv[:, 0] <= info.width - 1 - m)
        & (uv[:, 1] >= m)
        & (uv[:, 1] <= info.height - 1 - m)
        & (dist <= cfg.max_center_distance)
        & (above > 0)
    )
    return ok, dist


def _rank(cands: dict[str, list[Candidate]], cap: int) -> None:
    """Each GCP's candidates nearest the image centre first, ranked from 1, at most ``cap`` of them (0: all)."""
    for lst in cands.values():
        lst.sort(key=lambda c: c.center_distance)
        if cap:
            del lst[cap:]
        for r, c in enumerate(lst, start=1):
            c.rank = r


def write_candidates(path: Path, finder: Finder) -> Path:
    """``candidates.csv``: each GCP's candidate images, best first, to mark without the GUI if need be."""
    with atomic_open(path, "w") as fh:
        w = csv.writer(fh)
        w.writerow(["gcp", "rank", "image", "u_pred", "v_pred", "center_distance"])
        for lst in finder.candidates.values():
            for c in lst:
                w.writerow([c.gcp, c.rank, c.image, f"{c.u:.1f}", f"{c.v:.1f}", f"{c.center_distance:.3f}"])
    return path


def plot_candidates(path: Path, finder: Finder) -> Path:
    """Overview figure: image footprints, camera track and GCPs with their number of candidate images."""
    fig = figure(headless=True, figsize=(8, 7), dpi=100)
    ax = fig.add_subplot()
    ground = float(np.median([g.z for g in finder.gcps.values()]))
    for name, info in finder.images.items():
        h = (info.alt if info.alt is not None else ground) - ground
        if h > 0:
            fp = footprint(info, finder.ratio[name], finder.yaw[name], finder.pitch[name], h)
            ax.add_patch(Polygon(fp, closed=True, fill=False, lw=0.5, color="0.6"))
    cams = np.array([i.xyz[:2] for i in finder.images.values()])
    ax.plot(cams[:, 0], cams[:, 1], ".-", color="tab:blue", lw=0.6, ms=3, label="camera positions")
    for gid, g in finder.gcps.items():
        n = len(finder.candidates[gid])
        ax.plot(g.x, g.y, "s", color="tab:green" if n >= MIN_IMAGES_PER_GCP else "tab:red", ms=7)
        ax.annotate(f"{gid} ({n})", (g.x, g.y), xytext=(4, 4), textcoords="offset points", fontsize=8)
    ax.set_aspect("equal")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("GCPs (number of candidate images) and image footprints")
    ax.legend(loc="best", fontsize=8)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
