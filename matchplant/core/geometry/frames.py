"""The frame a reconstruction is in, and its exact conversion to the map CRS (docs/DESIGN.md §3).

1. :class:`OffsetFrame` - modern ODM: UTM (the CRS on line 1 of ``odm_georeferencing/coords.txt``)
   minus the integer offset on line 2. ``map = recon + (ox, oy, 0)``.
2. :class:`TopocentricFrame` - plain OpenSfM and older ODM: local east-north-up around
   ``reference_lla`` on the WGS84 ellipsoid, converted exactly through geocentric coordinates with
   PROJ's ``topocentric`` operation (treating it as shifted UTM is off by metres at 200 m).

Both convert arrays of (N, 3) points both ways; heights are ellipsoidal in case 2.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.io import write_text
from matchplant.core.runtime.validate import read_text

if TYPE_CHECKING:
    from pyproj import CRS


def _proj():
    """pyproj, imported on first use: training and detection import this module (through core.formats.odm) and
    must run where no GIS library is installed (a GPU node)."""
    import pyproj
    import pyproj.exceptions

    return pyproj


_UTM_TEXT = re.compile(r"^\s*WGS\s*84\s+UTM\s+(\d{1,2})\s*([NS])\s*$", re.IGNORECASE)


def parse_crs(crs, *, source: str | Path | None = None, key: str | None = None) -> CRS:
    """The one way a CRS is read: from text (``EPSG:32615``, ``WGS84 UTM 15N`` as in ODM's coords.txt, an EPSG
    number, a PROJ string or WKT) or from a file's CRS object (pyproj's as it is, rasterio's through its WKT).

    Text that is no CRS is an InputError naming ``source``; with ``key`` (text from that config key) a
    ConfigError naming the key."""
    if isinstance(crs, _proj().CRS):
        return crs
    if hasattr(crs, "to_wkt"):
        return _proj().CRS.from_user_input(crs.to_wkt())
    text = str(crs).strip()
    m = _UTM_TEXT.match(text)
    try:
        if m:
            zone, hemi = int(m.group(1)), m.group(2).upper()
            return _proj().CRS.from_epsg((32600 if hemi == "N" else 32700) + zone)
        if text.isdigit():
            return _proj().CRS.from_epsg(int(text))
        return _proj().CRS.from_user_input(text)
    except _proj().exceptions.CRSError as exc:
        problem = f"unrecognised coordinate reference system {text!r}"
        fix = "use an EPSG code such as EPSG:32615, 'WGS84 UTM 15N' or a PROJ string"
        if key is not None:
            raise ConfigError(f"config key '{key}': {problem}", path=source, fix=fix) from None
        raise InputError(problem, path=source, fix=fix) from exc


def utm_crs_for(lon: float, lat: float) -> CRS:
    """The WGS 84 UTM CRS of the zone holding a longitude and latitude."""
    zone = int((lon + 180.0) // 6.0) % 60 + 1
    return _proj().CRS.from_epsg((32600 if lat >= 0 else 32700) + zone)


def read_coords_txt(path: str | Path) -> tuple[CRS, np.ndarray]:
    """``odm_georeferencing/coords.txt``: line 1 the CRS, line 2 the integer offset ``x y`` (BOM, CRLF and
    UTF-16 accepted); a missing, empty or garbled file is an error naming the line."""
    path = Path(path)
    fix = "restore coords.txt from ODM's output (line 1: e.g. 'WGS84 UTM 14N', line 2: 'x y'), or re-run ODM"
    if not path.is_file():
        raise InputError(
            "coords.txt not found", path=path, fix="ODM writes it when the images carry GPS or a gcp_list.txt is given"
        )
    try:
        text = read_text(path, what="coords.txt")
    except InputError as exc:
        raise InputError(exc.problem, path=path, fix=fix) from exc
    lines = [(i + 1, ln.strip()) for i, ln in enumerate(text.split("\n")) if ln.strip()]
    if len(lines) < 2:
        raise InputError(
            f"coords.txt has {len(lines)} line(s): it must hold the CRS on line 1 and the offset 'x y' on line 2",
            path=path,
            fix=fix,
        )
    crs = parse_crs(lines[0][1], source=path)
    if crs.is_geographic:
        raise InputError(
            f"coords.txt line {lines[0][0]}: {lines[0][1]!r} is a geographic CRS; ODM writes a "
            "projected one (UTM) there",
            path=path,
            fix=fix,
        )
    lineno, second = lines[1]
    try:
        values = [float(v) for v in second.replace(",", " ").split()[:2]]
    except ValueError:
        values = []
    if len(values) != 2 or not np.all(np.isfinite(values)):
        raise InputError(
            f"coords.txt line {lineno} is not an 'x y' offset (two numbers): {second!r}", path=path, fix=fix
        )
    return crs, np.array(values + [0.0])


def write_coords_txt(path: str | Path, crs: CRS, offset: np.ndarray) -> Path:
    """Write ODM's coords.txt: the CRS (``WGS84 UTM 14N`` style for UTM) and the integer offset."""
    epsg = crs.to_epsg()
    utm = crs.utm_zone if hasattr(crs, "utm_zone") else None
    if utm and epsg and 32601 <= epsg <= 32760:
        first = f"WGS84 UTM {utm[:-1]}{utm[-1].upper()}"
    else:
        first = f"EPSG:{epsg}" if epsg else crs.to_proj4()
    return write_text(path, f"{first}\n{int(round(offset[0]))} {int(round(offset[1]))}\n")


