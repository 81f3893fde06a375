"""The OASIS encoder's compiled kernel (issue #35): the placements of one tile in one pass, the twin of
:func:`metadesign.layouts.tiled.tile_records_numpy` (the same bytes, tested).

Per atom present (ascending): a PLACEMENT at its first pillar in raster order and a type-11 repetition
whose g-deltas step through the others; the pillars are grouped by atom with a counting sort (two passes
over the tile) instead of a stable argsort."""

from __future__ import annotations

import numpy as np

from ..jit import njit

__all__ = ["tile_records_kernel"]


@njit(inline=True)
def _uint(buf, p, v):
    # OASIS unsigned integer: little-endian base 128, continuation bit (oasis.uint)
    while v >= 128:
        buf[p] = (v & 0x7F) | 0x80
        v >>= 7
        p += 1
    buf[p] = v
    return p + 1


@njit(inline=True)
def _sint(buf, p, v):
    return _uint(buf, p, (-v << 1) | 1 if v < 0 else v << 1)


@njit
def _records(blk, r0, c0, n_atoms, pitch, x0, buf):
    h, w = blk.shape
    counts = np.zeros(n_atoms, np.int64)
    for i in range(h):
        for j in range(w):
            v = blk[i, j]
            if v < n_atoms:
                counts[v] += 1
    start = np.empty(n_atoms, np.int64)
    total = 0
    for a in range(n_atoms):
        start[a] = total
        total += counts[a]
    if total == 0:
        return 0
    fill = start.copy()
    ys = np.empty(total, np.int64)
    xs = np.empty(total, np.int64)
    for i in range(h):
        for j in range(w):
            v = blk[i, j]
            if v < n_atoms:
                t = fill[v]
                ys[t] = r0 + i
                xs[t] = c0 + j
                fill[v] = t + 1
    p = 0
    for a in range(n_atoms):
        c = counts[a]
        if c == 0:
            continue
        s = start[a]
        buf[p] = 17
        buf[p + 1] = 0xF8 if c > 1 else 0xF0
        p = _uint(buf, p + 2, a)
        p = _sint(buf, p, xs[s] * pitch + x0)
        p = _sint(buf, p, ys[s] * pitch + x0)
        if c > 1:
            p = _uint(buf, p, 11)
            p = _uint(buf, p, c - 2)
            p = _uint(buf, p, pitch)
            for t in range(s + 1, s + c):
                dx = xs[t] - xs[t - 1]
                dy = ys[t] - ys[t - 1]
                if dy == 0 and dx > 0:  # g-delta form 1, east
                    p = _uint(buf, p, dx << 4)
                else:  # form 2
                    p = _uint(buf, p, (-dx << 2) | 3 if dx < 0 else (dx << 2) | 1)
                    p = _uint(buf, p, (-dy << 1) | 1 if dy < 0 else dy << 1)
    return p


def tile_records_kernel(blk: np.ndarray, r0: int, c0: int, n_atoms: int, pitch: int, x0: int) -> bytes:
    """The placements of one tile (``blk``: its index map, global origin ``r0, c0``; values ``>= n_atoms``
    are empty cells), uncompressed."""
    h, w = blk.shape
    per = 2 * (1 + (max(h, w, 1) << 4).bit_length() // 7)  # a g-delta's two integers at most
    head = 6 + 3 * 10 + 3 * 10  # a placement and its repetition's head at most
    buf = np.empty(h * w * per + n_atoms * head + 16, np.uint8)
    n = _records(np.ascontiguousarray(blk), int(r0), int(c0), int(n_atoms), int(pitch), int(x0), buf)
    return buf[:n].tobytes()
