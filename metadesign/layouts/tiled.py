"""Centimetre apertures: design and OASIS layout in one streamed pass, tile by tile, in bounded memory.

The aperture is cut into stripes of ``tile`` rows (a multiple of the design's ``tile_rows`` and of the
supercell); a worker maps a stripe's cells to atoms (the discretizer's kernel, the same numbers as the
whole-array path) and encodes each ``tile x tile`` square as OASIS placements: one per atom present,
a type-11 repetition on the lattice pitch holding its pillars in raster order.  Finished stripes are
kept on disk (resumable), each with its piece of the design's index map already deflated
(:mod:`metadesign.deflate`); the main process then only concatenates: the pieces into ``design.npz``'s
index map (CRCs combined, never re-compressed) and the tiles' compressed blocks into ``layout.oas``, so
assembly runs at disk speed, the peak memory is a few stripes whatever the aperture, and the bytes do
not depend on the worker count or the scheduler (the design's arrays equal the whole-array path's).

OASIS reference numbers: atom ``a`` is ``a``, the top cell ``len(atoms)``, tile ``(r, c)``
``len(atoms) + 1 + r * n_tiles + c`` (the order in which the names are declared).

Hierarchy (``hierarchy``): ``"tiles"`` puts each tile in a cell ``TILE_<row>_<col>`` placed once by
the top cell; ``"flat"`` writes every placement in the top cell.  The top cell, the atom cells, the
provenance property, the outline and the labels are those of :mod:`metadesign.layouts.writer`.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..design.build import DesignStream, accumulate, empty_index, map_rows
from ..design.discretize import AtomTable, Metric, NearestAtom
from ..design.phase import SupercellSpec
from ..design.recipe import DesignRecipe
from ..design.store import Design, check_library, design_meta, select_recipe_atoms
from .. import __version__, jit
from ..deflate import DeflatedArray, Piece, deflate_piece
from ..execution import SERIAL, Execution
from ..io import atomic_path, remove_stale_temps, atomic_write_text, json_array, read_npz, write_npz
from ..library.store import load_library
from ..outputs import Need
from ..tasks import TaskFolder, content_key
from ..validation import ValidationError
from . import oasis as O
from .kernel import tile_records_kernel
from .writer import TOP_CELL, LayoutOptions, layout_geometry, outline_polygons, provenance_of, snap_widths

__all__ = ["TiledPlan", "build_tiled", "tile_records", "tile_records_numpy", "HIERARCHIES", "DEFAULT_TILE"]

HIERARCHIES = ("tiles", "flat")
DEFAULT_TILE = 1024
#: deflate level of the design file's index map (each stripe's piece, on its worker).  Measured
#: (benchmarks/bench_tiled.py, quiet machine, paper design rows): level 1 7.9 ns/pillar to 0.40 of the raw
#: bytes, level 6 10.3 ns to 0.27 (10 cm rows: 0.48 vs 0.44): +2 % of a pillar's worker cost (~130 ns)
#: for a file up to a third smaller
DESIGN_DEFLATE_LEVEL = 6
#: OASIS bytes per pillar of the streamed encoder (measured: 5 mm 0.60, 2.5 cm 0.40; the larger for estimates)
OASIS_BYTES_PER_PILLAR = 0.6


@dataclass
class TiledPlan:
    """Everything a worker needs for a stripe (sent once per worker)."""

    spec: SupercellSpec
    atoms: AtomTable
    metric: Metric
    offsets: tuple[float, float]
    dtype: str
    empty: int | None
    tile_rows: int
    tile: int
    p_nm: int
    x0: int
    hierarchy: str
    compression: int
    design_level: int = DESIGN_DEFLATE_LEVEL  # the design file's deflate level
    # local workers write their stripe's file here themselves (nothing crosses the pipe); None: returned
    # (Dask workers, which may not share this file system)
    save_dir: str | None = None
    _mapper: object = field(default=None, repr=False, compare=False)

    @property
    def n_tiles(self) -> int:
        return -(-self.spec.n_cells // self.tile)

    def tile_ref(self, r: int, c: int) -> int:
        """OASIS reference number of cell ``TILE_<r>_<c>`` (after the atoms and the top cell)."""
        return len(self.atoms) + 1 + r * self.n_tiles + c

    def mapper(self):
        if self._mapper is None:
            self._mapper = NearestAtom(self.atoms, self.metric)
        return self._mapper

    def __getstate__(self):
        d = dict(self.__dict__)
        d["_mapper"] = self.mapper()  # its tables travel once per worker (a rebuild costs each worker ~1 s)
        return d


def tile_records(blk: np.ndarray, r0: int, c0: int, plan: TiledPlan) -> bytes:
    """The placements of one tile (``blk``: its index map, global origin ``r0, c0``), uncompressed:
    per atom present, one PLACEMENT at its first pillar in raster order with a type-11 repetition on
    the lattice pitch through the others.  Compiled (:mod:`metadesign.layouts.kernel`), or without numba
    its numpy twin :func:`tile_records_numpy`: the same bytes."""
    if jit.enabled():
        return tile_records_kernel(blk, r0, c0, len(plan.atoms), plan.p_nm, plan.x0)
    return tile_records_numpy(blk, r0, c0, plan)


def tile_records_numpy(blk: np.ndarray, r0: int, c0: int, plan: TiledPlan) -> bytes:
    """:func:`tile_records` in numpy (the reference of the compiled kernel)."""
    w = blk.shape[1]
    flat = blk.ravel()
    order = np.argsort(flat, kind="stable")  # raster order within each atom
    counts = np.bincount(flat, minlength=len(plan.atoms) + 1)[:len(plan.atoms)]
    present = np.flatnonzero(counts)
    n_placed = int(counts[present].sum())
    if not n_placed:  # a tile outside the clear aperture
        return b""
    order = order[:n_placed]  # the empty sentinel (max of the dtype) sorts last
    iy, ix = np.divmod(order, w)
    iy, ix = iy + r0, ix + c0
    # g-deltas inside each atom's run (a run of c pillars has c - 1)
    starts = np.concatenate(([0], np.cumsum(counts[present])[:-1]))
    inside = np.ones(n_placed, bool)
    inside[starts] = False
    dx, dy = np.diff(ix)[inside[1:]], np.diff(iy)[inside[1:]]
    gbytes, per = O.gdelta_array(dx, dy)
    gbytes = gbytes.tobytes()
    boff = np.concatenate(([0], np.cumsum(per)))
    doff = np.concatenate(([0], np.cumsum(counts[present] - 1)))
    out = []
    p, x0 = plan.p_nm, plan.x0
    for j, a in enumerate(present):
        s, c = int(starts[j]), int(counts[a])
        out.append(O.placement_head(int(a), int(ix[s]) * p + x0, int(iy[s]) * p + x0, c > 1))
        if c > 1:
            out.append(O.repetition_head(c, p))
            out.append(gbytes[boff[doff[j]]:boff[doff[j + 1]]])
    return b"".join(out)


def _stripe(plan: TiledPlan, r0: int) -> dict:
    """Worker: rows ``r0 : r0 + tile`` of the design (in ``tile_rows`` sub-stripes, as the whole-array
    path sums its metrics), the OASIS bytes of the stripe's tiles and its deflated piece of the index map."""
    spec, n = plan.spec, plan.spec.n_cells
    r1 = min(n, r0 + plan.tile)
    blk = np.empty((r1 - r0, n), plan.dtype)
    parts = []
    for s0 in range(r0, r1, plan.tile_rows):
        s1 = min(r1, s0 + plan.tile_rows)
        b, st = map_rows(spec, plan.atoms, plan.mapper(), plan.offsets, plan.dtype, plan.empty, s0, s1)
        blk[s0 - r0:s1 - r0] = b
        parts.append(st)
    return {"r0": r0, "stats": parts, "oasis": encode_stripe(plan, blk, r0),
            "design": deflate_piece(memoryview(blk).cast("B"), plan.design_level)}


