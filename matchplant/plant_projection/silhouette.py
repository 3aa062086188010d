"""A plant's map box from the rays along its photo box's edges (the silhouette), compiled.

The rays of :func:`~matchplant.plant_projection.geometry.project_boxes` have met the ground on the edges facing
the image's nadir point (a leaf tip on the soil, even behind a neighbour) and the DSM, stopped just above it,
on the others: such an edge may be the image of the plant's *top* displaced outwards by relief, and only its
ray grazing the top (stopped on it by the intersection's clearance) marks where the plant is. So each side is
the *innermost* hit of its edge. A side whose innermost hit stands more than ``hidden_height`` above the
ground, or whose ray skimmed a plant before landing on the soil, lay behind the plant's top (or behind another
plant): it is mirrored from the opposite side about the plant's top (the highest DSM point inside the box),
assuming a roughly symmetric plant.

Per box this is a few dozen numbers and a few DSM samples; numpy would need a dozen (boxes x points) passes and
temporaries for it (a third of module 8's time on a large field), so one compiled loop does it all.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from matchplant.core.geometry.raycast import TINY, bilinear
from matchplant.plant_projection.relief import APEX_WORK, Scene, apex_one, skimmed_one

APEX_REACH = 0.25  # how far past a hidden side (share of the box) the plant's top is looked for
FACING = 0.3  # a photo edge bears on a map side when its outward normal's component towards it exceeds this
DEGENERATE = 1e-18  # m²: a box frame whose axes span less than this (rays crossing) has no inside


class Silhouette(NamedTuple):
    """The compiled silhouette's results over M boxes (:func:`silhouette_boxes`)."""

    bounds: np.ndarray  # (M, 4) xmin, ymin, xmax, ymax
    centre: np.ndarray  # (M, 2)
    z: np.ndarray  # (M,) mean height of the DSM hits
    area: np.ndarray  # (M,) of the parallelogram, m²
    off_nadir: np.ndarray  # (M,) degrees between the plumb line and the ray to the centre
    unseen: np.ndarray  # (M, 4) map sides west, south, east, north not seen directly
    beside_cut: np.ndarray  # (M, 4) map sides beside a border cut
    across: np.ndarray  # (M, 4) map sides seen across the plant

    @classmethod
    def empty(cls, m: int) -> Silhouette:
        """Uninitialised results for ``m`` boxes, to be filled in."""
        sides = lambda: np.empty((m, 4), dtype=np.bool_)  # noqa: E731
        return cls(np.empty((m, 4)), np.empty((m, 2)), np.empty(m), np.empty(m), np.empty(m), sides(), sides(), sides())


