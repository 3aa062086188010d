"""Which band of a raster is which: names from ``band_order`` (the user's word), from the raster's band
descriptions, or from its colour labels where those mean something; configured band numbers are checked
against them and unset ones taken from them.

GDAL labels bands 1-3 red/green/blue whenever a TIFF says "photometric RGB", which generic writers (rasterio,
tifffile, many camera tools) write for any image of three or more samples: a 5-band reflectance file (blue,
green, red, red edge, NIR) is then "RGB + 2 extra samples", and its blue band is labelled red. So a colour
label is trusted only on a 3- or 4-band 8-bit image (an RGB(A) photo or orthophoto); band descriptions
("Red", "NIR reflectance": MicaSense's, ODM's and most GIS exports) are trusted; ``band_order`` overrules
both. A band number is only ever suggested from a trusted name.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from rasterio.enums import ColorInterp

from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.log import get_logger

log = get_logger("spatial_stat_extractor")

# words of a band description, longest first when matching: "red edge" is not "red", "near-infrared" not "red"
_DESCRIPTION_WORDS = {
    "rededge": ("red edge", "rededge", "red-edge", "red_edge"),
    "nir": ("near-infrared", "near infrared", "near_infrared", "nir"),
    "green": ("green",),
    "blue": ("blue",),
    "red": ("red",),
}
# what users write in band_order for the same bands
_SYNONYMS = {
    "red_edge": "rededge",
    "re": "rededge",
    "edge": "rededge",
    "near_infrared": "nir",
    "nearinfrared": "nir",
    "infrared": "nir",
    "ir": "nir",
    "r": "red",
    "g": "green",
    "b": "blue",
}
_COLOUR_LABELS = {
    ColorInterp.red: "red",
    ColorInterp.green: "green",
    ColorInterp.blue: "blue",
    ColorInterp.alpha: "alpha",
}
_said: set[tuple[str, str]] = set()  # (file, message) logged once per run, not once per layer


def normalise_name(name: str, key: str) -> str:
    """A band name as used in band_order and formulas: lower case, '_' for spaces and dashes, synonyms
    (red_edge, re -> rededge; near_infrared -> nir) folded."""
    text = re.sub(r"[\s\-]+", "_", str(name).strip().lower())
    text = _SYNONYMS.get(text, text)
    if not re.fullmatch(r"[a-z][a-z0-9_]*", text) or re.fullmatch(r"b\d+", text):
        raise ConfigError(
            f"{key}: {name!r} is not a band name (letters, digits, _; not b1, b2 ..., which "
            "formulas already use for the band numbers)",
            fix="name the bands like [blue, green, red, rededge, nir]",
        )
    return text


def check_order(order: Sequence[str], key: str) -> tuple[str, ...]:
    """The band names of ``key``, normalised, each named once (else a ConfigError naming the key)."""
    names = tuple(normalise_name(n, f"{key}[{i}]") for i, n in enumerate(order))
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(
            f"{key} names {dup} more than once: {list(order)}",
            fix="give each band of the raster its own name, in file order",
        )
    return names


@dataclass
class BandNames:
    """Band number -> name, and where the names came from (for messages)."""

    roles: dict[int, str] = field(default_factory=dict)
    source: str = ""

    def number(self, name: str) -> int | None:
        """The band number holding the role ``name``, or None."""
        return next((b for b, r in self.roles.items() if r == name), None)

    def listing(self) -> str:
        """The bands and their roles, for a message (``1 red, 2 green``)."""
        return ", ".join(f"{b} {r}" for b, r in sorted(self.roles.items()))


def file_name(ds) -> str:
    """The file behind a dataset (a WarpedVRT names its source)."""
    src = getattr(ds, "src_dataset", None)
    return str(src.name if src is not None else ds.name)


def described_roles(ds) -> dict[int, str]:
    """Band number -> role from the band descriptions (always meant by whoever wrote them)."""
    roles: dict[int, str] = {}
    words = sorted(((w, role) for role, ws in _DESCRIPTION_WORDS.items() for w in ws), key=lambda t: -len(t[0]))
    for i, desc in enumerate(ds.descriptions, start=1):
        text = (desc or "").lower()
        for w, role in words:
            if re.search(rf"(^|[^a-z-]){re.escape(w)}($|[^a-z-])", text):
                roles[i] = role
                break
    return roles


def labels_meaningful(ds) -> bool:
    """Colour labels name the bands only on an 8-bit image of 3 or 4 bands (RGB or RGBA)."""
    return ds.count in (3, 4) and all(str(dt) == "uint8" for dt in ds.dtypes)


def band_names(ds, order: Sequence[str] = (), key: str = "band_order") -> BandNames:
    """The names of ``ds``'s bands: ``order`` when given (checked against the band count), else the band
    descriptions and, on an 8-bit RGB(A) image, the colour labels; GDAL's default labels on other files are
    left out, and that is said once in the log."""
    name = file_name(ds)
    ds = getattr(ds, "src_dataset", None) or ds  # a raster warped to metres: the file's own names
    if order:
        order = check_order(order, key)
        if len(order) != ds.count:
            raise ConfigError(
                f"{key} names {len(order)} band(s) {list(order)}, but the raster has {ds.count}",
                path=name,
                fix=f"list all {ds.count} bands of {Path(name).name} in file order, "
                "e.g. [blue, green, red, rededge, nir]",
            )
        described = described_roles(ds)
        clash = {b: r for b, r in described.items() if order[b - 1] != r}
        if clash:
            says = [f"band {b} is described as {r!r}, {key} says {order[b - 1]!r}" for b, r in sorted(clash.items())]
            _once(
                name,
                "warning",
                f"{Path(name).name}: {key} overrules the raster's band descriptions ({', '.join(says)})",
            )
        return BandNames({i: n for i, n in enumerate(order, start=1)}, key)
    roles = described_roles(ds)
    source = "its band descriptions" if roles else ""
    labels = {i: _COLOUR_LABELS[c] for i, c in enumerate(ds.colorinterp, start=1) if c in _COLOUR_LABELS}
    labels = {i: r for i, r in labels.items() if i not in roles}
    if labels and labels_meaningful(ds):
        roles.update(labels)
        source = "its band descriptions and colour labels" if source else "its colour labels (an 8-bit RGB image)"
    elif {r for r in labels.values()} & {"red", "green", "blue"}:
        shown = ", ".join(f"{b} {r}" for b, r in sorted(labels.items()))
        _once(
            name,
            "info",
            f"{Path(name).name}: colour labels ({shown}) not used as band names: they are GDAL's "
            f"defaults for a {ds.count}-band {ds.dtypes[0]} TIFF written as photometric RGB (+ extra "
            f"samples), not a statement of which band is red; set band_order to name the bands",
        )
    return BandNames(roles, source)


def _once(name: str, level: str, message: str) -> None:
    if (name, message) not in _said:
        _said.add((name, message))
        getattr(log, level)("%s", message)


def pick_band(ds, names: BandNames, role: str, given: int | str | None, key: str) -> int:
    """The band number for ``role`` (config key ``key``): ``given`` as a number, as a name of ``names``, or
    unset (``None``: the band ``names`` gives that role)."""
    if isinstance(given, str):
        wanted = normalise_name(given, key)
        band = names.number(wanted)
        if band is None:
            known = f"named by {names.source}: {names.listing()}" if names.roles else "its bands are not named"
            raise ConfigError(
                f"{key} = {given!r}, but no band of the raster is named {wanted!r} ({known})",
                path=file_name(ds),
                fix=f"set band_order: [...] (every band's name, in file order), or {key} to a band number (1 = first)",
            )
        return band
    if given is not None:
        return int(given)
    band = names.number(role)
    if band is None:
        known = (
            f"named by {names.source}: {names.listing()}"
            if names.roles
            else "no band descriptions; colour labels only count on 8-bit RGB images"
        )
        raise ConfigError(
            f"{key} is not set and the raster's {ds.count} bands do not say which one is {role} ({known})",
            path=file_name(ds),
            fix="set band_order: [...] (every band's name in file order, e.g. "
            f"[blue, green, red, rededge, nir]) or {key}: <band number>",
        )
    _once(file_name(ds), "info", f"{Path(file_name(ds)).name}: {key} = {band} ({role}, from {names.source})")
    return band


def check_bands(ds, names: BandNames, wanted: dict[str, int], keys: dict[str, str], order_key: bool = True) -> None:
    """Stop when a configured band (role -> number; ``keys``: its config key) is named as another role;
    ``order_key``: band_order applies to this raster (the fix may name it)."""
    for role, band in wanted.items():  # (a band number past the count is reported when the band is read)
        said = names.roles.get(band)
        if said is not None and said != role:
            right = names.number(role)
            hint = f"set {keys[role]}: {right}" if right is not None else f"check {keys[role]}"
            other = "correct band_order" if names.source == "band_order" else "set band_order if those names are wrong"
            raise ConfigError(
                f"{keys[role]} = {band}, but band {band} of the raster is '{said}' (named by "
                f"{names.source}: {names.listing()})",
                path=file_name(ds),
                fix=f"{hint}, or {other}" if order_key else hint,
            )
