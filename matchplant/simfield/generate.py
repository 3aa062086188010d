"""Build the field, fly it, render the images and write the ODM-shaped project with its truth."""

from __future__ import annotations

import datetime as dt
import io
import multiprocessing as mp
import os
import signal
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image
from pyproj import CRS, Transformer

from matchplant.core.formats.coco import make_annotation, new_dataset, write_dataset
from matchplant.core.formats.reconstruction import Reconstruction, write_reconstruction
from matchplant.core.geometry.frames import OffsetFrame, TopocentricFrame, utm_crs_for, write_coords_txt
from matchplant.core.geometry.shot import Shot
from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.io import write_json, write_text
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.simfield.config import SITE_LAT, SITE_LON, Settings, SimFieldConfig, resolve
from matchplant.simfield.field_files import write_csv, write_plants, write_plot_truth, write_rasters
from matchplant.simfield.flight import (
    SENSOR_WIDTH_MM,
    SHOT_INTERVAL_S,
    TURN_S,
    Exposure,
    footprint,
    gps_time_of_week,
    make_camera,
    plan_flight,
    render,
)
from matchplant.simfield.layout import FieldPaths
from matchplant.simfield.noise import (
    BAND_ORDER,
    REALISTIC,
    antialiased_mask,
    mask_objects,
)
from matchplant.simfield.photo_files import (
    CAMERA_MAKE,
    camera_model,
    encode,
    with_exif,
    write_bytes,
    write_image,
    write_mask,
)
from matchplant.simfield.scene import GCP_SIZE, Grid, Plants, Rasters, Terrain, make_gcps, make_plants, rasterize
from matchplant.simfield.traits import grow, vigour
from matchplant.simfield.truth import candidates_near, image_boxes

log = get_logger("simfield")


