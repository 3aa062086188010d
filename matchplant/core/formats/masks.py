"""Masks (label images) to boxes: a plant's box is the extent of its pixels, in pixel edges.

A mask image has the size of its photo and may be in any image format photos come in (PNG, JPEG, TIFF,
BMP, GIF, WebP; grey, 16-bit, RGB, RGBA or palette). Two kinds are read, and which one a mask is, is
decided from its pixels (:func:`decide_mode`), unless the user says (``mode``):

- an **instance mask**: one value per plant (uint16 ids, or one RGB colour per plant as many tools export
  them); one box per value, over all pixels of that value;
- a **binary mask**: background and one foreground value, split into 8-connected components, one box each.
  Masks saved through GIF or JPEG or resized have anti-aliased edges: 100-250 grey levels, most of them at
  object edges. They are still binary: every object peaks at the same foreground value, and the levels in
  between are a thin spread around the objects. They are cut at ``threshold`` (half the foreground value
  by default). A colour mask of one hue (white or green on black) is binary too.

Objects with fewer than ``min_area`` pixels are dropped (specks, noise) and counted.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from PIL import Image
from scipy import ndimage

from matchplant.core.formats.coco import LabelledBox
from matchplant.core.formats.images import IMAGE_SUFFIXES
from matchplant.core.runtime.errors import InputError

MASK_SUFFIXES = IMAGE_SUFFIXES + (".gif", ".webp")  # GIF: what web tools and some labelling apps save
MODES = ("auto", "binary", "instance")
SAME_PEAK = 0.04  # objects whose peak value is within 4 % of the mask's top value share its population
BINARY_SHARE = 0.7  # ... and when this share of the objects does, the mask is binary
FLAT_TOP_SHARE = 0.9  # ... or when this share of its flat (interior) pixels is at the top value
MIN_BLOB = 4  # px: blobs smaller than this do not vote (JPEG speckle)
FAINT = 0.15  # with many levels, pixels under this share of the top value are noise, not objects
FEW_LEVELS = 16  # (an instance mask of a few ids may have faint ids: 1 and 7)
EDGE_PX = 2  # in-between values within this many px of an object edge are its anti-aliasing
SPAN_WARN = 0.5  # an "instance" whose box covers more of the image than this is suspicious
PIECES_WARN = 5  # ... as is one falling into more separate pieces than this
HUE_TOLERANCE = 0.2  # a colour mask whose colours are this close to one hue (scaled to their brightness) ...
ONE_HUE_SHARE = 0.8  # ... in this share of its pixels is one colour (JPEG's chroma blurs edges)


@dataclass
class MaskObjects:
    """What one mask gave: the boxes kept, how the mask was read and why, what was dropped or is doubtful."""

    boxes: list[LabelledBox]
    mode: str
    reason: str
    dropped: int = 0  # objects under min_area
    threshold: float | None = None
    warnings: list[str] = field(default_factory=list)
    top: float = 0.0  # the mask's highest value (binary: what a threshold is compared with)


def read_mask(path: str | Path) -> np.ndarray:
    """A mask's pixels: grey as 2-D, colour as RGB(A); palette images (GIF, palette PNG) as their colours."""
    path = Path(path)
    img = None
    if path.suffix.lower() not in (".gif",):
        data = np.fromfile(path, dtype=np.uint8)
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if img is not None and img.ndim == 3 and img.shape[2] in (3, 4):
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)
    if img is None:  # GIF, and what OpenCV cannot decode
        try:
            with Image.open(path) as im:
                im.seek(0)  # an animated GIF: its first frame
                if im.mode in ("P", "PA"):
                    im = im.convert("RGBA" if im.mode == "PA" or "transparency" in im.info else "RGB")
                elif im.mode == "1":
                    im = im.convert("L")
                img = np.asarray(im)
        except Exception as exc:  # noqa: BLE001 - PIL raises many kinds for a file that is no image
            raise InputError(
                f"not a readable mask image ({exc.__class__.__name__})",
                path=path,
                fix="save the mask as PNG (8- or 16-bit grey, or RGB), or remove the file",
            ) from None
    return img


