"""Read a layout back (gdstk, and KLayout as an independent reader), rebuild
the index map exactly, check it against the design, and run design rules."""

from __future__ import annotations

import json
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..config import InputError
from ..execution import SERIAL, Execution
from ..io import NpzRows, from_json_array, iter_npz_rows
from .rules import DESIGN_RULES, DesignRules
from .writer import PROPERTY, TOP_CELL, layout_geometry, snap_widths

__all__ = ["open_layout", "IndexRows", "read_tiled_contents", "LayoutContents", "read_layout", "read_layout_klayout",
           "verify_against_design", "drc_check", "check_file", "layout_format", "verify_tiled", "layout_tiling"]

_OASIS_MAGIC = b"%SEMI-OASIS\r\n"
_GDS_MAGIC = b"\x00\x06\x00\x02"


def layout_format(path: Path) -> str:
    """``"oas"`` or ``"gds"``: the format of a layout file by its first bytes, before anything reads it
    (one-line InputError for a missing path, a folder or a file of neither format)."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such layout file")
    if not path.is_file():
        raise InputError(f"{path}: is a folder, expected a layout file (.oas or .gds)")
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError as exc:
        raise InputError(f"{path}: cannot read the layout file ({exc.strerror or exc})") from None
    if head.startswith(_OASIS_MAGIC):
        return "oas"
    if head.startswith(_GDS_MAGIC):
        return "gds"
    raise InputError(f"{path}: not an OASIS or GDSII file")


def check_file(path: Path) -> str:
    """Format of a layout file after integrity checks; one-line InputError otherwise."""
    import gdstk

    fmt = layout_format(path)
    with open(path, "rb") as fh:
        fh.seek(max(0, path.stat().st_size - 4))
        tail = fh.read(4)
    if fmt == "oas":
        ok, _sig = gdstk.oas_validate(str(path))
        if ok is None:
            raise InputError(f"{path}: OASIS file without a validation signature (truncated, or not written "
                             "by metadesign)")
        if not ok:
            raise InputError(f"{path}: OASIS file is corrupt (CRC32 mismatch)")
        return "oas"
    if tail != b"\x00\x04\x04\x00":  # ENDLIB record
        raise InputError(f"{path}: GDSII file is truncated (no ENDLIB record)")
    return "gds"


@dataclass
class LayoutContents:
    index_map: np.ndarray  # [iy, ix], -1 where no pillar was placed
    atom_widths_nm: np.ndarray  # (n_atoms, 2) rectangle sizes read from the atom cells
    atom_centres_nm: np.ndarray  # (n_atoms, 2) rectangle centres (x2, to keep integers)
    provenance: dict
    n_placements: int
    duplicates: int
    off_lattice: int
    period_nm: int
    origin_nm: int
    seconds: float


def _provenance(top) -> dict:
    prop = top.get_property(PROPERTY)
    if not prop:
        raise InputError(f"layout has no '{PROPERTY}' property on its top cell: not written by metadesign")
    raw = prop[0]
    return json.loads(raw.decode() if isinstance(raw, bytes) else raw)


def _place(index_map, p_nm, x0, a, xs, ys, origin: tuple[int, int] = (0, 0)):
    """Scatter atom ``a`` at positions (nm) into ``index_map``, whose cell ``[0, 0]`` is lattice cell
    ``(c0, r0)`` (``origin = (r0, c0)``); returns (duplicates, off-lattice or outside the map).

    Readers return float positions (gdstk accumulates the repetition deltas in
    doubles, ~1e-6 nm off); each must be within 0.01 nm of an integer nm,
    which must then lie exactly on the lattice (integer arithmetic)."""
    r0, c0 = origin
    xi, yi = np.rint(xs).astype(np.int64), np.rint(ys).astype(np.int64)
    near = (np.abs(xs - xi) < 0.01) & (np.abs(ys - yi) < 0.01)
    ix, rx = np.divmod(xi - x0, p_nm)
    iy, ry = np.divmod(yi - x0, p_nm)
    ix, iy = ix - c0, iy - r0
    h, w = index_map.shape
    bad = ~near | (rx != 0) | (ry != 0) | (ix < 0) | (ix >= w) | (iy < 0) | (iy >= h)
    ix, iy = ix[~bad], iy[~bad]
    dup = int(np.count_nonzero(index_map[iy, ix] >= 0))
    index_map[iy, ix] = a
    return dup, int(bad.sum())


def read_layout(path: str | Path) -> LayoutContents:
    """gdstk reader: every pillar, exactly."""
    import gdstk

    path = Path(path)
    t0 = time.perf_counter()
    fmt = check_file(path)
    try:
        lib = gdstk.read_oas(str(path), unit=1e-9) if fmt == "oas" else gdstk.read_gds(str(path), unit=1e-9)
    except Exception as exc:  # gdstk raises RuntimeError/OSError on damaged files
        raise InputError(f"{path}: cannot read layout ({exc})") from None
    cells = {c.name: c for c in lib.cells}
    if TOP_CELL not in cells:
        raise InputError(f"{path}: no top cell {TOP_CELL!r}: not a metadesign layout")
    top = cells[TOP_CELL]
    if fmt == "gds":  # GDSII keeps no cell properties: provenance is in the text label
        prov = None
        for lab in top.labels:
            if lab.texttype == 1 and lab.text.startswith("{"):
                prov = json.loads(lab.text)
        if prov is None:
            raise InputError(f"{path}: no provenance label: not written by metadesign")
    else:
        prov = _provenance(top)
    n = int(prov["n_cells"])
    p_nm, x0 = layout_geometry(n, prov["period_nm"] * 1e-9)
    n_atoms = int(prov["n_atoms"])
    widths = np.zeros((n_atoms, 2), np.int64)
    centres2 = np.zeros((n_atoms, 2), np.int64)
    for a in range(n_atoms):
        c = cells.get(f"ATOM_{a:03d}")
        if c is None:  # an atom the layout does not place: its rectangle from the provenance's atom table
            widths[a], centres2[a] = _unplaced_atom(path, prov, a)
            continue
        if len(c.polygons) != 1:
            raise InputError(f"{path}: atom cell ATOM_{a:03d} is not a single rectangle")
        (xa, ya), (xb, yb) = c.polygons[0].bounding_box()
        widths[a] = round(xb - xa), round(yb - ya)
        centres2[a] = round(xa + xb), round(ya + yb)
    im = np.full((n, n), -1, np.int16 if n_atoms < 32767 else np.int32)
    dup = off = count = 0
    # GDSII stores one SREF per pillar: group them per atom cell first
    groups: dict[int, list] = {}
    refs = []
    for ref in top.references:  # a tiled layout (layouts.tiled) places tile cells, once each, at the origin
        name = ref.cell.name if hasattr(ref.cell, "name") else str(ref.cell)
        if name.startswith("TILE_") and name in cells:
            if ref.repetition.size > 1 or tuple(ref.origin) != (0, 0):
                raise InputError(f"{path}: tile cell {name!r} placed off the origin or repeated")
            refs += cells[name].references
        else:
            refs.append(ref)
    for ref in refs:
        name = ref.cell.name if hasattr(ref.cell, "name") else str(ref.cell)
        if not name.startswith("ATOM_"):
            raise InputError(f"{path}: unexpected reference to cell {name!r}")
        a = int(name[5:])
        if name not in cells:
            raise InputError(f"{path}: reference to the missing atom cell {name!r}")
        ox, oy = ref.origin
        if ref.repetition.size > 1:
            offs = np.asarray(ref.repetition.offsets)
            xs = np.concatenate([[0.0], offs[:, 0]]) + ox
            ys = np.concatenate([[0.0], offs[:, 1]]) + oy
        else:
            xs, ys = np.array([ox]), np.array([oy])
        groups.setdefault(a, []).append((xs, ys))
    for a, parts in groups.items():
        xs = np.concatenate([p[0] for p in parts])
        ys = np.concatenate([p[1] for p in parts])
        count += xs.size
        d, o = _place(im, p_nm, x0, a, xs, ys)
        dup += d
        off += o
    return LayoutContents(im, widths, centres2, prov, count, dup, off, p_nm, x0, time.perf_counter() - t0)


def read_layout_klayout(path: str | Path) -> LayoutContents:
    """Independent reader: KLayout's own OASIS/GDS parser (expands repetitions)."""
    import klayout.db as kdb

    path = Path(path)
    t0 = time.perf_counter()
    ly, top, prov = _klayout_open(path, editable=True)
    n = int(prov["n_cells"])
    p_nm, x0 = layout_geometry(n, prov["period_nm"] * 1e-9)
    n_atoms = int(prov["n_atoms"])
    widths, centres2, index_of = _klayout_atoms(ly, path, prov)
    from array import array

    xs = {a: array("q") for a in range(n_atoms)}  # compact: paper scale is 51 M instances
    ys = {a: array("q") for a in range(n_atoms)}
    count = 0
    insts = []
    for inst in top.each_inst():  # a tiled layout's tile cells, placed once each at the origin
        name = ly.cell(inst.cell_index).name
        if name.startswith("TILE_"):
            if inst.size() != 1 or inst.trans.disp != kdb.Vector(0, 0):
                raise InputError(f"{path}: tile cell {name!r} placed off the origin or repeated")
            insts += list(ly.cell(inst.cell_index).each_inst())
        else:
            insts.append(inst)
    for inst in insts:
        a = index_of.get(inst.cell_index)
        if a is None:
            raise InputError(f"{path}: unexpected instance of cell {ly.cell(inst.cell_index).name!r}")
        if inst.is_regular_array():
            na, nb = inst.na, inst.nb
            base = inst.trans.disp
            for i in range(na):
                for j in range(nb):
                    v = base + inst.a * i + inst.b * j
                    xs[a].append(v.x)
                    ys[a].append(v.y)
            count += na * nb
        else:
            d = inst.trans.disp
            xs[a].append(d.x)
            ys[a].append(d.y)
            count += 1
    im = np.full((n, n), -1, np.int32)
    dup = off = 0
    for a in range(n_atoms):
        if len(xs[a]):
            d, o = _place(im, p_nm, x0, a, np.frombuffer(xs[a], np.int64).astype(float),
                          np.frombuffer(ys[a], np.int64).astype(float))
            dup += d
            off += o
    return LayoutContents(im, widths, centres2, prov, count, dup, off, p_nm, x0, time.perf_counter() - t0)


