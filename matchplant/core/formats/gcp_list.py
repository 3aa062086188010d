"""ODM's ``gcp_list.txt``: ground control points marked in images (docs/DESIGN.md §2).

Line 1 is the CRS (``EPSG:32614``, ``WGS84 UTM 14N`` or a PROJ string); every other line is
``geo_x geo_y geo_z im_x im_y image_name [gcp_name [extra ...]]`` with pixel coordinates in the original
image (the centre of the first pixel is 0, 0). Step 1 writes it, step 2 hands it to ODM; the reader
accepts every header and layout ODM accepts, so lists made by other tools can be continued.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from matchplant.core.geometry.frames import parse_crs
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import atomic_open


@dataclass
class Mark:
    """One line of gcp_list.txt: a GCP's map position and its pixel in one image."""

    x: float
    y: float
    z: float
    u: float
    v: float
    image: str
    gcp: str = ""
    extra: list[str] = field(default_factory=list)


def crs_header(crs) -> str:
    """Line 1 of gcp_list.txt: 'EPSG:nnnn' when the CRS has a code, else its PROJ string."""
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else crs.to_proj4()


def read_gcp_list(path: str | Path) -> tuple[str, object, list[Mark]]:
    """Read an ODM gcp_list.txt: (header line, its CRS, marks). Any header ODM accepts."""
    path = Path(path)
    if not path.is_file():
        raise InputError("gcp_list.txt not found", path=path, fix="check the path")
    lines = path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
    body = [(i, ln) for i, ln in enumerate(lines, start=1) if ln.strip() and not ln.lstrip().startswith("#")]
    if not body:
        raise InputError("gcp_list.txt is empty", path=path, fix="line 1 must be the CRS, e.g. EPSG:32614")
    header = body[0][1].strip()
    try:
        crs = parse_crs(header, source=path)
    except InputError:
        raise InputError(
            f"gcp_list.txt line {body[0][0]} must be the CRS of the coordinates, not {header!r}",
            path=path,
            fix="insert the CRS as the first line, e.g. EPSG:32614 or 'WGS84 UTM 14N'",
        ) from None
    marks = []
    for lineno, ln in body[1:]:
        tok = ln.split()
        try:
            if len(tok) < 6:
                raise ValueError
            x, y, z, u, v = (float(t) for t in tok[:5])
        except ValueError:
            raise InputError(
                f"gcp_list.txt line {lineno} is not 'geo_x geo_y geo_z im_x im_y image [gcp_name]': {ln.strip()!r}",
                path=path,
                fix="repair or delete that line",
            ) from None
        if not all(math.isfinite(a) for a in (x, y, z, u, v)) or min(u, v) < -0.5:
            raise InputError(
                f"gcp_list.txt line {lineno} has a value that is not a coordinate (NaN, infinite or "
                f"a negative pixel): {ln.strip()!r}",
                path=path,
                fix="repair or delete that line",
            )
        marks.append(Mark(x, y, z, u, v, tok[5], tok[6] if len(tok) > 6 else "", tok[7:]))
    return header, crs, marks


def write_gcp_list(path: str | Path, header: str, marks: list[Mark]) -> Path:
    """Write gcp_list.txt atomically (TAB-separated, pixel coordinates to 1/1000 px)."""
    with atomic_open(path, "w") as fh:
        fh.write(header.strip() + "\n")
        for m in marks:
            fh.write(f"{m.x:.4f}\t{m.y:.4f}\t{m.z:.4f}\t{m.u:.3f}\t{m.v:.3f}\t{m.image}\t{m.gcp}\n")
    return Path(path)
