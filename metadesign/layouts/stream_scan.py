"""The streaming verifier's pass over a tiled layout's file (:mod:`metadesign.layouts.stream`): the
top-level records read once, in order (names, the signature, the top cell and the atom cells parsed, where
each tile cell's records lie, their CBLOCKs read for the signature but not inflated), then each tile cell's
placements read on their own by the stripe workers.  Problems go to a ``problem(msg)`` callback, each with
its byte offset where it has one; a malformed record ends the scan with one such line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .oasis_read import END_BYTES, MAGIC, Element, Modal, OasisError, OasisFile
from .writer import TOP_CELL

__all__ = ["scan_file", "tile_placements", "tile_size_of"]


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


def scan_file(path: Path, problem) -> dict:
    """One pass over the file's top-level records: the names, where each tile cell's records lie (their
    CBLOCK payloads read for the signature, not inflated), the top cell and the atom cells parsed, END and
    the signature checked."""
    f = OasisFile(path)
    names: dict[int, str] = {}
    tiles: list = []  # (name, r, c, offset, length)
    atom_rects: dict[int, list] = {}
    top: list = []
    prov = None
    cell = None
    tile_at = None  # (name, r, c, offset) of the tile cell being skipped
    modal = Modal()
    res = {"ended": False, "scheme": None, "signature_ok": None, "unit": None, "bytes": f.size}

    def close_cell(at: int) -> None:
        nonlocal tile_at
        if tile_at is not None:
            name, r, c, off = tile_at
            tiles.append((name, r, c, off, at - off))
            tile_at = None

    def take(el: Element) -> None:
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
                modal = Modal()
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