@numba.njit(cache=True, nogil=True)
def _silhouette_kernel(g, d, near, cut, ok, scene, inscribed, res):
    m, p = g.shape[0], g.shape[1]
    q = p // 4
    dsm, gnd, cam = scene.dsm, scene.ground, scene.cam
    unseen, beside, across = res.unseen, res.beside_cut, res.across
    inner = np.empty(4)
    hidden = np.zeros(4, dtype=np.bool_)
    normal = np.empty((4, 2))
    work = np.empty(APEX_WORK)  # apex_one's scratch
    for i in range(m):
        unseen[i, :] = False
        beside[i, :] = False
        across[i, :] = False
        if not ok[i]:
            res.bounds[i, :] = math.nan
            res.centre[i, :] = math.nan
            res.z[i], res.area[i], res.off_nadir[i] = math.nan, math.nan, math.nan
            continue
        # the box's frame from its corners on the ground: axes along the photo's x (a) and y (b)
        x0, y0, x1, y1 = g[i, 0, 0], g[i, 0, 1], g[i, q, 0], g[i, q, 1]
        x2, y2, x3, y3 = g[i, 2 * q, 0], g[i, 2 * q, 1], g[i, 3 * q, 0], g[i, 3 * q, 1]
        cx, cy = (x0 + x1 + x2 + x3) / 4, (y0 + y1 + y2 + y3) / 4
        ax, ay = (x1 - x0 + x2 - x3) / 4, (y1 - y0 + y2 - y3) / 4
        bx, by = (x3 - x0 + x2 - x1) / 4, (y3 - y0 + y2 - y1) / 4
        det = ax * by - ay * bx
        if not abs(det) > DEGENERATE:
            det = math.nan
        for k in range(4):  # top, right, bottom, left: the innermost hit of each edge, in box coordinates
            src = g if near[i, k] else d  # a near edge's hits are on the ground, even at a shared corner
            best, arg = math.nan, k * q
            for j in range(q + 1):
                n = (k * q + j) % p
                ex, ey = src[i, n, 0] - cx, src[i, n, 1] - cy
                c = (ex * by - ey * bx) / det if k % 2 else (ax * ey - ay * ex) / det  # -1 .. 1 across the box
                if j == 0 or (c < best if k == 1 or k == 2 else c > best):
                    best, arg = c, n
            inner[k] = best
            hidden[k] = False
            if not near[i, k]:
                hx, hy, hz = src[i, arg, 0], src[i, arg, 1], src[i, arg, 2]
                hidden[k] = hz - bilinear(gnd.data, gnd.inv, hx, hy) > scene.hidden_height
                if not hidden[k]:
                    hidden[k] = skimmed_one(scene, hx, hy, hz)
        t, r, bo, le = inner[0], inner[1], inner[2], inner[3]
        if (hidden[0] or hidden[1] or hidden[2] or hidden[3]) and r > le and bo > t:
            # the plant's top: the highest DSM point in the box, which reaches past a hidden side (the clearance
            # stops a grazing ray a little before its tangent point, short of the top)
            w, h = r - le, bo - t
            window = (
                le - w * (APEX_REACH if hidden[3] else 0.0),
                r + w * (APEX_REACH if hidden[1] else 0.0),
                t - h * (APEX_REACH if hidden[0] else 0.0),
                bo + h * (APEX_REACH if hidden[2] else 0.0),
            )
            aa, ab = apex_one(dsm, (cx, cy, ax, ay, bx, by), window, work)
            t, r, bo, le = (
                min(t, 2 * ab - bo) if hidden[0] else t,
                max(r, 2 * aa - le) if hidden[1] else r,
                max(bo, 2 * ab - t) if hidden[2] else bo,
                min(le, 2 * aa - r) if hidden[3] else le,
            )
        if not (r > le and bo > t and math.isfinite(det)):  # inverted (rays crossing): the corners' box
            t, r, bo, le = -1.0, 1.0, 1.0, -1.0
        mx = cx + ((le + r) / 2) * ax + ((t + bo) / 2) * bx
        my = cy + ((le + r) / 2) * ay + ((t + bo) / 2) * by
        hax, hay = ax * ((r - le) / 2), ay * ((r - le) / 2)
        hbx, hby = bx * ((bo - t) / 2), by * ((bo - t) / 2)
        if inscribed:  # the box of the ellipse inscribed in the parallelogram
            wx, wy = math.sqrt(hax * hax + hbx * hbx), math.sqrt(hay * hay + hby * hby)
        else:
            wx, wy = abs(hax) + abs(hbx), abs(hay) + abs(hby)
        z = 0.0
        for n in range(p):
            z += d[i, n, 2]
        z /= p
        vx, vy, vz = mx - cam[0], my - cam[1], z - cam[2]
        cos = -vz / math.sqrt(vx * vx + vy * vy + vz * vz)
        res.bounds[i, 0], res.bounds[i, 1], res.bounds[i, 2], res.bounds[i, 3] = mx - wx, my - wy, mx + wx, my + wy
        res.centre[i, 0], res.centre[i, 1], res.z[i] = mx, my, z
        res.area[i] = abs(det) * (r - le) * (bo - t)
        res.off_nadir[i] = math.degrees(math.acos(min(max(cos, -1.0), 1.0)))
        # the map sides (west, south, east, north) a photo edge bears on: those its outward normal faces
        normal[0, 0], normal[0, 1], normal[1, 0], normal[1, 1] = -bx, -by, ax, ay  # top, right
        normal[2, 0], normal[2, 1], normal[3, 0], normal[3, 1] = bx, by, -ax, -ay  # bottom, left
        for k in range(4):
            length = max(math.sqrt(normal[k, 0] ** 2 + normal[k, 1] ** 2), TINY)
            nx, ny = normal[k, 0] / length, normal[k, 1] / length
            hid = hidden[k] or cut[i, k]
            # a box cut by a border bounds only the plant's part inside the photo: the edges beside the cut are
            # the plant's only if its outermost point there lies inside the photo
            by_cut = (cut[i, (k + 3) % 4] or cut[i, (k + 1) % 4]) and not hid
            for side in range(4):
                faces = (-nx if side == 0 else -ny if side == 1 else nx if side == 2 else ny) > FACING
                if faces and hid:
                    unseen[i, side] = True
                if faces and by_cut:
                    beside[i, side] = True
                if faces and not near[i, k]:
                    across[i, side] = True


def silhouette_boxes(
    g_pts: np.ndarray,
    d_pts: np.ndarray,
    near: np.ndarray,
    ok: np.ndarray,
    cut: np.ndarray,
    scene: Scene,
    inscribed: bool,
) -> Silhouette:
    """Map boxes of plants from their outline rays (module docstring).

    ``g_pts`` and ``d_pts`` (M, P, 3): where each outline ray (:func:`~.geometry.box_outline` order, corners at 0,
    P/4, P/2, 3P/4) met the ground and the DSM; the corners on the ground set the box's frame (axes along the
    photo's x and y, so any flight heading works). ``near`` (M, 4: top, right, bottom, left): edges facing the
    image's nadir point; ``ok`` (M,): boxes whose rays all hit (the others get NaN); ``cut`` (M, 4): edges cut
    by the photo or tile border; ``scene``: the DSM, the ground, the camera and the heights that tell a hidden
    side (:class:`~.relief.Scene`). ``inscribed``: the box of the ellipse inscribed in the resulting
    parallelogram (a round plant's box whatever the flight heading), else the box of the parallelogram.

    :class:`Silhouette` fields: ``across`` are the map sides borne by an edge facing away from the nadir point,
    seen across the plant: where a ray that passed over the plant's top unnoticed lands on the soil beyond it;
    ``unseen`` those behind the plant's top or cut by a border.
    """
    res = Silhouette.empty(g_pts.shape[0])
    f64 = lambda v: np.ascontiguousarray(v, dtype=np.float64)  # noqa: E731
    b8 = lambda v: np.ascontiguousarray(v, dtype=np.bool_)  # noqa: E731
    _silhouette_kernel(f64(g_pts), f64(d_pts), b8(near), b8(cut), b8(ok), scene, bool(inscribed), res)
    return res
