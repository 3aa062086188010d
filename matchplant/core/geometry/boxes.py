"""Axis-aligned boxes ``[xmin, ymin, xmax, ymax]``: IoU, overlapping pairs, one-to-one matching and
non-maximum suppression.

One implementation for every step that compares boxes or plants: merging imported predictions (step 4),
merging the detections of overlapping tiles (step 7), merging the views of one plant and scoring projected
plants (step 8), matching two plant sets (step 9).

Overlapping pairs come from a hierarchical grid compiled with numba (one thread). A box of level ``k``
spans at most the side ``base * 2**k`` (less :data:`_LEVEL_MARGIN`, for rounding); the boxes are sorted
by level, then by the column and row (both finer than the side) of their lower left corner. A box looks
for its partners on its own level and the coarser ones only: there, a partner's corner lies less than
one side to the left of and below its own corner, so a few columns of a few rows hold every candidate.
A pair is thus found once, from its finer box, and a few huge boxes among small ones cost a few
candidates per small box rather than a scan of their area: the cost grows with the number of overlaps,
not with the product of the set sizes. The pairs are then put in (i, j) order by a radix sort.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_LEVEL_MARGIN = 0.999  # share of the side a box of that level may span: a margin for rounding
_COLUMNS, _ROWS = 2, 8  # columns and rows per side in the sort key: the finer, the fewer wasted candidates
_BITS = 29  # bits of the column and of the row in a sort key; the level sits above them
_MAX_SIDES = 2.0**25  # the field spans at most this many sides of the finest level (keys fit their bits)
_SAMPLE = 4096  # queries sampled to size the buffers of the pairs
_BUCKET = 4096  # pairs per bucket of the first pass of their sort (a bucket is then sorted in cache)
_DIGIT = 11  # bits per pass, at most, of the radix sort within a bucket


def iou_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of box pairs ``a[i]``, ``b[i]`` (each (N, 4), ``[xmin, ymin, xmax, ymax]``)."""
    iw = np.clip(np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0]), 0, None)
    ih = np.clip(np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1]), 0, None)
    inter = iw * ih
    area = lambda x: (x[:, 2] - x[:, 0]) * (x[:, 3] - x[:, 1])  # noqa: E731
    union = area(a) + area(b) - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)


@numba.njit(cache=True, nogil=True)
def _index(v, origin, step):
    """Column or row of coordinate ``v`` (steps of ``step`` from ``origin``), at least 0."""
    return max(np.int64(math.floor((v - origin) / step)), 0)


@numba.njit(cache=True, nogil=True)
def _grid(box, valid):
    """Level and sort key of every box (invalid ones: level -1, the largest key), the grid's origin and
    finest side."""
    n = box.shape[0]
    ox = oy = np.inf
    ex = ey = -np.inf
    smallest = np.inf
    for k in range(n):
        if valid[k]:
            ox, oy = min(ox, box[k, 0]), min(oy, box[k, 1])
            ex, ey = max(ex, box[k, 2]), max(ey, box[k, 3])
            smallest = min(smallest, max(box[k, 2] - box[k, 0], box[k, 3] - box[k, 1]))
    base = max(smallest, max(ex - ox, ey - oy) / _MAX_SIDES)
    level = np.full(n, -1, dtype=np.int64)
    key = np.full(n, np.iinfo(np.int64).max, dtype=np.int64)
    for k in range(n):
        if not valid[k]:
            continue
        size = max(box[k, 2] - box[k, 0], box[k, 3] - box[k, 1])
        lv, side = 0, base
        while size > side * _LEVEL_MARGIN:
            lv += 1
            side *= 2.0
        level[k] = lv
        key[k] = (
            (lv << (2 * _BITS))
            | (_index(box[k, 0], ox, side / _COLUMNS) << _BITS)
            | _index(box[k, 1], oy, side / _ROWS)
        )
    return level, key, ox, oy, base


