"""Is a split-merge project whole? (docs/DESIGN.md §6)

A submodel folder without a reconstruction (its node failed, or its results were never copied back) and a
submodel copied from another run (its frame elsewhere: its ``reference_lla`` far from the others, the images
it shares with its neighbours placed metres away) would otherwise be skipped or mixed in silently: modules 3
and 8 would run on what is left, exit 0. :func:`split_problems` names each such submodel; modules 3 and 8
stop on them (:func:`check_split`), module 2's output check reports them.
"""

from __future__ import annotations

import numpy as np
import rasterio
from pyproj import Geod, Transformer

from matchplant.core.formats.odm import OUTPUTS, SUBMODELS_DIR, ODMProject
from matchplant.core.runtime.errors import InputError, MatchPlantError
from matchplant.core.runtime.log import get_logger

log = get_logger("odm")

FAR_REFERENCE_M = 1000.0  # a submodel's reference_lla farther than this (and than the field) from the others'
SHARED_TOLERANCE_M = 5.0  # images two submodels share, placed farther apart than this: not one run's frames
GEOD = Geod(ellps="WGS84")


def split_problems(project: ODMProject) -> list[str]:
    """Every reason the submodels of a split-merge project cannot be read as one run (empty: whole)."""
    folder = project.root / SUBMODELS_DIR
    if not folder.is_dir():
        return []
    problems = []
    for p in sorted(folder.iterdir()):
        if (
            p.is_dir()
            and p.name.startswith("submodel_")
            and not any((p / OUTPUTS[n].relpath).is_file() for n in ("reconstruction", "undistorted_reconstruction"))
        ):
            problems.append(
                f"{SUBMODELS_DIR}/{p.name} has no {OUTPUTS['reconstruction'].relpath} (its node failed "
                f"or its results were not copied back): that part of the field would be missing"
            )
    if len(project.submodels) > 1:
        try:
            problems += _frame_problems(project)
        except MatchPlantError as exc:  # an unreadable submodel: said by the steps that read it
            log.debug("split frame check skipped: %s", exc.problem)
    return problems


def check_split(project: ODMProject) -> None:
    """An error naming every incomplete or foreign submodel of a split-merge project (nothing when whole)."""
    problems = split_problems(project)
    if problems:
        raise InputError(
            "the split-merge project is not whole: " + "; ".join(problems),
            path=project.root / SUBMODELS_DIR,
            fix="copy the missing or foreign submodel's results of THIS run back (ClusterODM: check that "
            "node's log, or re-run ODM with --split), or move that submodel folder out of "
            "submodels/ to process the field without its part",
        )


def _shots(sub: ODMProject) -> dict:
    for name in ("undistorted_reconstruction", "reconstruction"):
        if sub.has(name):
            return sub._read(name).shots
    return {}


def _frame_problems(project: ODMProject) -> list[str]:
    subs = project.submodels
    crs = project.frame().crs
    refs = []
    for sub in subs:
        rec = sub._read("reconstruction" if sub.has("reconstruction") else "undistorted_reconstruction")
        ref = rec.reference_lla or {}
        refs.append((ref.get("longitude"), ref.get("latitude")) if ref else None)
    placed = []
    for sub in subs:
        shots = _shots(sub)
        ids = sorted(shots)
        centres = sub.frame(crs).to_map(np.array([shots[i].center for i in ids]))[:, :2] if ids else np.zeros((0, 2))
        placed.append(dict(zip(ids, centres)))
    problems = []
    far = set()
    known = [k for k, r in enumerate(refs) if r is not None]
    anchor = _merged_centre(project)
    for k in known:
        others = [refs[j] for j in known if j != k]
        if anchor is not None:
            (lon, lat), span, what = anchor[:2], anchor[2], "the merged outputs' centre"
        elif len(others) >= 2:
            (lon, lat), what = np.median(np.array(others, float), axis=0), "the other submodels'"
            span = _span([d for j, d in enumerate(placed) if j != k])
        else:
            continue
        _, _, dist = GEOD.inv(refs[k][0], refs[k][1], lon, lat)
        if dist > max(FAR_REFERENCE_M, 2 * span):
            far.add(k)
            problems.append(
                f"{SUBMODELS_DIR}/{subs[k].name}: its reference_lla ({refs[k][1]:.6f}, {refs[k][0]:.6f}) "
                f"is {dist / 1000:.1f} km from {what} (a field {span:.0f} m across): copied from "
                "another run?"
            )
    for p in range(len(subs)):
        for q in range(p + 1, len(subs)):
            shared = sorted(set(placed[p]) & set(placed[q]))
            if not shared or p in far or q in far:
                continue
            gap = float(np.median([np.hypot(*(placed[p][s] - placed[q][s])) for s in shared]))
            if gap > SHARED_TOLERANCE_M:
                problems.append(
                    f"{SUBMODELS_DIR}/{subs[p].name} and {subs[q].name} place the {len(shared)} images they "
                    f"share (e.g. {shared[0]}) {gap:.1f} m apart (ODM aligns them to centimetres): one of "
                    "them is from another run"
                )
    return problems


def _merged_centre(project: ODMProject) -> tuple[float, float, float] | None:
    """(longitude, latitude, diagonal in metres) of the merged DSM or orthophoto at the top; None without one."""
    for name in ("dsm", "orthophoto"):
        path = project.root / OUTPUTS[name].relpath
        if not path.is_file():
            continue
        try:
            with rasterio.open(path) as src:
                if src.crs is None:
                    continue
                b = src.bounds
                to_ll = Transformer.from_crs(src.crs, "EPSG:4326", always_xy=True)
                lon, lat = to_ll.transform((b.left + b.right) / 2, (b.bottom + b.top) / 2)
                diagonal = float(np.hypot(b.right - b.left, b.top - b.bottom)) if src.crs.is_projected else 0.0
                return float(lon), float(lat), diagonal
        except Exception as exc:  # noqa: BLE001 - an unreadable raster is reported by the steps that read it
            log.debug("split check: %s unreadable (%s)", path, exc)
    return None


def _span(placed: list[dict]) -> float:
    """The field's size: the diagonal of every submodel's camera positions (metres, map CRS)."""
    xy = np.array([c for d in placed for c in d.values()], float).reshape(-1, 2)
    return float(np.hypot(*(xy.max(axis=0) - xy.min(axis=0)))) if len(xy) else 0.0


__all__ = ["check_split", "split_problems"]