def generate(cfg: SimFieldConfig) -> FieldPaths:
    """Write the synthetic field a config describes: rasters, images, reconstruction, GNSS log, GCPs and truth.

    The one function of the library over 100 lines (tests/test_layers.py names it). The plan for it: cut it along
    its five sections into parts over one record of the field (settings, frame, terrain, GCPs, plants, grid,
    rasters and the six random streams, drawn here in this order): the field; the images with their per-image
    truth; the ODM outputs; modules 0 and 1's inputs; the truth. Each part takes the record and the streams it
    uses, so no part draws from another's stream; the check is that a field of every preset and seed stays the
    same file for file (only ``elapsed_s`` in truth/field.json differs), as the split of :func:`rasterize` was
    checked.
    """
    t0 = time.perf_counter()
    s = resolve(cfg)
    paths = FieldPaths(Path(cfg.output_dir))
    if paths.root.exists() and not paths.root.is_dir():
        raise ConfigError(
            "output_dir is a file, not a folder",
            path=paths.root,
            fix="choose a new or existing folder for the synthetic field",
        )
    paths.root.mkdir(parents=True, exist_ok=True)
    streams = np.random.SeedSequence(cfg.seed).spawn(6)
    rng_terrain, rng_gcp, rng_plants, rng_flight, rng_raster, rng_noise = (np.random.default_rng(x) for x in streams)

    # -- the field, in the local frame (map CRS minus the integer offset) ---------------------------
    crs = utm_crs_for(SITE_LON, SITE_LAT)
    to_map = Transformer.from_crs(CRS.from_epsg(4326), crs, always_xy=True)
    e0, n0 = to_map.transform(SITE_LON, SITE_LAT)
    offset = np.array([np.floor(e0), np.floor(n0), 0.0])
    ref_lon, ref_lat = to_map.transform(offset[0], offset[1], direction="INVERSE")
    frame = OffsetFrame(crs=crs, offset=offset)

    terrain = Terrain.random(s, rng_terrain)
    gcps = make_gcps(s, terrain, rng_gcp)
    plants = make_plants(s, terrain, rng_plants, gcps)
    if cfg.vigour:  # a stream of its own: every other output stays as without vigour
        plants.ndvi = vigour(len(plants), np.random.default_rng([cfg.seed, 1901]))
    camera = make_camera(s)
    ucamera = camera.undistorted()
    exposures = plan_flight(s, terrain, camera, rng_flight)

    # rasters cover every ray of every image: a ray meets the canopy between the camera and its ground
    # footprint, so the footprints (plus a small margin) are enough
    feet = np.array(
        [footprint(e.shot, terrain) for e in exposures]
        + [footprint(e.shot.with_camera(ucamera), terrain) for e in exposures]
    )
    margin = 0.1
    area = (
        min(feet[:, 0].min(), 0) - margin,
        min(feet[:, 1].min(), 0) - margin,
        max(feet[:, 2].max(), s.field_width) + margin,
        max(feet[:, 3].max(), s.field_length) + margin,
    )
    grid = Grid.covering(*area, s.raster_res)
    rasters = rasterize(s, grid, plants, gcps, rng_raster)
    log.info(
        "field: %d plants, %d GCPs, %d images of %dx%d px, GSD %.2f cm, rasters %dx%d at %.1f mm",
        len(plants),
        len(gcps),
        len(exposures),
        camera.width,
        camera.height,
        100 * s.gsd,
        grid.width,
        grid.height,
        1000 * s.raster_res,
    )

    # -- images and per-image truth ------------------------------------------------------------------
    top = s.height_max + 0.01
    step = max(s.raster_res, s.gsd)
    reach = s.height_max * 1.5 + float(plants.radius().max()) if len(plants) else 1.0
    clock_offset = float(np.round(rng_noise.uniform(-4.0, 4.0), 3))
    raw_ds = new_dataset(
        ["plant"],
        {"description": f"MatchPlant synthetic field ({cfg.preset}, seed {cfg.seed}): every plant in every raw image"},
    )
    und_ds = new_dataset(
        ["plant"],
        {
            "description": f"MatchPlant synthetic field ({cfg.preset}, seed {cfg.seed}): "
            "every plant in every undistorted image"
        },
    )
    gcp_rows = []
    image_info = []
    lla = Transformer.from_crs(crs, CRS.from_epsg(4326), always_xy=True)
    noise_streams = streams[5].spawn(len(exposures) * 2)
    for e in exposures:
        cam_time = e.utc + dt.timedelta(seconds=clock_offset)
        centre_map = frame.to_map(e.shot.center[None, :])[0]
        lon, lat = lla.transform(centre_map[0], centre_map[1])
        uv = e.shot.project(frame.from_map(gcps + offset))
        for g, (u, v) in enumerate(uv):
            if np.isfinite(u) and camera.in_image(np.array([u, v])):
                gcp_rows.append([f"GCP{g + 1:02d}", e.name, f"{u:.3f}", f"{v:.3f}"])
        week, tow = gps_time_of_week(e.utc)
        image_info.append(
            {
                "name": e.name,
                "line": e.line,
                "utc": e.utc.isoformat(),
                "camera_time": cam_time.replace(tzinfo=None).isoformat(timespec="milliseconds"),
                "gps_week": week,
                "gps_tow": round(tow, 3),
                "center": [float(v) for v in centre_map],
                "lat": lat,
                "lon": lon,
            }
        )
    jobs = [
        ImageJob(
            e,
            e.shot.with_camera(ucamera),
            noise_streams[2 * k],
            noise_streams[2 * k + 1],
            dt.datetime.fromisoformat(info["camera_time"]),
            (info["lat"], info["lon"], info["center"][2]),
        )
        for k, (e, info) in enumerate(zip(exposures, image_info))
    ]
    realistic = cfg.noise == "realistic"
    scene = Scene(s, paths, terrain, rasters, plants, plants.surface_offsets(terrain), top, step, reach, realistic)
    objects = []
    for k, (raw_boxes, und_boxes, mask_truth) in enumerate(
        progress(_run_jobs(scene, jobs, _workers(cfg)), total=len(jobs), desc="rendering images", unit="image")
    ):
        e = exposures[k]
        if mask_truth is not None:
            objects.append([e.name, *mask_truth])
        for ds, boxes, undist in ((raw_ds, raw_boxes, False), (und_ds, und_boxes, True)):
            cam = ucamera if undist else camera
            entry = {
                "id": k + 1,
                "file_name": e.name + (".tif" if undist else ""),
                "width": cam.width,
                "height": cam.height,
            }
            if undist:
                entry["shot_id"] = e.name
            ds["images"].append(entry)
            for b, i, c, px in boxes:
                # the box is the whole plant (occluded parts included); visible_px counts its rendered pixels
                ds["annotations"].append(
                    make_annotation(
                        len(ds["annotations"]) + 1,
                        k + 1,
                        [b[0], b[1], b[2] - b[0], b[3] - b[1]],
                        plant_id=int(i + 1),
                        truncated=bool(c),
                        visible_px=px,
                    )
                )

    # -- ODM outputs ---------------------------------------------------------------------------------
    write_coords_txt(paths.coords, crs, offset)
    reference = {"latitude": ref_lat, "longitude": ref_lon, "altitude": 0.0}
    topo = TopocentricFrame(ref_lat, ref_lon, terrain.z0, crs)
    sparse = _sparse_points(grid, rasters, terrain, rng_flight)
    shots = {}
    topo_shots = {}
    for e, info in zip(exposures, image_info):
        epoch = dt.datetime.fromisoformat(info["camera_time"]).replace(tzinfo=dt.timezone.utc).timestamp()
        c_topo = topo.from_map(np.array(info["center"])[None, :])[0]
        gps = [float(v) for v in c_topo]  # ODM leaves gps_position unconverted (topocentric)
        shots[e.name] = Shot(
            id=e.name,
            camera=camera,
            rotation=e.shot.rotation,
            translation=e.shot.translation,
            capture_time=epoch,
            gps_position=tuple(gps),
            extra={"gps_dop": 0.05},
        )
        Q = _map_to_topo_rotation(topo, c_topo)
        topo_shots[e.name] = Shot.from_center(
            e.name, camera, e.shot.R @ Q, c_topo, capture_time=epoch, gps_position=tuple(gps), extra={"gps_dop": 0.05}
        )
    ids = [str(i) for i in range(len(sparse))]
    rec = Reconstruction(
        cameras={camera.id: camera}, shots=shots, point_ids=ids, points=sparse, reference_lla=reference
    )
    write_reconstruction(paths.reconstruction, rec)
    urec = Reconstruction(
        cameras={camera.id: ucamera},
        shots={k: v.with_camera(ucamera) for k, v in shots.items()},
        point_ids=ids,
        points=sparse,
        reference_lla=reference,
    )
    write_reconstruction(paths.undistorted_reconstruction, urec)
    trec = Reconstruction(
        cameras={camera.id: camera},
        shots=topo_shots,
        point_ids=ids,
        points=topo.from_map(sparse + offset),
        reference_lla={"latitude": ref_lat, "longitude": ref_lon, "altitude": terrain.z0},
    )
    write_reconstruction(paths.topocentric_reconstruction, trec)
    # the noise has streams of its own: an exact and a realistic field of one seed share everything else
    noise = write_rasters(
        paths, grid, rasters, terrain, offset, crs, np.random.default_rng([cfg.seed, 1904]) if realistic else None
    )

    # -- inputs of modules 0 and 1 -------------------------------------------------------------------
    lines = ["Timestamp\tX\tY\tZ"] + [
        f"{i['gps_tow']:.3f}\t{i['center'][0]:.4f}\t{i['center'][1]:.4f}\t{i['center'][2]:.4f}" for i in image_info
    ]
    write_text(paths.gnss_log, "\n".join(lines) + "\n")
    gmap = gcps + offset
    write_csv(
        paths.gcp_survey,
        ["id", "x", "y", "z"],
        [[f"GCP{g + 1:02d}", f"{x:.4f}", f"{y:.4f}", f"{z:.4f}"] for g, (x, y, z) in enumerate(gmap)],
    )

    # -- truth ---------------------------------------------------------------------------------------
    write_plants(paths, plants, rasters, s.raster_res, offset)
    write_plot_truth(paths, s, plants, offset, f"EPSG:{crs.to_epsg()}")
    if cfg.second_date:
        later = grow(plants, terrain, np.random.default_rng([cfg.seed, 1902]))
        rasters2 = rasterize(s, grid, later, gcps, np.random.default_rng([cfg.seed, 1903]))
        noise2 = write_rasters(
            paths.later,
            grid,
            rasters2,
            terrain,
            offset,
            crs,
            np.random.default_rng([cfg.seed, 1905]) if realistic else None,
        )
        if noise2:
            write_json(paths.later.noise_json, noise2)
        write_plants(paths.later, later, rasters2, s.raster_res, offset)
    ext = plants.extents() + np.r_[offset[:2], offset[:2]]
    write_csv(
        paths.map_boxes,
        ["id", "xmin", "ymin", "xmax", "ymax"],
        [[int(i)] + [f"{v:.4f}" for v in b] for i, b in zip(plants.ids, ext)],
    )
    write_csv(paths.gcp_pixels, ["gcp_id", "image", "u", "v"], gcp_rows)
    write_dataset(paths.boxes_raw, raw_ds)
    write_dataset(paths.boxes_undistorted, und_ds)
    week = image_info[0]["gps_week"] if image_info else 0
    field = {
        "crs": f"EPSG:{crs.to_epsg()}",
        "offset": [float(offset[0]), float(offset[1])],
        "reference_lla": reference,
        "topocentric_reference_lla": trec.reference_lla,
        "clock_offset_s": clock_offset,
        "clock_offset_meaning": "camera clock (EXIF DateTimeOriginal + SubSecTimeOriginal) minus true UTC",
        "gnss_time": f"events.txt Timestamp is GPS seconds of week {week} (GPS time = UTC + 18 s)",
        "gps_week": week,
        "gps_leap_seconds": 18,
        "gsd": s.gsd,
        "raster_res": s.raster_res,
        "preset": cfg.preset,
        "seed": cfg.seed,
        "settings": {k: getattr(s, k) for k in s.__dataclass_fields__},
        "camera": {
            "id": camera.id,
            "opensfm": camera.to_opensfm(),
            "make": CAMERA_MAKE,
            "model": camera_model(s),
            "sensor_width_mm": SENSOR_WIDTH_MM,
            "focal_mm": s.focal * SENSOR_WIDTH_MM,
        },
        "flight": {
            "altitude": s.altitude,
            "overlap_front": s.overlap_front,
            "overlap_side": s.overlap_side,
            "tilt_deg": s.tilt_deg,
            "attitude_noise_deg": s.attitude_noise_deg,
            "lines": int(max(e.line for e in exposures) + 1),
            "images": len(exposures),
            "shot_interval_s": SHOT_INTERVAL_S,
            "turn_s": TURN_S,
        },
        "images": image_info,
        "n_plants": len(plants),
        "gcps": [
            {"id": f"GCP{g + 1:02d}", "x": float(x), "y": float(y), "z": float(z), "size_m": GCP_SIZE}
            for g, (x, y, z) in enumerate(gmap)
        ],
        "labels": {"plant": "id >= 1", "soil": 0, "weed": -1, "gcp_target": -2},
        "conventions": {
            "coco_bbox": "pixel edges: the image spans [0, W] x [0, H]; camera pixel (u, v) is at (u + 0.5, v + 0.5)",
            "gcp_pixels": "camera pixels (OpenSfM/ODM gcp_list): pixel centres at integers, origin top-left",
            "plants_z": "ground height at the plant centre; the top of the plant is z + height",
            "heights": "ellipsoidal (WGS84) metres everywhere",
        },
        "elapsed_s": round(time.perf_counter() - t0, 2),
    }
    field["noise"] = cfg.noise
    field["multispectral"] = {
        "bands": list(BAND_ORDER) if realistic else ["red", "nir"],
        "gdal_color_interpretation": ["red", "green", "blue", "undefined", "undefined"]
        if realistic
        else ["gray", "undefined"],
        "band_descriptions": not realistic,
    }
    if realistic:
        write_json(
            paths.noise_json,
            {
                **noise,
                "multispectral_bands": list(BAND_ORDER),
                "masks": {
                    "folders": [
                        "truth/masks_antialiased (PNG)",
                        "truth/masks_antialiased_jpg (JPEG)",
                        "truth/masks_antialiased_gif (GIF)",
                    ],
                    "of": "undistorted images",
                    "truth": "truth/mask_objects.csv",
                },
            },
        )
        write_csv(paths.mask_objects, ["image", "plants", "parts", "pixels"], objects)
    write_json(paths.field_json, field)
    _remove_stale(paths, {e.name for e in exposures}, realistic)
    log.info("synthetic field written to %s in %.1f s", paths.root, time.perf_counter() - t0)
    return paths


