"""Outlines of a label image along its pixel edges, in one compiled pass.

Each 4-connected piece of one label becomes a polygon whose rings run along pixel edges (vertices only where
a ring turns); pixels of one label that touch only at a corner are separate pieces, and a label in several
pieces becomes a multipolygon. This is what ``rasterio.features.shapes(labels, connectivity=4)`` gives
(GDAL's polygonize), at a fraction of the cost: GDAL walks every pixel of the image into its own polygon
records and rasterio hands each ring back as Python tuples, 22 % of the outlining time on the survey bench;
here the scan skips the empty pixels, and the rings come back as one coordinate array.

A ring is followed with its label on the right (clockwise on the raster, rows down). At a corner where the
label holds two diagonal pixels only, the ring keeps to the pixel it follows (4-connectivity). Rings with a
positive area are shells, the others holes, each in the shell of the piece that holds the pixel next to it.
A shell that meets its own hole at a corner comes out touching itself (invalid); :func:`valid_polygons` in
outlines repairs it, as it did GDAL's, checking only the outlines whose rings pass such a corner.
"""

from __future__ import annotations

import numba
import numpy as np
import shapely


@numba.njit(cache=True, nogil=True)
def _grown(xy):
    out = np.empty((2 * xy.shape[0], 2), np.int64)
    out[: xy.shape[0]] = xy
    return out


