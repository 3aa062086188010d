"""Module 1: find the images that see each ground control point, mark them, write ODM's ``gcp_list.txt``.

1. Read each image's metadata once (:mod:`.metadata`): size, EXIF focal length and GPS, and DJI XMP
   (relative altitude, gimbal/flight yaw, gimbal pitch) when present.
2. Read the GCP survey (:mod:`.survey`: ``id,x,y,z`` in a stated CRS, lon/lat or projected) and convert
   it to the output CRS (a metric one: the survey's own, or the GCPs' UTM zone).
3. Predict where each GCP appears in each image (:mod:`.pose`): a pinhole camera at the GPS position,
   rotated by yaw and pitch, at its height above the GCP; the sensor width comes from a built-in table
   of common drone cameras or the config. An image is a candidate for a GCP when the prediction lies
   inside it and within ``max_center_distance`` of its centre; candidates are ranked by that distance
   (the centre has the least distortion and relief error) (:mod:`.candidates`).
4. Mark the exact pixel in the GUI (:mod:`.gui`, marks kept by :mod:`.marks`) or let ``auto`` find the
   target (a black-and-white square) near each prediction to sub-pixel precision (:mod:`.target`).
5. Write ``gcp_list.txt`` (:mod:`matchplant.core.formats.gcp_list`): line 1 the CRS, then
   ``geo_x geo_y geo_z im_x im_y image_name gcp_name`` with pixel coordinates in the original image
   (the centre of the first pixel is 0, 0). ODM wants every GCP in at least 3 images. With ``formats``,
   the same marks for Pix4D and Metashape too (:mod:`matchplant.core.formats.gcp_marks`).

This module is the orchestration: the candidates' CSV and figure, and ``auto`` marking.
"""

from __future__ import annotations

from pathlib import Path

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.guard import check_outputs, staged_outputs
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.gcp_finder.candidates import Candidate, Finder, find_candidates, plot_candidates, write_candidates
from matchplant.gcp_finder.config import GcpFinderConfig
from matchplant.gcp_finder.marks import MarkStore, store_for
from matchplant.gcp_finder.target import load_gray, locate_target

log = get_logger("gcp_finder")


def auto_mark(finder: Finder, store: MarkStore, cfg: GcpFinderConfig) -> int:
    """Detect every GCP's target near its predicted pixel in each candidate image; returns the count."""
    by_image: dict[str, list[Candidate]] = {}
    for lst in finder.candidates.values():
        for c in lst:
            by_image.setdefault(c.image, []).append(c)
    found = 0
    for image, cs in progress(sorted(by_image.items()), desc="finding targets", unit="img"):
        info = finder.images[image]
        gray = load_gray(info.path)
        for c in cs:
            uv = locate_target(
                gray, c.u, c.v, cfg.target_size_m / finder.gsd(c.gcp, image), cfg.search_radius_px, cfg.target_pattern
            )
            if uv is None:
                log.info("%s: no target found near (%.0f, %.0f) in %s", c.gcp, c.u, c.v, image)
                continue
            store.set(c.gcp, image, uv[0], uv[1], record=False)
            found += 1
    return found


def run(cfg: GcpFinderConfig) -> Finder:
    """Module 1 without the GUI: each GCP's candidate images (CSV and figure); with ``auto``, gcp_list.txt too.

    ``auto`` detects each GCP's target near its predicted pixel in every candidate image. Everything is computed
    before anything is written, and the files are written into a temporary folder moved into ``output_dir`` at
    the end, so a failed run leaves no half set of outputs.

    Parameters
    ----------
    cfg : GcpFinderConfig
        The step's settings, as loaded from its YAML config (``1_gcp_finder/config.yaml``) or built in Python.

    Returns
    -------
    Finder
        The GCPs, the images' metadata and each GCP's ranked candidate images (what the GUI opens).
    """
    out = Path(cfg.output_dir)
    check_outputs(cfg)
    finder = find_candidates(cfg)
    for gid, lst in finder.candidates.items():
        log.info("%s: %d candidate images%s", gid, len(lst), f" (best: {lst[0].image})" if lst else "")
    store = store_for(cfg, finder, autosave=False)
    if cfg.auto:
        n = auto_mark(finder, store, cfg)
        if not store.marks:
            raise InputError(
                f"auto: no GCP target was found in any of the {sum(map(len, finder.candidates.values()))}"
                " candidate images, so gcp_list.txt would be empty",
                path=cfg.images,
                fix="check 'target_pattern' and 'target_size_m' (the target's look and size), or mark "
                "the GCPs by hand with --gui",
            )
    with staged_outputs(out) as stage:
        write_candidates(stage / "candidates.csv", finder)
        plot_candidates(stage / "candidates.png", finder)
        if cfg.auto or store.continued:  # a continued list is written back without the lines it dropped
            store.path = stage / "gcp_list.txt"
            store.save()
            store.path = out / "gcp_list.txt"
    log.info("candidates: %s", out / "candidates.csv")
    if cfg.auto:
        store.warn_few()
        log.info("found %d targets; wrote %s (review it with --gui)", n, store.path)
    else:
        log.info(
            "mark the GCPs with --gui (or run with --set auto=true)%s",
            f"; {store.path} continues {store.continued}" if store.continued else "",
        )
    return finder