@numba.njit(cache=True, nogil=True)
def _reach(box, level, base, top):
    """How far left of and below a box's corner the corners of its partners of each level can lie: the
    widest and the tallest box of that level, with a margin for rounding, and at most the level's side."""
    reach = np.zeros((top + 1, 2))
    scale = 0.0
    for k in range(box.shape[0]):
        if level[k] >= 0:
            reach[level[k], 0] = max(reach[level[k], 0], box[k, 2] - box[k, 0])
            reach[level[k], 1] = max(reach[level[k], 1], box[k, 3] - box[k, 1])
            scale = max(scale, abs(box[k, 0]), abs(box[k, 1]), abs(box[k, 2]), abs(box[k, 3]))
    for lv in range(top + 1):
        side = base * 2.0**lv
        for a in range(2):
            reach[lv, a] = min(reach[lv, a] * (1 + 2.0**-30) + scale * 2.0**-48, side)
    return reach


@numba.njit(cache=True, nogil=True)
def _columns(skey, level_start, top, budget):
    """Where each column of each level starts in the sorted keys (``starts[offset[lv] + c]``, one more
    entry per level for its end), or empty arrays when that index would exceed ``budget`` entries."""
    mask = (np.int64(1) << _BITS) - 1
    count = np.zeros(top + 1, dtype=np.int64)
    for lv in range(top + 1):
        if level_start[lv + 1] > level_start[lv]:
            count[lv] = ((skey[level_start[lv + 1] - 1] >> _BITS) & mask) + 1
    offset = np.zeros(top + 2, dtype=np.int64)
    offset[1:] = np.cumsum(count + 1)
    if offset[-1] > budget:
        return np.zeros(0, dtype=np.int64), offset, count
    starts = np.empty(offset[-1], dtype=np.int64)
    for lv in range(top + 1):
        c = 0
        for p in range(level_start[lv], level_start[lv + 1]):
            col = (skey[p] >> _BITS) & mask
            while c <= col:
                starts[offset[lv] + c] = p
                c += 1
        starts[offset[lv] + c : offset[lv + 1]] = level_start[lv + 1]
    return starts, offset, count


@numba.njit(cache=True, nogil=True)
def _index_grid(box, valid):
    """The boxes sorted by key, with what a query needs to find a column of a level."""
    level, key, ox, oy, base = _grid(box, valid)
    reach = _reach(box, level, base, level.max())
    order = np.argsort(key)
    skey = key[order]
    sbox = box[order]  # in key order: scanning a column reads memory in sequence
    top = level.max()
    level_start = np.searchsorted(skey, np.arange(top + 2, dtype=np.int64) << (2 * _BITS))
    starts, offset, count = _columns(skey, level_start, top, 4 * box.shape[0] + 1024)
    return level, order, skey, sbox, ox, oy, base, level_start, starts, offset, count, reach


@numba.njit(cache=True, nogil=True)
def _scan(grid, n_first, same, j_bits, out_key, out_iou, m, first_query, stride):
    """Append every overlapping pair to ``out_key`` (``i << j_bits | j``, ``i`` in the first set, ``j`` in
    the second) and ``out_iou`` from position ``m``, for every ``stride``-th query (in key order) from
    ``first_query`` on. Returns the pairs written and the next query: the end, or the query that did not
    fit the buffers (its pairs are then left out, to be found again in larger buffers)."""
    level, order, skey, sbox, ox, oy, base, level_start, starts, offset, count, reach = grid
    top = level_start.shape[0] - 2
    cap = out_key.shape[0]
    mask = (np.int64(1) << _BITS) - 1
    for pq in range(first_query, level_start[top + 1], stride):  # queries in key order: neighbours, in memory too
        m_query = m
        q = order[pq]
        qx0, qy0, qx1, qy1 = sbox[pq, 0], sbox[pq, 1], sbox[pq, 2], sbox[pq, 3]
        q_area = (qx1 - qx0) * (qy1 - qy0)
        q_first = q < n_first
        own = level[q]
        side = base * 2.0**own
        for lv in range(own, top + 1):
            if level_start[lv + 1] > level_start[lv]:
                c0, c1 = _index(qx0 - reach[lv, 0], ox, side / _COLUMNS), _index(qx1, ox, side / _COLUMNS)
                r0, r1 = _index(qy0 - reach[lv, 1], oy, side / _ROWS), min(_index(qy1, oy, side / _ROWS), mask)
                if lv == own:  # one level: the pair is found from its box that comes first in key order
                    c0 = (skey[pq] >> _BITS) & mask
                if starts.size:
                    c1 = min(c1, count[lv] - 1)
                for c in range(c0, c1 + 1):
                    col_key = (lv << (2 * _BITS)) | (c << _BITS)
                    lo, hi = level_start[lv], level_start[lv + 1]
                    if starts.size:
                        lo, hi = starts[offset[lv] + c], starts[offset[lv] + c + 1]
                    p = lo + np.searchsorted(skey[lo:hi], col_key | r0)
                    if lv == own:
                        p = max(p, pq + 1)
                    end = col_key | r1
                    while p < hi and skey[p] <= end:
                        iw = min(qx1, sbox[p, 2]) - max(qx0, sbox[p, 0])
                        ih = min(qy1, sbox[p, 3]) - max(qy0, sbox[p, 1])
                        p += 1
                        if iw <= 0 or ih <= 0:
                            continue
                        j = order[p - 1]
                        if not same and (j < n_first) == q_first:
                            continue  # two sets: pairs across them only
                        # the arithmetic of iou_pairs, operation for operation (the same result to the bit)
                        inter = iw * ih
                        union = q_area + (sbox[p - 1, 2] - sbox[p - 1, 0]) * (sbox[p - 1, 3] - sbox[p - 1, 1]) - inter
                        iou = inter / union if union > 0 else 0.0
                        if not iou > 0:
                            continue
                        if m == cap:
                            return m_query, pq
                        if same:
                            out_key[m] = (min(q, j) << j_bits) | max(q, j)
                        elif q_first:
                            out_key[m] = (q << j_bits) | (j - n_first)
                        else:
                            out_key[m] = (j << j_bits) | (q - n_first)
                        out_iou[m] = iou
                        m += 1
            side *= 2.0
    return m, level_start[top + 1]


