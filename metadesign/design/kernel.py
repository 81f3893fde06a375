"""The discretizer's compiled kernel (issue #35): rows of a design mapped onto atoms in one pass per cell,
the twin of :func:`metadesign.design.build.map_rows_numpy` (the same index map and error sums, bit for bit,
tested).

Per cell: the Eq. 1 phase of its lens for both polarisations (or a given unwrapped phase, for lenses with
Zernike terms), the constant offset, the wrap, the nearest atom (the look-up table of
:class:`~metadesign.design.discretize.NearestAtom`, unsafe table cells resolved among their candidates), the
clear aperture, and the terms of the error sums, summed in raster order the way ``np.sum`` does (numpy's
pairwise blocks and splits, replicated: the same bits, without keeping the terms)."""

from __future__ import annotations

import math

import numpy as np

from ..jit import njit
from .phase import SupercellSpec

__all__ = ["lens_table", "map_rows_kernel"]

_PI = math.pi
_TWO_PI = 2 * math.pi
# 2 pi = _C1 + _C2 exactly, _C1 with 27 significant bits and _C2 with at most 26: n * _C1 and n * _C2 are exact
# for |n| < 2^26 (Cody and Waite's reduction, with an exact two-term constant)
_C1 = float(np.frombuffer((np.frombuffer(np.float64(_TWO_PI).tobytes(), np.uint64) & ~np.uint64((1 << 26) - 1))
                          .tobytes(), np.float64)[0])
_C2 = _TWO_PI - _C1
_BIG = 2.0 ** 25 * _TWO_PI


@njit(inline=True)
def _wrap(v):
    """numpy's ``(v + pi) % (2 pi) - pi``, the same float (tested bit for bit), 10x faster: ``x - n 2 pi``
    with the truncated quotient ``n`` is exactly a float (what fmod returns); computed exactly in two steps,
    ``n`` corrected by one if its division rounded across an integer, then Python's sign rule."""
    x = v + _PI
    if not abs(x) < _BIG:  # NaN, infinities and beyond 2^25 turns: fmod itself
        return x % _TWO_PI - _PI
    n = np.trunc(x / _TWO_PI)
    r = (x - n * _C1) - n * _C2
    if x >= 0.0:
        if r < 0.0:
            n -= 1.0
            r = (x - n * _C1) - n * _C2
        elif r >= _TWO_PI:
            n += 1.0
            r = (x - n * _C1) - n * _C2
    else:
        if r > 0.0:
            n += 1.0
            r = (x - n * _C1) - n * _C2
        elif r <= -_TWO_PI:
            n -= 1.0
            r = (x - n * _C1) - n * _C2
        r = r + _TWO_PI if r < 0.0 else 0.0  # a remainder of the divisor's sign; zero is +0
    return r - _PI


#: numpy's pairwise summation (``np.sum`` of a contiguous float64 array): blocks of at most this many terms
_PW_BLOCK = 128


