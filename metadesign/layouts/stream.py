"""A streaming verifier of the project's OASIS files: the file read once, in the memory of one tile,
whatever its size (a 10 cm device's ~8 GB included), with no other reader in between.

What it checks, against the design written with the layout (``design.npz``, its index map streamed by
stripes):

* the file: magic, START, every record well-formed (an unknown or malformed record, or a file that ends
  before END, is a problem with its byte offset), END at its fixed size, the CRC32 (or checksum)
  signature over every byte before it;
* every pillar: each tile cell's placements expanded (type-11 repetitions, g-deltas decoded with numpy)
  onto the lattice and compared **cell by cell** with the design's index map (not a sample): a pillar
  dropped, moved, duplicated, off the lattice or of another atom is counted; the pillar count per atom
  equals the design's;
* the geometry: each atom cell one rectangle, centred on its origin as the writer centres it, its size the
  design's width snapped to the grid; the top cell places every tile cell once at the origin;
* the design rules on the placed geometry: every pillar's width against ``min_feature_nm``, and the gap
  between every pair of lattice neighbours (across tile borders too) against ``min_gap_nm``, counted per
  pair of atoms as the tiles stream by and evaluated once the atom rectangles (written last) are read.

The reader covers the OASIS records the project's writers use (SEMI P39: PAD, START, END, CELLNAME,
TEXTSTRING, PROPNAME, PROPSTRING, CELL, XYABSOLUTE/XYRELATIVE, PLACEMENT, TEXT, RECTANGLE, POLYGON,
PROPERTY, CBLOCK; repetitions of types 0-3 and 8-11); any other record is reported, not skipped.  Pillar
positions need a tiled layout (``hierarchy = "tiles"``: a cell ``TILE_<r>_<c>`` per tile, as
:mod:`metadesign.layouts.tiled` writes); KLayout (``layout verify --klayout``) stays the independent
reader at the sizes it can hold."""

from __future__ import annotations

import json
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io import NpzRows, from_json_array
from ..parallel import run_tasks
from ..validation import InputError
from .rules import DESIGN_RULES
from .writer import TOP_CELL, layout_geometry, snap_widths

__all__ = ["verify_stream", "gdelta_decode", "OasisError"]

MAGIC = b"%SEMI-OASIS\r\n"
END_BYTES = 256
CHUNK = 1 << 24  # bytes read at a time


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
class _Modal:
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
class _Element:
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


