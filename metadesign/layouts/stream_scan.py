"""The streaming verifier's pass over a tiled layout's file (:mod:`metadesign.layouts.stream`): the
top-level records read once, in order (names, the signature, the top cell and the atom cells parsed, where
each tile cell's records lie, their CBLOCKs read for the signature but not inflated), then each tile cell's
placements read on their own by the stripe workers.  Problems go to a ``problem(msg)`` callback, each with
its byte offset where it has one; a malformed record ends the scan with one such line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .oasis_read import DECODE_ERRORS, END_BYTES, MAGIC, Element, Modal, OasisError, OasisFile
from .writer import TOP_CELL

__all__ = ["scan_file", "tile_placements", "tile_size_of", "decode_error"]


def decode_error(exc: Exception, f: OasisFile) -> str:
    """What decoding a damaged file raised, in one line: an :class:`OasisError`'s own message (it names
    its byte), any other with the byte the reader had reached."""
    if isinstance(exc, OasisError):
        return str(exc)
    return f"{type(exc).__name__}: {exc} (near byte {f.tell()})"


def tile_placements(f: OasisFile, offset: int, length: int, problem) -> list:
    """The placements of one tile cell (its records at ``offset``, ``length`` bytes), as
    ``(atom, x, y, dx offsets, dy offsets)``."""
    f.seek(offset, length)
    modal = Modal()  # modal variables are reset at each CELL record
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


def _placed(el: Element) -> tuple:
    if el.rep is None:
        return el.ref, el.x, el.y, np.zeros(1, np.int64), np.zeros(1, np.int64)
    return el.ref, el.x, el.y, el.rep[0], el.rep[1]


def tile_size_of(path: Path, given: int | None) -> int | None:
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


class _Scan:
    """The state of one pass over the top-level records: the cell names, the tile cells and where their
    records lie (``(name, r, c, offset, length)``), the top cell's placements and its ``metadesign``
    property, the atom cells' rectangles."""

    def __init__(self, problem):
        self.problem = problem
        self.names: dict[int, str] = {}
        self.tiles: list = []
        self.atom_rects: dict[int, list] = {}
        self.top: list = []
        self.prov = None
        self.cell = None
        self.tile_at = None  # (name, r, c, offset) of the tile cell being skipped
        self.modal = Modal()
        self.next_ref = 0

    def close_cell(self, at: int) -> None:
        if self.tile_at is not None:
            name, r, c, off = self.tile_at
            self.tiles.append((name, r, c, off, at - off))
            self.tile_at = None

    def take(self, el: Element) -> None:
        """An element of a cell that is not a tile: the top cell's placements and property, the atom cells'
        rectangles (anything else where it does not belong is a problem)."""
        problem = self.problem
        name = self.names.get(self.cell, "")
        if el.kind == "placement":
            rep = len(el.rep[0]) if el.rep else 1
            if name == TOP_CELL:
                self.top.append((el.ref, el.x, el.y, rep))
            else:
                problem(f"cell {name or self.cell!r} places cell {el.ref}: only tiles and the top cell place cells")
        elif el.kind == "rectangle":
            if name.startswith("ATOM_"):
                self.atom_rects.setdefault(int(name[5:]), []).append((el.w, el.h, el.x, el.y, el.rep))
            else:
                problem(f"cell {name or self.cell!r} holds a rectangle: pillars belong in atom cells")
        elif el.kind == "property" and name == TOP_CELL and el.name == b"metadesign" and el.values:
            try:
                prov = json.loads(el.values[0])
            except (TypeError, ValueError):
                problem("the top cell's metadesign property is not JSON")
            else:
                if isinstance(prov, dict):
                    self.prov = prov
                else:
                    problem("the top cell's metadesign property is not a JSON object")

    def open_cell(self, f: OasisFile, rid: int) -> None:
        """A CELL record (its id byte read): by reference number (13) or by name (14)."""
        if rid == 14:
            nm = f.string().decode(errors="replace")
            self.cell = next((k for k, v in self.names.items() if v == nm), nm)
            self.names.setdefault(self.cell, nm)
        else:
            self.cell = f.uint()
        self.modal = Modal()
        name = self.names.get(self.cell, "")
        if name.startswith("TILE_"):
            try:
                _, r, c = name.split("_")
                r, c = int(r), int(c)
                if r < 0 or c < 0:
                    raise ValueError
            except ValueError:
                raise OasisError(f"tile cell name {name!r} is not TILE_<row>_<col>") from None
            self.tile_at = (name, r, c, f.tell())

    def record(self, f: OasisFile, rid: int, at: int) -> None:
        """One top-level record other than END (its id byte ``rid``, at byte ``at``, read)."""
        if rid == 0:
            return
        if rid in (3, 4):
            nm = f.string().decode(errors="replace")
            ref = f.uint() if rid == 4 else self.next_ref
            self.next_ref = ref + 1
            self.names[ref] = nm
        elif rid in (5, 6, 7, 8, 9, 10):
            f.string()
            if rid % 2 == 0:
                f.uint()
        elif rid in (13, 14):
            self.close_cell(at)
            self.open_cell(f, rid)
        elif self.tile_at is not None:  # a tile's records: the workers read them; here only their bytes
            if rid == 34:
                f.cblock(inflate=False)
            else:
                f.element(rid, self.modal)
        elif rid == 34:
            for el in f.cblock().elements(self.modal):
                self.take(el)
        else:
            el = f.element(rid, self.modal)
            if el is not None:
                self.take(el)


def _read_start(f: OasisFile, res: dict) -> None:
    """The magic bytes and the START record: the database unit (an integer per micrometre) into ``res``."""
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


def _read_end(f: OasisFile, at: int, res: dict, problem) -> None:
    """The END record (its id byte, at byte ``at``, read): padding, validation scheme and signature, 256
    bytes in all, the last of the file; the signature checked against every byte before it."""
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


def scan_file(path: Path, problem) -> dict:
    """One pass over the file's top-level records: the names, where each tile cell's records lie (their
    CBLOCK payloads read for the signature, not inflated), the top cell and the atom cells parsed, END and
    the signature checked."""
    f = OasisFile(path)
    scan = _Scan(problem)
    res = {"ended": False, "scheme": None, "signature_ok": None, "unit": None, "bytes": f.size}
    try:
        _read_start(f, res)
        while True:
            at = f.tell()
            rid = f.byte()
            if rid == 2:
                scan.close_cell(at)
                _read_end(f, at, res, problem)
                break
            scan.record(f, rid, at)
    except DECODE_ERRORS as exc:
        problem(f"malformed file: {decode_error(exc, f)}")
    finally:
        f.close()
    if not res["ended"]:
        problem("the file has no END record (truncated?)")
    res.update(names=scan.names, tiles=scan.tiles, atom_rects=scan.atom_rects, top=scan.top, prov=scan.prov)
    return res