def _stripe_task(plan: TiledPlan, r0: int) -> tuple[str, dict]:
    """The resumable task of a stripe: its name and its arrays (as kept in the task folder)."""
    res = _stripe(plan, r0)
    st = res["stats"]
    piece = res["design"]
    name = f"stripe-{r0:07d}"
    arrays = {"design": np.frombuffer(piece.data, np.uint8),
              "design_crc_size": np.array([piece.crc, piece.size], np.int64),
              "oasis": np.frombuffer(res["oasis"], np.uint8),
              "sse": np.array([p[0] for p in st]), "peak": np.array([p[1] for p in st]),
              "eff": np.array([p[2] for p in st]), "count": np.array([p[3] for p in st], np.int64),
              "used": np.array([p[4] for p in st], np.int64)}
    if plan.save_dir is None:
        return name, arrays
    target = Path(plan.save_dir) / f"{name}.npz"
    if not target.parent.is_dir():  # the job's folder is gone (this worker outlived its job): write nothing
        raise RuntimeError(f"{target.parent}: the stripe folder of this job no longer exists")
    write_npz(target, arrays, compress=False)  # atomically, as the folder would
    return name, None


def _load_stripe(path: Path) -> dict:
    z = read_npz(path, "stripe of an interrupted tiled build")
    stats = [(z["sse"][k], z["peak"][k], z["eff"][k], int(z["count"][k]), z["used"][k])
             for k in range(len(z["count"]))]
    crc, size = (int(v) for v in z["design_crc_size"])
    return {"design": Piece(z["design"].tobytes(), crc, size), "oasis": z["oasis"].tobytes(), "stats": stats}