class _Reader:
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

    def repetition(self, modal: _Modal) -> tuple:
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
            jy, jx = np.divmod(np.arange(nx * ny, dtype=np.int64), nx)
            rep = (jx * sx, jy * sy)
        elif t in (8, 9):
            n = self.uint() + 2
            m = self.uint() + 2 if t == 8 else 1
            ndx, ndy = self.gdelta()
            mdx, mdy = self.gdelta() if t == 8 else (0, 0)
            jm, jn = np.divmod(np.arange(n * m, dtype=np.int64), n)
            rep = (jn * ndx + jm * mdx, jn * ndy + jm * mdy)
        elif t in (10, 11):
            n = self.uint() + 2
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

    def _xy(self, info: int, modal: _Modal, kind: str) -> None:
        """The x (info bit 0x10) and y (0x08) of a geometry or text record into its modal variables."""
        for bit, name in ((0x10, f"{kind}_x"), (0x08, f"{kind}_y")):
            if info & bit:
                v = self.sint()
                setattr(modal, name, getattr(modal, name) + v if modal.xy_relative else v)

    def _layer(self, info: int, modal: _Modal) -> None:
        if info & 0x01:
            modal.layer = self.uint()
        if info & 0x02:
            modal.datatype = self.uint()

    def element(self, rid: int, modal: _Modal) -> _Element | None:
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
            return _Element("placement", modal.placement_cell, modal.placement_x, modal.placement_y, rep)
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
            return _Element("rectangle", None, modal.geometry_x, modal.geometry_y, rep, modal.geometry_w,
                            modal.geometry_h, modal.layer, modal.datatype)
        if rid == 21:
            info = self.byte()
            self._layer(info, modal)
            if info & 0x20:
                modal.polygon = self.point_list()
            self._xy(info, modal, "geometry")
            rep = self.repetition(modal) if info & 0x04 else None
            return _Element("polygon", None, modal.geometry_x, modal.geometry_y, rep, layer=modal.layer or 0,
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
            return _Element("text", None, modal.text_x, modal.text_y, rep,
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
            return _Element("property", name=name if isinstance(name, bytes) else b"", values=values)
        if rid == 29:
            if modal.last_property is None:
                raise OasisError(f"PROPERTY repeat with no previous property ({self.where()})")
            return _Element("property", name=modal.last_property[0], values=modal.last_property[1])
        raise OasisError(f"record type {rid} is not supported by the streaming verifier ({self.where()})")


class _Block(_Reader):
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

    def elements(self, modal: _Modal):
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


class _File(_Reader):
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

    def cblock(self, inflate: bool = True) -> "_Block | None":
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
        return _Block(data, at)

    def signature_base(self) -> tuple[int, int]:
        """CRC32 and byte sum of every byte consumed so far."""
        done = memoryview(self.buf)[:self.i]
        return zlib.crc32(done, self.crc), (self.sum + _byte_sum(done)) & 0xFFFFFFFF


# ----------------------------------------------------------------------------------------------------------
# the verifier

class _Problems(list):
    """Problem lines, at most ``limit`` kept (then one line saying more were found)."""

    def __init__(self, limit: int = 20):
        super().__init__()
        self.limit = limit

    def __call__(self, msg: str) -> None:
        if len(self) < self.limit:
            self.append(msg)
        elif len(self) == self.limit:
            self.append("... (more problems not listed)")


@dataclass(frozen=True)
class _Grid:
    """What a stripe worker needs (sent once per worker)."""

    path: str
    design: str
    n: int
    n_atoms: int
    p_nm: int
    x0: int
    tile: int
    empty: int | None

    @property
    def itype(self):
        """Index maps in the verifier: atoms and -1 (no pillar) in 2 bytes a cell where they fit."""
        return np.int16 if self.n_atoms < 2**15 else np.int32


#: a worker's open reader of the design's index map, kept across its stripes: a deflated entry is read
#: forward only, so a fresh reader per stripe would inflate everything above the stripe again (quadratic
#: in the stripes: at 10 cm, 279 stripes of a 20 GB map)
_ROWS: dict[str, NpzRows] = {}


def _rows_of(design: str) -> NpzRows:
    rows = _ROWS.get(design)
    if rows is None:
        for old in _ROWS.values():
            old.close()
        _ROWS.clear()
        rows = _ROWS[design] = NpzRows(design, "index_map")
    return rows


def _design_rows(rows: NpzRows, g: _Grid, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
    """The design's rows ``r0:r1`` as an index map (-1 = no pillar) and their per-atom counts."""
    raw = rows[r0:r1]
    want = np.bincount(raw.ravel(), minlength=g.n_atoms + 1)[:g.n_atoms].astype(np.int64)
    if g.empty is not None and g.empty < g.n_atoms:
        want[g.empty] = 0
    im = raw.astype(g.itype)
    if g.empty is not None:
        im[raw == g.empty] = -1
    return im, want


def _pairs(a: np.ndarray, b: np.ndarray, k: int) -> np.ndarray:
    """Counts of neighbour pairs (a, b), both pillars, as a flat k x k table."""
    m = (a >= 0) & (b >= 0)
    return np.bincount(a[m].astype(np.int64) * k + b[m], minlength=k * k)


def _tile_elements(f: "_File", offset: int, length: int, problem) -> list:
    """The placements of one tile cell (its records at ``offset``, ``length`` bytes), as
    ``(atom, x, y, dx offsets, dy offsets)``."""
    f.seek(offset, length)
    modal = _Modal()  # modal variables are reset at each CELL record
    atoms = []
    end = offset + length
    while f.tell() < end:
        rid = f.byte()
        if rid == 0:
            continue
        if rid == 34:
            blk = f.cblock()
            for el in blk.elements(modal):
                if el.kind == "placement":
                    atoms.append(_placed(el))
                else:
                    problem(f"a tile cell holds a {el.kind} (byte {blk.base}): tiles hold placements only")
            continue
        el = f.element(rid, modal)
        if el is not None and el.kind == "placement":
            atoms.append(_placed(el))
        elif el is not None:
            problem(f"a tile cell holds a {el.kind} (byte {f.tell()}): tiles hold placements only")
    return atoms


def _placed(el: _Element) -> tuple:
    if el.rep is None:
        return el.ref, el.x, el.y, np.zeros(1, np.int64), np.zeros(1, np.int64)
    return el.ref, el.x, el.y, el.rep[0], el.rep[1]


def _stripe_job(g: _Grid, job: tuple) -> dict:
    """Worker: the tiles of one stripe (``job = (r, [(name, c, offset, length), ...])``) against the
    design's rows: per-atom counts, neighbour pairs, mismatches, and the stripe's bottom and top rows (for
    the pairs across stripes)."""
    r, tiles = job
    problem = _Problems()
    k = g.n_atoms
    out = {"r": r, "counts": np.zeros(k, np.int64), "pairs_h": np.zeros(k * k, np.int64),
           "pairs_v": np.zeros(k * k, np.int64), "mismatched": 0, "duplicates": 0, "off_lattice": 0,
           "problems": problem, "tiles": 0}
    r0 = r * g.tile
    h = min(g.tile, g.n - r0)
    rows = _rows_of(g.design)
    f = _File(Path(g.path), sign=False)
    try:
        block, out["want"] = _design_rows(rows, g, r0, r0 + h)
        covered = np.zeros(g.n, bool)
        top = np.full(g.n, -1, g.itype)
        bottom = np.full(g.n, -1, g.itype)
        left = None
        for name, c, offset, length in sorted(tiles, key=lambda t: t[1]):
            c0 = c * g.tile
            if c0 >= g.n:
                problem(f"{name}: outside the design's {g.n} columns")
                continue
            w = min(g.tile, g.n - c0)
            if covered[c0:c0 + w].any():
                problem(f"{name}: a second cell for the same tile")
            covered[c0:c0 + w] = True
            try:
                placed = _tile_elements(f, offset, length, problem)
            except OasisError as exc:
                problem(f"malformed file: {name}: {exc}")
                placed = []
            out["tiles"] += 1
            got = _tile_map(name, placed, g, r0, c0, h, w, out, problem)
            ref = block[:, c0:c0 + w]
            mm = int(np.count_nonzero(got != ref))
            if mm:
                out["mismatched"] += mm
                j, i = np.argwhere(got != ref)[0]
                problem(f"{name}: {mm} cells differ from the design (first: row {r0 + j}, column {c0 + i}: "
                        f"layout {int(got[j, i])}, design {int(ref[j, i])}; -1 = no pillar)")
            out["pairs_h"] += _pairs(got[:, :-1], got[:, 1:], k)
            out["pairs_v"] += _pairs(got[:-1, :], got[1:, :], k)
            if left is not None and left[0] == c - 1:
                out["pairs_h"] += _pairs(left[1], got[:, 0], k)
            left = (c, got[:, -1].copy())
            bottom[c0:c0 + w], top[c0:c0 + w] = got[0], got[-1]
        lost = int(np.count_nonzero(block[:, ~covered] >= 0))
        if lost:
            out["mismatched"] += lost
            problem(f"stripe {r}: {lost} designed pillars in columns no tile cell covers")
        out["bottom"], out["top"] = bottom, top
    finally:
        f.close()
    return out


def _tile_map(name: str, placed: list, g: _Grid, r0: int, c0: int, h: int, w: int, out: dict, problem) -> np.ndarray:
    """The tile's pillars on its lattice cells (-1: none), counting what lies off the lattice, outside the
    tile, on an occupied cell or is not an atom."""
    got = np.full((h, w), -1, g.itype)
    if not placed:
        return got
    ids = np.array([a for a, *_ in placed], np.int64)
    sizes = np.array([len(ox) for *_, ox, _ in placed], np.int64)
    aa = np.repeat(ids, sizes)
    xs = np.concatenate([px + ox for _, px, _, ox, _ in placed])
    ys = np.concatenate([py + oy for _, _, py, _, oy in placed])
    foreign = (aa < 0) | (aa >= g.n_atoms)
    if foreign.any():
        problem(f"{name}: places cells {sorted(set(aa[foreign].tolist()))[:5]}, not atoms of the design")
    ix, rx = np.divmod(xs - g.x0, g.p_nm)
    iy, ry = np.divmod(ys - g.x0, g.p_nm)
    ix -= c0
    iy -= r0
    bad = (rx != 0) | (ry != 0) | (ix < 0) | (ix >= w) | (iy < 0) | (iy >= h) | foreign
    nb = int(np.count_nonzero(bad))
    if nb:
        out["off_lattice"] += nb
        j = int(np.flatnonzero(bad)[0])
        problem(f"{name}: {nb} pillars off the {g.p_nm} nm lattice or outside the tile (first: atom {int(aa[j])} "
                f"at ({int(xs[j])}, {int(ys[j])}) nm)")
        keep = ~bad
        aa, ix, iy = aa[keep], ix[keep], iy[keep]
    out["counts"] += np.bincount(aa, minlength=g.n_atoms)
    flat = iy * w + ix
    hits = np.bincount(flat, minlength=h * w)
    d = int((hits[hits > 1] - 1).sum())
    if d:
        out["duplicates"] += d
        problem(f"{name}: {d} pillars placed on an occupied cell")
    got.ravel()[flat] = aa
    return got


def _tile_size(path: Path, given: int | None) -> int | None:
    """The tile size to stream with: given, or the one the writer's side-car names (the file's own record
    of it, in the top cell's property, is read only at the end of the file: it is checked there, so a
    wrong value fails the verification, never passes it)."""
    if given:
        return int(given)
    try:
        side = json.loads(path.with_suffix(path.suffix + ".json").read_text())
        return int(side["tile_cells"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _scan(path: Path, problem) -> dict:
    """One pass over the file's top-level records: the names, where each tile cell's records lie (their
    CBLOCK payloads read for the signature, not inflated), the top cell and the atom cells parsed, END and
    the signature checked."""
    f = _File(path)
    names: dict[int, str] = {}
    tiles: list = []  # (name, r, c, offset, length)
    atom_rects: dict[int, list] = {}
    top: list = []
    prov = None
    cell = None
    tile_at = None  # (name, r, c, offset) of the tile cell being skipped
    modal = _Modal()
    res = {"ended": False, "scheme": None, "signature_ok": None, "unit": None, "bytes": f.size}

    def close_cell(at: int) -> None:
        nonlocal tile_at
        if tile_at is not None:
            name, r, c, off = tile_at
            tiles.append((name, r, c, off, at - off))
            tile_at = None

    def take(el: _Element) -> None:
        nonlocal prov
        name = names.get(cell, "")
        if el.kind == "placement":
            rep = len(el.rep[0]) if el.rep else 1
            if name == TOP_CELL:
                top.append((el.ref, el.x, el.y, rep))
            else:
                problem(f"cell {name or cell!r} places cell {el.ref}: only tiles and the top cell place cells")
        elif el.kind == "rectangle":
            if name.startswith("ATOM_"):
                atom_rects.setdefault(int(name[5:]), []).append((el.w, el.h, el.x, el.y, el.rep))
            else:
                problem(f"cell {name or cell!r} holds a rectangle: pillars belong in atom cells")
        elif el.kind == "property" and name == TOP_CELL and el.name == b"metadesign" and el.values:
            try:
                prov = json.loads(el.values[0])
            except ValueError:
                problem("the top cell's metadesign property is not JSON")

    try:
        if f.read(len(MAGIC)) != MAGIC:
            raise OasisError("not an OASIS file (no magic bytes)")
        if f.byte() != 1:
            raise OasisError("no START record after the magic bytes")
        version = f.string()
        if version != b"1.0":
            raise OasisError(f"OASIS version {version!r}, expected '1.0'")
        unit_type = f.uint()
        if unit_type != 0:
            raise OasisError(f"a database unit of real type {unit_type}, not an integer per micrometre as this "
                             "project writes it: a file of another writer (use layout verify without --stream)")
        res["unit"] = f.uint()
        if f.uint() != 0:
            raise OasisError("name tables at the end of the file are not supported (offset flag 1)")
        for _ in range(12):
            f.uint()
        next_ref = 0
        while True:
            at = f.tell()
            rid = f.byte()
            if rid == 0:
                continue
            if rid == 2:  # END: padding, validation scheme, signature; 256 bytes in all
                close_cell(at)
                f.string()
                scheme = f.uint()
                base_crc, base_sum = f.signature_base()
                sig = int.from_bytes(f.read(4), "little")
                if f.tell() - at != END_BYTES:
                    problem(f"END record of {f.tell() - at} bytes, expected {END_BYTES}")
                if f.tell() != f.size:
                    problem(f"{f.size - f.tell()} bytes after the END record")
                if scheme not in (0, 1, 2):
                    raise OasisError(f"validation scheme {scheme} unknown")
                res["scheme"] = {0: None, 1: "crc32", 2: "checksum32"}[scheme]
                res["signature_ok"] = None if scheme == 0 else sig == (base_crc if scheme == 1 else base_sum)
                if res["signature_ok"] is False:
                    problem(f"the file's {res['scheme']} signature does not match its bytes (the file was changed "
                            "or damaged after it was written)")
                res["ended"] = True
                break
            if rid in (3, 4):
                nm = f.string().decode(errors="replace")
                ref = f.uint() if rid == 4 else next_ref
                next_ref = ref + 1
                names[ref] = nm
                continue
            if rid in (5, 6, 7, 8, 9, 10):
                f.string()
                if rid % 2 == 0:
                    f.uint()
                continue
            if rid in (13, 14):
                close_cell(at)
                if rid == 14:
                    nm = f.string().decode(errors="replace")
                    cell = next((k for k, v in names.items() if v == nm), nm)
                    names.setdefault(cell, nm)
                else:
                    cell = f.uint()
                modal = _Modal()
                name = names.get(cell, "")
                if name.startswith("TILE_"):
                    try:
                        _, r, c = name.split("_")
                        tile_at = (name, int(r), int(c), f.tell())
                    except ValueError:
                        raise OasisError(f"tile cell name {name!r} is not TILE_<row>_<col>") from None
                continue
            if tile_at is not None:  # a tile's records: the workers read them; here only their bytes
                if rid == 34:
                    f.cblock(inflate=False)
                else:
                    f.element(rid, modal)
                continue
            if rid == 34:
                for el in f.cblock().elements(modal):
                    take(el)
                continue
            el = f.element(rid, modal)
            if el is not None:
                take(el)
    except OasisError as exc:
        problem(f"malformed file: {exc}")
    finally:
        f.close()
    if not res["ended"]:
        problem("the file has no END record (truncated?)")
    res.update(names=names, tiles=tiles, atom_rects=atom_rects, top=top, prov=prov)
    return res


def verify_stream(path: str | Path, design_path: str | Path, min_feature_nm: int = DESIGN_RULES.min_feature_nm,
                  min_gap_nm: int = DESIGN_RULES.min_gap_nm, tile: int | None = None, workers: int = 1,
                  scheduler: str | None = None, progress=None, max_problems: int = 20) -> dict:
    """Read the OASIS file ``path`` and check it against the design ``design_path`` (see the module's
    docstring): one pass over the top-level records (names, the signature, the top and atom cells, where
    each tile lies), then the stripes of tiles, each against its rows of the design, on ``workers`` local
    processes or a Dask ``scheduler`` (the same report whatever the count: sums, combined in stripe order).
    ``tile``: the tiling's cells per tile side (default: the side-car's, checked against the file's own
    record).  Returns the report: ``exact`` (every pillar as designed, the file well-formed, its signature
    right), ``drc`` (``passed``), the counts and timings."""
    path, design_path = Path(path), Path(design_path)
    tile_size = _tile_size(path, tile)
    if tile_size is None:
        raise InputError(f"{path}: no tile size (no side-car {path.name}.json): pass --tile")
    t0 = time.perf_counter()
    problem = _Problems(max_problems)
    try:
        with np.load(design_path, allow_pickle=False) as z:
            dmeta = from_json_array(z["meta"])
            awx, awy = z["atom_wx_m"], z["atom_wy_m"]
    except (OSError, KeyError, ValueError) as exc:
        raise InputError(f"{design_path}: not a design file ({exc})") from None
    rows = NpzRows(design_path, "index_map")
    n = rows.shape[0]
    rows.close()
    period = (dmeta.get("spec") or {}).get("period_m")
    if period is None:
        raise InputError(f"{design_path}: its metadata has no lattice period")
    n_atoms = len(awx)
    ew = np.stack([snap_widths(awx, 1)[0], snap_widths(awy, 1)[0]], 1).astype(np.int64)
    p_nm, x0 = layout_geometry(n, float(period))
    g = _Grid(str(path), str(design_path), n, n_atoms, p_nm, x0, tile_size, dmeta.get("empty_index"))

    scan = _scan(path, problem)
    t_scan = time.perf_counter() - t0
    names = scan["names"]
    by_row: dict[int, list] = {}
    for name, r, c, off, ln in scan["tiles"]:
        by_row.setdefault(r, []).append((name, c, off, ln))
    stripes = sorted(by_row)
    for r in stripes:
        if r * tile_size >= n:
            problem(f"tile row {r} is outside the design's {n} rows")
    counts = np.zeros(n_atoms, np.int64)
    want = np.zeros(n_atoms, np.int64)
    ph = np.zeros(n_atoms * n_atoms, np.int64)
    pv = np.zeros(n_atoms * n_atoms, np.int64)
    tot = {"mismatched": 0, "duplicates": 0, "off_lattice": 0, "tiles": 0}
    rows = NpzRows(design_path, "index_map")
    last = [None]  # (stripe, its top row) of the stripe folded last

    def fold(r: int, res: dict | None) -> None:
        """Stripe ``r``'s result into the totals, in stripe order (the same report whatever the worker
        count); only its top row is kept, for the vertical pairs across the next border."""
        nonlocal counts, want, ph, pv
        if res is None:  # a stripe without a tile cell: its designed pillars are in no tile
            _, w_r = _design_rows(rows, g, r * tile_size, min(n, (r + 1) * tile_size))
            want += w_r
            if w_r.sum():
                tot["mismatched"] += int(w_r.sum())
                problem(f"stripe {r} (rows {r * tile_size}..): no tile cell, {int(w_r.sum())} designed pillars "
                        "missing")
            last[0] = None
            return
        for msg in res["problems"]:
            problem(msg)
        counts += res["counts"]
        want += res["want"]
        ph += res["pairs_h"]
        pv += res["pairs_v"]
        for k in tot:
            tot[k] += res[k]
        if last[0] is not None and last[0][0] == r - 1:  # vertical neighbours across the stripe border
            pv += _pairs(last[0][1], res["bottom"], n_atoms)
        last[0] = (r, res["top"])

    expected = {r for r in stripes if r * tile_size < n}
    n_stripes = -(-n // tile_size)
    pending: dict[int, dict] = {}  # results ahead of their turn (few: stripes are dispatched in order)
    nxt = done = 0
    try:
        for res in run_tasks(_stripe_job, [(r, by_row[r]) for r in sorted(expected)], workers, g,
                             scheduler=scheduler, key="verify-stripe"):
            pending[res["r"]] = res
            done += 1
            while nxt < n_stripes and (nxt in pending or nxt not in expected):
                fold(nxt, pending.pop(nxt, None))
                nxt += 1
            if progress:
                progress(done, len(stripes))
        while nxt < n_stripes:
            fold(nxt, pending.pop(nxt, None))
            nxt += 1
    finally:
        rows.close()
        for r in _ROWS.values():  # an in-process worker's reader (workers <= 1)
            r.close()
        _ROWS.clear()
    # --- the tiling, the top cell, the atoms, the counts, the rules
    prov, tiling = scan["prov"], (scan["prov"] or {}).get("tiling") or {}
    if prov is None:
        problem("the top cell has no metadesign property: not a file of this project")
    elif tiling.get("tile_cells") != tile_size or tiling.get("hierarchy") != "tiles":
        problem(f"the file records its tiling as {tiling or 'none'}; streamed with {tile_size} cells per tile")
    if not scan["tiles"]:
        problem("no tile cell in the file: not a tiled layout (layout verify without --stream)")
    for ref, x, y, cnt in scan["top"]:
        if not names.get(ref, "").startswith("TILE_") or (x, y) != (0, 0) or cnt != 1:
            problem(f"the top cell places {names.get(ref, ref)!r} at ({x}, {y}) x {cnt}: expected each tile once at "
                    "the origin")
    placed = [names.get(r) for r, *_ in scan["top"]]
    if len(placed) != len(set(placed)):
        problem("the top cell places a tile cell more than once")
    unplaced = {t[0] for t in scan["tiles"]} - set(placed)
    if unplaced:
        problem(f"{len(unplaced)} tile cells are never placed by the top cell (first: {sorted(unplaced)[0]})")
    widths = ew.copy()
    for a in range(n_atoms):
        rects = scan["atom_rects"].get(a)
        if counts[a] == 0 and not rects:
            continue
        if not rects or len(rects) != 1 or rects[0][4] is not None:
            problem(f"atom cell ATOM_{a:03d}: {len(rects or [])} rectangles, expected one")
            continue
        w_, h_, rx, ry, _ = rects[0]
        widths[a] = (w_, h_)
        if (w_, h_) != (int(ew[a, 0]), int(ew[a, 1])):
            problem(f"atom cell ATOM_{a:03d}: {w_} x {h_} nm, the design's snapped widths are {int(ew[a, 0])} x "
                    f"{int(ew[a, 1])} nm")
        if (rx, ry) != (-(w_ // 2) - (w_ % 2), -(h_ // 2) - (h_ % 2)):
            problem(f"atom cell ATOM_{a:03d}: not centred on its origin")
    if not np.array_equal(counts, want):
        bad = np.flatnonzero(counts != want)
        problem(f"per-atom pillar counts differ from the design for {bad.size} atoms (layout {int(counts.sum()):,}, "
                f"design {int(want.sum()):,})")
    used = np.flatnonzero(counts)
    gap_x = p_nm - (widths[:, 0][:, None] + widths[:, 0][None, :]) / 2  # centred: the gap of a pair
    gap_y = p_nm - (widths[:, 1][:, None] + widths[:, 1][None, :]) / 2
    ph, pv = ph.reshape(n_atoms, n_atoms), pv.reshape(n_atoms, n_atoms)
    width_viol = int(counts[(widths < min_feature_nm).any(1)].sum())
    space_viol = int(ph[gap_x < min_gap_nm].sum() + pv[gap_y < min_gap_nm].sum())
    min_gap = min(float(gap_x[ph > 0].min()) if (ph > 0).any() else np.inf,
                  float(gap_y[pv > 0].min()) if (pv > 0).any() else np.inf)
    return {"file": str(path), "design": str(design_path), "reader": "stream", "exact": not problem,
            "problems": list(problem), "pillars": int(counts.sum()), "pillars_design": int(want.sum()),
            "tiles": tot["tiles"], "tile_cells": tile_size, "mismatched_cells": tot["mismatched"],
            "duplicates": tot["duplicates"], "off_lattice": tot["off_lattice"],
            "signature": {"scheme": scan["scheme"], "ok": scan["signature_ok"]}, "unit_per_um": scan["unit"],
            "bytes": scan["bytes"], "workers": workers,
            "drc": {"rules": {"min_feature_nm": min_feature_nm, "min_gap_nm": min_gap_nm},
                    "min_feature_nm": int(widths[used].min()) if used.size else None,
                    "min_gap_nm": None if not np.isfinite(min_gap) else round(min_gap, 1),
                    "pairs_checked": int(ph.sum() + pv.sum()), "width_violations": width_viol,
                    "space_violations": space_viol, "passed": width_viol == 0 and space_viol == 0},
            "scan_seconds": t_scan, "seconds": time.perf_counter() - t0}