def layout_tiling(path: str | Path) -> dict | None:
    """The tiling a tiled layout's side-car (``LAYOUT.json``) records, None for a whole-array layout."""
    side = Path(path).with_suffix(Path(path).suffix + ".json")
    try:
        return json.loads(side.read_text()).get("provenance", {}).get("tiling")
    except (OSError, ValueError):
        return None


def _klayout_open(path: Path, editable: bool):
    """``(layout, top cell, provenance)`` of a metadesign layout read by KLayout (``editable`` False:
    viewer mode, where OASIS repetitions stay arrays instead of one instance per pillar)."""
    import klayout.db as kdb

    check_file(path)
    ly = kdb.Layout(editable)
    try:
        ly.read(str(path))
    except Exception as exc:
        raise InputError(f"{path}: KLayout cannot read the layout ({exc})") from None
    if abs(ly.dbu - 1e-3) > 1e-12:
        raise InputError(f"{path}: database unit {ly.dbu} um, expected 0.001 um (1 nm)")
    top = ly.cell(TOP_CELL)
    if top is None:
        raise InputError(f"{path}: no top cell {TOP_CELL!r}")
    prov = None
    for li in ly.layer_indexes():
        for sh in top.shapes(li).each():
            if sh.is_text() and sh.text.string.startswith("{"):
                prov = json.loads(sh.text.string)
    if prov is None:
        prop = top.property(PROPERTY)
        prov = json.loads(prop) if prop else None
    if prov is None:
        raise InputError(f"{path}: no provenance: not written by metadesign")
    return ly, top, prov