@njit
def _leaves(n):
    """The block lengths of numpy's pairwise sum of ``n`` terms, in order (its recursion split ``n`` into
    ``n2 = n // 2 - (n // 2) % 8`` and the rest until a block has at most 128 terms)."""
    out = np.empty(n // 32 + 2, np.int64)
    stack = np.empty(128, np.int64)
    stack[0] = n
    top, k = 1, 0
    while top:
        top -= 1
        m = stack[top]
        if m <= _PW_BLOCK:
            out[k] = m
            k += 1
        else:
            m2 = m // 2
            m2 -= m2 % 8
            stack[top] = m - m2  # the right half after the left
            stack[top + 1] = m2
            top += 2
    return out[:k]


@njit(inline=True)
def _block_sum(a, m):
    """numpy's pairwise_sum on a block of ``m`` <= 128 terms: 8 accumulators, combined as a tree, then the tail."""
    if m < 8:
        res = 0.0
        for i in range(m):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[0], a[1], a[2], a[3]
    r4, r5, r6, r7 = a[4], a[5], a[6], a[7]
    i = 8
    while i < m - m % 8:
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < m:
        res += a[i]
        i += 1
    return res


@njit
def _combine(sums, n):
    """numpy's pairwise recursion over ``n`` terms whose blocks' sums are ``sums`` (in order), without
    recursion (a recursive compiled function does not reload from numba's cache): left + right at each
    split, as ``pairwise_sum`` returns."""
    size = np.empty(128, np.int64)
    state = np.zeros(128, np.int64)  # 0: fresh, 1: left half pending, 2: right half pending
    left = np.zeros(128)
    size[0], top, idx, v = n, 0, 0, 0.0
    while True:
        m = size[top]
        if m <= _PW_BLOCK or state[top] == 3:
            if m <= _PW_BLOCK:
                v = sums[idx]
                idx += 1
            if top == 0:
                return v
            top -= 1  # hand v to the parent
            if state[top] == 1:
                left[top] = v
                m2 = size[top] // 2
                m2 -= m2 % 8
                state[top] = 2
                top += 1
                size[top], state[top] = size[top - 1] - m2, 0
            else:
                v = left[top] + v
                state[top] = 3
        else:
            m2 = m // 2
            m2 -= m2 % 8
            state[top] = 1
            top += 1
            size[top], state[top] = m2, 0


@njit
def _kernel(r0, r1, c0, c1, n, period, m, lenses, scale, offx, offy, use_offx, use_offy, phx, phy, mask_mode,
            radius2, mask, G, lut_scale, code, cand, ph, T0, empty, out, used):
    """The block's index map into ``out``, the atoms' counts into ``used``; returns the four sums (the
    squared errors and the efficiencies per polarisation, summed as ``np.sum`` would the terms in raster
    order, bit for bit), the two peak errors and the count of cells in the aperture.  Each row's Eq. 1
    phases are computed first, one loop per lens over the cells of its column (loops that vectorise:
    cheaper than a scalar lens per cell), in ``lens_phase``'s operations."""
    half = (n - 1) / 2
    h, w = r1 - r0, c1 - c0
    lo, hi = _spans(r0, r1, c0, c1, half, period, mask_mode, radius2)
    n_in = 0
    for i in range(h):
        n_in += hi[i] - lo[i]
    if mask_mode == 2:
        n_in = 0
        for i in range(h):
            for j in range(w):
                n_in += mask[i, j]
    leaves = _leaves(n_in)
    rowbuf = np.empty((2, m, w // m + 1))
    seen = np.zeros(m, np.int64)
    sums = np.zeros((4, leaves.size))
    buf = np.empty((4, _PW_BLOCK))
    leaf, pos = 0, 0
    peakx = 0.0
    peaky = 0.0
    for i in range(h):
        iy = r0 + i
        y = (iy - half) * period
        b = iy % m
        for j in range(lo[i]):
            out[i, j] = empty
        for j in range(hi[i], w):
            out[i, j] = empty
        if not phx.shape[0]:  # the row's Eq. 1 phases (see the docstring)
            for p in range(2):
                for cc in range(m):
                    ch = cc + m * b
                    f, ox, dy = lenses[p, ch, 0], lenses[p, ch, 1], y - lenses[p, ch, 2]
                    dy2, ff = dy * dy, f * f  # lens_phase's r2 and f * f, the same floats
                    j0 = lo[i] + (cc - (c0 + lo[i])) % m  # the row's first cell in column cc of its supercell
                    for q in range((hi[i] - j0 + m - 1) // m):
                        dx = (c0 + j0 + m * q - half) * period - ox
                        r2 = dx * dx + dy2
                        rowbuf[p, cc, q] = scale * r2 / (f + math.sqrt(ff + r2))
        col = (c0 + lo[i]) % m  # the cell's column in its supercell, counted (an integer division per cell costs)
        seen[:] = 0  # per column of the supercell: the cells of the row met so far (a cell's slot in rowbuf)
        for j in range(lo[i], hi[i]):
            cc_j = col
            q_j = seen[col]
            seen[col] += 1
            col += 1
            if col == m:
                col = 0
            if mask_mode == 2:
                if not mask[i, j]:
                    out[i, j] = empty
                    continue
            if phx.shape[0]:
                ax = phx[i, j]
                ay = phy[i, j]
            else:
                ax = rowbuf[0, cc_j, q_j]
                ay = rowbuf[1, cc_j, q_j]
            if use_offx:
                ax = ax + offx
            if use_offy:
                ay = ay + offy
            ax = _wrap(ax)
            ay = _wrap(ay)
            # the nearest atom (NearestAtom.__call__), written out here (as a called function: 8x slower);
            # code: the table cell's atom, or -(row + 1) of its candidates when the cell is unsafe
            lx = min(max(np.int64((ax + _PI) * lut_scale), 0), G - 1)
            ly = min(max(np.int64((ay + _PI) * lut_scale), 0), G - 1)
            k = np.int64(code[lx * G + ly])
            if k < 0:  # resolved exactly among the candidates, the first of equal costs as argmin
                row = -k - 1
                best = np.inf
                for q in range(cand.shape[1]):
                    a = cand[row, q]
                    if a < 0:
                        break
                    dx = _wrap(ax - ph[a, 0])
                    dy = _wrap(ay - ph[a, 1])
                    c = dx * dx + dy * dy
                    if c < best:
                        best = c
                        k = a
            out[i, j] = k
            ex = _wrap(ph[k, 0] - ax)
            ey = _wrap(ph[k, 1] - ay)
            buf[0, pos] = ex * ex
            buf[1, pos] = ey * ey
            buf[2, pos] = T0[k, 0]
            buf[3, pos] = T0[k, 1]
            peakx = max(peakx, abs(ex))
            peaky = max(peaky, abs(ey))
            used[k] += 1
            pos += 1
            if pos == leaves[leaf]:
                for t in range(4):
                    sums[t, leaf] = _block_sum(buf[t], pos)
                leaf += 1
                pos = 0
    res = np.zeros(4)
    if n_in:
        for t in range(4):
            res[t] = _combine(sums[t], n_in)
    return res, peakx, peaky, n_in


@njit
def _spans(r0, r1, c0, c1, half, period, mask_mode, radius2):
    """Per row of the block, the columns ``lo:hi`` inside a circular aperture (``x^2 + y^2 <= r^2``, the
    numpy mask's test: monotonic in ``|x|``, so one run per row), else the whole row."""
    h, w = r1 - r0, c1 - c0
    lo = np.zeros(h, np.int64)
    hi = np.full(h, w, np.int64)
    if mask_mode != 1:
        return lo, hi
    for i in range(h):
        y = (r0 + i - half) * period
        yy = y * y
        j = 0
        while j < w:
            x = (c0 + j - half) * period
            if x * x + yy <= radius2:
                break
            j += 1
        lo[i] = j
        k = w
        while k > j:
            x = (c0 + k - 1 - half) * period
            if x * x + yy <= radius2:
                break
            k -= 1
        hi[i] = k
    return lo, hi


def lens_table(spec: SupercellSpec) -> np.ndarray | None:
    """``[pol, channel, (f, offset_x, offset_y)]`` of the design's lenses, or None when a lens carries
    Zernike terms (its phase is then computed by numpy and handed to the kernel)."""
    chans = [spec.channels(p) for p in (0, 1)]
    if any(c.zernike for cs in chans for c in cs):
        return None
    return np.array([[[c.focal_length, c.offset_x, c.offset_y] for c in cs] for cs in chans], np.float64)


def map_rows_kernel(spec: SupercellSpec, atoms, mapper, offsets, dtype, empty, r0: int, r1: int, c0: int, c1: int,
                    lenses, phases, mask):
    """Rows ``r0:r1``, columns ``c0:c1`` of the index map and their error sums (see
    :func:`metadesign.design.build.map_rows`).  ``lenses``: :func:`lens_table` (or None with ``phases``, the
    two unwrapped design phases of the block); ``mask``: the clear aperture as a boolean block, or None
    (a circle is tested in the kernel, a full square needs no test)."""
    h, w = r1 - r0, c1 - c0
    if phases is None:
        phx = phy = np.zeros((0, 0))
        lt = lenses
    else:
        phx, phy = (np.ascontiguousarray(p, np.float64) for p in phases)
        lt = np.zeros((2, 1, 3))
    mask_mode, radius2, marr = 0, 0.0, np.zeros((0, 0), bool)
    if spec.bounded:
        if spec.aperture_wkt:
            mask_mode, marr = 2, np.ascontiguousarray(mask)
        else:
            r = spec.aperture / 2
            mask_mode, radius2 = 1, r * r
    out = np.empty((h, w), dtype)
    used = np.zeros(len(atoms), np.int64)
    ph = np.ascontiguousarray(atoms.phase, np.float64)
    T0 = np.ascontiguousarray(atoms.T0, np.float64)
    G = int(mapper.G)
    s, px, py, n_in = _kernel(r0, r1, c0, c1, spec.n_cells, float(spec.period), spec.supercell, lt,
                        -(2 * np.pi / spec.wavelength), float(offsets[0]), float(offsets[1]),
                        bool(offsets[0]), bool(offsets[1]), phx, phy, mask_mode, radius2, marr, G,
                        G / (2 * np.pi), mapper.code, mapper.cand, ph, T0,
                        empty if empty is not None else 0, out, used)
    return out, (s[:2].copy(), np.array([px, py]), s[2:].copy(), int(n_in), used)