# -- rendering, one image at a time (in worker processes when asked) --------------------------------


@dataclass
class Scene:
    """Everything a worker needs to render images: settings, paths, terrain, rasters, plants and ray-casting limits."""

    s: Settings
    paths: FieldPaths
    terrain: Terrain
    rasters: Rasters
    plants: Plants
    offsets: np.ndarray  # canopy surface points of every plant, relative to its centre
    top: float
    step: float
    reach: float
    realistic: bool = False  # noise: realistic (anti-aliased masks too)


@dataclass
class ImageJob:
    """One exposure to render: raw and undistorted shots, their noise seeds, camera time and GPS fix."""

    exposure: Exposure
    ushot: Shot
    noise_raw: np.random.SeedSequence
    noise_und: np.random.SeedSequence
    cam_time: dt.datetime
    gps: tuple


_SCENE: Scene | None = None


def _init_worker(scene: Scene, worker: bool = False) -> None:
    global _SCENE
    _SCENE = scene
    if worker:  # Ctrl-C is the parent's to report (one line); workers just stop with it
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _render_job(job: ImageJob) -> tuple[list, list, tuple | None]:
    """Render, write and box one exposure (raw and undistorted); returns the boxes of both and, for a
    realistic field, the truth of its anti-aliased mask."""
    sc = _SCENE
    out = []
    objects = None
    for shot, seed, undist in ((job.exposure.shot, job.noise_raw, False), (job.ushot, job.noise_und, True)):
        rgb, ids = render(shot, sc.terrain, sc.rasters, sc.top, sc.step)
        noise = np.random.default_rng(seed).normal(0, 1.5, rgb.shape)
        rgb = np.clip(rgb + noise, 0, 255).astype(np.uint8)
        name = job.exposure.name
        if undist:
            write_image(sc.paths.undistorted_images / f"{name}.tif", rgb, ".tif")
            write_mask(sc.paths.masks_undistorted / f"{name}.png", ids)
            if sc.realistic:
                objects = mask_objects(ids)
                _write_antialiased(sc.paths, name, antialiased_mask(ids))
        else:
            jpeg = encode(rgb, ".jpg", sc.s.jpeg_quality)
            write_bytes(sc.paths.images / name, with_exif(jpeg, sc.s, job.cam_time, job.gps))
            write_bytes(sc.paths.images_nogps / name, with_exif(jpeg, sc.s, job.cam_time, None))
            write_mask(sc.paths.masks_raw / f"{name}.png", ids)
        foot = footprint(shot, sc.terrain)
        boxes, which, cut = image_boxes(
            shot, sc.plants, sc.terrain, candidates_near(sc.plants, foot, sc.reach), sc.offsets
        )
        seen_px = np.bincount(ids.ravel(), minlength=len(sc.plants) + 1)  # rendered pixels per plant id
        out.append([(b.tolist(), int(i), bool(c), int(seen_px[i + 1])) for b, i, c in zip(boxes, which, cut)])
    return out[0], out[1], objects