def _klayout_atoms(ly, path: Path, prov: dict):
    """Each atom's rectangle (size, doubled centre) from its cell in a KLayout layout (from the
    provenance's table when the layout places none of it), and ``{cell index: atom}``."""
    n_atoms = int(prov["n_atoms"])
    layer = ly.find_layer(prov["layer"][0], prov["layer"][1])
    widths = np.zeros((n_atoms, 2), np.int64)
    centres2 = np.zeros((n_atoms, 2), np.int64)
    index_of = {}
    for a in range(n_atoms):
        c = ly.cell(f"ATOM_{a:03d}")
        if c is None:  # not placed (instances of it would name a cell that exists)
            widths[a], centres2[a] = _unplaced_atom(path, prov, a)
            continue
        shapes = list(c.shapes(layer).each())
        if len(shapes) != 1:
            raise InputError(f"{path}: atom cell ATOM_{a:03d} holds {len(shapes)} shapes, expected 1")
        b = shapes[0].bbox()
        widths[a] = b.width(), b.height()
        centres2[a] = b.left + b.right, b.bottom + b.top
        index_of[c.cell_index()] = a
    return widths, centres2, index_of


def _unplaced_atom(path: Path, prov: dict, a: int) -> tuple[list[int], list[int]]:
    """Width and doubled centre of an atom the layout writes no cell for (it places none): from the
    provenance's atom table, centred as the writer centres rectangles."""
    table = prov.get("atom_widths_nm")
    if not table or a >= len(table):
        raise InputError(f"{path}: atom cell ATOM_{a:03d} missing (and no atom table in the provenance)")
    w = [int(table[a][0]), int(table[a][1])]
    return w, [-(w[0] % 2), -(w[1] % 2)]


