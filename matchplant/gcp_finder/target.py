"""Finding a square GCP target (2x2 black and white checker, or a plain square) near a predicted pixel.

Both target kinds are point-symmetric about their centre, which neither soil nor plants are; the
detector therefore scores point symmetry rather than matching a template of a known size and angle.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from PIL import Image


def symmetry_peaks(
    gray: np.ndarray, u0: float, v0: float, radius: int = 60, min_contrast: float = 40.0, n: int = 1
) -> list[tuple[float, float]]:
    """Up to ``n`` sub-pixel centres of point symmetry near (u0, v0), strongest first.

    A black-and-white square target (black and white quadrants, or a square of one tone on the other)
    is point-symmetric about its centre. The (high-passed) window is correlated with itself rotated by
    180°: a peak at lag p means symmetry about the point half-way, refined by a parabola fit. Empty when
    the window has no contrast (no target there).
    """
    h, w = gray.shape[:2]
    u0i, v0i = int(round(u0)), int(round(v0))
    x0, x1 = max(0, u0i - radius), min(w, u0i + radius + 1)
    y0, y1 = max(0, v0i - radius), min(h, v0i + radius + 1)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return []
    win = gray[y0:y1, x0:x1].astype(np.float32)
    lo, hi = np.percentile(win, [1, 99])
    if hi - lo < min_contrast:
        return []
    win = win - cv2.GaussianBlur(win, (0, 0), radius / 2.0)  # remove the soil's slow shading
    sub = win[::-1, ::-1]
    cc = cv2.filter2D(win, cv2.CV_32F, sub, borderType=cv2.BORDER_CONSTANT)
    # local maxima, strongest first
    dil = cv2.dilate(cc, np.ones((5, 5), np.uint8))
    ys, xs = np.nonzero((cc >= dil) & (cc > 0))
    order = np.argsort(-cc[ys, xs])[:n]

    def parabola(a, b, c):
        den = a - 2 * b + c
        return 0.0 if den == 0 else 0.5 * (a - c) / den

    # filter2D anchors the kernel at its centre k: a peak at px means symmetry about (px + n - 1 - k) / 2
    kx, ky = (sub.shape[1] - 1) / 2.0, (sub.shape[0] - 1) / 2.0
    out = []
    for py, px in zip(ys[order], xs[order]):
        dx = parabola(cc[py, px - 1], cc[py, px], cc[py, px + 1]) if 0 < px < cc.shape[1] - 1 else 0.0
        dy = parabola(cc[py - 1, px], cc[py, px], cc[py + 1, px]) if 0 < py < cc.shape[0] - 1 else 0.0
        out.append((x0 + (px + dx + win.shape[1] - 1 - kx) / 2.0, y0 + (py + dy + win.shape[0] - 1 - ky) / 2.0))
    return out


def detect_target(
    gray: np.ndarray, u0: float, v0: float, radius: int = 60, min_contrast: float = 40.0
) -> tuple[float, float] | None:
    """The strongest centre of symmetry near (u0, v0) (see :func:`symmetry_peaks`), or None."""
    peaks = symmetry_peaks(gray, u0, v0, radius, min_contrast, n=1)
    return peaks[0] if peaks else None


def symmetry_score(gray: np.ndarray, uv: tuple[float, float], r: int, pattern: str = "checker") -> float:
    """How much the (2r+1)-pixel patch centred at ``uv`` looks like the centre of a target (up to 1).

    Both target kinds are symmetric under a 180° turn. Under a 90° turn a 2x2 checker's centre is
    anti-symmetric (black and white quadrants swap) and a plain square's symmetric; the score is the
    smaller of the two correlations (with the sign the pattern calls for), so the centre of one
    checker quadrant - a plain square of its own - does not pass for a checker's centre.
    """
    patch = cv2.getRectSubPix(
        np.ascontiguousarray(gray, dtype=np.float32), (2 * r + 1, 2 * r + 1), (float(uv[0]), float(uv[1]))
    )
    a = patch - patch.mean()
    energy = max(float((a * a).sum()), 1e-6)
    c180 = float((a * a[::-1, ::-1]).sum()) / energy
    c90 = float((a * np.rot90(a)).sum()) / energy
    return min(c180, -c90 if pattern == "checker" else c90)


def symmetry_map(
    gray: np.ndarray, u: float, v: float, radius: int, r: int, pattern: str = "checker"
) -> tuple[np.ndarray, int, int] | None:
    """:func:`symmetry_score` of the (2r+1)-pixel patch centred on every pixel within ``radius`` of
    (u, v) (patches inside the image only), vectorised: sums of products of shifted views.

    Returns (score map, x of its first column, y of its first row), or None when no patch fits.
    """
    h, w = gray.shape[:2]
    x0, x1 = max(r, int(round(u)) - radius), min(w - 1 - r, int(round(u)) + radius)
    y0, y1 = max(r, int(round(v)) - radius), min(h - 1 - r, int(round(v)) + radius)
    if x1 < x0 or y1 < y0:
        return None
    g = gray[y0 - r : y1 + r + 1, x0 - r : x1 + r + 1].astype(np.float64)
    ny, nx = y1 - y0 + 1, x1 - x0 + 1

    def view(dy: int, dx: int) -> np.ndarray:
        return g[r + dy : r + dy + ny, r + dx : r + dx + nx]

    s180 = np.zeros((ny, nx))
    s90 = np.zeros((ny, nx))
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            a = view(dy, dx)
            s180 += a * view(-dy, -dx)
            s90 += a * view(dx, -dy)
    n = (2 * r + 1) ** 2
    box = (2 * r + 1, 2 * r + 1)
    mean = cv2.boxFilter(g, -1, box, normalize=True, borderType=cv2.BORDER_ISOLATED)[r : r + ny, r : r + nx]
    sq = cv2.boxFilter(g * g, -1, box, normalize=True, borderType=cv2.BORDER_ISOLATED)[r : r + ny, r : r + nx]
    var = n * (sq - mean * mean)
    with np.errstate(divide="ignore", invalid="ignore"):
        c180 = (s180 - n * mean * mean) / var
        c90 = (s90 - n * mean * mean) / var
    score = np.minimum(c180, -c90 if pattern == "checker" else c90)
    score[~(var > n * 25.0)] = -1.0  # flat patches (std below 5 grey levels) are no target
    return score, x0, y0


def locate_target(
    gray: np.ndarray,
    u: float,
    v: float,
    target_px: float,
    search_px: int = 0,
    pattern: str = "checker",
    min_symmetry: float = 0.6,
    tries: int = 5,
) -> tuple[float, float] | None:
    """Find a target of about ``target_px`` pixels near a predicted (u, v).

    Every pixel of the search window is scored by how much its neighbourhood looks like a target's
    centre (:func:`symmetry_map`); the best few local maxima are refined to sub-pixel precision with a
    window fitted to the target (kept inside the image, so a target cut by the edge still has a
    symmetric neighbourhood around its centre) and checked again (:func:`symmetry_score` above
    ``min_symmetry``; ``pattern`` is 'checker' for black and white quadrants, 'square' for a plain
    square). Returns the best, or None (not found, or its centre too close to the edge).
    """
    h, w = gray.shape[:2]
    radius = search_px or max(16, int(0.06 * w), int(0.75 * target_px))
    found = symmetry_map(gray, u, v, radius, int(np.clip(0.15 * target_px, 3, 8)), pattern)
    if found is None:
        return None
    score, x0, y0 = found
    score = score.astype(np.float32)
    peaks = (score >= cv2.dilate(score, np.ones((5, 5), np.uint8))) & (score > 0.5 * min_symmetry)
    ys, xs = np.nonzero(peaks)
    best, best_score = None, min_symmetry
    for k in np.argsort(-score[ys, xs])[:tries]:
        uv: tuple[float, float] | None = (float(x0 + xs[k]), float(y0 + ys[k]))
        for _ in range(2):
            edge = min(uv[0], uv[1], w - 1 - uv[0], h - 1 - uv[1])
            uv = detect_target(gray, uv[0], uv[1], max(4, min(int(0.9 * target_px), int(edge) - 1)))
            if uv is None:
                break
        if uv is None:
            continue
        r = int(min(0.25 * target_px, min(uv[0], uv[1], w - 1 - uv[0], h - 1 - uv[1]) - 1))
        if r >= 3:
            s = symmetry_score(gray, uv, r, pattern)
            if s > best_score:
                best, best_score = uv, s
    return best


def load_gray(path: Path) -> np.ndarray:
    """An image as float32 grey levels (PIL's luma): the detector works on contrast, not colour."""
    with Image.open(path) as im:
        return np.asarray(im.convert("L"), dtype=np.float32)