def mask_values(mask: np.ndarray) -> tuple[np.ndarray, str]:
    """(2-D values, kind): grey masks as they are; a colour mask as one id per colour (kind "colour"), or as
    its brightness when it is one hue (white, or one colour, on black: kind "one-colour")."""
    if mask.dtype == bool:
        mask = mask.astype(np.uint8)
    if mask.ndim == 2:
        return mask, "grey"
    if mask.shape[2] in (2, 4):  # alpha: transparent pixels are background
        alpha = mask[..., -1]
        colour = mask[..., :-1].copy()
        if alpha.min() != alpha.max():
            colour[alpha == 0] = 0
            if all(np.ptp(colour[..., c][alpha > 0]) == 0 for c in range(colour.shape[2])):
                return alpha, "grey"  # the mask is in the alpha band
        mask = colour
    if (
        mask.shape[2] == 1
        or np.array_equal(mask[..., :1], mask[..., 1:2])
        and np.array_equal(mask[..., :1], mask[..., -1:])
    ):
        return mask[..., 0], "grey"
    rgb = mask[..., :3].astype(np.uint32)
    packed = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
    colours = np.unique(packed[packed != 0])
    bright = np.maximum(np.maximum(mask[..., 0], mask[..., 1]), mask[..., 2])  # (faster than max(axis=2))
    if len(colours) <= 1 or _one_hue(mask[..., :3], bright):
        return bright, "one-colour"
    return packed, "colour"


def _one_hue(rgb: np.ndarray, bright: np.ndarray) -> bool:
    """True when every non-black colour is (nearly) one colour scaled: an anti-aliased one-colour mask."""
    # dark edge pixels have a noisy hue (JPEG, 8-bit rounding); judge by the pixels of some brightness
    strong = bright >= 0.25 * float(bright.max())
    scaled = rgb[strong].astype(float) / bright[strong, None].astype(float)
    hue = np.median(scaled, axis=0)
    return bool(np.mean(np.abs(scaled - hue).max(axis=1) <= HUE_TOLERANCE) >= ONE_HUE_SHARE)


def decide_mode(values: np.ndarray, kind: str = "grey") -> tuple[str, str]:
    """("binary" | "instance", why) from the pixels of a 2-D mask.

    The test: split the non-zero pixels into blobs (8-connected). In a binary mask every blob peaks at the
    same foreground value, however many grey levels its anti-aliased edges hold; in an instance mask each
    plant has its own value, so the blobs peak at many values."""
    nz = values > 0
    if kind == "colour":
        return "instance", "colour mask: one object per colour"
    levels = np.unique(values[nz]) if nz.any() else np.zeros(0)
    if len(levels) <= 1:
        return "binary", "one non-zero value"
    own = _own_values(values)
    if own:  # whatever the values (ids 1001-1040 all lie within 4 % of the top: read as binary, plants merged)
        return "instance", f"{own}: one object per value"
    top = float(levels.max())
    # with many levels (JPEG, anti-aliasing) faint pixels are background noise that would join the objects
    solid = nz if len(levels) <= FEW_LEVELS else values > FAINT * top
    n, blobs = _blobs(solid)
    sizes = np.bincount(blobs.ravel(), minlength=n + 1)[1:]
    peaks = np.zeros(n + 1)
    np.maximum.at(peaks, blobs[solid], values[solid].astype(float))  # only the objects' pixels
    peaks = peaks[1:]
    voting = sizes >= MIN_BLOB
    if not voting.any():
        voting = sizes > 0
    share = float(np.mean(peaks[voting] >= top * (1 - SAME_PEAK)))
    flat_top = _flat_top_share(values, top)  # pixel-weighted: small blurred objects do not sway it
    if share < BINARY_SHARE and flat_top < FLAT_TOP_SHARE:
        return "instance", (
            f"{len(levels)} values whose objects peak at different values (only {share:.0%} of "
            f"{int(voting.sum())} blobs, {flat_top:.0%} of the flat pixels at the top value "
            f"{top:g}): one object per value"
        )
    fg = (values >= top / 2).astype(np.uint8)
    kernel = np.ones((2 * EDGE_PX + 1, 2 * EDGE_PX + 1), np.uint8)
    edge = (cv2.dilate(fg, kernel) > 0) & ~(cv2.erode(fg, kernel) > 0)
    between = nz & (values > 0.15 * top) & (values < 0.85 * top)
    at_edges = float(edge[between].mean()) if between.any() else 1.0
    what = "one colour on black" if kind == "one-colour" else f"{len(levels)} grey levels"
    return "binary", (
        f"{what}, but {share:.0%} of the {int(voting.sum())} objects peak at the same value {top:g} "
        f"and {flat_top:.0%} of the interior pixels are at it (two populations: background 0, "
        f"foreground ~{top:g}), and {at_edges:.0%} of the in-between pixels lie at object edges "
        "(anti-aliasing)"
    )


