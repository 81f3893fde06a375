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

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..execution import SERIAL, Execution
from ..io import NpzRows, from_json_array
from ..validation import InputError
from .oasis_read import DECODE_ERRORS, OasisError, OasisFile, gdelta_decode
from .rules import DESIGN_RULES, DesignRules
from .stream_scan import decode_error, scan_file, tile_placements, tile_size_of
from .writer import layout_geometry, snap_widths

__all__ = ["verify_stream", "gdelta_decode", "OasisError"]


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
    f = OasisFile(Path(g.path), sign=False)
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
                placed = tile_placements(f, offset, length, problem)
            except DECODE_ERRORS as exc:
                problem(f"malformed file: {name}: {decode_error(exc, f)}")
                placed = []
            out["tiles"] += 1
            try:
                got = _tile_map(name, placed, g, (r0, c0, h, w), out)
            except DECODE_ERRORS as exc:  # a position or an atom beyond any range: a damaged file
                problem(f"malformed file: {name}: {type(exc).__name__}: {exc}")
                got = np.full((h, w), -1, g.itype)
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


def _tile_map(name: str, placed: list, g: _Grid, box: tuple[int, int, int, int], out: dict) -> np.ndarray:
    """The tile's pillars on its lattice cells (-1: none; ``box``: the tile's first row and column and its
    height and width in cells), counting into ``out`` (and its ``problems``) what lies off the lattice,
    outside the tile, on an occupied cell or is not an atom."""
    r0, c0, h, w = box
    problem = out["problems"]
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


def _read_design(design_path: Path) -> tuple[dict, np.ndarray, int, float]:
    """The design file's metadata, its atoms' widths snapped to the 1 nm grid (``(n_atoms, 2)``), its cells
    per side and its lattice period (m); one-line InputErrors for a file that is not a design."""
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
    ew = np.stack([snap_widths(awx, 1)[0], snap_widths(awy, 1)[0]], 1).astype(np.int64)
    return dmeta, ew, n, float(period)


class _Totals:
    """The stripes' results summed in stripe order (the same report whatever the worker count): per-atom
    counts (layout and design), neighbour-pair tables and the mismatch counts."""

    def __init__(self, g: _Grid, rows: NpzRows, problem):
        k = g.n_atoms
        self.g, self.rows, self.problem = g, rows, problem
        self.counts = np.zeros(k, np.int64)
        self.want = np.zeros(k, np.int64)
        self.ph = np.zeros(k * k, np.int64)
        self.pv = np.zeros(k * k, np.int64)
        self.tot = {"mismatched": 0, "duplicates": 0, "off_lattice": 0, "tiles": 0}
        self.last = None  # (stripe, its top row) of the stripe folded last

    def fold(self, r: int, res: dict | None) -> None:
        """Stripe ``r``'s result into the totals; only its top row is kept, for the vertical pairs across
        the next border."""
        g, problem = self.g, self.problem
        if res is None:  # a stripe without a tile cell: its designed pillars are in no tile
            _, w_r = _design_rows(self.rows, g, r * g.tile, min(g.n, (r + 1) * g.tile))
            self.want += w_r
            if w_r.sum():
                self.tot["mismatched"] += int(w_r.sum())
                problem(f"stripe {r} (rows {r * g.tile}..): no tile cell, {int(w_r.sum())} designed pillars "
                        "missing")
            self.last = None
            return
        for msg in res["problems"]:
            problem(msg)
        self.counts += res["counts"]
        self.want += res["want"]
        self.ph += res["pairs_h"]
        self.pv += res["pairs_v"]
        for k in self.tot:
            self.tot[k] += res[k]
        if self.last is not None and self.last[0] == r - 1:  # vertical neighbours across the stripe border
            self.pv += _pairs(self.last[1], res["bottom"], g.n_atoms)
        self.last = (r, res["top"])