def verify_against_design(lc: LayoutContents, design, grid_nm: int = 1) -> dict:
    """Exact comparison of every pillar (position, atom, size) with the design."""
    spec = design.spec
    want = design.index_map.astype(np.int64)
    if design.empty is not None:
        want = np.where(design.index_map == design.empty, -1, want)
    problems = []
    if lc.index_map.shape != want.shape:
        problems.append(f"grid {lc.index_map.shape} vs design {want.shape}")
        mismatched = -1
    else:
        mismatched = int(np.count_nonzero(lc.index_map != want))
        if mismatched:
            problems.append(f"{mismatched} cells hold another atom than the design")
    wx, _ = snap_widths(design.atoms.wx, grid_nm)
    wy, _ = snap_widths(design.atoms.wy, grid_nm)
    exp_w = np.stack([wx, wy], axis=1)
    if lc.atom_widths_nm.shape != exp_w.shape or np.any(lc.atom_widths_nm != exp_w):
        problems.append("atom rectangle sizes differ from the design's snapped widths")
    # centres: exactly 0, or -1 (half a nm, doubled) for odd widths
    if np.any((lc.atom_centres_nm != 0) & (lc.atom_centres_nm != -(exp_w % 2))):
        problems.append("atom rectangles are not centred on their cell origin")
    p_nm, x0 = layout_geometry(spec.n_cells, spec.period)
    if (lc.period_nm, lc.origin_nm) != (p_nm, x0):
        problems.append(f"lattice {lc.period_nm} nm / origin {lc.origin_nm} vs design {p_nm} / {x0}")
    if lc.duplicates:
        problems.append(f"{lc.duplicates} cells placed more than once")
    if lc.off_lattice:
        problems.append(f"{lc.off_lattice} pillars off the {p_nm} nm lattice or outside the aperture")
    expected = int(np.count_nonzero(want >= 0))
    if lc.n_placements != expected:
        problems.append(f"{lc.n_placements} pillars placed, design has {expected}")
    return {"exact": not problems, "problems": problems, "pillars": lc.n_placements, "expected": expected,
            "mismatched_cells": mismatched, "read_seconds": lc.seconds,
            "counts_per_atom": np.bincount(lc.index_map[lc.index_map >= 0].ravel(),
                                           minlength=len(design.atoms)).tolist()}


def drc_check(lc: LayoutContents, min_feature_nm: int = DESIGN_RULES.min_feature_nm,
              min_gap_nm: int = DESIGN_RULES.min_gap_nm, window_cells: int = 64) -> dict:
    """Design rules: from the atom table, and geometrically with KLayout regions
    on a central window of the layout as read back from the file (merged
    semantics off, so abutting pillars are not fused; one window, no tiles, so
    no violation is counted twice)."""
    table = _atom_table_rules(lc.atom_widths_nm, lc.period_nm)
    n = lc.index_map.shape[0]
    c = min(window_cells, n)
    s = (n - c) // 2
    lat = _AtomLattice(lc.atom_widths_nm, lc.atom_centres_nm, lc.period_nm, lc.origin_nm)
    win = _window_drc(lc.index_map[s:s + c, s:s + c], (s, s), lat, DesignRules(min_feature_nm, min_gap_nm))
    geo = {"window_cells": c, "pillars_in_window": win["pillars"], "width_violations": win["width_violations"],
           "space_violations": win["space_violations"]}
    passed = _rules_pass(table, [win], min_feature_nm, min_gap_nm)
    return {"rules": {"min_feature_nm": min_feature_nm, "min_gap_nm": min_gap_nm}, "from_atom_table": table,
            "geometric_window": geo, "passed": passed}