@numba.njit(cache=True, nogil=True)
def _rings(lab):
    """Every ring of ``lab``: corner (col, row) vertices, ring offsets, label, twice the signed area, the pixel
    (row * cols + col) whose top edge starts it (the first in raster order), and whether it passes a diagonal
    corner."""
    rows, cols = lab.shape
    seen = np.zeros((rows, (cols + 7) // 8), np.uint8)  # top edges already on a ring (one bit each)
    xy = np.empty((1024, 2), np.int64)
    nxy = 0
    starts = [0]
    labels = []
    area2 = []
    first_pixel = []
    corner = []  # the ring passes a corner where its label holds two diagonal pixels only (see outline_pieces)
    for r in range(rows):
        for c in range(cols):
            v = lab[r, c]
            if v == 0 or (r > 0 and lab[r - 1, c] == v) or seen[r, c >> 3] & (1 << (c & 7)):
                continue
            # the corner (vr, vc) and the direction d: 0 east, 1 south, 2 west, 3 north (clockwise, rows down);
            # the label is on the right of each step
            vr, vc, d = r, c, 0
            a2 = 0
            begin = nxy
            diagonal = False
            while True:
                # one step, then the pixels ahead of the corner on the left (lr, lc) and on the right (qr, qc)
                if d == 0:
                    seen[vr, vc >> 3] |= np.uint8(1 << (vc & 7))
                    vc += 1
                    lr, lc, qr, qc = vr - 1, vc, vr, vc
                elif d == 1:
                    vr += 1
                    lr, lc, qr, qc = vr, vc, vr, vc - 1
                elif d == 2:
                    vc -= 1
                    lr, lc, qr, qc = vr, vc - 1, vr - 1, vc - 1
                else:
                    vr -= 1
                    lr, lc, qr, qc = vr - 1, vc - 1, vr - 1, vc
                on_left = 0 <= lr < rows and 0 <= lc < cols and lab[lr, lc] == v
                on_right = 0 <= qr < rows and 0 <= qc < cols and lab[qr, qc] == v
                nd = d
                if on_right:
                    if on_left:
                        nd = (d + 3) & 3  # turn left
                else:
                    nd = (d + 1) & 3  # turn right; also where only the left one is (a diagonal: another piece)
                    diagonal = diagonal or on_left
                if nd != d:
                    if nxy == xy.shape[0]:
                        xy = _grown(xy)
                    xy[nxy, 0], xy[nxy, 1] = vc, vr
                    if nxy > begin:
                        a2 += xy[nxy - 1, 0] * vr - vc * xy[nxy - 1, 1]
                    nxy += 1
                    d = nd
                if vr == r and vc == c and d == 0:
                    break
            if nxy == xy.shape[0]:
                xy = _grown(xy)
            xy[nxy] = xy[begin]  # closed
            a2 += xy[nxy - 1, 0] * xy[begin, 1] - xy[begin, 0] * xy[nxy - 1, 1]
            nxy += 1
            starts.append(nxy)
            labels.append(v)
            area2.append(a2)
            first_pixel.append(r * cols + c)
            corner.append(diagonal)
    return (
        xy[:nxy],
        np.array(starts, np.int64),
        np.array(labels, np.int64),
        np.array(area2, np.int64),
        np.array(first_pixel, np.int64),
        np.array(corner, np.bool_),
    )


def outline_pieces(
    labels: np.ndarray, transform, row0: int = 0, col0: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The outline of every label of ``labels`` (integers, 0: none; cut at ``row0, col0`` from a raster whose
    pixel corners ``transform`` puts on the map): the labels, ascending, one (multi)polygon each, and whether
    it may be invalid. Only a ring through a corner where its label holds two diagonal pixels can touch itself
    (a shell meeting its hole, two holes meeting) or touch another piece; the others need no validity check."""
    xy, starts, lab, area2, first, corner = _rings(labels)
    if not len(lab):
        return np.zeros(0, np.int64), np.zeros(0, dtype=object), np.zeros(0, bool)
    shell = area2 > 0
    piece = np.full(len(lab), -1, np.int64)
    piece[shell] = np.arange(int(shell.sum()))
    piece[~shell] = _holes_shell(xy, starts, lab, area2, first, labels.shape[1])
    # rings in polygon order: by piece, the shell before its holes
    order = np.lexsort((~shell, piece))
    sizes = np.diff(starts)[order]
    take = np.repeat(starts[:-1][order] - np.concatenate([[0], np.cumsum(sizes)[:-1]]), sizes) + np.arange(sizes.sum())
    ring_off = np.concatenate([[0], np.cumsum(sizes)])
    poly_off = np.r_[np.flatnonzero(shell[order]), len(order)]
    # from the raster's own corner numbers: a vertex's coordinates do not depend on where the image was cut
    c, r = (xy[take, 0] + col0).astype(float), (xy[take, 1] + row0).astype(float)
    t = transform
    coords = np.column_stack([t.a * c + t.b * r + t.c, t.d * c + t.e * r + t.f])
    polys = shapely.from_ragged_array(shapely.GeometryType.POLYGON, coords, (ring_off, poly_off))
    owner = lab[order][shell[order]]
    # one geometry per label: its pieces as a multipolygon where it has several (they touch at most at a corner)
    by = np.argsort(owner, kind="stable")
    owner, polys = owner[by], polys[by]
    first_of = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    count = np.diff(np.r_[first_of, len(owner)])
    suspect = np.isin(owner[first_of], lab[corner])
    if (count == 1).all():
        return owner, polys, suspect
    out = polys[first_of].copy()
    multi = np.flatnonzero(count > 1)
    members = np.isin(np.repeat(np.arange(len(first_of)), count), multi)
    group = np.repeat(np.arange(len(first_of)), count)[members]
    out[multi] = shapely.multipolygons(polys[members], indices=np.searchsorted(multi, group))
    return owner[first_of], out, suspect


def _holes_shell(xy, starts, lab, area2, first, cols) -> np.ndarray:
    """For each hole, the index (among the shells, in ring order) of the shell it lies in: the label's only
    shell, else the smallest shell of its label holding the pixel whose edge started the hole (a pixel of the
    piece around the hole; an outer piece's shell holds it too)."""
    shells = np.flatnonzero(area2 > 0)
    holes = np.flatnonzero(area2 <= 0)
    out = np.full(len(holes), -1, np.int64)
    if not len(holes):
        return out
    shell_lab = lab[shells]
    order = np.argsort(shell_lab, kind="stable")
    lo = np.searchsorted(shell_lab[order], lab[holes], side="left")
    hi = np.searchsorted(shell_lab[order], lab[holes], side="right")
    one = hi - lo == 1
    out[one] = order[lo[one]]
    for h in np.flatnonzero(~one):
        cand = order[lo[h] : hi[h]]
        pr, pc = divmod(int(first[holes[h]]), cols)
        rings = [shapely.polygons(xy[starts[shells[k]] : starts[shells[k] + 1]].astype(float)) for k in cand]
        inside = [k for k, g in zip(cand, rings) if shapely.contains_xy(g, pc + 0.5, pr + 0.5)]
        out[h] = min(inside, key=lambda k: area2[shells[k]]) if inside else cand[0]
    return out
