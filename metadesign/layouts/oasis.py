"""A streaming OASIS writer (SEMI P39) for lattice layouts: records are encoded with numpy and written
as they are made, so a layout of any size is written in the memory of one tile.

Only what a metasurface needs: CELLNAME (implicit reference numbers), CELL, RECTANGLE, PLACEMENT
with an arbitrary-with-grid repetition (type 11: the lattice pitch is the grid, so the displacement
from one pillar to the next in raster order is a small integer: one byte within a row), POLYGON
(all-angle point list), TEXT, PROPERTY (a b-string value), CBLOCK (raw deflate) and END with a CRC32
validation signature.  The encoders are pure functions returning bytes; :class:`OasisWriter` owns the
file, the running CRC and the reference numbers.

Integers: unsigned = little-endian base-128 with a continuation bit; signed = magnitude << 1 | sign;
g-delta form 1 (one unsigned: ``mag << 4 | dir << 1``, dir 0 = east) for a step along +x, form 2
otherwise (``|dx| << 2 | sign_x << 1 | 1``, then the signed ``dy``).
"""

from __future__ import annotations

import zlib

import numpy as np

__all__ = ["OasisWriter", "uint_array", "uints", "sint", "uint", "gdelta_array", "gdelta_grid", "placement_head",
           "repetition_head", "placement_record", "rectangle_record", "polygon_record", "text_record",
           "property_record", "cblock", "MAGIC"]

MAGIC = b"%SEMI-OASIS\r\n"
_END_BYTES = 256