@numba.njit(cache=True, nogil=True)
def _digit_starts(key, shift, mask, lo, hi):
    """Where each value of the digit ``(key >> shift) & mask`` of ``key[lo:hi]`` starts once sorted on it
    (from ``lo``; one more entry for the end)."""
    start = np.zeros(mask + 2, dtype=np.int64)
    for t in range(lo, hi):
        start[((key[t] >> shift) & mask) + 1] += 1
    start[0] = lo
    for d in range(mask + 1):
        start[d + 1] += start[d]
    return start


@numba.njit(cache=True, nogil=True)
def _count_sort(key, value, shift, mask, lo, hi, out_key, out_value):
    """``key[lo:hi]`` and ``value[lo:hi]`` into ``out_*[lo:hi]`` ordered (stably) on a digit; returns the
    digits' starts (:func:`_digit_starts`)."""
    start = _digit_starts(key, shift, mask, lo, hi)
    place = start[:-1].copy()
    for t in range(lo, hi):
        d = (key[t] >> shift) & mask
        out_key[place[d]], out_value[place[d]] = key[t], value[t]
        place[d] += 1
    return start


@numba.njit(cache=True, nogil=True)
def _count_sort_split(key, value, shift, mask, j_bits, out_i, out_j, out_value):
    """The last pass of :func:`_count_sort`, writing each key as its ``i`` and ``j``."""
    place = _digit_starts(key, shift, mask, 0, key.shape[0])[:-1]
    j_mask = (np.int64(1) << j_bits) - 1
    for t in range(key.shape[0]):
        d = (key[t] >> shift) & mask
        out_i[place[d]], out_j[place[d]], out_value[place[d]] = key[t] >> j_bits, key[t] & j_mask, value[t]
        place[d] += 1


@numba.njit(cache=True, nogil=True)
def _split(key, j_bits):
    """``i`` of every key ``i << j_bits | j``; ``key`` itself becomes ``j``."""
    i = np.empty_like(key)
    j_mask = (np.int64(1) << j_bits) - 1
    for t in range(key.shape[0]):
        i[t] = key[t] >> j_bits
        key[t] &= j_mask
    return i