def _blobs(mask: np.ndarray) -> tuple[int, np.ndarray]:
    """(count, labels 1..count) of the 8-connected blobs of a boolean image (OpenCV: fast on 20 Mpx)."""
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    return int(n) - 1, labels


MIN_FLAT = 50  # flat (interior) pixels a mask needs before its interiors' values decide its kind


def _flat(values: np.ndarray) -> np.ndarray:
    """The non-zero pixels equal to their four neighbours (object interiors; an anti-aliased edge is never flat)."""
    v = values
    flat = (
        (v[1:-1, 1:-1] > 0)
        & (v[1:-1, 1:-1] == v[:-2, 1:-1])
        & (v[1:-1, 1:-1] == v[2:, 1:-1])
        & (v[1:-1, 1:-1] == v[1:-1, :-2])
        & (v[1:-1, 1:-1] == v[1:-1, 2:])
    )
    return v[1:-1, 1:-1][flat]


def _own_values(values: np.ndarray) -> str:
    """Why the objects' interiors hold values of their own (an instance mask), or "" when they do not: a binary
    mask's interiors are all at its one foreground value however many grey levels its edges hold (measured:
    100 % of the interior pixels on resized, Lanczos, JPEG and GIF masks), an instance mask's each at its id
    (1/N of them at the commonest). Exact values, not a share of the top value: 16-bit ids 1001-1040 lie within
    4 % of their top, and 40 of them are still 40 plants."""
    inner = _flat(values)
    if inner.size < MIN_FLAT:
        return ""
    uniq, counts = np.unique(inner, return_counts=True)
    held = int((counts >= MIN_BLOB).sum())  # values whose interiors are more than a speck
    share = float(counts.max()) / inner.size
    if held < 2 or share >= FLAT_TOP_SHARE:
        return ""
    return (
        f"the objects' interiors hold {held} distinct values (values {uniq.min():g}-{uniq.max():g}; only "
        f"{share:.0%} of the interior pixels at the commonest)"
    )


def _flat_top_share(values: np.ndarray, top: float) -> float:
    """Of the non-zero pixels equal to their four neighbours (object interiors), the share at the top value: ~1
    in a binary mask (its edges are gradients, never flat), low in an instance mask (every id has an interior)."""
    inner = _flat(values)
    return float(np.mean(inner >= top * (1 - SAME_PEAK))) if inner.size else 0.0


