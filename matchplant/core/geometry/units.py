"""Units of an elevation raster: which of its CRS's axes are not metres, and the unit of its heights.

A DSM's heights are in the unit its file says: the vertical axis of its CRS (a compound CRS such as
``UTM + NAVD88 height (ftUS)``) or, for a CRS without one, the band's unit type (GDAL's ``GetUnitType``,
rasterio's ``src.units``: ``"ft"``, ``"US survey foot"``, ``"m"``...). :func:`height_unit` gives the metres per
unit from PROJ's unit table (exact: 0.3048 for the foot, 1200/3937 for the US survey foot).
"""

from __future__ import annotations

from matchplant.core.geometry.frames import _proj, parse_crs
from matchplant.core.runtime.errors import InputError

METRE_NAMES = {"", "m", "metre", "meter", "metres", "meters"}


def not_metres(crs) -> str:
    """The CRS's linear axes that are not in metres, as text ("US survey foot (easting, northing, up)"), or "":
    degrees (a geographic CRS, warped onto a metric grid where read) and metres are fine."""
    if crs is None:
        return ""
    c = crs if isinstance(crs, _proj().CRS) else parse_crs(crs)
    units: dict[str, list[str]] = {}
    for crs_part in c.sub_crs_list or [c]:
        for axis in crs_part.axis_info:
            if axis.unit_name in ("metre", "meter") or axis.unit_name.startswith("degree"):
                continue
            if axis.unit_auth_code == "9001" or abs(axis.unit_conversion_factor - 1.0) < 1e-12:
                continue
            if crs_part.is_geographic and axis.direction not in ("up", "down"):
                continue  # angles (grads, arc-seconds): warped like degrees
            units.setdefault(axis.unit_name, []).append(axis.name or axis.direction)
    return "; ".join(f"{u} ({', '.join(names)})" for u, names in units.items())


def vertical_axis(crs):
    """The 'up' axis of ``crs`` (a compound or 3D CRS), or None for a CRS without heights."""
    if crs is None:
        return None
    c = crs if isinstance(crs, _proj().CRS) else parse_crs(crs)
    for part in c.sub_crs_list or [c]:
        for axis in part.axis_info:
            if axis.direction in ("up", "down"):
                return axis
    return None


def height_unit(crs, band_unit: str | None, path=None) -> tuple[float, str]:
    """Metres per height unit of an elevation raster, and the unit's name: from the CRS's vertical axis, else the
    band's unit type; (1.0, "") when neither says (heights taken as metres). An unknown unit name is an error."""
    axis = vertical_axis(crs)
    if axis is not None:
        return float(axis.unit_conversion_factor), axis.unit_name
    name = (band_unit or "").strip()
    if name.lower() in METRE_NAMES:
        return 1.0, ""
    units = _proj().database.get_units_map(category="linear")
    lower = {k.lower(): u for k, u in units.items()} | {u.name.lower(): u for u in units.values()}
    lower |= {u.proj_short_name.lower(): u for u in units.values() if u.proj_short_name}
    aliases = {"feet": "foot", "ftus": "us-ft", "us survey feet": "us survey foot", "us_survey_foot": "us survey foot"}
    unit = lower.get(aliases.get(name.lower(), name.lower()))
    if unit is None:
        raise InputError(
            f"the elevation raster's heights are in '{name}' (its band unit type), a unit PROJ does not know",
            path=path,
            fix="convert its heights to metres (gdal_calc.py) and set the unit to 'm' (gdal_edit.py -units m)",
        )
    return float(unit.conv_factor), unit.name


def metric_heights(crs):
    """``crs`` with its vertical axis in metres (same datum, same horizontal axes): the map CRS of rays walked over
    a DSM whose heights :class:`~matchplant.core.geometry.surface.Surface` converted to metres. ``crs`` itself
    when its heights are already metres or it has none."""
    axis = vertical_axis(crs)
    if axis is None or abs(axis.unit_conversion_factor - 1.0) < 1e-12:
        return crs
    c = crs if isinstance(crs, _proj().CRS) else parse_crs(crs)
    d = c.to_json_dict()
    for part in d.get("components", [d]):
        for ax in part["coordinate_system"]["axis"]:
            if ax["direction"] in ("up", "down"):
                ax["unit"] = "metre"
        if part["coordinate_system"].get("subtype") == "vertical":
            part["name"] += " in metres"
            part.pop("id", None)
    d["name"] += " (heights in metres)"
    d.pop("id", None)
    return _proj().CRS.from_json_dict(d)
