"""The GCP survey: a table ``id,x,y,z`` in a stated CRS, converted to the metric CRS of gcp_list.txt."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pyproj import CRS, Transformer

from matchplant.core.geometry.frames import parse_crs, utm_crs_for
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.validate import check_coordinates, read_csv


@dataclass
class GCP:
    """A surveyed ground control point, in the output CRS."""

    id: str
    x: float  # output CRS
    y: float
    z: float


_ALIASES = {
    "id": ("name", "gcp", "gcp_id", "label", "point", "point_name", "gcp_name"),
    "x": ("lon", "longitude", "long", "lng", "easting", "east", "e"),
    "y": ("lat", "latitude", "northing", "north", "n"),
    "z": ("elevation", "elev", "alt", "altitude", "height", "h", "ellh"),
}


def read_survey(path: str | Path, crs_text: str, output_crs=None) -> tuple[list[GCP], object]:
    """GCP table ``id,x,y,z`` in ``crs_text``; returns the GCPs in the output CRS and that CRS.

    The output CRS is ``output_crs`` if given, else the survey's own CRS when projected, else the UTM
    zone of the GCPs (ODM wants metres). Every value is checked against the CRS's units (degrees or
    metres) before it is used, and every error names the survey's line.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("GCP survey file not found", path=path, fix="set 'survey' to the GCP table (id,x,y,z)")
    if not crs_text:
        raise ConfigError(
            "the GCP survey's CRS is not set",
            path=path,
            fix="set 'survey_crs' to its EPSG code, e.g. EPSG:32614 (UTM 14N) or EPSG:4326 (lon/lat)",
        )
    src = parse_crs(crs_text, source=path, key="survey_crs")
    table = read_csv(path, required=("id",), numeric=("x", "y", "z"), aliases=_ALIASES, what="GCP survey")
    ids = [i.strip() for i in table.column("id")]
    for i, gid in enumerate(ids):
        if not gid or any(c.isspace() for c in gid):
            raise InputError(
                f"GCP survey, line {table.lines[i]}: the id {gid!r} is empty or contains spaces "
                "(gcp_list.txt is separated by spaces)",
                path=path,
                fix="give every GCP a one-word id, e.g. GCP01",
            )
    seen: dict[str, int] = {}
    for gid, line in zip(ids, table.lines):
        if gid in seen:
            raise InputError(
                f"GCP survey: the id '{gid}' is on lines {seen[gid]} and {line}",
                path=path,
                fix="give each GCP its own id (or delete the repeated line)",
            )
        seen[gid] = line
    pts = np.stack([table.numbers[k] for k in ("x", "y", "z")], axis=-1)
    check_coordinates(
        pts[:, 0],
        pts[:, 1],
        geographic=src.is_geographic,
        what="GCP survey x, y",
        path=path,
        lines=table.lines,
        fix=f"check 'survey_crs' (now {crs_text}): EPSG:4326 for lon/lat degrees, the projected "
        "CRS (e.g. EPSG:32614) for metres; x is the easting or longitude",
    )
    if output_crs is not None:
        dst = parse_crs(output_crs, source=path, key="output_crs")
        if not dst.is_projected:
            raise ConfigError(
                f"config key 'output_crs' = {output_crs!s} is not a projected CRS: gcp_list.txt and "
                "the camera model work in metres",
                fix="leave 'output_crs' empty (the survey's CRS or its UTM zone), or give a UTM EPSG code",
            )
    elif src.is_projected:
        dst = src
    else:
        lonlat = Transformer.from_crs(src, CRS.from_epsg(4326), always_xy=True).transform(
            pts[:, 0].mean(), pts[:, 1].mean()
        )
        dst = utm_crs_for(*lonlat)
    if not dst.equals(src):
        x, y = Transformer.from_crs(src, dst, always_xy=True).transform(pts[:, 0], pts[:, 1])
        pts = np.stack([x, y, pts[:, 2]], axis=-1)
    if not np.all(np.isfinite(pts)):
        raise InputError(
            "some GCPs cannot be converted to the output CRS",
            path=path,
            fix="check 'survey_crs' and 'output_crs' (x = easting or longitude, y = northing or latitude)",
        )
    return [GCP(i, *p) for i, p in zip(ids, pts)], dst