def _write_antialiased(paths: FieldPaths, name: str, mask: np.ndarray) -> None:
    """One binary mask with smooth edges as PNG, JPEG (its artefacts too) and GIF."""
    write_bytes(paths.masks_antialiased / f"{name}.png", cv2.imencode(".png", mask)[1].tobytes())
    write_bytes(
        paths.masks_antialiased_jpg / f"{name}.jpg",
        cv2.imencode(".jpg", mask, [cv2.IMWRITE_JPEG_QUALITY, REALISTIC.mask_jpeg_quality])[1].tobytes(),
    )
    buf = io.BytesIO()
    Image.fromarray(mask, "L").save(buf, format="GIF")
    write_bytes(paths.masks_antialiased_gif / f"{name}.gif", buf.getvalue())


def _workers(cfg: SimFieldConfig) -> int:
    if cfg.workers is not None:
        return cfg.workers
    return 1 if cfg.preset == "tiny" else 0


def _run_jobs(scene: Scene, jobs: list[ImageJob], workers: int):
    """Results in job order; ``workers`` processes (0: one per CPU core, at most 8)."""
    n = min(workers or min(os.cpu_count() or 1, 8), len(jobs))
    if n <= 1:
        _init_worker(scene)
        try:
            for job in jobs:
                yield _render_job(job)
        finally:
            _init_worker(None)
        return
    # fork shares the field's rasters with the workers without copying them; elsewhere they are pickled once
    context = mp.get_context("fork" if sys.platform.startswith("linux") else "spawn")
    with ProcessPoolExecutor(n, mp_context=context, initializer=_init_worker, initargs=(scene, True)) as pool:
        yield from pool.map(_render_job, jobs)


