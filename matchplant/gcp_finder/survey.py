"""The GCP survey: a table ``id,x,y,z`` in a stated CRS, converted to the metric CRS of gcp_list.txt."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pyproj import CRS, Transformer

from matchplant.core.errors import ConfigError, InputError
from matchplant.core.frames import parse_crs, utm_crs_for


@dataclass
class GCP:
    """A surveyed ground control point, in the output CRS."""

    id: str
    x: float  # output CRS
    y: float
    z: float


_SURVEY_COLUMNS = {
    "id": ("id", "name", "gcp", "gcp_id", "label", "point", "point_name", "gcp_name"),
    "x": ("x", "easting", "east", "e", "lon", "long", "longitude", "lng"),
    "y": ("y", "northing", "north", "n", "lat", "latitude"),
    "z": ("z", "elevation", "elev", "alt", "altitude", "height", "h", "ellh"),
}


def read_survey(path: str | Path, crs_text: str, output_crs=None) -> tuple[list[GCP], object]:
    """GCP table ``id,x,y,z`` in ``crs_text``; returns the GCPs in the output CRS and that CRS.

    The output CRS is ``output_crs`` if given, else the survey's own CRS when projected, else the UTM
    zone of the GCPs (ODM wants metres).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("GCP survey file not found", path=path, fix="set 'survey' to the GCP table (id,x,y,z)")
    if not crs_text:
        raise ConfigError("the GCP survey's CRS is not set", path=path,
                          fix="set 'survey_crs' to its EPSG code, e.g. EPSG:32614 (UTM 14N) or EPSG:4326 (lon/lat)")
    src = parse_crs(crs_text, source=path)
    lines = [ln for ln in path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
             if ln.strip() and not ln.lstrip().startswith("#")]
    if len(lines) < 2:
        raise InputError("the GCP survey holds no points (a header line and one line per GCP are needed)",
                         path=path, fix="write it as CSV with the header id,x,y,z")
    head = lines[0]
    delim = "," if "," in head else ";" if ";" in head else "\t" if "\t" in head else None
    rows = list(csv.reader(lines, delimiter=delim)) if delim else [ln.split() for ln in lines]
    norm = [h.strip().lower() for h in rows[0]]
    cols = {}
    for key, names in _SURVEY_COLUMNS.items():
        hits = [norm.index(n) for n in names if n in norm]
        if hits:
            cols[key] = hits[0]
    # lon/lat named columns: x must be the longitude whatever the order in the file
    if "lon" in norm or "longitude" in norm:
        cols["x"] = norm.index("lon") if "lon" in norm else norm.index("longitude")
    if "lat" in norm or "latitude" in norm:
        cols["y"] = norm.index("lat") if "lat" in norm else norm.index("latitude")
    missing = [k for k in ("id", "x", "y", "z") if k not in cols]
    if missing:
        raise InputError(f"the GCP survey lacks the column(s) {', '.join(missing)} (header: {rows[0]})", path=path,
                         fix="the first line must name the columns id,x,y,z (x = easting or longitude)")
    ids, pts = [], []
    for lineno, r in enumerate(rows[1:], start=2):
        try:
            ids.append(r[cols["id"]].strip())
            pts.append([float(r[cols[k]]) for k in ("x", "y", "z")])
        except (ValueError, IndexError):
            raise InputError(f"survey line {lineno} cannot be read: {lines[lineno - 1]!r}", path=path,
                             fix="each line needs an id and numeric x, y, z") from None
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})
        raise InputError(f"duplicate GCP ids in the survey: {', '.join(dup)}", path=path, fix="give each GCP its own id")
    pts = np.asarray(pts, dtype=float)
    if src.is_geographic and (np.abs(pts[:, 1]) > 90).any():
        raise InputError("survey latitudes beyond ±90°: are x and y swapped, or is the CRS projected?", path=path,
                         fix="x is the longitude and y the latitude; or set 'survey_crs' to the projected CRS")
    if output_crs is not None:
        dst = parse_crs(output_crs) if isinstance(output_crs, str) else output_crs
    elif src.is_projected:
        dst = src
    else:
        lonlat = Transformer.from_crs(src, CRS.from_epsg(4326), always_xy=True).transform(pts[:, 0].mean(),
                                                                                         pts[:, 1].mean())
        dst = utm_crs_for(*lonlat)
    if not dst.equals(src):
        x, y = Transformer.from_crs(src, dst, always_xy=True).transform(pts[:, 0], pts[:, 1])
        pts = np.stack([x, y, pts[:, 2]], axis=-1)
    if not np.all(np.isfinite(pts)):
        raise InputError("some GCPs cannot be converted to the output CRS", path=path,
                         fix="check 'survey_crs' (x = easting or longitude, y = northing or latitude)")
    return [GCP(i, *p) for i, p in zip(ids, pts)], dst