def mask_objects(
    mask: np.ndarray, min_area: int = 1, label: str = "plant", mode: str = "auto", threshold: float | None = None
) -> MaskObjects:
    """The objects of a mask (2-D, or RGB(A) colour) as boxes ``[x1, y1, x2, y2]`` in pixel edges.

    ``mode`` "auto" decides from the pixels (:func:`decide_mode`); a ``threshold`` (pixel value; foreground
    at or above it) reads the mask as binary."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}")
    values, kind = mask_values(mask)
    if threshold is not None and mode == "auto":
        mode, reason = "binary", f"mask_threshold {threshold:g} given"
    elif mode == "auto":
        mode, reason = decide_mode(values, kind)
    else:
        reason = f"mask_mode: {mode}"
    if mode == "binary":
        out = _binary(values, min_area, label, reason, threshold)
        own = _own_values(values) if kind != "colour" else "a colour mask of many colours"
        if own:  # binary by mask_mode or mask_threshold: the data says instance ids (touching plants merge)
            out.warnings.append(
                f"read as binary ({reason}), but {own}: an instance mask (one id per plant), whose touching "
                "plants a binary reading merges into one box"
            )
        return out
    return _instances(values, min_area, label, reason)


def mask_boxes(mask: np.ndarray, min_area: int = 1, label: str = "plant") -> list[LabelledBox]:
    """Boxes of the objects of a mask, its kind decided from the pixels (see :func:`mask_objects`)."""
    return mask_objects(mask, min_area, label).boxes


def _binary(values: np.ndarray, min_area: int, label: str, reason: str, threshold: float | None) -> MaskObjects:
    top = float(values.max()) if values.size else 0.0
    if threshold is None:
        levels = np.unique(values[values > 0]) if top > 0 else np.zeros(0)
        threshold = top / 2 if len(levels) > 1 else min(1.0, top) if top > 0 else 1.0
    fg = (values >= threshold) & (values > 0)
    _, _, stats, _ = cv2.connectedComponentsWithStats(fg.astype(np.uint8), connectivity=8)
    stats = stats[1:]
    keep = stats[:, 4] >= min_area
    boxes = [LabelledBox([float(x), float(y), float(x + w), float(y + h)], label) for x, y, w, h, _ in stats[keep]]
    return MaskObjects(boxes, "binary", reason, int((~keep).sum()), float(threshold), top=top)


def _instances(values: np.ndarray, min_area: int, label: str, reason: str) -> MaskObjects:
    nz = values != 0
    ids = np.zeros(values.shape, np.int32)
    uniq, inverse = np.unique(values[nz], return_inverse=True)
    ids[nz] = inverse.astype(np.int32) + 1  # dense labels 1..K, one per value
    k = len(uniq)
    counts = np.bincount(ids.ravel(), minlength=k + 1)[1:]
    slices = ndimage.find_objects(ids, max_label=k)
    keep = counts >= min_area
    out = MaskObjects([], "instance", reason, int((~keep).sum()))
    h, w = values.shape
    spans = []
    for i in np.flatnonzero(keep):
        ys, xs = slices[i]
        out.boxes.append(LabelledBox([float(xs.start), float(ys.start), float(xs.stop), float(ys.stop)], label))
        spans.append((xs.stop - xs.start) * (ys.stop - ys.start) / float(w * h))
    big = [s for s in spans if s > SPAN_WARN]
    if big and len(out.boxes) > 1 or big and max(big) > 0.9:
        out.warnings.append(
            f"{len(big)} instance(s) span more than {SPAN_WARN:.0%} of the image (largest "
            f"{max(big):.0%}): an anti-aliased or class mask read as instances?"
        )
    pieces = _pieces(ids, nz, k)[keep]
    if len(pieces) and pieces.max() > PIECES_WARN:
        many = int((pieces > PIECES_WARN).sum())
        out.warnings.append(
            f"{many} instance(s) fall into more than {PIECES_WARN} separate pieces (up to "
            f"{int(pieces.max())}): a class mask (one value per category) read as instances?"
        )
    return out


def _pieces(ids: np.ndarray, nz: np.ndarray, k: int) -> np.ndarray:
    """For each instance label 1..K, the number of separate blobs of the mask it has pixels in."""
    n, blobs = _blobs(nz)
    pairs = np.unique(ids[nz].astype(np.int64) * (n + 1) + blobs[nz])
    return np.bincount(pairs // (n + 1), minlength=k + 1)[1:]


__all__ = [
    "MASK_SUFFIXES",
    "MODES",
    "MaskObjects",
    "decide_mode",
    "mask_boxes",
    "mask_objects",
    "mask_values",
    "read_mask",
]
