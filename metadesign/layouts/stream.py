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
        """A repetition as ``("offsets", dx, dy)`` (every copy's offset from the first, int64 arrays)."""
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
            rep = ("offsets", jx * sx, jy * sy)
        elif t in (8, 9):
            n = self.uint() + 2
            m = self.uint() + 2 if t == 8 else 1
            ndx, ndy = self.gdelta()
            mdx, mdy = self.gdelta() if t == 8 else (0, 0)
            jm, jn = np.divmod(np.arange(n * m, dtype=np.int64), n)
            rep = ("offsets", jn * ndx + jm * mdx, jn * ndy + jm * mdy)
        elif t in (10, 11):
            n = self.uint() + 2
            grid = self.uint() if t == 11 else 1
            dx, dy = self.gdeltas(n - 1)
            ox = np.zeros(n, np.int64)
            oy = np.zeros(n, np.int64)
            np.cumsum(dx * grid, out=ox[1:])
            np.cumsum(dy * grid, out=oy[1:])
            rep = ("offsets", ox, oy)
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
            if info & 0x01:
                modal.layer = self.uint()
            if info & 0x02:
                modal.datatype = self.uint()
            if info & 0x40:
                modal.geometry_w = self.uint()
            if info & 0x80:  # square: the height is the width
                if info & 0x20:
                    raise OasisError(f"a square rectangle with a height ({self.where()})")
                modal.geometry_h = modal.geometry_w
            elif info & 0x20:
                modal.geometry_h = self.uint()
            for bit, name in ((0x10, "geometry_x"), (0x08, "geometry_y")):
                if info & bit:
                    v = self.sint()
                    setattr(modal, name, getattr(modal, name) + v if modal.xy_relative else v)
            rep = self.repetition(modal) if info & 0x04 else None
            if None in (modal.layer, modal.datatype, modal.geometry_w, modal.geometry_h):
                raise OasisError(f"a rectangle with an unset modal variable ({self.where()})")
            return _Element("rectangle", None, modal.geometry_x, modal.geometry_y, rep, modal.geometry_w,
                            modal.geometry_h, modal.layer, modal.datatype)
        if rid == 21:
            info = self.byte()
            if info & 0x01:
                modal.layer = self.uint()
            if info & 0x02:
                modal.datatype = self.uint()
            if info & 0x20:
                modal.polygon = self.point_list()
            for bit, name in ((0x10, "geometry_x"), (0x08, "geometry_y")):
                if info & bit:
                    v = self.sint()
                    setattr(modal, name, getattr(modal, name) + v if modal.xy_relative else v)
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
            for bit, name in ((0x10, "text_x"), (0x08, "text_y")):
                if info & bit:
                    v = self.sint()
                    setattr(modal, name, getattr(modal, name) + v if modal.xy_relative else v)
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

    def gdeltas(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        if count < 64:  # short lists: the scalar reader is cheaper than the vector set-up
            return super().gdeltas(count)
        _ = self.arr
        dx, dy, end = gdelta_decode(self._arr, self._ends, self.pos, count)
        self.pos = end
        return dx, dy

    def string(self) -> bytes:
        n = self.uint()
        if self.pos + n > len(self.data):
            raise OasisError(f"a string runs past the end of its block ({self.where()})")
        s = self.data[self.pos:self.pos + n]
        self.pos += n
        return s

    def read(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise OasisError(f"a record runs past the end of its block ({self.where()})")
        s = self.data[self.pos:self.pos + n]
        self.pos += n
        return s

class _File(_Reader):
    """The file read forward in chunks, with the running CRC32 (and byte sum) of every byte consumed."""

    def __init__(self, path: Path):
        self.fh = open(path, "rb")
        self.size = path.stat().st_size
        self.buf, self.i, self.off = b"", 0, 0  # off: file offset of buf[0]
        self.crc = 0
        self.sum = 0

    def close(self) -> None:
        self.fh.close()

    def tell(self) -> int:
        return self.off + self.i

    def _fill(self, n: int) -> None:
        if len(self.buf) - self.i >= n:
            return
        done = self.buf[:self.i]
        self.crc = zlib.crc32(done, self.crc)
        self.sum += sum(done) if len(done) < 4096 else int(np.frombuffer(done, np.uint8).sum(dtype=np.uint64))
        self.off += self.i
        self.buf = self.buf[self.i:] + self.fh.read(max(CHUNK, n))
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

    def uint(self) -> int:
        v = shift = 0
        while True:
            b = self.byte()
            v |= (b & 0x7F) << shift
            if b < 128:
                return v
            shift += 7
            if shift > 63:
                raise OasisError(f"an unsigned integer of more than 63 bits (byte {self.tell()})")

    def string(self) -> bytes:
        return self.read(self.uint())

    def where(self) -> str:
        return f"byte {self.tell()}"

    def signature_base(self) -> tuple[int, int]:
        """CRC32 and byte sum of every byte consumed so far."""
        done = self.buf[:self.i]
        return zlib.crc32(done, self.crc), (self.sum + int(np.frombuffer(done, np.uint8).sum(dtype=np.uint64))) \
            & 0xFFFFFFFF


# ----------------------------------------------------------------------------------------------------------
# the verifier

@dataclass
class _Tile:
    name: str
    r: int
    c: int
    atoms: list = field(default_factory=list)  # (atom, x0, y0, dx offsets, dy offsets)


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


def verify_stream(path: str | Path, design_path: str | Path, min_feature_nm: int = DESIGN_RULES.min_feature_nm,
                  min_gap_nm: int = DESIGN_RULES.min_gap_nm, tile: int | None = None, progress=None,
                  max_problems: int = 20) -> dict:
    """Read the OASIS file ``path`` once, in bounded memory, and check it against the design
    ``design_path`` (see the module's docstring); ``tile``: the tiling's cells per tile side (default:
    the side-car's, checked against the file's own record at its end).  Returns the report: ``exact``
    (every pillar as designed, the file well-formed, its signature right), ``drc`` (``passed``), the
    counts and timings."""
    path, design_path = Path(path), Path(design_path)
    tile_size = _tile_size(path, tile)
    if tile_size is None:
        raise InputError(f"{path}: no tile size (no side-car {path.name}.json): pass --tile")
    t0 = time.perf_counter()
    problems: list[str] = []

    def problem(msg: str) -> None:
        if len(problems) < max_problems:
            problems.append(msg)
        elif len(problems) == max_problems:
            problems.append("... (more problems not listed)")

    # --- the design: its grid, atoms and sentinel; its index map streamed by stripes
    try:
        with np.load(design_path, allow_pickle=False) as z:
            dmeta = from_json_array(z["meta"])
            awx, awy = z["atom_wx_m"], z["atom_wy_m"]
    except (OSError, KeyError, ValueError) as exc:
        raise InputError(f"{design_path}: not a design file ({exc})") from None
    rows = NpzRows(design_path, "index_map")
    n = rows.shape[0]
    empty = dmeta.get("empty_index")
    spec = dmeta.get("spec", {})
    period = spec.get("period_m") or spec.get("period")
    if period is None:
        raise InputError(f"{design_path}: its metadata has no lattice period")
    n_atoms = len(awx)
    grid_nm = 1
    ewx, _ = snap_widths(awx, grid_nm)
    ewy, _ = snap_widths(awy, grid_nm)
    p_nm, x0 = layout_geometry(n, float(period))

    counts = np.zeros(n_atoms, np.int64)
    want = np.zeros(n_atoms, np.int64)
    pairs_h = np.zeros(n_atoms * n_atoms, np.int64)  # horizontally adjacent pillars, per (left, right) atom
    pairs_v = np.zeros(n_atoms * n_atoms, np.int64)
    mismatched = duplicates = off_lattice = 0
    tiles_seen = 0
    # the stripe of tiles being read: its design rows, which columns its tiles covered, its top row
    stripe = {"r": None, "block": None, "covered": None, "top": None, "below": None}
    left = {}  # the right column of the previous tile in this stripe

    def design_rows(r0: int, r1: int) -> np.ndarray:
        raw = rows[r0:r1]
        b = np.bincount(raw.ravel(), minlength=n_atoms + 1)
        want[:] += b[:n_atoms]
        im = raw.astype(np.int32)
        if empty is not None:
            im[raw == empty] = -1
        return im

    def close_stripe() -> None:
        """The design cells of the finished stripe that no tile covered: a missing tile drops them."""
        nonlocal mismatched
        if stripe["r"] is None:
            return
        miss = ~stripe["covered"]
        lost = int(np.count_nonzero(stripe["block"][:, miss] >= 0))
        if lost:
            mismatched += lost
            problem(f"stripe {stripe['r']}: {lost} designed pillars in columns no tile cell covers")

    def open_stripe(r: int) -> None:
        close_stripe()
        if stripe["r"] is not None and r != stripe["r"] + 1:
            problem(f"tile row {r} follows row {stripe['r']}: tile rows missing or out of order")
        r0 = r * tile_size
        if r0 >= n:
            raise OasisError(f"tile row {r} is outside the design's {n} rows")
        stripe["below"] = stripe["top"] if stripe["r"] == r - 1 else None
        stripe["r"], stripe["block"] = r, design_rows(r0, min(n, r0 + tile_size))
        stripe["covered"] = np.zeros(n, bool)
        stripe["top"] = np.full(n, -1, np.int32)
        left.clear()

    def finish_tile(t: _Tile) -> None:
        nonlocal mismatched, duplicates, off_lattice, tiles_seen
        tiles_seen += 1
        r0, c0 = t.r * tile_size, t.c * tile_size
        if stripe["r"] != t.r:
            open_stripe(t.r)
        if c0 >= n:
            problem(f"{t.name}: outside the design's {n} columns")
            return
        h, w = min(tile_size, n - r0), min(tile_size, n - c0)
        if stripe["covered"][c0:c0 + w].any():
            problem(f"{t.name}: a second cell for the same tile")
        stripe["covered"][c0:c0 + w] = True
        ref = stripe["block"][:, c0:c0 + w]
        got = np.full((h, w), -1, np.int32)
        if t.atoms:
            ids = np.array([a for a, *_ in t.atoms], np.int64)
            sizes = np.array([len(ox) for *_, ox, _ in t.atoms], np.int64)
            aa = np.repeat(ids, sizes)
            xs = np.concatenate([px + ox for _, px, _, ox, _ in t.atoms])
            ys = np.concatenate([py + oy for _, _, py, _, oy in t.atoms])
            foreign = (aa < 0) | (aa >= n_atoms)
            if foreign.any():
                problem(f"{t.name}: places cells {sorted(set(aa[foreign].tolist()))[:5]}, not atoms of the design")
            ix, rx = np.divmod(xs - x0, p_nm)
            iy, ry = np.divmod(ys - x0, p_nm)
            ix -= c0
            iy -= r0
            bad = (rx != 0) | (ry != 0) | (ix < 0) | (ix >= w) | (iy < 0) | (iy >= h) | foreign
            nb = int(np.count_nonzero(bad))
            if nb:
                off_lattice += nb
                j = int(np.flatnonzero(bad)[0])
                problem(f"{t.name}: {nb} pillars off the {p_nm} nm lattice or outside the tile (first: atom "
                        f"{int(aa[j])} at ({int(xs[j])}, {int(ys[j])}) nm)")
                keep = ~bad
                aa, ix, iy = aa[keep], ix[keep], iy[keep]
            np.add.at(counts, aa, 1) if len(aa) < 64 else counts.__iadd__(np.bincount(aa, minlength=n_atoms))
            flat = iy * w + ix
            hits = np.bincount(flat, minlength=h * w)
            d = int((hits[hits > 1] - 1).sum())
            if d:
                duplicates += d
                problem(f"{t.name}: {d} pillars placed on an occupied cell")
            got.ravel()[flat] = aa
        mm = int(np.count_nonzero(got != ref))
        if mm:
            mismatched += mm
            j, i = np.argwhere(got != ref)[0]
            problem(f"{t.name}: {mm} cells differ from the design (first: row {r0 + j}, column {c0 + i}: layout "
                    f"{int(got[j, i])}, design {int(ref[j, i])}; -1 = no pillar)")
        # lattice neighbours, inside the tile and across its left and lower borders
        for A, B, acc in ((got[:, :-1], got[:, 1:], pairs_h), (got[:-1, :], got[1:, :], pairs_v)):
            m = (A >= 0) & (B >= 0)
            acc += np.bincount(A[m].astype(np.int64) * n_atoms + B[m], minlength=n_atoms * n_atoms)
        if t.c - 1 in left:
            A, B = left.pop(t.c - 1), got[:, 0]
            m = (A >= 0) & (B >= 0)
            pairs_h[:] += np.bincount(A[m].astype(np.int64) * n_atoms + B[m], minlength=n_atoms * n_atoms)
        left[t.c] = got[:, -1].copy()
        if stripe["below"] is not None:
            A, B = stripe["below"][c0:c0 + w], got[0]
            m = (A >= 0) & (B >= 0)
            pairs_v[:] += np.bincount(A[m].astype(np.int64) * n_atoms + B[m], minlength=n_atoms * n_atoms)
        stripe["top"][c0:c0 + w] = got[-1]

    # --- the file, once
    f = _File(path)
    modal = _Modal()
    names: dict[int, str] = {}
    atom_rects: dict[int, list] = {}
    top_placements: list = []
    prov = None
    cell = None  # the current cell's reference number
    tile: _Tile | None = None
    crc_ok = None
    ended = False
    scheme = unit = None
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
            raise OasisError("a database unit that is not an integer per micrometre")
        unit = f.uint()
        if f.uint() != 0:
            raise OasisError("name tables at the end of the file are not supported (offset flag 1)")
        for _ in range(12):
            f.uint()
        next_ref = 0

        def close_cell():
            nonlocal tile
            if tile is not None:
                finish_tile(tile)
                if progress:
                    progress(f.tell(), f.size)
                tile = None

        def take(el: _Element):
            nonlocal prov
            name = names.get(cell, "")
            if el.kind == "placement":
                rep = el.rep[1:] if el.rep else (np.zeros(1, np.int64), np.zeros(1, np.int64))
                if tile is not None:
                    tile.atoms.append((el.ref, el.x, el.y, rep[0], rep[1]))
                elif name == top_name:
                    top_placements.append((el.ref, el.x, el.y, len(rep[0])))
                else:
                    problem(f"cell {name or cell!r} places cell {el.ref}: only tiles and the top cell place cells")
            elif el.kind == "rectangle":
                if name.startswith("ATOM_"):
                    atom_rects.setdefault(int(name[5:]), []).append((el.w, el.h, el.x, el.y, el.rep))
                else:
                    problem(f"cell {name or cell!r} holds a rectangle: pillars belong in atom cells")
            elif el.kind == "property" and name == top_name and el.name == b"metadesign" and el.values:
                try:
                    prov = json.loads(el.values[0])
                except ValueError:
                    problem("the top cell's metadesign property is not JSON")

        top_name = TOP_CELL
        while True:
            rid = f.byte()
            if rid == 0:
                continue
            if rid == 2:  # END: padding, validation scheme, signature; 256 bytes in all
                start = f.tell() - 1
                f.string()
                scheme = f.uint()
                base_crc, base_sum = f.signature_base()
                sig = f.read(4)
                if f.tell() - start != END_BYTES:
                    problem(f"END record of {f.tell() - start} bytes, expected {END_BYTES}")
                if f.tell() != f.size:
                    problem(f"{f.size - f.tell()} bytes after the END record")
                if scheme == 1:
                    crc_ok = int.from_bytes(sig, "little") == base_crc
                elif scheme == 2:
                    crc_ok = int.from_bytes(sig, "little") == base_sum
                elif scheme == 0:
                    crc_ok = None
                else:
                    raise OasisError(f"validation scheme {scheme} unknown")
                if crc_ok is False:
                    problem(f"the file's {'CRC32' if scheme == 1 else 'checksum'} signature does not match its bytes "
                            "(the file was changed or damaged after it was written)")
                ended = True
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
                close_cell()
                if rid == 14:
                    nm = f.string().decode(errors="replace")
                    cell = next((k for k, v in names.items() if v == nm), None)
                    names.setdefault(cell, nm)
                else:
                    cell = f.uint()
                modal = _Modal()
                name = names.get(cell, "")
                if name.startswith("TILE_"):
                    try:
                        _, r, c = name.split("_")
                        tile = _Tile(name, int(r), int(c))
                    except ValueError:
                        raise OasisError(f"tile cell name {name!r} is not TILE_<row>_<col>") from None
                continue
            if rid == 34:  # CBLOCK
                at = f.tell()
                if f.uint() != 0:
                    raise OasisError(f"CBLOCK at byte {at} with an unknown compression type")
                n_raw, n_z = f.uint(), f.uint()
                z = f.read(n_z)
                try:
                    d = zlib.decompressobj(-15)
                    data = d.decompress(z, n_raw + 1)
                except zlib.error as exc:
                    raise OasisError(f"CBLOCK at byte {at} does not inflate ({exc})") from None
                if len(data) != n_raw:
                    raise OasisError(f"CBLOCK at byte {at}: {len(data)} bytes inflated, its header says {n_raw}")
                blk = _Block(data, at)
                while blk.pos < len(blk.data):
                    r = blk.byte()
                    if r == 0:
                        continue
                    el = blk.element(r, modal)
                    if el is not None:
                        take(el)
                continue
            if rid in (15, 16, 17, 19, 20, 21, 28, 29):
                # a plain element record (the atom cells' rectangles), read from the file itself
                el = f.element(rid, modal)
                if el is not None:
                    take(el)
                continue
            raise OasisError(f"record type {rid} at byte {f.tell() - 1} is not supported by the streaming verifier")
    except OasisError as exc:
        problem(f"malformed file: {exc}")
    finally:
        f.close()
    try:
        close_stripe()
        # --- after the stream: the rows no tile covered, the tiling, the top cell, the atoms, the counts
        if stripe["r"] is None:
            problem("no tile cell in the file: not a tiled layout (layout verify without --stream)")
            covered = 0
        else:
            covered = min(n, (stripe["r"] + 1) * tile_size)
        if covered < n:
            lost = int(np.count_nonzero(design_rows(covered, n) >= 0))
            mismatched += lost
            problem(f"the file's tiles end at row {covered} of {n}: {lost} designed pillars in no tile")
    finally:
        rows.close()
    if not ended:
        problem("the file has no END record (truncated?)")
    # --- after the stream: the tiling, the top cell, the atoms, the counts, the rules
    tiling = (prov or {}).get("tiling") or {}
    if prov is None:
        problem("the top cell has no metadesign property: not a file of this project")
    elif tiling.get("tile_cells") != tile_size or tiling.get("hierarchy") != "tiles":
        problem(f"the file records its tiling as {tiling or 'none'}; streamed with {tile_size} cells per tile")
    for ref, x, y, cnt in top_placements:
        if not names.get(ref, "").startswith("TILE_") or (x, y) != (0, 0) or cnt != 1:
            problem(f"the top cell places {names.get(ref, ref)!r} at ({x}, {y}) x {cnt}: expected each tile once at "
                    "the origin")
    placed_tiles = {names.get(r) for r, *_ in top_placements}
    declared = {v for v in names.values() if v.startswith("TILE_")}
    if declared - placed_tiles:
        problem(f"{len(declared - placed_tiles)} tile cells are never placed")
    widths = np.zeros((n_atoms, 2), np.int64)
    for a in range(n_atoms):
        rects = atom_rects.get(a)
        if counts[a] == 0 and not rects:
            widths[a] = (ewx[a], ewy[a])
            continue
        if not rects or len(rects) != 1 or rects[0][4] is not None:
            problem(f"atom cell ATOM_{a:03d}: {len(rects or [])} rectangles, expected one")
            widths[a] = (ewx[a], ewy[a])
            continue
        w_, h_, rx, ry, _ = rects[0]
        widths[a] = (w_, h_)
        if (w_, h_) != (int(ewx[a]), int(ewy[a])):
            problem(f"atom cell ATOM_{a:03d}: {w_} x {h_} nm, the design's snapped widths are {int(ewx[a])} x "
                    f"{int(ewy[a])} nm")
        if (rx, ry) != (-(w_ // 2) - (w_ % 2), -(h_ // 2) - (h_ % 2)):
            problem(f"atom cell ATOM_{a:03d}: not centred on its origin")
    if not np.array_equal(counts, want):
        bad = np.flatnonzero(counts != want)
        problem(f"per-atom pillar counts differ from the design for {bad.size} atoms (layout {int(counts.sum()):,}, "
                f"design {int(want.sum()):,})")
    used = np.flatnonzero(counts)
    min_feature = int(widths[used].min()) if used.size else 0
    gap_x = p_nm - (widths[:, 0][:, None] + widths[:, 0][None, :]) / 2  # centred: the gap of a pair
    gap_y = p_nm - (widths[:, 1][:, None] + widths[:, 1][None, :]) / 2
    ph, pv = pairs_h.reshape(n_atoms, n_atoms), pairs_v.reshape(n_atoms, n_atoms)
    width_viol = int(counts[(widths < min_feature_nm).any(1)].sum())
    space_viol = int(ph[gap_x < min_gap_nm].sum() + pv[gap_y < min_gap_nm].sum())
    min_gap = min(float(gap_x[ph > 0].min()) if (ph > 0).any() else np.inf,
                  float(gap_y[pv > 0].min()) if (pv > 0).any() else np.inf)
    exact = not problems
    return {"file": str(path), "design": str(design_path), "reader": "stream", "exact": exact,
            "problems": problems, "pillars": int(counts.sum()), "pillars_design": int(want.sum()),
            "tiles": tiles_seen, "tile_cells": tile_size, "mismatched_cells": mismatched, "duplicates": duplicates,
            "off_lattice": off_lattice, "signature": {"scheme": {0: "none", 1: "crc32", 2: "checksum32"}.get(scheme),
                                                       "ok": crc_ok},
            "unit_per_um": unit, "bytes": f.size,
            "drc": {"rules": {"min_feature_nm": min_feature_nm, "min_gap_nm": min_gap_nm},
                    "min_feature_nm": min_feature, "min_gap_nm": None if not np.isfinite(min_gap) else min_gap,
                    "pairs_checked": int(ph.sum() + pv.sum()), "width_violations": width_viol,
                    "space_violations": space_viol, "passed": width_viol == 0 and space_viol == 0},
            "seconds": time.perf_counter() - t0}