# -- helpers ------------------------------------------------------------------------------------------


def _remove_stale(paths: FieldPaths, names: set[str], realistic: bool = False) -> None:
    """Delete images of an earlier, larger run in the same folder (only files this generator names), and
    an earlier realistic run's extra truth from an exact one."""
    if not realistic:
        for f in (paths.noise_json, paths.mask_objects, paths.later.noise_json):
            f.unlink(missing_ok=True)
    noisy = (paths.masks_antialiased, paths.masks_antialiased_jpg, paths.masks_antialiased_gif)
    for folder, suffix in (
        (paths.images, ""),
        (paths.images_nogps, ""),
        (paths.undistorted_images, ".tif"),
        (paths.masks_raw, ".png"),
        (paths.masks_undistorted, ".png"),
        *zip(noisy, (".png", ".jpg", ".gif")),
    ):
        keep = names if realistic or folder not in noisy else set()
        for f in folder.glob("SIM_*"):
            if f.name.removesuffix(suffix) not in keep:
                f.unlink()


def _map_to_topo_rotation(topo: TopocentricFrame, c_topo: np.ndarray, h: float = 1.0) -> np.ndarray:
    """Rotation part (polar decomposition) of d(map)/d(topocentric) at ``c_topo``: ``R_topo = R_map @ Q``."""
    pts = c_topo[None, :] + np.concatenate([np.eye(3) * h, -np.eye(3) * h])
    m = topo.to_map(pts)
    J = ((m[:3] - m[3:]) / (2 * h)).T
    u, _, vt = np.linalg.svd(J)
    return u @ vt


def _sparse_points(grid: Grid, rasters: Rasters, terrain: Terrain, rng: np.random.Generator, n: int = 400):
    r = rng.integers(0, grid.height, n)
    c = rng.integers(0, grid.width, n)
    x = grid.x0 + (c + 0.5) * grid.res
    y = grid.y1 - (r + 0.5) * grid.res
    return np.column_stack([x, y, terrain.height(x, y) + rasters.canopy[r, c]])