def encode_stripe(plan: TiledPlan, blk: np.ndarray, r0: int) -> bytes:
    """The OASIS bytes of one stripe's tiles (a CELL record per tile with ``hierarchy="tiles"``)."""
    out = []
    tr = r0 // plan.tile
    for tc, c0 in enumerate(range(0, plan.spec.n_cells, plan.tile)):
        rec = tile_records(blk[:, c0:c0 + plan.tile], r0, c0, plan)
        if plan.hierarchy == "tiles":
            out.append(bytes([13]) + O.uint(plan.tile_ref(tr, tc)))
        if rec:
            out.append(O.cblock(rec, plan.compression))
    return b"".join(out)


#: the design file's index map deflates to at most this fraction of its raw bytes (measured at level 6:
#: the paper design 0.27, the 10 cm one 0.44; the larger for estimates)
DESIGN_DEFLATE_RATIO = 0.5


def tiled_need(recipe: DesignRecipe, tile: int = DEFAULT_TILE, workers: int = 1) -> Need:
    """What ``build_tiled`` needs at its peak: on disk the kept stripes (index blocks deflated + their OASIS
    bytes) beside the final design and layout (the same bytes again); in memory one stripe of ``tile`` x n cells
    per worker (measured: 2.5 cm, 2 workers, tile 1024: 1.55 GB for the process tree; this gives 1.57 GB)."""
    n = recipe.spec.n_cells
    lib = load_library(recipe.library_path)
    atoms = select_recipe_atoms(recipe, lib)
    dtype, _ = empty_index(len(atoms), recipe.spec.bounded)
    item = np.dtype(dtype).itemsize
    cells = float(n) * n
    return Need(disk=cells * 2 * (item * DESIGN_DEFLATE_RATIO + OASIS_BYTES_PER_PILLAR),
                memory=0.4e9 + workers * tile * n * 16.0,
                what="a smaller aperture, fewer -j workers or a smaller --tile")


