"""A reader of the OASIS records the project's writers use (SEMI P39), read forward in bounded memory: the
decoder under the streaming verifier (:mod:`metadesign.layouts.stream`).

It covers PAD, START, END, CELLNAME, TEXTSTRING, PROPNAME, PROPSTRING, CELL, XYABSOLUTE/XYRELATIVE,
PLACEMENT, TEXT, RECTANGLE, POLYGON, PROPERTY, CBLOCK and repetitions of types 0-3 and 8-11; any other
record is an :class:`OasisError` naming its byte offset, never skipped.  :class:`OasisFile` reads the file
forward in chunks (with the running CRC32 and byte sum of the END record's signature), :class:`Block` the
records in memory (a CBLOCK's inflated bytes), both through :class:`RecordReader`; :func:`gdelta_decode`
decodes long g-delta lists (type-11 repetitions) with numpy."""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["MAGIC", "END_BYTES", "CHUNK", "MAX_COPIES", "DECODE_ERRORS", "OasisError", "gdelta_decode", "Modal", "Element", "RecordReader", "Block",
           "OasisFile"]

MAGIC = b"%SEMI-OASIS\r\n"
END_BYTES = 256
CHUNK = 1 << 24  # bytes read at a time
#: the most copies a repetition may have (a tile of the project's layouts holds ~1e6 pillars)
MAX_COPIES = 1 << 31
#: what decoding a damaged file may raise besides :class:`OasisError` (a count or a value out of any
#: range, a property of the wrong type): the verifier reports each as a malformed file
DECODE_ERRORS = (ValueError, IndexError, OverflowError, ZeroDivisionError, MemoryError, TypeError)


class OasisError(ValueError):
    """A malformed or unsupported record (the message names the byte offset)."""


# ----------------------------------------------------------------------------------------------------------
# g-deltas, vectorised

_DIR1 = np.array([[1, 0], [0, 1], [-1, 0], [0, -1], [1, 1], [-1, 1], [-1, -1], [1, -1]], np.int64)