class Frame:
    """A reconstruction frame and its map CRS."""

    crs: CRS
    kind: str

    def to_map(self, points: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        """Points (N, 3) in the reconstruction frame to the map CRS."""
        raise NotImplementedError

    def from_map(self, points: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        """Points (N, 3) in the map CRS to the reconstruction frame."""
        raise NotImplementedError

    @property
    def is_affine(self) -> bool:
        """True when straight lines stay straight (a shift), so rays can be intersected in map space."""
        return False

    def map_directions(self, dirs: np.ndarray) -> np.ndarray:
        """Unit directions in the frame as unit directions in the map, for an affine frame (a shift keeps them)."""
        return np.asarray(dirs, dtype=float)


@dataclass
class OffsetFrame(Frame):
    """A reconstruction frame that is the map CRS minus an offset (ODM's coords.txt)."""

    crs: CRS
    offset: np.ndarray  # (3,)
    kind: str = "utm_offset"

    def to_map(self, points: np.ndarray) -> np.ndarray:
        """Points (N, 3) in the reconstruction frame to the map CRS (plus the offset)."""
        return np.asarray(points, dtype=float) + self.offset

    def from_map(self, points: np.ndarray) -> np.ndarray:
        """Points (N, 3) in the map CRS to the reconstruction frame (minus the offset)."""
        return np.asarray(points, dtype=float) - self.offset

    @property
    def is_affine(self) -> bool:
        """True: a shift keeps straight lines straight."""
        return True

    def describe(self) -> str:
        """The frame in words, for logs and messages."""
        return f"{self.crs.name} minus offset ({self.offset[0]:.0f}, {self.offset[1]:.0f})"


class TopocentricFrame(Frame):
    """OpenSfM's topocentric frame (east, north, up around a reference latitude, longitude, altitude) and a map CRS."""

    kind = "topocentric"

    def __init__(self, lat: float, lon: float, alt: float, crs: CRS | None = None):
        self.lat, self.lon, self.alt = float(lat), float(lon), float(alt)
        self.crs = crs if crs is not None else utm_crs_for(lon, lat)
        self._enu_to_lla = _proj().Transformer.from_pipeline(
            f"+proj=pipeline +step +inv +proj=topocentric +ellps=WGS84 +lat_0={self.lat!r} "
            f"+lon_0={self.lon!r} +h_0={self.alt!r} +step +inv +proj=cart +ellps=WGS84 "
            f"+step +proj=unitconvert +xy_in=rad +xy_out=deg"
        )
        target = self.crs.to_3d() if not self.crs.is_geographic else _proj().CRS.from_epsg(4979)
        self._lla_to_map = _proj().Transformer.from_crs(_proj().CRS.from_epsg(4979), target, always_xy=True)

    def to_lla(self, points: np.ndarray) -> np.ndarray:
        """Topocentric points (N, 3) to longitude, latitude and ellipsoidal height (N, 3)."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        lon, lat, h = self._enu_to_lla.transform(p[:, 0], p[:, 1], p[:, 2])
        return np.stack([lon, lat, h], axis=-1)

    def to_map(self, points: np.ndarray) -> np.ndarray:
        """Topocentric points (N, 3) to the map CRS."""
        shape = np.shape(points)
        lla = self.to_lla(points)
        x, y, z = self._lla_to_map.transform(lla[:, 0], lla[:, 1], lla[:, 2])
        return np.stack([x, y, z], axis=-1).reshape(shape)

    def from_map(self, points: np.ndarray) -> np.ndarray:
        """Points (N, 3) in the map CRS to topocentric coordinates."""
        shape = np.shape(points)
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        lon, lat, h = self._lla_to_map.transform(p[:, 0], p[:, 1], p[:, 2], direction="INVERSE")
        e, n, u = self._enu_to_lla.transform(lon, lat, h, direction="INVERSE")
        return np.stack([e, n, u], axis=-1).reshape(shape)

    def rotation_from_map(self, local: np.ndarray, h: float = 1.0) -> np.ndarray:
        """The rotation Q (3, 3) closest to d(map)/d(local) at the local point ``local``: a world->camera rotation
        ``R_map`` in map axes is ``R_map @ Q`` in this frame's axes (polar decomposition of the Jacobian; the map
        projection's scale, about 1e-4, is what is left out)."""
        pts = np.asarray(local, dtype=float)[None, :] + np.concatenate([np.eye(3) * h, -np.eye(3) * h])
        m = self.to_map(pts)
        u, _, vt = np.linalg.svd(((m[:3] - m[3:]) / (2 * h)).T)
        return u @ vt

    def describe(self) -> str:
        """The frame in words, for logs and messages."""
        return f"topocentric around lat {self.lat:.7f}, lon {self.lon:.7f} -> {self.crs.name}"


def detect_frame(
    reference_lla: dict | None,
    coords: tuple[CRS, np.ndarray] | None = None,
    has_topocentric_copy: bool = False,
    crs: CRS | None = None,
    *,
    source: str | Path | None = None,
) -> Frame:
    """Decide which frame a reconstruction is in (docs/DESIGN.md §3) and return it.

    ``coords`` is coords.txt's (CRS, offset) if present; ``has_topocentric_copy`` says whether a
    ``reconstruction.topocentric.json`` lies beside the file; ``crs`` overrides the map CRS.
    """
    if reference_lla is None:
        if coords is not None:
            return OffsetFrame(crs=coords[0], offset=coords[1])
        raise InputError(
            "the reconstruction has no reference_lla and there is no coords.txt, so it is not georeferenced",
            path=source,
            fix="run ODM with GPS-tagged images or a gcp_list.txt",
        )
    lat, lon = float(reference_lla["latitude"]), float(reference_lla["longitude"])
    alt = float(reference_lla.get("altitude", 0.0))
    if coords is not None:
        map_crs = coords[0]
        e, n = _proj().Transformer.from_crs(_proj().CRS.from_epsg(4326), map_crs, always_xy=True).transform(lon, lat)
        if has_topocentric_copy or (abs(e - coords[1][0]) < 0.05 and abs(n - coords[1][1]) < 0.05):
            return OffsetFrame(crs=map_crs, offset=coords[1])
        return TopocentricFrame(lat, lon, alt, crs or map_crs)
    map_crs = crs or utm_crs_for(lon, lat)
    e, n = _proj().Transformer.from_crs(_proj().CRS.from_epsg(4326), map_crs, always_xy=True).transform(lon, lat)
    if has_topocentric_copy or (abs(e - round(e)) < 1e-3 and abs(n - round(n)) < 1e-3):
        return OffsetFrame(crs=map_crs, offset=np.array([round(e), round(n), 0.0]))
    return TopocentricFrame(lat, lon, alt, map_crs)