def _check_tiling(recipe: DesignRecipe, tile: int, hierarchy: str) -> None:
    """One-line ValidationErrors for a hierarchy or a tile size the build cannot use."""
    if hierarchy not in HIERARCHIES:
        raise ValidationError(f"--hierarchy: expected one of {', '.join(HIERARCHIES)}, got {hierarchy!r}")
    if tile % recipe.tile_rows or tile % recipe.spec.supercell:
        raise ValidationError(f"--tile: {tile} cells must be a multiple of the design's tile_rows "
                              f"({recipe.tile_rows}) and of the supercell ({recipe.spec.supercell})")


def _stripes_folder(out_dir: Path, key: str, log) -> TaskFolder:
    """The folder of this job's stripes: named by its key, so a worker of an earlier (killed) job that
    finishes its stripe late can never write into this one's; other jobs' folders go (the output's lock
    keeps any other writer out)."""
    root = out_dir / f".tiled-partial-{key[:16]}"
    out_dir.mkdir(parents=True, exist_ok=True)  # the output's folder, not a scratch one (no marker in it)
    for old in out_dir.glob(".tiled-partial*"):
        if old != root and old.is_dir() and not old.is_symlink():
            log(f"discarding {old} (made by another job: other inputs or version)")
            shutil.rmtree(old, ignore_errors=True)
    return TaskFolder(root, key, log)


def _compute_stripes(plan: TiledPlan, key: str, out_dir: Path, run: Execution) -> tuple[TaskFolder, dict, int]:
    """Phase one: every stripe not yet kept in this job's folder, on ``run``'s workers (local workers write
    their stripe's file themselves); returns the folder, the stripes' names (by first row) and how many
    were reused from an interrupted run."""
    n, tile = plan.spec.n_cells, plan.tile
    folder = _stripes_folder(out_dir, key, run.log)
    names = {r0: f"stripe-{r0:07d}" for r0 in range(0, n, tile)}
    for nm in names.values():  # what killed writers left half-written
        remove_stale_temps(folder.root / f"{nm}.npz")
    if not run.distributed:
        plan.save_dir = str(folder.root)
    rows = {names[r0]: min(tile, n - r0) for r0 in names}  # a stripe's weight in the progress
    _, computed = run.run(_stripe_task, {names[r0]: r0 for r0 in names}, folder, store="npz", compress=False,
                          keep=False, shared=plan, weight=rows.__getitem__, unit="row")
    return folder, names, len(names) - len(computed)