def _varints(buf: np.ndarray, ends: np.ndarray, s: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` unsigned integers starting at byte ``s`` of ``buf`` (``ends``: the positions of every byte
    < 128 in ``buf``, the last byte of each integer): their values and end positions (fewer when ``buf``
    ends first)."""
    i0 = int(np.searchsorted(ends, s))
    e = ends[i0:i0 + k]
    st = np.empty(len(e), np.int64)
    if len(e):
        st[0] = s
        st[1:] = e[:-1] + 1
    ln = e - st + 1
    if len(ln) and ln.max() > 9:
        raise OasisError(f"an integer of more than 63 bits at byte {int(st[np.argmax(ln)])} of a block")
    v = np.zeros(len(e), np.uint64)
    for j in range(int(ln.max()) if len(ln) else 0):
        m = ln > j
        v[m] |= (buf[st[m] + j].astype(np.uint64) & np.uint64(0x7F)) << np.uint64(7 * j)
    return v, e


def gdelta_decode(buf: np.ndarray, ends: np.ndarray, s: int, count: int) -> tuple[np.ndarray, np.ndarray, int]:
    """``count`` g-deltas starting at byte ``s`` of ``buf`` (form 1: one integer, bit 0 clear, an octangular
    direction and a magnitude; form 2: ``|dx| << 2 | sign << 1 | 1`` then a signed ``dy``): ``(dx, dy, end)``
    with ``end`` the byte after the last.  Which integers start a g-delta is decided without a loop: after an
    even integer the next one starts a g-delta; in a run of odd integers the starts alternate from the
    run's first."""
    if count == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), s
    for k in (count + count // 4 + 8, 2 * count):  # most g-deltas are one integer: try a little more first
        v, e = _varints(buf, ends, s, k)
        odd = (v & np.uint64(1)).astype(bool)
        if not odd.any():
            starts = np.arange(min(count, len(v)))
        else:
            t = np.arange(len(v))
            first = np.ones(len(v), bool)
            first[1:] = ~odd[:-1]
            u = np.maximum.accumulate(np.where(first, t, 0))
            starts = np.flatnonzero(((t - u) & 1) == 0)[:count]
        if len(starts) == count and not (odd[starts[-1]] and starts[-1] + 1 >= len(v)):
            break
    else:
        raise OasisError(f"a g-delta list of {count} runs past the end of its block (byte {s})")
    a = v[starts].astype(np.int64)
    two = odd[starts]
    dx = np.empty(count, np.int64)
    dy = np.empty(count, np.int64)
    one = ~two
    d = _DIR1[(a[one] >> 1) & 7]
    mag = a[one] >> 4
    dx[one], dy[one] = d[:, 0] * mag, d[:, 1] * mag
    b = v[starts[two] + 1].astype(np.int64)
    dx[two] = np.where((a[two] >> 1) & 1, -(a[two] >> 2), a[two] >> 2)
    dy[two] = np.where(b & 1, -(b >> 1), b >> 1)
    last = starts[-1] + (2 if two[-1] else 1)
    return dx, dy, int(e[last - 1]) + 1


# ----------------------------------------------------------------------------------------------------------
# records

@dataclass
class Modal:
    """OASIS modal variables (the ones the supported records use)."""

    xy_relative: bool = False
    placement_cell: int | None = None
    placement_x: int = 0
    placement_y: int = 0
    layer: int | None = None
    datatype: int | None = None
    geometry_w: int | None = None
    geometry_h: int | None = None
    geometry_x: int = 0
    geometry_y: int = 0
    repetition: tuple | None = None
    text_x: int = 0
    text_y: int = 0
    textlayer: int | None = None
    texttype: int | None = None
    text: bytes | None = None
    polygon: np.ndarray | None = None
    last_property: tuple | None = None


@dataclass
class Element:
    kind: str  # "placement", "rectangle", "polygon", "text", "property"
    ref: int | None = None
    x: int = 0
    y: int = 0
    rep: tuple | None = None
    w: int = 0
    h: int = 0
    layer: int = 0
    datatype: int = 0
    name: bytes = b""
    values: list = field(default_factory=list)


class RecordReader:
    """The OASIS readers shared by a block in memory and the file itself: integers, reals, g-deltas,
    repetitions, point lists and the element records; a subclass gives ``byte``, ``uint``, ``string``,
    ``read`` and ``where``."""

    def uint(self) -> int:
        v = shift = 0
        while True:
            b = self.byte()
            v |= (b & 0x7F) << shift
            if b < 128:
                return v
            shift += 7
            if shift > 63:
                raise OasisError(f"an unsigned integer of more than 63 bits ({self.where()})")

    def string(self) -> bytes:
        return self.read(self.uint())

    def sint(self) -> int:
        v = self.uint()
        return -(v >> 1) if v & 1 else v >> 1

    def real(self, t: int | None = None) -> float:
        t = self.uint() if t is None else t
        if t in (0, 1):
            v = float(self.uint())
            return v if t == 0 else -v
        if t in (2, 3):
            v = 1.0 / self.uint()
            return v if t == 2 else -v
        if t in (4, 5):
            v = self.uint() / self.uint()
            return v if t == 4 else -v
        if t in (6, 7):
            n = 4 if t == 6 else 8
            raw = self.read(n)
            return float(np.frombuffer(raw, "<f4" if n == 4 else "<f8")[0])
        raise OasisError(f"real of unknown type {t} ({self.where()})")

    def gdelta(self) -> tuple[int, int]:
        a = self.uint()
        if not a & 1:
            d = _DIR1[(a >> 1) & 7]
            return int(d[0]) * (a >> 4), int(d[1]) * (a >> 4)
        dx = -(a >> 2) if (a >> 1) & 1 else a >> 2
        return dx, self.sint()

    def gdeltas(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        d = np.array([self.gdelta() for _ in range(count)], np.int64).reshape(-1, 2)
        return d[:, 0], d[:, 1]

    def _copies(self, count: int) -> int:
        """A repetition's count of copies, refused beyond :data:`MAX_COPIES` (a damaged count would ask for
        arrays of any size)."""
        if count > MAX_COPIES:
            raise OasisError(f"a repetition of {count} copies ({self.where()}): more than any layout holds")
        return count

    def repetition(self, modal: Modal) -> tuple:
        """A repetition as ``(dx, dy)``: every copy's offset from the first (int64 arrays)."""
        t = self.uint()
        if t == 0:
            if modal.repetition is None:
                raise OasisError(f"repetition type 0 with no previous repetition ({self.where()})")
            return modal.repetition
        if t in (1, 2, 3):
            nx = self.uint() + 2 if t in (1, 2) else 1
            ny = self.uint() + 2 if t in (1, 3) else 1
            sx = self.uint() if t in (1, 2) else 0
            sy = self.uint() if t in (1, 3) else 0
            self._copies(nx * ny)
            jy, jx = np.divmod(np.arange(nx * ny, dtype=np.int64), nx)
            rep = (jx * sx, jy * sy)
        elif t in (8, 9):
            n = self.uint() + 2
            m = self.uint() + 2 if t == 8 else 1
            ndx, ndy = self.gdelta()
            mdx, mdy = self.gdelta() if t == 8 else (0, 0)
            self._copies(n * m)
            jm, jn = np.divmod(np.arange(n * m, dtype=np.int64), n)
            rep = (jn * ndx + jm * mdx, jn * ndy + jm * mdy)
        elif t in (10, 11):
            n = self._copies(self.uint() + 2)
            grid = self.uint() if t == 11 else 1
            dx, dy = self.gdeltas(n - 1)
            ox = np.zeros(n, np.int64)
            oy = np.zeros(n, np.int64)
            np.cumsum(dx * grid, out=ox[1:])
            np.cumsum(dy * grid, out=oy[1:])
            rep = (ox, oy)
        else:
            raise OasisError(f"repetition type {t} is not supported by the streaming verifier ({self.where()})")
        modal.repetition = rep
        return rep

    def point_list(self) -> np.ndarray:
        t = self.uint()
        n = self.uint()
        if t in (0, 1):
            d = [self.sint() for _ in range(n)]
            pts = [(0, 0)]
            horiz = t == 0
            for v in d:
                x, y = pts[-1]
                pts.append((x + v, y) if horiz else (x, y + v))
                horiz = not horiz
            return np.array(pts, np.int64)
        if t == 4:
            dx, dy = self.gdeltas(n)
            return np.stack([np.concatenate(([0], np.cumsum(dx))), np.concatenate(([0], np.cumsum(dy)))], 1)
        raise OasisError(f"point list of type {t} is not supported by the streaming verifier ({self.where()})")

    def _xy(self, info: int, modal: Modal, kind: str) -> None:
        """The x (info bit 0x10) and y (0x08) of a geometry or text record into its modal variables."""
        for bit, name in ((0x10, f"{kind}_x"), (0x08, f"{kind}_y")):
            if info & bit:
                v = self.sint()
                setattr(modal, name, getattr(modal, name) + v if modal.xy_relative else v)

    def _layer(self, info: int, modal: Modal) -> None:
        if info & 0x01:
            modal.layer = self.uint()
        if info & 0x02:
            modal.datatype = self.uint()

    def element(self, rid: int, modal: Modal) -> Element | None:
        """The element record ``rid`` (its id byte read), or None for the modal-only records."""
        if rid == 15 or rid == 16:
            modal.xy_relative = rid == 16
            return None
        if rid == 17:
            info = self.byte()
            if info & 0x80:
                if not info & 0x40:
                    raise OasisError(f"a placement naming its cell by string is not supported ({self.where()})")
                modal.placement_cell = self.uint()
            if modal.placement_cell is None:
                raise OasisError(f"a placement with no cell ({self.where()})")
            if info & 0x06 or info & 0x01:
                raise OasisError(f"a rotated or flipped placement ({self.where()}): the lattice has none")
            x, y = (self.sint() if info & 0x20 else None), (self.sint() if info & 0x10 else None)
            modal.placement_x = (modal.placement_x + x if modal.xy_relative else x) if x is not None else modal.placement_x
            modal.placement_y = (modal.placement_y + y if modal.xy_relative else y) if y is not None else modal.placement_y
            rep = self.repetition(modal) if info & 0x08 else None
            return Element("placement", modal.placement_cell, modal.placement_x, modal.placement_y, rep)
        if rid == 20:
            info = self.byte()
            self._layer(info, modal)
            if info & 0x40:
                modal.geometry_w = self.uint()
            if info & 0x80:  # square: the height is the width
                if info & 0x20:
                    raise OasisError(f"a square rectangle with a height ({self.where()})")
                modal.geometry_h = modal.geometry_w
            elif info & 0x20:
                modal.geometry_h = self.uint()
            self._xy(info, modal, "geometry")
            rep = self.repetition(modal) if info & 0x04 else None
            if None in (modal.layer, modal.datatype, modal.geometry_w, modal.geometry_h):
                raise OasisError(f"a rectangle with an unset modal variable ({self.where()})")
            return Element("rectangle", None, modal.geometry_x, modal.geometry_y, rep, modal.geometry_w,
                            modal.geometry_h, modal.layer, modal.datatype)
        if rid == 21:
            info = self.byte()
            self._layer(info, modal)
            if info & 0x20:
                modal.polygon = self.point_list()
            self._xy(info, modal, "geometry")
            rep = self.repetition(modal) if info & 0x04 else None
            return Element("polygon", None, modal.geometry_x, modal.geometry_y, rep, layer=modal.layer or 0,
                            datatype=modal.datatype or 0)
        if rid == 19:
            info = self.byte()
            if info & 0x40:
                modal.text = self.uint() if info & 0x20 else self.string()
            if info & 0x01:
                modal.textlayer = self.uint()
            if info & 0x02:
                modal.texttype = self.uint()
            self._xy(info, modal, "text")
            rep = self.repetition(modal) if info & 0x04 else None
            return Element("text", None, modal.text_x, modal.text_y, rep,
                            name=modal.text if isinstance(modal.text, bytes) else b"")
        if rid == 28:
            info = self.byte()
            name = b""
            if info & 0x04:
                name = self.uint() if info & 0x02 else self.string()
            values = []
            if not info & 0x08:
                n = info >> 4
                if n == 15:
                    n = self.uint()
                for _ in range(n):
                    vt = self.uint()
                    if vt <= 7:
                        values.append(self.real(vt))
                    elif vt == 8:
                        values.append(self.uint())
                    elif vt == 9:
                        values.append(self.sint())
                    elif vt in (10, 11, 12):
                        values.append(self.string())
                    elif vt in (13, 14, 15):
                        values.append(self.uint())
                    else:
                        raise OasisError(f"property value of unknown type {vt} ({self.where()})")
            modal.last_property = (name, values)
            return Element("property", name=name if isinstance(name, bytes) else b"", values=values)
        if rid == 29:
            if modal.last_property is None:
                raise OasisError(f"PROPERTY repeat with no previous property ({self.where()})")
            return Element("property", name=modal.last_property[0], values=modal.last_property[1])
        raise OasisError(f"record type {rid} is not supported by the streaming verifier ({self.where()})")


class Block(RecordReader):
    """Records in memory (a CBLOCK's inflated bytes, or a run of plain records): a byte position and the
    readers of OASIS integers and strings; ``ends`` for the vectorised g-delta lists."""

    def __init__(self, data: bytes, base: int):
        self.data, self.pos, self.base = data, 0, base
        self._arr = self._ends = None

    @property
    def arr(self) -> np.ndarray:
        if self._arr is None:
            self._arr = np.frombuffer(self.data, np.uint8)
            self._ends = np.flatnonzero(self._arr < 128)
        return self._arr

    def where(self) -> str:
        return f"byte {self.base + self.pos}"

    def byte(self) -> int:
        if self.pos >= len(self.data):
            raise OasisError(f"a record runs past the end of its block ({self.where()})")
        b = self.data[self.pos]
        self.pos += 1
        return b

    def gdeltas(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        if count < 64:  # short lists: the scalar reader is cheaper than the vector set-up
            return super().gdeltas(count)
        _ = self.arr
        dx, dy, end = gdelta_decode(self._arr, self._ends, self.pos, count)
        self.pos = end
        return dx, dy

    def elements(self, modal: Modal):
        """The block's element records, in order (PAD and the modal-only records skipped)."""
        while self.pos < len(self.data):
            r = self.byte()
            if r:
                el = self.element(r, modal)
                if el is not None:
                    yield el

    def read(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise OasisError(f"a record runs past the end of its block ({self.where()})")
        s = self.data[self.pos:self.pos + n]
        self.pos += n
        return s


def _byte_sum(b) -> int:
    return int(np.frombuffer(b, np.uint8).sum(dtype=np.uint64))


class OasisFile(RecordReader):
    """The file read forward in chunks; with ``sign``, the running CRC32 and byte sum of every byte
    consumed (the scan's; a stripe worker reads its tiles' bytes and nothing else)."""

    def __init__(self, path: Path, sign: bool = True):
        self.fh = open(path, "rb")
        self.size = path.stat().st_size
        self.buf, self.i, self.off = b"", 0, 0  # off: file offset of buf[0]
        self.sign, self.chunk = sign, CHUNK
        self.crc = 0
        self.sum = 0

    def close(self) -> None:
        self.fh.close()

    def tell(self) -> int:
        return self.off + self.i

    def _fill(self, n: int) -> None:
        if len(self.buf) - self.i >= n:
            return
        if self.sign:
            done = memoryview(self.buf)[:self.i]
            self.crc = zlib.crc32(done, self.crc)
            self.sum += _byte_sum(done)
        self.off += self.i
        self.buf = self.buf[self.i:] + self.fh.read(max(self.chunk, n))
        self.i = 0
        if len(self.buf) < n:
            raise OasisError(f"the file ends at byte {self.off + len(self.buf)} inside a record (truncated)")

    def read(self, n: int) -> bytes:
        self._fill(n)
        b = self.buf[self.i:self.i + n]
        self.i += n
        return b

    def byte(self) -> int:
        self._fill(1)
        b = self.buf[self.i]
        self.i += 1
        return b

    def where(self) -> str:
        return f"byte {self.tell()}"

    def seek(self, offset: int, span: int = CHUNK) -> None:
        """Read on from ``offset``, ``span`` bytes at a time (a worker's tile: its own bytes, not a chunk of
        the file per tile); only for a reader without a signature."""
        if self.sign:
            raise RuntimeError("a signed read goes through the file once, in order")
        self.fh.seek(offset)
        self.buf, self.i, self.off, self.chunk = b"", 0, offset, max(1, span)

    def cblock(self, inflate: bool = True) -> Block | None:
        """A CBLOCK's records (its id byte read): inflated into a block, or (``inflate`` False) only read."""
        at = self.tell() - 1
        if self.uint() != 0:
            raise OasisError(f"CBLOCK at byte {at} with an unknown compression type")
        n_raw, n_z = self.uint(), self.uint()
        z = self.read(n_z)
        if not inflate:
            return None
        try:
            data = zlib.decompressobj(-15).decompress(z, n_raw + 1)
        except zlib.error as exc:
            raise OasisError(f"CBLOCK at byte {at} does not inflate ({exc})") from None
        if len(data) != n_raw:
            raise OasisError(f"CBLOCK at byte {at}: {len(data)} bytes inflated, its header says {n_raw}")
        return Block(data, at)

    def signature_base(self) -> tuple[int, int]:
        """CRC32 and byte sum of every byte consumed so far."""
        done = memoryview(self.buf)[:self.i]
        return zlib.crc32(done, self.crc), (self.sum + _byte_sum(done)) & 0xFFFFFFFF