def uint_array(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The unsigned-integer encoding of every value of ``v`` (non-negative): the bytes (uint8, all
    values concatenated) and each value's byte count."""
    v = np.asarray(v, dtype=np.uint64).ravel()
    if not v.size:
        return np.zeros(0, np.uint8), np.zeros(0, np.int64)
    nb = np.ones(v.size, np.int64)
    t = v >> np.uint64(7)
    while True:  # bytes per value, 7 bits at a time (a handful of passes)
        nz = t > 0
        if not nz.any():
            break
        nb += nz
        t >>= np.uint64(7)
    out = np.empty(int(nb.sum()), np.uint8)
    start = np.cumsum(nb) - nb
    for k in range(int(nb.max())):
        sel = nb > k if k else slice(None)
        byte = (v[sel] >> np.uint64(7 * k)) & np.uint64(0x7F)
        more = (nb[sel] > k + 1).astype(np.uint64) << np.uint64(7)
        out[start[sel] + k] = (byte | more).astype(np.uint8)
    return out, nb


def uints(v: np.ndarray) -> bytes:
    """The unsigned-integer encoding of every value of ``v`` (non-negative), concatenated."""
    return uint_array(v)[0].tobytes()


def uint(v: int) -> bytes:
    if v < 0:
        raise ValueError(f"unsigned integer {v} < 0")
    out = bytearray()
    while True:
        b = v & 0x7F
        v >>= 7
        out.append(b | (0x80 if v else 0))
        if not v:
            return bytes(out)


def sint(v: int) -> bytes:
    return uint((abs(v) << 1) | (1 if v < 0 else 0))


def astring(s: bytes) -> bytes:
    return uint(len(s)) + s


def gdelta_array(dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The g-deltas ``(dx, dy)`` (integers) as bytes (uint8) and each delta's byte count: form 1 for a
    step along +x, form 2 otherwise."""
    dx, dy = np.asarray(dx, np.int64).ravel(), np.asarray(dy, np.int64).ravel()
    east = (dy == 0) & (dx > 0)
    first = np.where(east, dx << 4, (np.abs(dx) << 2) | ((dx < 0).astype(np.int64) << 1) | 1)
    second = (np.abs(dy) << 1) | (dy < 0)
    vals = np.stack([first, second], 1)
    keep = np.stack([np.ones_like(east), ~east], 1)
    out, nb = uint_array(vals[keep].astype(np.uint64))
    per = np.zeros(vals.shape, np.int64)
    per[keep] = nb
    return out, per.sum(1)


def gdelta_grid(dx: np.ndarray, dy: np.ndarray) -> bytes:
    """The g-deltas ``(dx, dy)`` (integers), concatenated (see :func:`gdelta_array`)."""
    return gdelta_array(dx, dy)[0].tobytes()


def repetition_head(count: int, grid: int) -> bytes:
    """The start of a type-11 repetition of ``count`` >= 2 copies on ``grid`` (its g-deltas follow)."""
    return uint(11) + uint(count - 2) + uint(grid)


def placement_head(refnum: int, x: int, y: int, repetition: bool) -> bytes:
    """PLACEMENT (17) of cell ``refnum`` at (x, y) up to its repetition."""
    return bytes([17, 0xF0 | (0x08 if repetition else 0)]) + uint(refnum) + sint(x) + sint(y)


def rectangle_record(layer: int, datatype: int, w: int, h: int, x: int, y: int) -> bytes:
    """RECTANGLE (20): lower-left corner (x, y), size w x h."""
    return (bytes([20, 0x7B]) + uint(layer) + uint(datatype) + uint(w) + uint(h) + sint(x) + sint(y))


def placement_record(refnum: int, x: int, y: int, ix: np.ndarray | None = None, iy: np.ndarray | None = None,
                     grid: int = 1) -> bytes:
    """PLACEMENT (17) of cell ``refnum`` at (x, y); with ``ix, iy`` (the lattice indices of every copy,
    the first at (x, y), in the order written) a type-11 repetition on ``grid``."""
    rep = ix is not None and len(ix) > 1
    head = placement_head(refnum, x, y, rep)
    if not rep:
        return head
    return head + repetition_head(len(ix), grid) + gdelta_grid(np.diff(ix), np.diff(iy))


def polygon_record(layer: int, datatype: int, pts: np.ndarray) -> bytes:
    """POLYGON (21) through integer points (n, 2) (closed implicitly): all-angle point list."""
    pts = np.asarray(pts, np.int64)
    d = np.diff(pts, axis=0)
    return (bytes([21, 0x3B]) + uint(layer) + uint(datatype) + uint(4) + uint(len(d))
            + gdelta_grid(d[:, 0], d[:, 1]) + sint(int(pts[0, 0])) + sint(int(pts[0, 1])))


def text_record(text: bytes, layer: int, texttype: int, x: int, y: int) -> bytes:
    """TEXT (19) with an explicit string."""
    return bytes([19, 0x5B]) + astring(text) + uint(layer) + uint(texttype) + sint(x) + sint(y)


def property_record(name: bytes, value: bytes) -> bytes:
    """PROPERTY (28) named ``name`` with one b-string value, on the preceding element or cell."""
    return bytes([28, 0x14]) + astring(name) + bytes([11]) + astring(value)


def cblock(records: bytes, level: int = 1) -> bytes:
    """CBLOCK (34): ``records`` deflated (raw, no zlib header)."""
    c = zlib.compressobj(level, zlib.DEFLATED, -15)
    z = c.compress(records) + c.flush()
    return bytes([34]) + uint(0) + uint(len(records)) + uint(len(z)) + z


class OasisWriter:
    """Write an OASIS file record by record (database unit ``1 / unit_per_um`` um); the caller opens
    the file (atomically) and calls :meth:`close` to write END with the CRC32 signature."""

    def __init__(self, fh, unit_per_um: int = 1000):
        self.fh = fh
        self.crc = 0
        self.bytes = 0
        self.refnums: dict[str, int] = {}
        # START: version "1.0", unit (real type 0: positive integer), offset-flag 0 + six empty tables
        self._put(MAGIC + bytes([1]) + astring(b"1.0") + bytes([0]) + uint(unit_per_um) + uint(0) + bytes(12))

    def _put(self, b: bytes) -> None:
        self.fh.write(b)
        self.crc = zlib.crc32(b, self.crc)
        self.bytes += len(b)

    def cellname(self, name: str) -> int:
        """Declare a cell name; returns its reference number (implicit: 0, 1, ... in order)."""
        self.refnums[name] = len(self.refnums)
        self._put(bytes([3]) + astring(name.encode()))
        return self.refnums[name]

    def cell(self, name: str) -> None:
        self._put(bytes([13]) + uint(self.refnums[name]))

    def records(self, b: bytes, compress: int | None = 1) -> None:
        """Element records of the current cell, in one CBLOCK unless ``compress`` is None."""
        if b:
            self._put(cblock(b, compress) if compress is not None else b)

    def raw(self, b: bytes) -> None:
        """Bytes already encoded (e.g. a CBLOCK made by a worker)."""
        self._put(b)

    def close(self) -> None:
        body = bytes([2])
        pad = _END_BYTES - len(body) - 1 - 4
        n = pad - len(uint(pad))  # b-string: its length prefix counts against the padding
        while len(uint(n)) + n != pad:
            n -= 1
        self._put(body + uint(n) + bytes(n) + bytes([1]))  # validation scheme 1: CRC32
        self.fh.write(int(self.crc).to_bytes(4, "little"))
        self.bytes += 4