@dataclass
class _Assembly:
    """Phase two: the kept stripes streamed in order into ``layout.oas`` and ``design.npz`` (the design's
    error sums accumulated on the way into ``total``; its result, metrics included, in ``result``)."""

    recipe: DesignRecipe
    plan: TiledPlan
    stream: DesignStream
    meta: dict
    prov: dict
    opts: LayoutOptions
    folder: TaskFolder
    names: dict[int, str]
    total: list = field(default_factory=list)
    result: object = None
    stream_seconds: float = 0.0

    def __post_init__(self):
        self.total = [np.zeros(2), np.zeros(2), np.zeros(2), 0, np.zeros(len(self.plan.atoms), np.int64)]

    def write(self, out_dir: Path) -> Path:
        """Both files, appearing together: the design goes to a hidden name first and replaces
        ``design.npz`` once the layout is complete (a failure leaves neither, never a new design beside an
        old layout).  Returns the layout's path."""
        oas = out_dir / "layout.oas"
        design_tmp = out_dir / ".design.npz.tiled-partial"
        for target in (oas, design_tmp, out_dir / "layout.oas.json", out_dir / "metrics.json"):
            # what a SIGKILLed run left half-written (the output's lock keeps any other writer out)
            remove_stale_temps(target)
        try:
            with atomic_path(oas) as tmp, open(tmp, "wb") as fh:
                w = O.OasisWriter(fh)
                prov_json = self._head(w)
                t_stream = time.perf_counter()
                self._design(w, design_tmp)
                self.stream_seconds = time.perf_counter() - t_stream
                self._tail(w, prov_json)
                w.close()
            os.replace(design_tmp, out_dir / "design.npz")
        finally:
            design_tmp.unlink(missing_ok=True)
        return oas

    def _head(self, w: O.OasisWriter) -> bytes:
        """The cell names (atoms, the top cell, the tiles), and a flat layout's top cell with its provenance
        property (a tiled one's comes after the tiles); returns the provenance's JSON bytes."""
        nt = self.plan.n_tiles
        for a in range(len(self.plan.atoms)):
            w.cellname(f"ATOM_{a:03d}")
        w.cellname(TOP_CELL)
        for r in range(nt):
            for c in range(nt):
                w.cellname(f"TILE_{r:03d}_{c:03d}")
        prov_json = json.dumps(self.prov, sort_keys=True).encode()
        if self.plan.hierarchy == "flat":
            w.cell(TOP_CELL)
            w.raw(O.property_record(b"metadesign", prov_json))
        return prov_json

    def _design(self, w: O.OasisWriter, target: Path) -> None:
        """The design file, its index map the stripes' deflated pieces in order; each stripe's OASIS bytes
        go to ``w`` as its piece is consumed, and its error sums into ``total``."""
        plan, atoms, n = self.plan, self.plan.atoms, self.plan.spec.n_cells

        def stripes():
            for r0 in range(0, n, plan.tile):
                res = _load_stripe(self.folder.root / f"{self.names[r0]}.npz")
                w.raw(res["oasis"])
                for st_part in res["stats"]:
                    self.total[:] = accumulate(tuple(self.total), st_part)
                yield res["design"]

        def meta_array():
            self.stream.finish(self.total)
            self.result = self.stream.result()
            self.meta["metrics"] = self.result.metrics
            return json_array(self.meta)

        write_npz(target, {
            "index_map": DeflatedArray((n, n), np.dtype(self.stream.dtype), stripes()), "atom_wx_m": atoms.wx,
            "atom_wy_m": atoms.wy, "atom_t": atoms.t, "atom_T0": atoms.T0, "atom_lib_index": atoms.lib_index,
            "meta": meta_array})

    def _tail(self, w: O.OasisWriter, prov_json: bytes) -> None:
        """A tiled layout's top cell (its property, each tile placed once at the origin), the outline and the
        labels, then the cells of the atoms placed (an unreferenced cell would be a top cell)."""
        plan, opts, n, nt = self.plan, self.opts, self.plan.spec.n_cells, self.plan.n_tiles
        tail = []
        if plan.hierarchy == "tiles":
            w.cell(TOP_CELL)
            w.raw(O.property_record(b"metadesign", prov_json))
            tail += [O.placement_head(plan.tile_ref(r, c), 0, 0, False) for r in range(nt) for c in range(nt)]
        if opts.outline_layer is not None:
            for poly in outline_polygons(plan.spec, plan.p_nm, opts):
                pts = np.rint(poly.points).astype(np.int64)
                tail.append(O.polygon_record(opts.outline_layer, opts.datatype, pts))
        if opts.label_layer is not None:
            half = (n * plan.p_nm) // 2
            text = (opts.label or self.recipe.name).encode()
            tail.append(O.text_record(text, opts.label_layer, 0, -half, -half - 5000))
            tail.append(O.text_record(prov_json, opts.label_layer, 1, -half, -half - 10000))
        w.records(b"".join(tail), opts.compression_level)
        wx, _ = snap_widths(plan.atoms.wx, opts.grid_nm)
        wy, _ = snap_widths(plan.atoms.wy, opts.grid_nm)
        for a in np.flatnonzero(self.total[4]):
            w.cell(f"ATOM_{a:03d}")
            ww, hh = int(wx[a]), int(wy[a])
            x0a, y0a = -(ww // 2) - (ww % 2), -(hh // 2) - (hh % 2)  # centred as the gdstk writer centres
            w.raw(O.rectangle_record(opts.layer, opts.datatype, ww, hh, x0a, y0a))


def build_tiled(recipe: DesignRecipe, out_dir: Path, tile: int = DEFAULT_TILE, hierarchy: str = "tiles",
                opts: LayoutOptions = LayoutOptions(), run: Execution = SERIAL) -> dict:
    """Design ``recipe`` and write ``out_dir/design.npz`` and ``out_dir/layout.oas`` (+ ``.json``);
    returns the report.  ``run``: the local workers or the Dask scheduler of the stripes, the progress (in
    rows) and the log.

    Two phases, resumable after any interruption (SIGKILL included): the workers' stripes (index block,
    OASIS bytes, error sums) are kept, each written atomically, in ``out_dir/.tiled-partial-<key>/``
    (``key``: a hash of everything that shapes them), and a rerun computes only the missing ones; then
    the stripes are streamed in order into the two files, and the folder is removed."""
    t0 = time.perf_counter()
    spec = recipe.spec
    n = spec.n_cells
    _check_tiling(recipe, tile, hierarchy)
    out_dir = Path(out_dir)
    lib = load_library(recipe.library_path)
    check_library(recipe, lib)
    atoms = select_recipe_atoms(recipe, lib)
    st = DesignStream(spec, atoms, recipe.metric, recipe.optimise_offsets, recipe.tile_rows)
    p_nm, x0 = layout_geometry(n, spec.period)
    plan = TiledPlan(spec, atoms, recipe.metric, st.offsets, np.dtype(st.dtype).str, st.empty, recipe.tile_rows,
                     tile, p_nm, x0, hierarchy, opts.compression_level, DESIGN_DEFLATE_LEVEL,
                     _mapper=st.mapper)  # the stream's look-up tables (pickled once to each worker)
    nt = plan.n_tiles
    meta = design_meta(recipe, lib, atoms, st.offsets, st.empty, None, out_dir)
    prov = provenance_of(Design(spec, atoms, None, st.offsets, {}, meta, st.empty), opts)
    prov["library_path"] = meta["library"]["path"]
    prov["tiling"] = {"tile_cells": tile, "hierarchy": hierarchy, "tiles": nt * nt}
    key = content_key({"recipe": recipe.raw, "library": lib.identity, "tile": tile, "hierarchy": hierarchy,
                       "compression": opts.compression_level, "design_level": DESIGN_DEFLATE_LEVEL,
                       "stripe": 2, "version": __version__})
    t_stripes = time.perf_counter()
    folder, names, reused = _compute_stripes(plan, key, out_dir, run)
    t_stripes = time.perf_counter() - t_stripes
    job = _Assembly(recipe, plan, st, meta, prov, opts, folder, names)
    oas = job.write(out_dir)
    folder.remove()
    metrics = job.result.metrics
    atomic_write_text(out_dir / "metrics.json", json.dumps(metrics, indent=2, sort_keys=True))
    seconds = time.perf_counter() - t0
    pillars = int(job.total[3])
    wx, ex = snap_widths(atoms.wx, opts.grid_nm)
    wy, ey = snap_widths(atoms.wy, opts.grid_nm)
    report = {
        "design": str(out_dir / "design.npz"), "file": str(oas), "format": "oas", "bytes": oas.stat().st_size,
        "pillars": pillars, "atoms": len(atoms), "tiles": nt * nt, "tile_cells": tile, "hierarchy": hierarchy,
        "snapping": {"grid_nm": opts.grid_nm, "max_error_nm": max(ex, ey),
                     "odd_width_atoms": int(np.sum((wx % 2) | (wy % 2)))},
        "options": asdict(opts), "provenance": prov, "metrics": metrics,
    }
    side = {k: v for k, v in report.items() if k not in ("metrics",)}
    atomic_write_text(oas.with_suffix(".oas.json"), json.dumps(side, indent=2, sort_keys=True))
    report["seconds"] = seconds
    report["stream_seconds"] = job.stream_seconds
    report["stripe_seconds"] = t_stripes
    report["stripes_reused"] = reused
    report["pillars_per_second"] = pillars / seconds
    return report