@numba.njit(cache=True, nogil=True)
def _sort_pairs(key, value, bits, j_bits):
    """Pairs ``key = i << j_bits | j`` (below ``2**bits``) and ``value`` sorted on key, as ``i``, ``j`` and
    ``value``: a counting sort on the high bits into buckets of about :data:`_BUCKET` pairs, then a radix
    sort of each bucket in cache (least significant digit first). ``i`` and ``value`` are written into
    ``key`` and ``value``: tens of millions of pairs take memory enough."""
    m = key.shape[0]
    high = 0
    while high < bits and (m >> high) > _BUCKET:
        high += 1
    k2, v2 = np.empty_like(key), np.empty_like(value)
    bucket = _count_sort(key, value, bits - high, (1 << high) - 1, 0, m, k2, v2)
    largest = np.max(bucket[1:] - bucket[:-1])
    s_key, s_value = np.empty(largest, dtype=key.dtype), np.empty(largest, dtype=value.dtype)
    passes = max(1, -(-(bits - high) // _DIGIT))
    width = -(-(bits - high) // passes)
    mask = (1 << width) - 1
    for b in range(bucket.shape[0] - 1):
        lo, hi = bucket[b], bucket[b + 1]
        n = hi - lo
        if n == 0:
            continue
        # the passes alternate between the bucket in k2 and the scratch arrays, the last one reading scratch
        src_k, src_v, dst_k, dst_v = k2[lo:hi], v2[lo:hi], s_key[:n], s_value[:n]
        if passes % 2 == 1:
            dst_k[:], dst_v[:] = src_k, src_v
            src_k, src_v, dst_k, dst_v = dst_k, dst_v, src_k, src_v
        for p in range(passes - 1):
            _count_sort(src_k, src_v, p * width, mask, 0, n, dst_k, dst_v)
            src_k, src_v, dst_k, dst_v = dst_k, dst_v, src_k, src_v
        _count_sort_split(src_k, src_v, (passes - 1) * width, mask, j_bits, key[lo:hi], k2[lo:hi], value[lo:hi])
    return key, k2, value


def _as_boxes(x: np.ndarray, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return np.zeros((0, 4))
    if x.ndim != 2 or x.shape[1] != 4:
        raise ValueError(f"{name}: boxes must be an (N, 4) array [xmin, ymin, xmax, ymax], got shape {x.shape}")
    return x


def _expected_pairs(grid: tuple, n_first: int, same: bool, j_bits: int) -> int:
    """Room for the pairs: a fifth more than a sample of :data:`_SAMPLE` queries finds, scaled up (at least
    four pairs per box). Buffers are enlarged as needed anyway; a good guess saves copies and memory."""
    queries = int(grid[7][-1])
    if queries <= _SAMPLE:
        return 4 * queries + 1024
    stride = queries // _SAMPLE
    key, iou = np.empty(64 * _SAMPLE, dtype=np.int64), np.empty(64 * _SAMPLE)
    m, done = _scan(grid, n_first, same, j_bits, key, iou, 0, 0, stride)
    sampled = max(-(-done // stride), 1)
    return max(int(1.2 * m * queries / sampled), 4 * queries) + 1024


def _larger(x: np.ndarray, used: int) -> np.ndarray:
    out = np.empty(2 * len(x), dtype=x.dtype)
    out[:used] = x[:used]
    return out


def overlapping_pairs(
    a: np.ndarray, b: np.ndarray | None = None, *, ordered: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)`` of boxes of ``a`` and ``b`` with IoU > 0, and their IoU (as :func:`iou_pairs`
    computes it), sorted by ``(i, j)``. Within one set (``b`` None) each pair comes once, with ``i < j``.

    Boxes with a NaN or infinite coordinate, or without area (zero or negative width or height), overlap
    nothing; boxes that only touch (IoU 0) are no pair. ``ordered=False`` skips the sort (about half the
    time with tens of pairs per box) for callers that do not need it: the pairs then come in the grid's
    order, which depends only on the boxes (the same input gives the same output)."""
    same = b is None
    a = _as_boxes(a, "a")
    b = a if same else _as_boxes(b, "b")
    both = a if same else np.concatenate([a, b])
    valid = np.isfinite(both).all(axis=1) & (both[:, 2] > both[:, 0]) & (both[:, 3] > both[:, 1])
    if len(a) == 0 or len(b) == 0 or not valid.any():
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)
    j_bits = max(int(len(b) - 1).bit_length(), 1)
    grid = _index_grid(np.ascontiguousarray(both), valid)
    cap = _expected_pairs(grid, len(a), same, j_bits)
    key, iou = np.empty(cap, dtype=np.int64), np.empty(cap)  # (i, j) as one key, to sort
    m, done = _scan(grid, len(a), same, j_bits, key, iou, 0, 0, 1)
    while done < grid[7][-1]:  # the buffers are full: twice as large, and on from the query that did not fit
        key, iou = _larger(key, m), _larger(iou, m)
        m, done = _scan(grid, len(a), same, j_bits, key, iou, m, done, 1)
    if not ordered:
        return _split(key[:m], j_bits), key[:m], iou[:m]
    return _sort_pairs(key[:m], iou[:m], j_bits + max(int(len(a) - 1).bit_length(), 1), j_bits)


def greedy_matches(i: np.ndarray, j: np.ndarray, order: np.ndarray, n_a: int, n_b: int) -> np.ndarray:
    """Candidate pairs ``(i[k], j[k])`` kept by a greedy one-to-one matching visiting them in ``order``
    (best first): a pair is kept when neither of its members is taken yet. Returns the kept ``k``, in
    visiting order. Candidate pairs are few (each box overlaps a handful of others), so a loop is cheap."""
    used_a, used_b = np.zeros(n_a, dtype=bool), np.zeros(n_b, dtype=bool)
    kept = []
    for k in order:
        a, b = i[k], j[k]
        if not used_a[a] and not used_b[b]:
            used_a[a] = used_b[b] = True
            kept.append(k)
    return np.asarray(kept, dtype=np.int64)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _suppress(box, start, iou):
    """Greedy NMS within each group ``box[start[g]:start[g + 1]]`` of boxes in visiting order: the positions
    kept. The arithmetic of torchvision's CPU kernel, operation for operation (the same boxes kept); the
    boxes are in visiting order so that the inner loop reads memory in sequence."""
    area = (box[:, 2] - box[:, 0]) * (box[:, 3] - box[:, 1])
    suppressed = np.zeros(box.shape[0], dtype=np.bool_)
    keep = np.empty(box.shape[0], dtype=np.int64)
    m = 0
    for g in range(start.shape[0] - 1):
        for i in range(start[g], start[g + 1]):
            if suppressed[i]:
                continue
            keep[m] = i
            m += 1
            for j in range(i + 1, start[g + 1]):
                if suppressed[j]:
                    continue
                iw = max(min(box[i, 2], box[j, 2]) - max(box[i, 0], box[j, 0]), 0.0)
                ih = max(min(box[i, 3], box[j, 3]) - max(box[i, 1], box[j, 1]), 0.0)
                inter = iw * ih
                if inter / (area[i] + area[j] - inter) > iou:
                    suppressed[j] = True
    return keep[:m]


def nms(boxes: np.ndarray, scores: np.ndarray, iou: float, labels: np.ndarray | None = None) -> np.ndarray:
    """Non-maximum suppression: indices of the boxes kept, highest score first (equal scores: the earlier
    box first). A box goes when its IoU with a kept box of its label (of any box, without ``labels``) is
    above ``iou``: torchvision's ``batched_nms`` on float64 boxes, without PyTorch."""
    boxes = _as_boxes(boxes, "boxes")
    by_score = np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable")
    group = np.zeros(len(boxes), dtype=np.int64) if labels is None else np.asarray(labels)
    order = by_score[np.argsort(group[by_score], kind="stable")]  # one group per label, each in score order
    g = group[order]
    start = np.r_[0, np.flatnonzero(g[1:] != g[:-1]) + 1, len(g)]
    kept = order[_suppress(np.ascontiguousarray(boxes[order]), start, float(iou))]
    rank = np.empty(len(boxes), dtype=np.int64)
    rank[by_score] = np.arange(len(boxes))
    return kept[np.argsort(rank[kept])]


def match_boxes(reference: np.ndarray, predicted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matching, highest IoU first: for each reference box its predicted index (-1) and IoU."""
    i, j, iou = overlapping_pairs(reference, predicted)
    order = np.argsort(-iou, kind="stable")
    kept = greedy_matches(i, j, order, len(reference), len(predicted))
    ref_match = np.full(len(reference), -1, dtype=np.int64)
    ref_iou = np.zeros(len(reference))
    ref_match[i[kept]], ref_iou[i[kept]] = j[kept], iou[kept]
    return ref_match, ref_iou