def _atom_table_rules(widths: np.ndarray, p_nm: int) -> dict:
    """Minimum feature and gaps from the atom rectangles alone (every pillar is one of them)."""
    return {"min_feature_nm": int(widths.min()), "min_gap_x_nm": int(p_nm - widths[:, 0].max()),
            "min_gap_y_nm": int(p_nm - widths[:, 1].max())}


def _rules_pass(table: dict, windows: list[dict], min_feature_nm: int, min_gap_nm: int) -> bool:
    return (table["min_feature_nm"] >= min_feature_nm and min(table["min_gap_x_nm"], table["min_gap_y_nm"])
            >= min_gap_nm and all(w["width_violations"] == 0 and w["space_violations"] == 0 for w in windows))


class _AtomLattice(NamedTuple):
    """The atoms' rectangles (sizes and doubled centres, nm) and the lattice they are placed on (pitch and
    the first cell's centre, nm)."""

    widths: np.ndarray
    centres2: np.ndarray
    p_nm: int
    x0: int


def _window_drc(block: np.ndarray, origin: tuple[int, int], lat: _AtomLattice, rules: DesignRules) -> dict:
    """Geometric width and space checks (KLayout regions, merged semantics off) on the pillars of
    ``block`` (an index-map window read back from the file, -1 = none) at cell origin ``(r0, c0)``."""
    import klayout.db as kdb

    r0, c0 = origin
    widths, centres2, p_nm, x0 = lat

    region = kdb.Region()
    for j, i in zip(*np.nonzero(block >= 0)):
        a = int(block[j, i])
        cx2 = 2 * ((c0 + int(i)) * p_nm + x0) + int(centres2[a, 0])
        cy2 = 2 * ((r0 + int(j)) * p_nm + x0) + int(centres2[a, 1])
        ww, hh = int(widths[a, 0]), int(widths[a, 1])
        region.insert(kdb.Box((cx2 - ww) // 2, (cy2 - hh) // 2, (cx2 - ww) // 2 + ww, (cy2 - hh) // 2 + hh))
    region.merged_semantics = False
    return {"pillars": region.count(), "width_violations": region.width_check(rules.min_feature_nm).count(),
            "space_violations": region.space_check(rules.min_gap_nm).count()}


def _count_tiles(ly, top, index_of: dict, n_atoms: int, problems: list) -> tuple[np.ndarray, dict]:
    """Every pillar counted per atom through the hierarchy (KLayout's arrays, not expanded), and the tile
    cells the top cell places (name -> cell index)."""
    import klayout.db as kdb

    counts = np.zeros(n_atoms, np.int64)
    tiles = {}
    for inst in top.each_inst():
        name = ly.cell(inst.cell_index).name
        if not name.startswith("TILE_"):
            problems.append(f"top cell places {name!r}, expected tile cells only")
            continue
        if inst.size() != 1 or inst.trans.disp != kdb.Vector(0, 0):
            problems.append(f"tile cell {name!r} placed off the origin or repeated")
        tiles[name] = inst.cell_index
        for ti in ly.cell(inst.cell_index).each_inst():
            a = index_of.get(ti.cell_index)
            if a is None:
                problems.append(f"{name} places {ly.cell(ti.cell_index).name!r}, expected atom cells only")
                continue
            counts[a] += ti.size()
    return counts, tiles


def _design_empty(design_path: Path) -> int | None:
    """The design file's no-pillar index (None: every cell holds a pillar)."""
    try:
        with np.load(design_path, allow_pickle=False) as z:  # an NpzFile reads only the entry asked for
            dmeta = from_json_array(z["meta"])
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
        raise InputError(f"{design_path}: not a design file ({exc})") from None
    return dmeta.get("empty_index")


def _design_blocks(design_path: Path, n: int, n_atoms: int, tile: int, picks: dict[int, list], empty: int | None,
                   progress) -> tuple[np.ndarray, dict]:
    """The design's index map (``empty``: its no-pillar index) streamed one stripe of ``tile`` rows at a
    time: its per-atom pillar counts and the blocks of the tiles ``picks`` names (tile row -> tile columns)."""
    want = np.zeros(n_atoms + 1, np.int64)
    blocks = {}
    for r0, blk in iter_npz_rows(design_path, "index_map", tile):
        if blk.shape[1] != n:
            raise InputError(f"{design_path}: index map of {blk.shape[1]} columns, layout has {n}")
        b = np.bincount(blk.ravel(), minlength=max(n_atoms + 1, int(blk.max()) + 1))
        want += b[:n_atoms + 1] if empty is None else np.append(b[:n_atoms], 0)
        for tc in picks.get(r0 // tile, []):
            blocks[(r0 // tile, tc)] = blk[:, tc * tile:(tc + 1) * tile].copy()
        if progress:
            progress(min(n, r0 + tile), n)
    return want[:n_atoms], blocks


def _tile_pillars(ly, ci: int, index_of: dict, shape: tuple[int, int], lat: _AtomLattice,
                  origin: tuple[int, int]) -> tuple[np.ndarray, int, int]:
    """Tile cell ``ci``'s pillars expanded one by one onto its lattice cells (``origin``: its first row and
    column): the index map (-1 = none), duplicates, pillars off the lattice or outside the tile."""
    got = np.full(shape, -1, np.int64)
    dup = off = 0
    for ti in ly.cell(ci).each_inst():
        pts = np.array([(tt.disp.x, tt.disp.y) for tt in ti.cell_inst.each_trans()], np.float64).reshape(-1, 2)
        d, o = _place(got, lat.p_nm, lat.x0, index_of[ti.cell_index], pts[:, 0], pts[:, 1], origin)
        dup += d
        off += o
    return got, dup, off


def verify_tiled(path: str | Path, design_path: str | Path, sample_tiles: int = 8, seed: int = 0,
                 rules: DesignRules = DESIGN_RULES, run: Execution = SERIAL) -> dict:
    """Verification that scales, for a tiled layout (:mod:`metadesign.layouts.tiled`, ``hierarchy =
    "tiles"``): KLayout (viewer mode: repetitions stay arrays) counts every pillar, per atom, through the
    hierarchy; ``sample_tiles`` tiles drawn with ``seed`` are expanded pillar by pillar and compared
    exactly with the design's index map (streamed from ``design.npz``, one stripe at a time, reported to
    ``run.progress``); the geometric design ``rules`` run on a window of ``rules.window_cells`` at the
    centre of each sampled tile.  The report says which fraction of the pillars was compared exactly."""
    path, design_path = Path(path), Path(design_path)
    t0 = time.perf_counter()
    ly, top, prov = _klayout_open(path, editable=False)
    t_read = time.perf_counter() - t0
    tiling = prov.get("tiling")
    if not tiling or tiling.get("hierarchy") != "tiles":
        raise InputError(f"{path}: not a tiled layout with tile cells (use layout verify without --sample-tiles)")
    n, tile = int(prov["n_cells"]), int(tiling["tile_cells"])
    nt = -(-n // tile)
    p_nm, x0 = layout_geometry(n, prov["period_nm"] * 1e-9)
    n_atoms = int(prov["n_atoms"])
    widths, centres2, index_of = _klayout_atoms(ly, path, prov)
    lat = _AtomLattice(widths, centres2, p_nm, x0)
    problems = []
    counts, tiles = _count_tiles(ly, top, index_of, n_atoms, problems)
    t_count = time.perf_counter() - t0
    # --- the design, streamed: its per-atom counts and the sampled tiles' blocks
    empty = _design_empty(design_path)
    rng = np.random.default_rng(seed)
    k = min(sample_tiles, nt * nt)
    picks = sorted(rng.choice(nt * nt, size=k, replace=False).tolist()) if k else []
    want_rows = {}
    for t in picks:
        want_rows.setdefault(t // nt, []).append(t % nt)
    want, blocks = _design_blocks(design_path, n, n_atoms, tile, want_rows, empty, run.progress)
    if not np.array_equal(counts, want):
        bad = np.flatnonzero(counts != want)
        problems.append(f"per-atom pillar counts differ from the design for {bad.size} atoms "
                        f"(layout {int(counts.sum()):,}, design {int(want.sum()):,})")
    # --- sampled tiles, pillar by pillar
    sampled, mismatched, drc = 0, 0, []
    for (tr, tc), blk in sorted(blocks.items()):
        name = f"TILE_{tr:03d}_{tc:03d}"
        r0, c0 = tr * tile, tc * tile
        ci = tiles.get(name)
        if ci is None:
            problems.append(f"tile cell {name} missing")
            continue
        got, dup, off = _tile_pillars(ly, ci, index_of, blk.shape, lat, (r0, c0))
        ref = blk.astype(np.int64)
        if empty is not None:
            ref = np.where(blk == empty, -1, ref)
        mm = int(np.count_nonzero(got != ref))
        sampled += int((ref >= 0).sum())
        mismatched += mm
        if mm or dup or off:
            problems.append(f"{name}: {mm} cells differ from the design, {dup} duplicates, {off} off the tile")
        h = min(rules.window_cells, blk.shape[0], blk.shape[1])
        s0, s1 = (blk.shape[0] - h) // 2, (blk.shape[1] - h) // 2
        drc.append({"tile": name, **_window_drc(got[s0:s0 + h, s1:s1 + h], (r0 + s0, c0 + s1), lat, rules)})
    total = int(want.sum())
    table = _atom_table_rules(widths, p_nm)
    drc_ok = _rules_pass(table, drc, rules.min_feature_nm, rules.min_gap_nm)
    return {"file": str(path), "design": str(design_path), "exact": not problems, "problems": problems,
            "pillars_klayout": int(counts.sum()), "pillars_design": total, "tiles": nt * nt,
            "sampled_tiles": [f"TILE_{t // nt:03d}_{t % nt:03d}" for t in picks], "seed": seed,
            "sampled_pillars": sampled, "sampled_fraction": sampled / max(total, 1),
            "mismatched_cells": mismatched,
            "drc": {"rules": rules.limits(), "from_atom_table": table, "windows": drc,
                    "window_cells": rules.window_cells, "passed": drc_ok},
            "read_seconds": t_read, "count_seconds": t_count - t_read, "seconds": time.perf_counter() - t0}


class IndexRows:
    """A tiled design's index map, read by rows from ``design.npz`` (:class:`metadesign.io.NpzRows`),
    with the no-pillar sentinel as -1 (int32), as a layout's index map: a device of any size in the
    memory of the rows a consumer asks for."""

    def __init__(self, path: str | Path, empty: int | None):
        self.rows, self.empty = NpzRows(path, "index_map"), empty
        self.shape = self.rows.shape
        self.dtype = np.dtype(np.int32)

    def __getitem__(self, key) -> np.ndarray:
        raw = self.rows[key]
        im = raw.astype(np.int32)
        if self.empty is not None:
            im[raw == self.empty] = -1
        return im


def read_tiled_contents(path: Path) -> LayoutContents:
    """The pillars of a tiled layout, streamed from the design written with it (``design.npz`` beside
    it, which ``layout verify`` checks against the file: KLayout's count of every pillar and sampled
    tiles exactly), so a 1e9-pillar device never sits in memory; atom rectangles from the provenance."""
    path = Path(path)
    side = json.loads(path.with_suffix(path.suffix + ".json").read_text())
    prov = side["provenance"]
    design = path.parent / "design.npz"
    if not design.exists():
        raise InputError(f"{path}: a tiled layout is read through its design.npz, which is not beside it")
    n = int(prov["n_cells"])
    p_nm, x0 = layout_geometry(n, prov["period_nm"] * 1e-9)
    w = np.asarray(prov["atom_widths_nm"], np.int64)
    im = IndexRows(design, prov.get("empty_index"))
    if im.shape != (n, n):
        raise InputError(f"{design}: index map {im.shape}, the layout has {n} x {n} cells")
    return LayoutContents(im, w, -(w % 2), prov, int(side["pillars"]), 0, 0, p_nm, x0, 0.0)


def open_layout(path: str | Path) -> LayoutContents:
    """The one reader of a layout written by metadesign, whole or tiled: a whole layout's pillars read back
    from the file (gdstk); a tiled one's streamed by rows from the design written with it (its
    ``design.npz``, which ``layout verify`` ties to the file), so a 1e9-pillar device never sits in memory."""
    path = Path(path)
    return read_tiled_contents(path) if layout_tiling(path) else read_layout(path)