def _run_stripes(g: _Grid, by_row: dict[int, list], run: Execution, problem) -> _Totals:
    """Every stripe of tiles against its rows of the design, on ``run``'s workers, folded in stripe order
    as the results arrive (the few that arrive ahead of their turn wait)."""
    expected = {r for r in by_row if r * g.tile < g.n}
    n_stripes = -(-g.n // g.tile)
    rows = NpzRows(g.design, "index_map")
    acc = _Totals(g, rows, problem)
    pending: dict[int, dict] = {}
    nxt = done = 0
    try:
        for res in run.map(_stripe_job, [(r, by_row[r]) for r in sorted(expected)], shared=g, key="verify-stripe"):
            pending[res["r"]] = res
            done += 1
            while nxt < n_stripes and (nxt in pending or nxt not in expected):
                acc.fold(nxt, pending.pop(nxt, None))
                nxt += 1
            if run.progress:
                run.progress(done, len(by_row))
        while nxt < n_stripes:
            acc.fold(nxt, pending.pop(nxt, None))
            nxt += 1
    finally:
        rows.close()
        for r in _ROWS.values():  # an in-process worker's reader (workers <= 1)
            r.close()
        _ROWS.clear()
    return acc


def _check_hierarchy(scan: dict, tile_size: int, problem) -> None:
    """The tiling the file records, and the top cell placing every tile cell once at the origin."""
    names = scan["names"]
    prov, tiling = scan["prov"], (scan["prov"] or {}).get("tiling") or {}
    tiling = tiling if isinstance(tiling, dict) else {"tiling": tiling}
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


def _atom_widths(scan: dict, counts: np.ndarray, ew: np.ndarray, problem) -> np.ndarray:
    """Each atom's rectangle as the file writes it (``(n_atoms, 2)``, the design's where the file has none),
    checked against the design's snapped widths and for being centred on its cell's origin."""
    widths = ew.copy()
    for a in range(len(ew)):
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
    return widths


def _stream_drc(acc: _Totals, widths: np.ndarray, p_nm: int, rules: DesignRules) -> dict:
    """The design rules on every placed pillar (its atom's width) and every neighbour pair (the gap of the
    two atoms' centred rectangles), from the per-atom counts and the pair tables."""
    n_atoms, counts = len(widths), acc.counts
    used = np.flatnonzero(counts)
    gap_x = p_nm - (widths[:, 0][:, None] + widths[:, 0][None, :]) / 2  # centred: the gap of a pair
    gap_y = p_nm - (widths[:, 1][:, None] + widths[:, 1][None, :]) / 2
    ph, pv = acc.ph.reshape(n_atoms, n_atoms), acc.pv.reshape(n_atoms, n_atoms)
    width_viol = int(counts[(widths < rules.min_feature_nm).any(1)].sum())
    space_viol = int(ph[gap_x < rules.min_gap_nm].sum() + pv[gap_y < rules.min_gap_nm].sum())
    min_gap = min(float(gap_x[ph > 0].min()) if (ph > 0).any() else np.inf,
                  float(gap_y[pv > 0].min()) if (pv > 0).any() else np.inf)
    return {"rules": rules.limits(), "min_feature_nm": int(widths[used].min()) if used.size else None,
            "min_gap_nm": None if not np.isfinite(min_gap) else round(min_gap, 1),
            "pairs_checked": int(ph.sum() + pv.sum()), "width_violations": width_viol,
            "space_violations": space_viol, "passed": width_viol == 0 and space_viol == 0}


def verify_stream(path: str | Path, design_path: str | Path, rules: DesignRules = DESIGN_RULES,
                  tile: int | None = None, run: Execution = SERIAL, max_problems: int = 20) -> dict:
    """Read the OASIS file ``path`` and check it against the design ``design_path`` (see the module's
    docstring) under ``rules``: one pass over the top-level records (names, the signature, the top and atom
    cells, where each tile lies), then the stripes of tiles, each against its rows of the design, on
    ``run``'s local workers or Dask scheduler (the same report whatever the count: sums, combined in stripe
    order; ``run.progress`` counts the stripes).  ``tile``: the tiling's cells per tile side (default: the
    side-car's, checked against the file's own record).  Returns the report: ``exact`` (every pillar as
    designed, the file well-formed, its signature right), ``drc`` (``passed``), the counts and timings."""
    path, design_path = Path(path), Path(design_path)
    tile_size = tile_size_of(path, tile)
    if tile_size is None:
        raise InputError(f"{path}: no tile size (no side-car {path.name}.json): pass --tile")
    t0 = time.perf_counter()
    problem = _Problems(max_problems)
    dmeta, ew, n, period = _read_design(design_path)
    p_nm, x0 = layout_geometry(n, period)
    g = _Grid(str(path), str(design_path), n, len(ew), p_nm, x0, tile_size, dmeta.get("empty_index"))

    scan = scan_file(path, problem)
    t_scan = time.perf_counter() - t0
    by_row: dict[int, list] = {}
    for name, r, c, off, ln in scan["tiles"]:
        by_row.setdefault(r, []).append((name, c, off, ln))
    for r in sorted(by_row):
        if r * tile_size >= n:
            problem(f"tile row {r} is outside the design's {n} rows")
    acc = _run_stripes(g, by_row, run, problem)
    _check_hierarchy(scan, tile_size, problem)
    widths = _atom_widths(scan, acc.counts, ew, problem)
    if not np.array_equal(acc.counts, acc.want):
        bad = np.flatnonzero(acc.counts != acc.want)
        problem(f"per-atom pillar counts differ from the design for {bad.size} atoms (layout "
                f"{int(acc.counts.sum()):,}, design {int(acc.want.sum()):,})")
    drc = _stream_drc(acc, widths, p_nm, rules)
    tot = acc.tot
    return {"file": str(path), "design": str(design_path), "reader": "stream", "exact": not problem,
            "problems": list(problem), "pillars": int(acc.counts.sum()), "pillars_design": int(acc.want.sum()),
            "tiles": tot["tiles"], "tile_cells": tile_size, "mismatched_cells": tot["mismatched"],
            "duplicates": tot["duplicates"], "off_lattice": tot["off_lattice"],
            "signature": {"scheme": scan["scheme"], "ok": scan["signature_ok"]}, "unit_per_um": scan["unit"],
            "bytes": scan["bytes"], "workers": run.workers, "drc": drc,
            "scan_seconds": t_scan, "seconds": time.perf_counter() - t0}
